"""WanVideoPrior.from_pretrained on incomplete folders and bad empty-prompt files, checkpoints without the VAE
decoder (old ones with it still load), and the folder hash's cache written atomically."""

import importlib.util
import json
import shutil

import pytest
import torch

from anycity.models.video_prior import WanVideoPrior, folder_hash

pytestmark = pytest.mark.skipif(importlib.util.find_spec("diffusers") is None,
                                reason="the 'wan' extra (diffusers) is not installed")
WEIGHTS = "diffusion_pytorch_model.safetensors"


@pytest.fixture(autouse=True)
def _hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # folder_hash's cache, not the user's


@pytest.fixture
def wan_dir(tmp_path):
    """A whole tiny random Wan (VAE decoder and all 4 blocks) in the Diffusers layout."""
    torch.manual_seed(0)
    vae, tr = WanVideoPrior.tiny_parts()
    root = tmp_path / "wan"
    tr.save_pretrained(root / "transformer")
    vae.save_pretrained(root / "vae")
    return root


def _drop_keys(file, prefix: str) -> int:
    from safetensors.torch import load_file, save_file

    sd = load_file(file)
    save_file({k: v for k, v in sd.items() if not k.startswith(prefix)}, file)
    return sum(k.startswith(prefix) for k in sd)


@pytest.mark.parametrize("sub", ["transformer", "vae"])
def test_a_folder_without_weights_names_the_subfolder(wan_dir, sub):
    (wan_dir / sub / WEIGHTS).unlink()
    with pytest.raises(FileNotFoundError, match=rf"^Wan weights: no diffusion_pytorch_model\*\.safetensors in "
                                                rf"\S*wan/{sub}; copy {sub}/ of the Diffusers-format Wan folder"):
        WanVideoPrior.from_pretrained(wan_dir, dtype=torch.float32)


def test_missing_weights_are_refused_naming_the_folder_and_keys(wan_dir):
    n = _drop_keys(wan_dir / "transformer" / WEIGHTS, "blocks.0.attn1.")
    with pytest.raises(ValueError, match=rf"^Wan weights: \S*wan/transformer lacks {n} of the WanTransformer3DModel "
                                         r"weights \(e\.g\. \['blocks\.0\.attn1\..*copy transformer/ of the"):
        WanVideoPrior.from_pretrained(wan_dir, block=1, dtype=torch.float32)


def test_missing_vae_encoder_weights_are_refused_but_a_missing_decoder_is_fine(wan_dir):
    _drop_keys(wan_dir / "vae" / WEIGHTS, "decoder.")
    _drop_keys(wan_dir / "vae" / WEIGHTS, "post_quant_conv.")
    prior = WanVideoPrior.from_pretrained(wan_dir, block=1, dtype=torch.float32)  # the prior never decodes
    assert torch.isfinite(prior(torch.rand(1, 2, 3, 32, 32))).all()
    assert _drop_keys(wan_dir / "vae" / WEIGHTS, "encoder.conv_in.") == 2
    with pytest.raises(ValueError, match=r"wan/vae lacks 2 of the AutoencoderKLWan weights"):
        WanVideoPrior.from_pretrained(wan_dir, block=1, dtype=torch.float32)


def test_empty_prompt_file_is_validated(wan_dir, tmp_path):
    embeds = torch.randn(1, 5, 32)
    f = tmp_path / "prompt.pt"
    for obj in (embeds, embeds[0], (embeds, torch.randn(1, 5, 32)), (embeds, None)):  # encode_prompt's pair: first
        torch.save(obj, f)
        prior = WanVideoPrior.from_pretrained(wan_dir, block=1, dtype=torch.float32, empty_prompt_path=f)
        assert torch.equal(prior.empty_prompt, embeds)
    for obj, got in ((torch.randn(1, 5, 64), r"\[1, 5, 64\]"), (torch.randn(2, 5, 32), r"\[2, 5, 32\]"),
                     (torch.zeros(1, 0, 32), r"\[1, 0, 32\]"), ({"embeds": embeds}, "dict"),
                     (torch.full((1, 5, 32), float("nan")), r"\[1, 5, 32\] torch.float32 with non-finite values")):
        torch.save(obj, f)
        with pytest.raises(ValueError, match=rf"^empty prompt file \S*prompt\.pt: expected the umT5 embedding of '' as "
                                             rf"a finite \[1, L, 32\] float tensor \(torch\.save\), got {got}.*; save"):
            WanVideoPrior.from_pretrained(wan_dir, block=1, dtype=torch.float32, empty_prompt_path=f)


def _no_decoder_keys(sd) -> bool:
    return not any(k.startswith(("net.video_prior.vae.decoder.", "net.video_prior.vae.post_quant_conv.")) for k in sd)


def test_checkpoints_of_a_folder_prior_drop_and_restore_without_the_decoder(wan_dir):
    from anycity.lit import RefinementModule

    net = {"video_prior": "wan", "wan_dir": str(wan_dir), "wan_lora_rank": 2}
    m = RefinementModule(preset="tiny", net=net)
    assert _no_decoder_keys(m.state_dict())
    ckpt = {"state_dict": m.state_dict()}
    m.on_save_checkpoint(ckpt)
    fresh = RefinementModule(preset="tiny", net=net)
    fresh.on_load_checkpoint(ckpt)
    fresh.load_state_dict(ckpt["state_dict"], strict=True)
    for k, v in m.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[k], v, msg=k)


def test_a_wan_tiny_checkpoint_saved_with_the_decoder_still_loads():
    from diffusers import AutoencoderKLWan

    from anycity.lit import RefinementModule

    net = {"video_prior": "wan-tiny", "wan_lora_rank": 2}
    torch.manual_seed(0)
    m = RefinementModule(preset="tiny", net=net)
    ckpt = {"state_dict": m.state_dict()}
    m.on_save_checkpoint(ckpt)  # a random prior is saved whole, now without the decoder
    assert _no_decoder_keys(ckpt["state_dict"])
    whole = AutoencoderKLWan.from_config(m.net.video_prior.vae.config).state_dict()
    old = {f"net.video_prior.vae.{k}": v for k, v in whole.items() if k.startswith(("decoder.", "post_quant_conv."))}
    assert old
    ckpt["state_dict"].update(old)  # as checkpoints saved before the decoder was dropped carry it
    fresh = RefinementModule(preset="tiny", net=net)
    fresh.on_load_checkpoint(ckpt)
    fresh.load_state_dict(ckpt["state_dict"], strict=True)
    for k, v in m.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[k], v, msg=k)


def test_folder_hash_replaces_its_cache_file_whole(wan_dir, tmp_path):
    # DDP ranks hash and write the table at once: a reader must see the old table or the new one, never a part
    cache = tmp_path / "cache" / "anycity" / "folder_hash.json"
    cache.parent.mkdir(parents=True)
    before = {"/elsewhere": {"key": [], "sha256": "0" * 64}}
    cache.write_text(json.dumps(before))
    with open(cache) as reader:  # opened before the write: still the whole old table
        sha = folder_hash(wan_dir)
        assert json.loads(reader.read()) == before
    table = json.loads(cache.read_text())
    assert table[str(wan_dir.resolve())]["sha256"] == sha and "/elsewhere" in table
    assert not [p for p in cache.parent.iterdir() if p.name != cache.name]  # no temp file left
    shutil.rmtree(wan_dir / "vae")
    assert folder_hash(wan_dir) != sha
