"""Wan prior files that loaded silently in part or crashed with a bare error: LoRA files with half the adapters,
another rank, or cut short; a damaged shard index in the Wan folder; ``~`` in the folder's path."""

import importlib.util

import pytest
import torch
from safetensors.torch import load_file, save_file

from anycity.models.video_prior import WanVideoPrior

pytestmark = pytest.mark.skipif(importlib.util.find_spec("diffusers") is None or importlib.util.find_spec("peft")
                                is None, reason="the 'wan' extra (diffusers, peft) is not installed")


@pytest.fixture(autouse=True)
def _hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # folder_hash's cache, not the user's


def _one_line(e: pytest.ExceptionInfo) -> str:
    assert "\n" not in str(e.value), str(e.value)
    return str(e.value)


def _prior(rank: int = 4) -> WanVideoPrior:
    torch.manual_seed(0)
    p = WanVideoPrior.tiny_random()
    p.add_lora(rank=rank)
    return p


@pytest.fixture
def lora_file(tmp_path):
    p = _prior()
    with torch.no_grad():
        for n, q in p.transformer.named_parameters():
            if "lora_" in n:
                q.normal_()
    p.save_lora(path := tmp_path / "lora.safetensors")
    return path


def _lora(p: WanVideoPrior) -> dict:
    return {n: q.detach().clone() for n, q in p.transformer.named_parameters() if "lora_" in n}


def test_a_lora_file_with_half_the_adapters_is_refused_and_nothing_loads(lora_file, tmp_path):
    sd = load_file(str(lora_file))
    save_file(dict(list(sd.items())[: len(sd) // 2]), str(half := tmp_path / "half.safetensors"))
    p = _prior()
    before = _lora(p)
    with pytest.raises(ValueError, match=rf"^LoRA weights {half} do not fit this prior's adapters: {len(sd) // 2} ") \
            as e:
        p.load_lora(half)
    _one_line(e)
    assert all(torch.equal(before[n], v) for n, v in _lora(p).items())
    p.load_lora(lora_file)  # the whole file still loads
    assert all(torch.equal(load_file(str(lora_file))[k], v) for k, v in p.lora_state_dict().items())


def test_a_lora_file_of_another_rank_is_one_line(tmp_path):
    _prior(rank=8).save_lora(r8 := tmp_path / "r8.safetensors")
    with pytest.raises(ValueError, match=r"shapes differ \(e\.g\. .*lora_A.*: \[8, 24\] there, \[4, 24\] here\)") as e:
        _prior(rank=4).load_lora(r8)
    assert _one_line(e).startswith(f"LoRA weights {r8} ")


def test_a_truncated_lora_file_is_one_line_naming_it(lora_file, tmp_path):
    data = lora_file.read_bytes()
    (cut := tmp_path / "cut.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=rf"^LoRA weights {cut}: cannot read it \(.*\); the file is truncated") as e:
        _prior().load_lora(cut)
    _one_line(e)


def test_a_lora_path_with_a_tilde_is_expanded(lora_file, monkeypatch):
    monkeypatch.setenv("HOME", str(lora_file.parent))
    p = _prior()
    p.load_lora("~/lora.safetensors")
    assert all(torch.equal(load_file(str(lora_file))[k], v) for k, v in p.lora_state_dict().items())


@pytest.fixture
def sharded_wan(tmp_path):
    torch.manual_seed(0)
    vae, tr = WanVideoPrior.tiny_parts()
    root = tmp_path / "wan"
    vae.save_pretrained(root / "vae")
    tr.save_pretrained(root / "transformer", max_shard_size="20KB")
    assert list((root / "transformer").glob("*.index.json"))
    return root


def test_a_damaged_transformer_shard_index_names_the_folder_and_the_fix(sharded_wan, monkeypatch):
    """diffusers raised a bare JSONDecodeError ('Expecting property name ...'), naming no file."""
    monkeypatch.setenv("HOME", str(sharded_wan.parent))
    assert WanVideoPrior.from_pretrained("~/wan", block=1).source["dir"] == str(sharded_wan)  # ~ expanded
    index = next((sharded_wan / "transformer").glob("*.index.json"))
    index.write_text("{]")
    folder = sharded_wan / "transformer"
    with pytest.raises(OSError, match=rf"^Wan weights: cannot load {folder}: {index.name} is not valid JSON \(.*\); "
                                      r"copy transformer/ of the Diffusers-format Wan folder again$") as e:
        WanVideoPrior.from_pretrained(sharded_wan, block=1)
    _one_line(e)
