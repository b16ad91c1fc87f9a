"""Weight files that used to load wrongly or crash: sharded safetensors, NaN weights, wrapper prefixes
(torch.compile, nested), ``~`` and symlink loops, corrupt safetensors read by names only, damaged checkpoint
records. Each is one line naming the file, or a full load."""

import json

import pytest
import torch
from safetensors.torch import save_file

from anycity.models import build_network, load_checkpoint
from anycity.models.pretrained import load_pretrained


@pytest.fixture(scope="module")
def vggt():
    """A VGGT-layout state dict of the tiny network (aggregator + camera/depth heads)."""
    torch.manual_seed(3)
    return {k: v.clone().contiguous() for k, v in build_network("tiny").state_dict().items()
            if k.startswith(("aggregator.", "camera_head.", "depth_head."))}


def _one_line(e: pytest.ExceptionInfo) -> str:
    text = str(e.value)
    assert "\n" not in text, text
    return text


def _sharded(folder, sd: dict, index: bool = True):
    """``sd`` as a two-shard download: the whole aggregator in shard 1 (so shard 1 alone passes the backbone
    check), the heads in shard 2, and the index naming each key's file."""
    folder.mkdir()
    names = ("model-00001-of-00002.safetensors", "model-00002-of-00002.safetensors")
    parts = ({k: v for k, v in sd.items() if k.startswith("aggregator.")},
             {k: v for k, v in sd.items() if not k.startswith("aggregator.")})
    for name, part in zip(names, parts):
        save_file(part, str(folder / name))
    if index:
        weight_map = {k: name for name, part in zip(names, parts) for k in part}
        (folder / "model.safetensors.index.json").write_text(json.dumps({"metadata": {}, "weight_map": weight_map}))
    return folder


def _equal(net, sd) -> bool:
    own = net.state_dict()
    return all(torch.equal(own[k], v) for k, v in sd.items())


@pytest.mark.parametrize("given", ["folder", "index", "shard1", "shard2"])
def test_a_sharded_download_loads_every_shard_whichever_part_is_given(tmp_path, vggt, given):
    """Shard 1 alone (the whole aggregator) loaded with the camera/depth heads left random; the index.json was
    'truncated or not a torch file'; the folder's error suggested passing one shard."""
    folder = _sharded(tmp_path / "dl", vggt)
    path = {"folder": folder, "index": folder / "model.safetensors.index.json",
            "shard1": folder / "model-00001-of-00002.safetensors",
            "shard2": folder / "model-00002-of-00002.safetensors"}[given]
    net = build_network("tiny")
    report = load_pretrained(net, path)
    report.require_backbone(path)
    assert _equal(net, vggt) and sorted(report.loaded) == sorted(vggt)
    assert not any(k.startswith(("camera_head.", "depth_head.")) for k in report.missing)
    from anycity.models.pretrained import read_shapes

    assert set(read_shapes(path)) == set(vggt)


def test_shards_without_their_index_are_refused_never_one_shard_suggested(tmp_path, vggt):
    folder = _sharded(tmp_path / "dl", vggt, index=False)
    for path in (folder, folder / "model-00001-of-00002.safetensors"):
        with pytest.raises(ValueError) as e:
            load_pretrained(build_network("tiny"), path)
        line = _one_line(e)
        assert line.startswith(f"pretrained weights: {path} ") and "model.safetensors.index.json" in line
        assert "pass the folder" in line and "candidates" not in line


def test_a_damaged_or_incomplete_shard_index_is_one_line(tmp_path, vggt):
    folder = _sharded(tmp_path / "dl", vggt)
    index = folder / "model.safetensors.index.json"
    good = index.read_text()
    index.write_text("{]")
    with pytest.raises(ValueError, match=r"^cannot read pretrained weights .*index\.json: .*damaged") as e:
        load_pretrained(build_network("tiny"), folder)
    _one_line(e)
    index.write_text(good)
    (folder / "model-00002-of-00002.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match=r"lists 2 shards, 1 of which are not in .*model-00002") as e:
        load_pretrained(build_network("tiny"), folder)
    _one_line(e)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_pretrained_weights_are_refused_naming_the_file_and_key(tmp_path, vggt, bad):
    sd = dict(vggt)
    key = "camera_head.trunk.0.norm1.weight"
    sd[key] = sd[key].clone()
    sd[key].view(-1)[0] = bad
    torch.save(sd, path := tmp_path / "model.pt")
    net = build_network("tiny")
    before = {k: v.clone() for k, v in net.state_dict().items()}
    with pytest.raises(ValueError, match=rf"^pretrained weights: {path} holds non-finite values .* in {key};") as e:
        load_pretrained(net, path)
    _one_line(e)
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())  # nothing half loaded


@pytest.mark.parametrize("prefix", ["_orig_mod.", "model.module.", "module._orig_mod.", "model._orig_mod.module."])
def test_compiled_and_nested_wrapper_prefixes_are_stripped(tmp_path, vggt, prefix):
    """'_orig_mod.' (torch.compile) and 'model.module.' loaded 0 of the tensors ('pass VGGT or AnySplat weights')."""
    torch.save({prefix + k: v for k, v in vggt.items()}, path := tmp_path / "w.pt")
    net = build_network("tiny")
    load_pretrained(net, path).require_backbone(path)
    assert _equal(net, vggt)


def test_a_tilde_path_is_expanded(tmp_path, vggt, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    torch.save(vggt, tmp_path / "model.pt")
    net = build_network("tiny")
    load_pretrained(net, "~/model.pt")
    assert _equal(net, vggt)


def test_a_symlink_loop_is_reported_as_one(tmp_path):
    (tmp_path / "a.pt").symlink_to(tmp_path / "b.pt")
    (tmp_path / "b.pt").symlink_to(tmp_path / "a.pt")
    with pytest.raises(FileNotFoundError, match="a.pt is a symlink loop") as e:
        load_pretrained(build_network("tiny"), tmp_path / "a.pt")
    _one_line(e)


def test_reading_the_names_of_a_corrupt_safetensors_file_is_the_same_one_line_error(tmp_path, vggt):
    """pretrained_scaffold_gaps (a resumed Stage II fit's setup) read a corrupt file with safe_open: a
    SafetensorError traceback, which the fresh-fit handler (FileNotFoundError/ValueError) did not catch."""
    from anycity.lit.refinement import pretrained_scaffold_gaps
    from anycity.models.pretrained import read_shapes

    save_file(vggt, str(good := tmp_path / "good.safetensors"))
    data = good.read_bytes()
    (bad := tmp_path / "bad.safetensors").write_bytes(data[: len(data) // 2])
    for read in (read_shapes, lambda f: pretrained_scaffold_gaps(build_network("tiny"), f, "vggt")):
        with pytest.raises(ValueError, match=rf"^cannot read pretrained weights {bad}: .*truncated or corrupt") as e:
            read(bad)
        _one_line(e)
    assert read_shapes(good) == {k: tuple(v.shape) for k, v in vggt.items()}


def _stage2_ckpt(path, **extra):
    from anycity.lit import RefinementModule

    torch.manual_seed(0)
    m = RefinementModule(net={"video_prior": "none"})
    ckpt = {"pytorch-lightning_version": "2", "state_dict": m.state_dict(),
            "hyper_parameters": {**dict(m.hparams), "_class_path": "anycity.lit.RefinementModule"}, **extra}
    torch.save(ckpt, path)
    return ckpt


@pytest.mark.parametrize("record", ["x", {"dir": "/w"}, {"dir": "/w", "sha256": 5, "block": 1},
                                    {"dir": "/w", "sha256": "ab", "block": "1"}, ["/w", "ab", 1]])
def test_load_checkpoint_refuses_a_malformed_video_prior_record_in_one_line(tmp_path, record):
    """A string crashed with AttributeError ('str' object has no attribute 'get')."""
    _stage2_ckpt(path := tmp_path / "last.ckpt", video_prior=record)
    with pytest.raises(ValueError, match=rf"^checkpoint {path}: its video_prior record is .*damaged or was written "
                                         "by another anycity version") as e:
        load_checkpoint(path)
    _one_line(e)


def test_load_checkpoint_refuses_non_tensor_and_non_finite_weights_in_one_line(tmp_path):
    """A str under a weight key crashed with AttributeError ('str' object has no attribute 'shape'); NaN weights
    loaded without a word."""
    ckpt = _stage2_ckpt(path := tmp_path / "last.ckpt")
    ckpt["state_dict"]["net.aggregator.camera_token"] = "str"
    torch.save(ckpt, path)
    with pytest.raises(ValueError, match=r"holds a str under the key 'net.aggregator.camera_token', not a tensor") as e:
        load_checkpoint(path)
    _one_line(e)
    ckpt["state_dict"]["net.aggregator.camera_token"] = torch.full((1, 2, 1, 64), float("nan"))
    torch.save(ckpt, path)
    with pytest.raises(ValueError, match=rf"^checkpoint {path} holds non-finite values .* in net.aggregator.") as e:
        load_checkpoint(path)
    _one_line(e)
