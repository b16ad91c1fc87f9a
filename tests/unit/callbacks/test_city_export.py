"""Chunked prediction through the export callback: a photo folder -> chunks -> one merged scene."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.city import oracle_chunk_prediction
from PIL import Image

from anycity.callbacks import PredictionExport
from anycity.city import apply_sim3, plan_chunks, w2c_to_world
from anycity.city.align import sim3_parts
from anycity.city.oracle import orbit_scene, random_sim3
from anycity.export import load_ply, load_ply_extras, view_png
from anycity.export.provenance import summary
from anycity.geometry.projection import unproject_depth
from anycity.lit.datamodule import AerialDataModule
from anycity.structures import Gaussians, RenderOutput


def _chunked_photo_folder(photos, n: int, h: int, w: int, shade: int) -> AerialDataModule:
    """``n`` flat ``h`` x ``w`` photos (grey ``shade * i``) in ``photos``, predicted in chunks of 4 overlapping by 2."""
    photos.mkdir()
    for i in range(n):
        Image.fromarray(np.full((h, w, 3), shade * i, np.uint8)).save(photos / f"p{i}.png")
    return AerialDataModule(predict_images=str(photos), image_size=(h, w), patch_size=8, predict_chunk_size=4,
                            predict_chunk_overlap=2, num_workers=0)


def test_photo_folder_chunks_merge_into_one_scene(tmp_path, capsys):
    n, h, w = 10, 8, 8
    dm = _chunked_photo_folder(tmp_path / "city", n, h, w, shade=20)
    batches = list(dm.predict_dataloader())
    assert [b["chunk"]["views"] for b in batches] == plan_chunks(n, 4, 2)

    gt, _ = orbit_scene(n)
    K = torch.tensor([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]])
    depth = 5 + 0.2 * torch.rand(1, n, 1, h, w, generator=torch.Generator().manual_seed(0))  # within 5 % tol
    cb = PredictionExport(out_dir=str(tmp_path / "out"))
    trainer = SimpleNamespace(log_dir=None, default_root_dir=str(tmp_path))
    for k, b in enumerate(batches):  # an oracle network: true cameras and depth, each chunk in its own frame
        views = b["chunk"]["views"]
        G = random_sim3(torch.Generator().manual_seed(k))
        cams = w2c_to_world(gt[views], G).float()[None]
        Ks = K.expand(1, len(views), 3, 3)
        world = unproject_depth(depth[:, views].double(), Ks.double(), gt[views][None])
        means = apply_sim3(G, world.reshape(1, -1, 3)).float()
        m = means.shape[1]
        g = Gaussians(means, torch.tensor([1.0, 0, 0, 0]).expand(1, m, 4), torch.full((1, m, 3), 0.01),
                      torch.full((1, m), 0.5), torch.zeros(1, m, 1, 3))
        rgb = b["images"]
        pred = {"gaussians": g, "w2c": cams, "K": Ks, "images": rgb, "scaffold": g,
                "depth": depth[:, views] * sim3_parts(G)[0].float(),  # z-depth in the chunk's own frame
                "renders": RenderOutput(rgb=rgb, depth=depth[:, views], alpha=torch.ones_like(depth[:, views]))}
        cb.write_on_batch_end(trainer, None, pred, None, b, k)
        assert pred == {}  # consumed: trainer.predict keeps no chunk's Gaussians
    out = tmp_path / "out" / "city"
    cams = json.loads((out / "cameras.json").read_text())["views"]
    assert [c["name"] for c in cams] == [f"p{i}.png" for i in range(n)]
    from anycity.city.oracle import camera_errors

    err = camera_errors(torch.tensor([c["w2c"] for c in cams], dtype=torch.float64), gt)
    assert err["w2c_max_abs"] < 1e-4, err  # float32 chunks
    rep = json.loads((out / "chunks.json").read_text())
    assert rep["num_chunks"] == 4 and rep["gaussians"] == n * h * w
    assert rep["ordered_by"] == "name"  # PNGs carry no capture time: "auto" fell back to the names, and says so
    for kind in ("renders", "inputs"):  # photo v's images as inputs/NNN.png, written by the chunk that owns it
        assert sorted(p.name for p in (out / kind).iterdir()) == [f"{v:03d}.png" for v in range(n)]
    photo = {v: b["images"][0, j] for b in batches for j, v in enumerate(b["chunk"]["views"])}
    for v in range(n):
        back = torch.from_numpy(np.array(Image.open(view_png(out, "inputs", v)))).permute(2, 0, 1) / 255.0
        assert (back - photo[v].float().clamp(0, 1)).abs().max() <= 0.5 / 255 + 1e-6
    # provenance and the smoothing filter, as for a single-pass scene: every Gaussian is seen by its own view (and
    # the overlapping ones by more), none was changed by Stage II; the filter only grows the 0.01 scales
    extras = load_ply_extras(out / "scene.ply")
    assert set(extras) == {"obs_views", "completion"} and len(extras["obs_views"]) == n * h * w
    assert extras["obs_views"].min() >= 1 and extras["obs_views"].max() >= 2 and extras["completion"].max() == 0
    # the printed shares are those of the Gaussians written (each photo's from the chunk that owns it)
    share = summary({k: torch.from_numpy(v) for k, v in extras.items()})
    assert (f"city: {share['supported']:.0%} of Gaussians observation-supported (>= 2 views of their chunk, kept), "
            f"{share['completed']:.0%} completed by Stage II, {share['unsupported']:.0%} seen by < 2 views of their "
            f"chunk") in (printed := capsys.readouterr().out)
    assert f"{n} photos (ordered by name) in 4 chunks" in printed
    merged = load_ply(out / "scene.ply")
    assert merged.scales.min() > 0.01 * min(rep["chunks"][k]["scale_to_world"] for k in range(4)) * (1 - 1e-4)


def test_token_order_is_a_permutation_from_the_network(tmp_path):
    from anycity.models import build_network

    photos = tmp_path / "unordered"
    photos.mkdir()
    for i in range(6):
        Image.fromarray(np.random.default_rng(i).integers(0, 255, (16, 16, 3), dtype=np.uint8)).save(
            photos / f"{i}.png")
    dm = AerialDataModule(predict_images=str(photos), image_size=(16, 16), patch_size=8, predict_chunk_size=4,
                          predict_chunk_overlap=2, predict_order="tokens", num_workers=0)
    dm.trainer = SimpleNamespace(lightning_module=SimpleNamespace(net=build_network("tiny", patch_size=8).eval()))
    batches = list(dm.predict_dataloader())
    names = batches[0]["chunk"]["names"]
    assert sorted(names) == [f"{i}.png" for i in range(6)] and len(batches) == 2


def test_city_spill_goes_under_the_output_folder_and_is_gone_after_success(tmp_path, monkeypatch):
    """Not into $TMPDIR (RAM on a tmpfs /tmp): beside the scene, on its filesystem, removed when it is written;
    a killed run's leftover one (predict moved that run's scene folder aside, not it) is removed first."""
    import tempfile
    import warnings

    system_tmp = tmp_path / "system_tmp"
    system_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(system_tmp))
    n, h, w = 6, 8, 8
    dm = _chunked_photo_folder(tmp_path / "flight", n, h, w, shade=30)
    gt, _ = orbit_scene(n)
    K = torch.tensor([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]])
    cb = PredictionExport(out_dir=str(tmp_path / "out"), save_renders=False, smooth_3d=0)
    out = tmp_path / "out" / "flight"
    leftover = tmp_path / "out" / ".flight.anycity_city_work" / "chunk_00099.pt"
    leftover.parent.mkdir(parents=True)
    leftover.write_bytes(b"a killed run's chunk")
    for k, b in enumerate(dm.predict_dataloader()):  # an oracle network: true cameras and depth, chunk 0's frame
        views = b["chunk"]["views"]
        Ks = K.expand(1, len(views), 3, 3)
        means = unproject_depth(torch.full((1, len(views), 1, h, w), 5.0), Ks, gt[views][None].float())
        m = len(views) * h * w
        g = Gaussians(means.reshape(1, m, 3), torch.tensor([1.0, 0, 0, 0]).expand(1, m, 4),
                      torch.full((1, m, 3), 0.01), torch.full((1, m), 0.5), torch.zeros(1, m, 1, 3))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cb.write_on_batch_end(SimpleNamespace(log_dir=None, default_root_dir=str(tmp_path)), None,
                                  {"gaussians": g, "w2c": gt[views].float()[None], "K": Ks, "images": b["images"]},
                                  None, b, k)
        if k == 0:
            spill = cb._city.spill
            assert [str(w.message) for w in caught] == [f"{spill}: removing the spill folder an interrupted run left"]
            assert spill.parent == out.parent and spill.name.startswith(".") and not leftover.exists()
            assert any(spill.iterdir()) and not any(system_tmp.iterdir())
    assert not spill.exists() and not any(system_tmp.iterdir())
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["flight"]
    assert sorted(p.name for p in out.iterdir()) == ["cameras.json", "chunks.json", "scene.ply"]


def test_a_chunked_prediction_shows_its_bar_before_the_first_chunk_is_done(capsys):
    """The bar used to appear when chunk 0 had been written (tens of seconds of silence on a CPU)."""
    cb = PredictionExport()
    cb.on_predict_batch_start(None, None, {"chunk": {"index": 0, "count": 3}, "scene": ["beach"]}, 0)
    assert cb._bar is not None and cb._bar.total == 3 and cb._bar.n == 0
    cb.on_predict_batch_start(None, None, {"chunk": {"index": 1, "count": 3}, "scene": ["beach"]}, 1)
    assert cb._bar.total == 3  # the same bar, not a new one per chunk
    cb.on_predict_end(None, None)
    assert "city: chunks of beach" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore:Couldn't infer the batch indices")  # the CLI silences it too; the export needs none
def test_a_chunk_that_fails_leaves_no_spill_files(tmp_path):
    """Lightning calls ``on_exception``, not ``on_predict_end``, when a chunk fails (a photo that passes the header
    check but does not decode): the earlier chunks' spill files (gigabytes for a city) went on taking the disk."""
    import lightning.pytorch as pl

    plan, h, w = plan_chunks(12, 6, 3), 2, 2

    class Chunks(torch.utils.data.Dataset):
        def __len__(self):
            return len(plan)

        def __getitem__(self, k):
            if k == 2:
                raise ValueError("predict_images: cannot decode flight/p9.jpg")
            return {"images": torch.rand(1, 6, 3, h, w), "scene": ["flight"],
                    "chunk": {"index": k, "count": len(plan), "views": plan[k], "plan": plan, "hw": (h, w),
                              "names": [f"p{i}.jpg" for i in range(12)]}}

    class Oracle(pl.LightningModule):
        def predict_step(self, batch, batch_idx):
            return oracle_chunk_prediction(batch, h, w)

    cb = PredictionExport(out_dir=str(tmp_path / "out"), save_renders=False, smooth_3d=0)
    trainer = pl.Trainer(callbacks=[cb], logger=False, enable_progress_bar=False, accelerator="cpu",
                         enable_model_summary=False, default_root_dir=str(tmp_path))
    with pytest.raises(ValueError, match="cannot decode"):
        trainer.predict(Oracle(), torch.utils.data.DataLoader(Chunks(), batch_size=None))
    assert not (tmp_path / "out" / ".flight.anycity_city_work").exists()
    assert cb._city is None and cb._bar is None
    assert not (tmp_path / "out" / "flight" / "scene.ply").exists()


def test_voxel_merging_with_several_chunks_is_refused_before_the_network_runs(tmp_path):
    """--model.net.voxel_size with a folder of several chunks failed only after chunk 0's network pass and camera
    refinement, in ChunkedScene.add's terms (tensor shapes), not naming the option to drop."""
    import lightning.pytorch as pl

    class Net(pl.LightningModule):
        def __init__(self, voxel_size):
            super().__init__()
            self.net = SimpleNamespace(cfg=SimpleNamespace(voxel_size=voxel_size))
            self.calls = 0

        def predict_step(self, batch, batch_idx):
            self.calls += 1
            raise AssertionError("the network ran")

    def predict(folder, model):
        trainer = pl.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                             enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(tmp_path),
                             callbacks=[PredictionExport(out_dir=str(tmp_path / "out"))])
        trainer.predict(model, datamodule=folder, return_predictions=False)

    dm = _chunked_photo_folder(tmp_path / "city", 10, 8, 8, shade=20)
    model = Net(0.05)
    with pytest.raises(ValueError, match=r"^--model\.net\.voxel_size 0\.05: the 10 photos of --data\.predict_images "
                                         r"are predicted in 4 chunks, .*voxel merging is single-pass only; drop "
                                         r"--model\.net\.voxel_size or raise --data\.predict_chunk_size to 10 "
                                         r"\(one pass\)$"):
        predict(dm, model)
    assert model.calls == 0
    with pytest.raises(AssertionError, match="the network ran"):  # unmerged: no refusal
        predict(dm, Net(None))
    one = AerialDataModule(predict_images=str(tmp_path / "city"), image_size=(8, 8), patch_size=8,
                           predict_chunk_size=16, num_workers=0)
    with pytest.raises(AssertionError, match="the network ran"):  # one pass may merge voxels
        predict(one, Net(0.05))
