"""The export callback when a run does not end normally, and its DDP-safe output folder: a chunked city that never
finishes leaves nothing in its scene folder and says so; SIGTERM stops predict after the batch being written;
``trainer.log_dir`` (a collective under DDP) is read once, in the hook every rank runs."""

import warnings
from types import SimpleNamespace

import lightning.pytorch as pl
import pytest
import torch
from helpers.city import oracle_chunk_prediction
from lightning.pytorch.utilities.exceptions import SIGTERMException

from anycity.atomic import HAS_FLOCK
from anycity.callbacks import PredictionExport
from anycity.city import plan_chunks
from anycity.structures import Gaussians

H = W = 2
PLAN = plan_chunks(12, 6, 3)  # 3 chunks


class _Chunks(torch.utils.data.Dataset):
    """A 12-photo city in chunks of 6; chunk ``fail`` does not decode."""

    def __init__(self, fail: int | None = None) -> None:
        self.fail = fail

    def __len__(self):
        return len(PLAN)

    def __getitem__(self, k):
        if k == self.fail:
            raise ValueError("predict_images: cannot decode flight/p9.jpg")
        return {"images": torch.rand(1, 6, 3, H, W), "scene": ["flight"],
                "chunk": {"index": k, "count": len(PLAN), "views": PLAN[k], "plan": PLAN, "hw": (H, W),
                          "names": [f"p{i}.jpg" for i in range(12)]}}


class _Oracle(pl.LightningModule):
    """True cameras and depth, with renders (so ``save_renders`` writes PNGs); ``sigterm_at``: the batch during
    which the run receives SIGTERM."""

    def __init__(self, sigterm_at: int | None = None) -> None:
        super().__init__()
        self.sigterm_at = sigterm_at

    def predict_step(self, batch, batch_idx):
        if batch_idx == self.sigterm_at:
            self.trainer._signal_connector.received_sigterm = True  # what Lightning's SIGTERM handler sets
        return {**oracle_chunk_prediction(batch, H, W), "renders": SimpleNamespace(rgb=batch["images"].clone())}


def _predict(tmp_path, model, data, **trainer_kw):
    cb = PredictionExport(out_dir=str(tmp_path / "out"), save_renders=True, smooth_3d=0)
    trainer = pl.Trainer(callbacks=[cb], logger=False, enable_progress_bar=False, accelerator="cpu",
                         enable_model_summary=False, default_root_dir=str(tmp_path), **trainer_kw)
    return cb, trainer, lambda: trainer.predict(model, torch.utils.data.DataLoader(data, batch_size=None))


def _left(tmp_path) -> list[str]:
    out = tmp_path / "out"
    return sorted(str(p.relative_to(out)) for p in out.rglob("*")) if out.exists() else []


pytestmark = pytest.mark.filterwarnings("ignore:Couldn't infer the batch indices")  # the CLI silences it too


def test_a_finished_city_gets_its_renders_and_inputs(tmp_path):
    cb, _, run = _predict(tmp_path, _Oracle(), _Chunks())
    run()
    left = _left(tmp_path)
    assert {"flight/scene.ply", "flight/cameras.json", "flight/chunks.json", "flight/renders/011.png",
            "flight/inputs/000.png"} <= set(left)
    assert len([p for p in left if p.startswith("flight/renders/")]) == 12
    assert not [p for p in left if not p.startswith("flight")]  # no work or views folder left beside it
    assert cb.unfinished is None


def test_a_chunk_that_fails_leaves_no_renders_in_the_scene_folder(tmp_path):
    """The first chunks' PNGs went straight into out/flight/renders and inputs: a scene folder with images and no
    scene.ply, cameras.json or chunks.json."""
    cb, _, run = _predict(tmp_path, _Oracle(), _Chunks(fail=2))
    with pytest.raises(ValueError, match="cannot decode"):
        run()
    assert _left(tmp_path) == []
    assert cb.unfinished == "flight"


def test_a_city_cut_short_by_limit_predict_batches_writes_nothing_and_says_so(tmp_path):
    """The run ended with exit 0, no warning, and renders/ + inputs/ of two chunks in the scene folder."""
    _, _, run = _predict(tmp_path, _Oracle(), _Chunks(), limit_predict_batches=2)
    with pytest.warns(UserWarning, match=r"ended before the last of the 3 chunks of flight, so nothing was written "
                                         r"for it .*limit_predict_batches"):
        run()
    assert _left(tmp_path) == []


def test_predict_stops_after_the_batch_that_received_sigterm(tmp_path):
    """Lightning's predict loop never checks the SIGTERM flag: a preempted predict ran to the end."""
    seen = []
    cb, trainer, run = _predict(tmp_path, _Oracle(sigterm_at=0), _Chunks())
    cb.on_predict_batch_start = lambda trainer, module, batch, i, *a: seen.append(i)
    with pytest.raises(SIGTERMException):
        run()
    assert seen == [0]  # chunk 0 written, then stopped
    assert _left(tmp_path) == [] and cb.unfinished == "flight" and cb._city is None  # the city cleanup ran
    cb, trainer, run = _predict(tmp_path, _Oracle(sigterm_at=2), _Chunks())
    run()  # on the last batch: nothing left to stop, the run ends as usual
    assert "flight/scene.ply" in _left(tmp_path)


class _CountingTrainer(SimpleNamespace):
    reads = 0

    @property
    def log_dir(self):
        type(self).reads += 1
        return self._log_dir


def test_the_default_folder_is_resolved_once_in_setup_not_per_sample(tmp_path):
    """``trainer.log_dir`` broadcasts from rank 0 under DDP; read per exported sample, the ranks (which hold unequal
    sample counts) ran unmatched collectives: gloo "Connection closed by peer", a hang on NCCL."""
    trainer = _CountingTrainer(_log_dir=str(tmp_path / "logs"), default_root_dir=str(tmp_path), global_rank=0)
    cb = PredictionExport(save_renders=False, smooth_3d=0)
    cb.setup(trainer, _Oracle(), "predict")
    cb.on_predict_start(trainer, None)
    assert _CountingTrainer.reads == 1
    K = torch.tensor([[2.0, 0, 1], [0, 2, 1], [0, 0, 1]]).expand(1, 1, 3, 3)
    g = Gaussians(torch.rand(1, 4, 3) + torch.tensor([0, 0, 3.0]), torch.tensor([1.0, 0, 0, 0]).expand(1, 4, 4),
                  torch.full((1, 4, 3), 0.01), torch.full((1, 4), 0.5), torch.zeros(1, 4, 1, 3))
    pred = {"gaussians": g, "w2c": torch.eye(4)[None, None], "K": K, "images": torch.rand(1, 1, 3, H, W),
            "renders": None, "scene": ["s"]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(3):
            cb.write_on_batch_end(trainer, None, pred, None, {"scene": ["s"]}, i)
    assert _CountingTrainer.reads == 1
    assert sorted(p.name for p in (tmp_path / "logs" / "predictions").iterdir()) == ["s", "s-2", "s-3"]
    cb.teardown(trainer, None, "predict")
    assert cb.root(trainer) == tmp_path / "logs" / "predictions"


def test_a_killed_runs_renders_are_not_published_with_the_next_city(tmp_path):
    """The hidden views folder a killed run left (its renders of other photos) is emptied at chunk 0, with a
    warning, so its PNGs do not end up in the new scene's renders/."""
    stale = tmp_path / "out" / ".flight.anycity_city_views" / "renders"
    stale.mkdir(parents=True)
    (stale / "099.png").write_bytes(b"stale")
    _, _, run = _predict(tmp_path, _Oracle(), _Chunks())
    with pytest.warns(UserWarning, match="removing the renders an interrupted run left"):
        run()
    left = _left(tmp_path)
    assert "flight/renders/099.png" not in left
    assert len([p for p in left if p.startswith("flight/renders/")]) == 12
    assert not [p for p in left if not p.startswith("flight")]  # the views folder went too


def _one_pass(cb, trainer, scene: str = "flight") -> None:
    """A photo folder that fits one pass (no ``"chunk"``): two views of a few Gaussians."""
    from anycity.structures import RenderOutput

    n, v, h, w = 6, 2, 8, 8
    g = Gaussians(torch.rand(1, n, 3) + torch.tensor([0, 0, 3.0]), torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4),
                  torch.full((1, n, 3), 0.05), torch.full((1, n), 0.5), torch.zeros(1, n, 1, 3))
    imgs = torch.rand(1, v, 3, h, w)
    pred = {"gaussians": g, "w2c": torch.eye(4).expand(1, v, 4, 4), "scene": [scene], "images": imgs,
            "K": torch.tensor([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]]).expand(1, v, 3, 3),
            "renders": RenderOutput(rgb=imgs, depth=torch.ones(1, v, 1, h, w), alpha=torch.ones(1, v, 1, h, w))}
    cb.write_on_batch_end(trainer, None, pred, None, {"scene": [scene], "names": [["a.jpg", "b.jpg"]]}, 0)


def _killed_runs_leftovers(tmp_path):
    """What a chunked run of ``flight`` killed part-way leaves: its spill folder and its renders folder."""
    work = tmp_path / "out" / ".flight.anycity_city_work"
    views = tmp_path / "out" / ".flight.anycity_city_views" / "renders"
    work.mkdir(parents=True)
    (work / "chunk_00000.pt").write_bytes(b"a killed run's chunk")
    views.mkdir(parents=True)
    (views / "000.png").write_bytes(b"stale")
    return work, views.parent


def test_a_one_pass_rerun_removes_what_a_killed_chunked_run_left(tmp_path):
    """A killed chunked run's spill and renders stayed forever when the next run of the scene fitted one pass
    (rerun with a larger --data.predict_chunk_size): only a chunked run looked for them."""
    work, views = _killed_runs_leftovers(tmp_path)
    cb = PredictionExport(out_dir=str(tmp_path / "out"), save_renders=False, smooth_3d=0)
    trainer = SimpleNamespace(log_dir=None, default_root_dir=str(tmp_path), global_rank=0)
    cb.on_predict_start(trainer, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _one_pass(cb, trainer)
    said = [str(w.message) for w in caught if "interrupted run" in str(w.message)]
    assert said == [f"{work}: removing the spill folder an interrupted run left",
                    f"{views}: removing the renders an interrupted run left"]
    assert _left(tmp_path) == ["flight", "flight/cameras.json", "flight/scene.ply"]


@pytest.mark.skipif(not HAS_FLOCK, reason="needs flock (POSIX)")
def test_a_one_pass_run_leaves_the_spill_of_a_live_chunked_run_of_the_scene(tmp_path):
    """A chunked run of the scene still writing holds its spill folder's lock: a one-pass run must not take its
    spill and renders for a killed run's."""
    import fcntl
    import os

    work, views = _killed_runs_leftovers(tmp_path)
    fd = os.open(work, os.O_RDONLY)  # the live run's lock (another open file: flock conflicts within a process too)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        cb = PredictionExport(out_dir=str(tmp_path / "out"), save_renders=False, smooth_3d=0)
        trainer = SimpleNamespace(log_dir=None, default_root_dir=str(tmp_path), global_rank=0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _one_pass(cb, trainer)
        assert not [w for w in caught if "interrupted run" in str(w.message)]
        assert (work / "chunk_00000.pt").is_file() and (views / "renders" / "000.png").is_file()
    finally:
        os.close(fd)
