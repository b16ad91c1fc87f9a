import importlib.util

import pytest
import torch

from anycity.models import build_network
from anycity.models.video_prior import SmallVideoPrior, VideoPrior, WanVideoPrior, build_video_prior

needs_diffusers = pytest.mark.skipif(importlib.util.find_spec("diffusers") is None,
                                     reason="the 'wan' extra (diffusers) is not installed")


def test_small_prior_tokens():
    prior = SmallVideoPrior(dim=32, depth=1, num_heads=2, stride=16)
    assert isinstance(prior, VideoPrior)
    out = prior(torch.rand(2, 3, 3, 64, 32))
    assert out.shape == (2, 3 * 4 * 2, 32)
    # the view index is encoded: swapping two identical-content views changes nothing, distinct views differ
    x = torch.rand(1, 2, 3, 32, 32)
    assert not torch.allclose(prior(x), prior(x.flip(1)))
    # a side under the stride (a 20:1 strip photo's height) is resized up to it, as the Wan prior does: it was
    # refused as "SmallVideoPrior: images must be at least 16 px" after the checkpoint had loaded
    strip = torch.rand(1, 2, 3, 8, 216)
    assert prior(strip).shape == (1, 2 * 1 * 13, 32)
    up = torch.nn.functional.interpolate(strip[0], size=(16, 216), mode="bilinear", align_corners=False)
    assert torch.equal(prior(strip), prior(up[None]))


@pytest.mark.parametrize("dim, fix", [(65, 64), (1, 64), (200, 192)])
def test_a_small_prior_width_it_cannot_use_is_refused_at_build(dim, fix):
    """net.prior_dim 65 built, then the first forward was a bare 'size of tensor a (65) must match ... (64)' (the
    sin-cos frame embedding has 2 * (dim // 2) channels); 1 was a conv error, 200 an error naming 'Attention'."""
    with pytest.raises(ValueError, match=rf"^net.prior_dim: the small video prior needs an even width .*got {dim}; "
                                         rf"use a multiple of 64 \(e.g. {fix}\)$"):
        build_network("tiny", prior_dim=dim)
    assert build_network("tiny", prior_dim=66).video_prior.out_dim == 66  # even widths other than 64k still build


def test_build_video_prior_errors():
    with pytest.raises(ValueError, match="wan_dir"):
        build_video_prior("wan")
    with pytest.raises(ValueError, match="video_prior"):
        build_video_prior("sora")
    with pytest.raises(FileNotFoundError, match="config.json"):
        WanVideoPrior.from_pretrained("/nonexistent/wan")


@pytest.fixture(scope="module")
def wan():
    torch.manual_seed(0)
    prior = WanVideoPrior.tiny_random(block=1)
    prior.add_lora(rank=2)
    return prior


@needs_diffusers
def test_wan_prior_shapes_and_truncation(wan):
    assert len(wan.transformer.blocks) == 2  # cut after block 1
    out = wan(torch.rand(2, 3, 3, 64, 64))  # per-view single-frame latents: 3 frames of 4x4, 2x2 patches
    assert out.shape == (2, 3 * 2 * 2, wan.out_dim) and wan.out_dim == 24
    assert wan(torch.rand(1, 2, 3, 40, 70)).shape == (1, 2 * 1 * 2, 24)  # resized to multiples of 32


@needs_diffusers
def test_wan_lora_only_trains_and_roundtrips(wan, tmp_path):
    trainable = [n for n, p in wan.named_parameters() if p.requires_grad]
    assert trainable and all("lora_" in n for n in trainable)
    assert all(".attn1." in n for n in trainable)
    for p in wan.parameters():
        p.grad = None
    with torch.no_grad():  # make lora_B non-zero so lora_A also gets a gradient
        for n, p in wan.named_parameters():
            if "lora_B" in n:
                p.normal_(std=0.1)
    wan(torch.rand(1, 2, 3, 32, 32)).square().mean().backward()
    assert all(p.grad is None for n, p in wan.named_parameters() if "lora_" not in n)
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for n, p in wan.named_parameters() if "lora_A" in n)
    path = tmp_path / "lora.safetensors"
    wan.save_lora(path)
    saved = wan.lora_state_dict()
    assert all("lora_" in k for k in saved)
    torch.manual_seed(1)
    other = WanVideoPrior.tiny_random(block=1)
    other.add_lora(rank=2)
    other.load_lora(path)
    for k, v in other.lora_state_dict().items():
        assert torch.equal(v, saved[k]), k


@needs_diffusers
def test_wan_offline_folder_roundtrip(tmp_path):
    torch.manual_seed(0)
    prior = WanVideoPrior.tiny_random(block=3)
    prior.transformer.save_pretrained(tmp_path / "transformer")
    prior.vae.save_pretrained(tmp_path / "vae")
    torch.save(torch.zeros(1, 3, 32), tmp_path / "empty.pt")
    loaded = WanVideoPrior.from_pretrained(tmp_path, dtype=torch.float32, block=3,
                                           empty_prompt_path=tmp_path / "empty.pt")
    x = torch.rand(1, 2, 3, 32, 32)
    assert torch.allclose(loaded(x), prior(x), atol=1e-5)


@needs_diffusers
def test_network_with_wan_prior_trains_only_lora_and_completion():
    net = build_network("tiny", video_prior="wan-tiny", wan_block=1, wan_lora_rank=2)
    names = {n for n, p in net.named_parameters() if p.requires_grad and n.startswith("video_prior.")}
    assert names and all("lora_" in n for n in names)
    trainable = {id(p) for p in net.refinement_parameters()}
    assert all(id(p) in trainable for n, p in net.named_parameters() if n.startswith("completion."))
    out = net(torch.rand(1, 2, 3, 32, 32))
    assert len(out["gates"]) == len(net.completion.inject_layers)


@needs_diffusers
def test_wan_vae_encodes_one_view_at_a_time_without_a_decoder():
    # all B*V frames at once kept diffusers' causal-conv cache for every one (~16 GB at 64 views, 448 px, Wan 2.2),
    # and the never-run decoder took 2.2 GB on every GPU
    torch.manual_seed(0)
    prior = WanVideoPrior.tiny_random(block=1)
    assert prior.vae.use_slicing
    assert not any(n.startswith(("decoder.", "post_quant_conv.")) for n, _ in prior.vae.named_parameters())
    assert any(n.startswith("encoder.") for n, _ in prior.vae.named_parameters())
    seen = []
    hook = prior.vae.encoder.register_forward_pre_hook(lambda m, args: seen.append(args[0].shape[0]))
    x = torch.rand(2, 3, 3, 64, 64)
    sliced = prior(x)
    hook.remove()
    assert seen == [1] * 6  # one encoder pass per view
    prior.vae.use_slicing = False
    assert (sliced - prior(x)).abs().max() <= 1e-6
    with pytest.raises(RuntimeError, match="decoder was dropped"):
        prior.vae.decode(torch.zeros(1, 16, 1, 2, 2))


@needs_diffusers
def test_wan_feature_noise_repeats_in_eval_and_is_fresh_in_training():
    torch.manual_seed(0)
    prior = WanVideoPrior.tiny_random(block=1, t_feat=0.5).eval()
    x = torch.rand(1, 2, 3, 32, 32)
    torch.manual_seed(1)
    a = prior(x)
    torch.manual_seed(2)
    assert torch.equal(prior(x), a)  # test/predict give the same features run to run
    prior.train()
    torch.manual_seed(1)
    b = prior(x)
    torch.manual_seed(2)
    assert not torch.allclose(prior(x), b)
    torch.manual_seed(1)
    assert torch.equal(prior(x), b)  # training noise still comes from the global RNG, as before


@needs_diffusers
def test_lora_rank_0_builds_a_fully_frozen_prior_outside_the_refinement_parameters():
    """Rank 0 means no LoRA (not a peft error), the transformer stays frozen, and
    refinement_parameters() holds no frozen prior parameter."""
    torch.manual_seed(0)
    net = build_network("tiny", video_prior="wan-tiny", wan_block=1, wan_lora_rank=0)
    prior = [(n, p) for n, p in net.named_parameters() if n.startswith("video_prior.")]
    assert prior and not any(p.requires_grad for _, p in prior)
    trainable = {id(p) for p in net.refinement_parameters()}
    assert not any(id(p) in trainable for _, p in prior)
    torch.manual_seed(0)
    net = build_network("tiny", video_prior="wan-tiny", wan_block=1, wan_lora_rank=2)
    frozen = [p for n, p in net.named_parameters() if n.startswith("video_prior.") and not p.requires_grad]
    assert frozen and not any(id(p) in {id(q) for q in net.refinement_parameters()} for p in frozen)


@needs_diffusers
def test_lora_sits_on_the_four_self_attention_projections_of_every_kept_block(wan):
    """LoRA on to_q, to_k, to_v and to_out.0 of attn1, in each of the kept blocks."""
    got = {n.split(".lora_A")[0] for n, _ in wan.transformer.named_parameters() if ".lora_A." in n}
    want = {f"blocks.{b}.attn1.{t}" for b in range(len(wan.transformer.blocks))
            for t in ("to_q", "to_k", "to_v", "to_out.0")}
    assert got == want


@needs_diffusers
def test_lora_scaling_is_one_by_default(wan):
    """Alpha defaults to the rank (2 here), so every adapter's scaling alpha / r is 1."""
    scalings = [m.scaling for _, m in wan.transformer.named_modules() if isinstance(getattr(m, "scaling", None), dict)]
    assert len(scalings) == 4 * len(wan.transformer.blocks)
    assert all(s == {"default": 1.0} for s in scalings)


@needs_diffusers
def test_the_vae_encoder_sees_images_mapped_to_minus_one_one():
    """Images in [0, 1] reach the VAE as 2x - 1."""
    torch.manual_seed(0)
    prior = WanVideoPrior.tiny_random(block=1)
    seen = []
    hook = prior.vae.encoder.register_forward_pre_hook(lambda m, args: seen.append(args[0].detach().clone()))
    prior(torch.cat([torch.zeros(1, 1, 3, 32, 32), torch.ones(1, 1, 3, 32, 32)], dim=1))
    hook.remove()
    assert len(seen) == 2
    assert torch.equal(seen[0], torch.full_like(seen[0], -1.0)) and torch.equal(seen[1], torch.ones_like(seen[1]))


@needs_diffusers
def test_the_transformer_gets_timestep_1000_s_and_normalised_latents():
    """The timestep is 1000 t_feat, the latents (z - mean) / std."""
    torch.manual_seed(0)
    vae, tr = WanVideoPrior.tiny_parts()
    vae.register_to_config(latents_mean=[0.5] * 16, latents_std=[2.0] * 16)
    prior = WanVideoPrior(vae, tr, block=1, t_feat=0.25).eval()
    seen = {}
    hook = prior.transformer.register_forward_pre_hook(lambda m, a, kw: seen.update(kw), with_kwargs=True)
    x = torch.rand(1, 2, 3, 32, 32)
    prior(x)
    hook.remove()
    assert torch.equal(seen["timestep"], torch.full((1,), 250.0))
    with torch.no_grad():
        z = prior.vae.encode((x.flatten(0, 1) * 2 - 1)[:, :, None]).latent_dist.mode()
    z = ((z - 0.5) / 2.0)[:, :, 0].unflatten(0, (1, 2)).transpose(1, 2)
    z = 0.75 * z + 0.25 * prior._noise(z)
    assert torch.allclose(seen["hidden_states"], z, atol=1e-5)
