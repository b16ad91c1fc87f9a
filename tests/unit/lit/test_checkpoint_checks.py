"""Checkpoints that do not fit the module they are given to: a Stage II checkpoint as Stage II's init_from, a renamed,
non-tensor, reshaped or NaN weight under --ckpt_path, a damaged video_prior record, a corrupt pretrained file a
resumed fit does not need. Each is one line naming the file and the fix (tiny preset)."""

import types

import pytest
import torch
from safetensors.torch import save_file

from anycity.lit import RefinementModule, ScaffoldModule

NET = {"video_prior": "none"}


def _one_line(e: pytest.ExceptionInfo) -> str:
    assert "\n" not in str(e.value), str(e.value)
    return str(e.value)


def _ckpt(module, class_path: str | None = None) -> dict:
    hp = dict(module.hparams)
    if class_path:
        hp["_class_path"] = class_path
    return {"pytorch-lightning_version": "2.5.0", "epoch": 0, "global_step": 1, "state_dict": module.state_dict(),
            "hyper_parameters": hp}


@pytest.fixture(scope="module")
def stage1():
    torch.manual_seed(0)
    return ScaffoldModule()


@pytest.fixture(scope="module")
def stage2():
    torch.manual_seed(0)
    return RefinementModule(net=NET)


@pytest.mark.parametrize("class_path", ["anycity.lit.RefinementModule", None])
def test_a_stage2_checkpoint_as_init_from_is_refused_pointing_to_ckpt_path(tmp_path, stage2, class_path):
    """Its scaffold fits, so it was accepted and its trained completion branch silently thrown away."""
    ckpt = _ckpt(stage2, class_path)
    ckpt["hyper_parameters"]["init_from"] = "runs/stage1/checkpoints/last.ckpt"
    torch.save(ckpt, path := tmp_path / "stage2.ckpt")
    with pytest.raises(ValueError, match=rf"^model.init_from: {path} is a Stage II \(RefinementModule\) checkpoint, "
                                         rf"not a Stage I one; to continue that run pass it as --ckpt_path {path} .*"
                                         r"its own was runs/stage1/checkpoints/last.ckpt") as e:
        RefinementModule(net=NET).load_stage1(str(path))
    _one_line(e)


def test_a_stage1_checkpoint_still_loads_as_init_from(tmp_path, stage1):
    torch.save(_ckpt(stage1, "anycity.lit.ScaffoldModule"), path := tmp_path / "stage1.ckpt")
    m = RefinementModule(net=NET)
    m.load_stage1(str(path))
    theirs = stage1.state_dict()
    assert all(torch.equal(v, theirs[k]) for k, v in m.state_dict().items() if k.startswith("net.aggregator."))


def _renamed(ckpt):
    sd = ckpt["state_dict"]
    sd["net.agg.camera_token"] = sd.pop("net.aggregator.camera_token")


def _non_tensor(ckpt):
    ckpt["state_dict"]["net.aggregator.camera_token"] = "str"


def _reshaped(ckpt):
    ckpt["state_dict"]["net.aggregator.camera_token"] = torch.zeros(3)


def _nan(ckpt):
    sd = ckpt["state_dict"]
    sd["net.aggregator.camera_token"] = torch.full_like(sd["net.aggregator.camera_token"], float("nan"))


@pytest.mark.parametrize("damage, says", [
    (_renamed, r" does not fit this RefinementModule: 1 weights of the network are not in it \(e\.g\. "
               r"net\.aggregator\.camera_token\); 1 of its weights have no place \(e\.g\. net\.agg\.camera_token\); "
               r"it was written for another network"),
    (_non_tensor, r": its state_dict holds a str under the key 'net\.aggregator\.camera_token', not a tensor"),
    (_reshaped, r" does not fit this RefinementModule: 1 shapes differ \(e\.g\. net\.aggregator\.camera_token: \[3\] "
                r"there"),
    (_nan, r" holds non-finite values \(NaN or Inf\) in net\.aggregator\.camera_token; .*use an earlier checkpoint")])
def test_ckpt_path_weights_that_do_not_fit_are_one_line_naming_the_file(tmp_path, stage2, damage, says):
    """Lightning printed its ~50-line 'Error(s) in loading state_dict' (a non-tensor: an AttributeError)."""
    ckpt = _ckpt(stage2)
    damage(ckpt)
    m = RefinementModule(net=NET)
    m._trainer = types.SimpleNamespace(ckpt_path=str(tmp_path / "last.ckpt"))  # what the Trainer sets before the hook
    with pytest.raises(ValueError, match=rf"^--ckpt_path {tmp_path / 'last.ckpt'}{says}") as e:
        m.on_load_checkpoint(ckpt)
    _one_line(e)
    torch.save(ckpt, path := tmp_path / "damaged.ckpt")  # and without a Trainer, as load_from_checkpoint reads it
    with pytest.raises(ValueError, match=rf"^checkpoint{says}") as e:
        RefinementModule.load_from_checkpoint(path)
    _one_line(e)


def test_a_good_checkpoint_passes_the_check_and_loads(tmp_path, stage2):
    ckpt = _ckpt(stage2)
    m = RefinementModule(net=NET)
    m.on_load_checkpoint(ckpt)
    m.load_state_dict(ckpt["state_dict"])


def test_a_stage1_checkpoint_under_ckpt_path_of_stage2_points_to_init_from(stage1):
    m = RefinementModule(net=NET)
    m._trainer = types.SimpleNamespace(ckpt_path="runs/s1/last.ckpt")
    with pytest.raises(ValueError, match=r"weights of the network are not in it \(e\.g\. net\.completion\..*it is a "
                                         r"Stage I \(ScaffoldModule\) checkpoint: start Stage II from it with "
                                         r"--model.init_args.init_from runs/s1/last.ckpt, without --ckpt_path$") as e:
        m.on_load_checkpoint(_ckpt(stage1, "anycity.lit.ScaffoldModule"))
    _one_line(e)


def test_the_check_serves_the_scaffold_module_too(stage1, stage2):
    """What ScaffoldModule.on_load_checkpoint calls (after dropping an old checkpoint's completion branch)."""
    from anycity.lit.checkpoint_io import check_checkpoint_state

    check_checkpoint_state(ScaffoldModule(), _ckpt(stage1))
    ckpt = _ckpt(stage1)
    _renamed(ckpt)
    with pytest.raises(ValueError, match=r"^checkpoint does not fit this ScaffoldModule: .*net\.agg\.camera_token") \
            as e:
        check_checkpoint_state(ScaffoldModule(), ckpt)
    _one_line(e)


@pytest.mark.parametrize("record", ["x", {"dir": "/w"}, {"dir": "/w", "sha256": None, "block": 1}])
def test_a_malformed_video_prior_record_is_one_line(stage2, record):
    """A string crashed with TypeError in restore_frozen_prior ('string indices must be integers')."""
    ckpt = {**_ckpt(stage2), "video_prior": record}
    m = RefinementModule(net=NET)
    m._trainer = types.SimpleNamespace(ckpt_path="x.ckpt")
    with pytest.raises(ValueError, match=r"^--ckpt_path x\.ckpt: its video_prior record is .* the checkpoint is "
                                         r"damaged or was written by another anycity version") as e:
        m.on_load_checkpoint(ckpt)
    _one_line(e)


def test_a_resumed_fit_is_not_stopped_by_a_corrupt_pretrained_safetensors_file(tmp_path):
    """setup read the recorded pretrained file's names with safe_open: a SafetensorError traceback, although a
    resumed fit does not need that file. It is now the fresh-fit problem, one line, raised only without a resume."""
    from anycity.lit.base import resuming

    save_file({"aggregator.camera_token": torch.zeros(4)}, str(good := tmp_path / "w.safetensors"))
    data = good.read_bytes()
    (bad := tmp_path / "bad.safetensors").write_bytes(data[: len(data) // 2])
    with resuming():
        m = RefinementModule(net=NET, pretrained=str(bad))
    m.setup("fit")
    problem = m._fresh_fit_problems[0]
    assert isinstance(problem, ValueError) and "\n" not in str(problem)
    assert str(problem).startswith(f"cannot read pretrained weights {bad}: ")
