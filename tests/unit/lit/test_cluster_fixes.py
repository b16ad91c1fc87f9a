"""What a cluster run would hit first (issue 13 item 4): float32 LoRA on a bf16 Wan prior, the dtype the Wan
loader asks for, checkpoints that reference the frozen prior by content hash, init_from checked when fitting
starts, the Stage I checkpoint read memory-mapped, no completion branch in Stage I, the AnySplat focal decode,
the loud gsplat fallback warning."""

import importlib.util
import math
import warnings
from types import SimpleNamespace

import pytest
import torch

from anycity.geometry.pose_encoding import extri_intri_to_pose_encoding, pose_encoding_to_extri_intri
from anycity.lit import RefinementModule, ScaffoldModule
from anycity.models import build_network

needs_diffusers = pytest.mark.skipif(importlib.util.find_spec("diffusers") is None,
                                     reason="the 'wan' extra (diffusers) is not installed")


@pytest.fixture(autouse=True)
def _hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # folder_hash's cache, not the user's


@pytest.fixture(scope="module")
def wan_dir(tmp_path_factory):
    """A tiny random Wan 2.2-style prior saved in the Diffusers layout (transformer/, vae/) + empty_prompt.pt."""
    from anycity.models.video_prior import WanVideoPrior

    torch.manual_seed(0)
    prior = WanVideoPrior.tiny_random(block=3)  # keep all 4 blocks so the saved transformer is complete
    root = tmp_path_factory.mktemp("wan")
    prior.transformer.save_pretrained(root / "transformer")
    prior.vae.save_pretrained(root / "vae")
    torch.save(torch.randn(1, 3, 32), root / "empty_prompt.pt")
    return root


@needs_diffusers
def test_wan_loads_in_the_asked_dtype_with_float32_lora_and_middle_block(wan_dir):
    from anycity.models.video_prior import WanVideoPrior

    prior = WanVideoPrior.from_pretrained(wan_dir, dtype=torch.bfloat16)
    assert prior.block == 1 and len(prior.transformer.blocks) == 2  # None: the middle of 4 blocks
    assert prior.empty_prompt.shape == (1, 3, 32)  # picked up from <wan_dir>/empty_prompt.pt
    dtypes = [p.dtype for n, p in prior.transformer.named_parameters()
              if n.endswith(("to_q.weight", "ffn.net.2.weight"))]
    assert dtypes and set(dtypes) == {torch.bfloat16}  # (diffusers keeps some norm/time modules in float32)
    assert {p.dtype for p in prior.vae.parameters()} == {torch.float32}
    assert len(prior.content_hash()) == 64
    prior.add_lora(rank=2)
    lora = {n: p for n, p in prior.transformer.named_parameters() if "lora_" in n}
    assert lora and all(p.dtype == torch.float32 and p.requires_grad for p in lora.values())
    assert all(not p.requires_grad for n, p in prior.transformer.named_parameters() if "lora_" not in n)
    # a small update survives in float32; the same update on a bf16 copy rounds away
    a = next(p for n, p in lora.items() if "lora_A" in n)
    before = a.detach().clone()
    with torch.no_grad():
        a.add_(1e-6 * before.abs().max())
    assert not torch.equal(a, before)
    bf = before.bfloat16()
    assert torch.equal(bf + (1e-6 * before.abs().max()).bfloat16(), bf)
    out = prior(torch.rand(1, 2, 3, 32, 32))
    assert out.dtype == torch.float32 and torch.isfinite(out).all()


@needs_diffusers
def test_checkpoint_references_frozen_prior_by_hash_and_keeps_lora(wan_dir, tmp_path):
    import shutil

    net = {"video_prior": "wan", "wan_dir": str(wan_dir), "wan_lora_rank": 2}
    m = RefinementModule(preset="tiny", net=net)
    ckpt = {"state_dict": m.state_dict()}
    full = len(ckpt["state_dict"])
    m.on_save_checkpoint(ckpt)
    keys = ckpt["state_dict"].keys()
    assert not any(k.startswith(("net.video_prior.vae.", "net.video_prior.transformer.")) and "lora_" not in k
                   for k in keys)
    assert any("lora_A" in k for k in keys) and any(k.startswith("net.completion.") for k in keys)
    assert len(keys) < full and ckpt["video_prior"]["sha256"] == m.net.video_prior.content_hash()

    fresh = RefinementModule(preset="tiny", net=net)
    fresh.on_load_checkpoint(ckpt)
    fresh.load_state_dict(ckpt["state_dict"], strict=True)  # the frozen weights came from the folder
    for k, v in m.state_dict().items():
        torch.testing.assert_close(fresh.state_dict()[k], v, msg=k)

    other = tmp_path / "wan_other"
    shutil.copytree(wan_dir, other)
    (other / "vae" / "config.json").write_text((other / "vae" / "config.json").read_text() + "\n")
    moved = RefinementModule(preset="tiny", net={**net, "wan_dir": str(other)})
    with pytest.raises(ValueError, match="Wan prior mismatch"):
        moved.on_load_checkpoint({"state_dict": {}, "video_prior": dict(ckpt["video_prior"])})


@needs_diffusers
def test_a_checkpoint_trained_on_another_wan_block_is_refused_in_one_line(wan_dir):
    """The same Wan folder cut at another block: its LoRA and completion branch were trained on other features."""
    recut = RefinementModule(preset="tiny", net={"video_prior": "wan", "wan_dir": str(wan_dir), "wan_block": 1})
    ref = {"dir": str(wan_dir), "sha256": recut.net.video_prior.content_hash(), "block": 2}  # as saved at block 2
    with pytest.raises(ValueError, match=r"^checkpoint: trained on Wan block 2, this module cuts at block 1; set "
                                         r"net.wan_block=2$"):
        recut.on_load_checkpoint({"state_dict": {}, "video_prior": ref})


@needs_diffusers
def test_an_old_checkpoint_with_the_dropped_vae_decoder_still_loads_strictly(wan_dir):
    """Checkpoints saved before the Wan VAE decoder was dropped carry its keys; loading forgets them."""
    net = {"video_prior": "wan", "wan_dir": str(wan_dir), "wan_lora_rank": 2}
    m = RefinementModule(preset="tiny", net=net)
    ckpt = {"state_dict": m.state_dict()}
    m.on_save_checkpoint(ckpt)
    old = ("net.video_prior.vae.decoder.conv_in.weight", "net.video_prior.vae.post_quant_conv.bias")
    ckpt["state_dict"].update({k: torch.zeros(2) for k in old})
    fresh = RefinementModule(preset="tiny", net=net)
    fresh.on_load_checkpoint(ckpt)
    assert not set(old) & set(ckpt["state_dict"])
    fresh.load_state_dict(ckpt["state_dict"], strict=True)


def test_init_from_is_checked_when_fitting_starts_not_at_construction(tmp_path):
    m = RefinementModule(preset="tiny", init_from=str(tmp_path / "missing.ckpt"))  # test/predict: fine
    m._trainer = SimpleNamespace(ckpt_path=None, strategy=SimpleNamespace(restore_checkpoint_after_setup=False))
    m.setup("test")
    m.setup("predict")
    m.setup("fit")
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        m.on_fit_start()


def test_stage1_checkpoint_is_read_memory_mapped_tensors_only(tmp_path, monkeypatch):
    s1 = ScaffoldModule(preset="tiny", net={"focal_decode": "anysplat"})
    path = tmp_path / "s1.ckpt"
    torch.save({"state_dict": s1.state_dict(), "optimizer_states": [{"state": {0: torch.zeros(3)}}],
                "hyper_parameters": dict(s1.hparams)}, path)
    calls = []
    real = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: calls.append(k) or real(*a, **k))
    s2 = RefinementModule(preset="tiny")
    s2.load_stage1(str(path))
    assert calls and calls[0].get("mmap") is True and calls[0].get("weights_only") is True
    torch.testing.assert_close(s2.net.aggregator.camera_token, s1.net.aggregator.camera_token)
    assert s2.net.cfg.focal_decode == "anysplat" and s2.hparams.net["focal_decode"] == "anysplat"


def test_a_stage1_checkpoint_that_does_not_fit_the_scaffold_is_one_line_not_random_frozen_blocks(tmp_path):
    """Stage II with a deeper scaffold than its Stage I checkpoint loaded the checkpoint with strict=False and kept
    the extra blocks random (and frozen); another SH degree gave a many-line size-mismatch traceback. Now any
    missing, unexpected or misshapen scaffold weight is one line; only the later centre offset may be absent."""
    s1 = ScaffoldModule(preset="tiny")
    path = tmp_path / "s1.ckpt"
    torch.save({"state_dict": s1.state_dict()}, path)
    cases = (({"camera_trunk_depth": 2}, "scaffold weights of this network are not in it .*camera_head.trunk.1"),
             ({"depth": 3, "head_layers": (0, 1, 2, 2)}, "of its keys are not in this network .*aggregator."
                                                         "frame_blocks.3"),
             ({"sh_degree": 2}, "shapes differ .*gaussian_head.scratch.output_conv2.2.weight: \\[21, "))
    for net, what in cases:
        with pytest.raises(ValueError, match=f"model.init_from: .*s1.ckpt does not fit .*{what}") as e:
            RefinementModule(preset="tiny", net=net).load_stage1(str(path))
        assert "\n" not in str(e.value)
    # a Stage I checkpoint from before the centre offset: loads, and the offset stays zero (what it decoded)
    old = {k: v for k, v in s1.state_dict().items() if ".offset_conv." not in k}
    torch.save({"state_dict": old}, path)
    s2 = RefinementModule(preset="tiny")
    s2.load_stage1(str(path))
    torch.testing.assert_close(s2.net.depth_head.state_dict(), s1.net.depth_head.state_dict())
    assert not s2.net.gaussian_head.offset_conv.weight.any() and not s2.net.gaussian_head.offset_conv.bias.any()


def test_stage1_builds_no_completion_branch():
    m = ScaffoldModule(preset="tiny")
    assert m.net.completion is None and m.net.video_prior is None
    assert not any(n.startswith(("net.completion.", "net.video_prior.")) for n, _ in m.named_parameters())
    with pytest.raises(ValueError, match="completion"):
        ScaffoldModule(preset="tiny", net={"completion": True})


def test_anysplat_focal_decode_and_its_inverse():
    enc = torch.tensor([0.1, 0.2, 0.3, 0.0, 0.0, 0.0, 1.0, 1.0, 1.2])
    _, K_v = pose_encoding_to_extri_intri(enc, (448, 448))
    _, K_a = pose_encoding_to_extri_intri(enc, (448, 448), "anysplat")
    assert K_v[1, 1].item() == pytest.approx(448 / (2 * math.tan(0.5)), rel=1e-6)
    assert K_a[1, 1].item() == pytest.approx(224 / (math.tan(0.5) + 1e-3), rel=1e-6)
    assert 1e-3 < (K_v[1, 1] / K_a[1, 1] - 1).item() < 3e-3  # "about 2e-3 relative in K"
    w2c = torch.eye(4)
    back = extri_intri_to_pose_encoding(w2c, K_a, (448, 448), "anysplat")
    torch.testing.assert_close(back[7:], enc[7:], atol=1e-5, rtol=0)


def test_load_pretrained_anysplat_records_the_decode_in_net_and_hparams(tmp_path):
    from anycity.models.pretrained import load_pretrained

    src = build_network("tiny", completion=False)
    net = build_network("tiny", completion=False)
    load_pretrained(net, {f"encoder.{k}": v for k, v in src.state_dict().items()}, kind="anysplat")
    assert net.cfg.focal_decode == "anysplat"
    path = tmp_path / "anysplat.pt"
    torch.save({f"encoder.{k}": v for k, v in src.state_dict().items()}, path)
    m = ScaffoldModule(preset="tiny", pretrained=str(path), pretrained_kind="anysplat")
    assert m.net.cfg.focal_decode == "anysplat" and m.hparams.net["focal_decode"] == "anysplat"


def test_auto_backend_on_cuda_without_gsplat_warns_once(monkeypatch):
    from anycity.render import api

    monkeypatch.setattr(api, "_module_available", lambda name: False)
    api._warn_no_gsplat.cache_clear()
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert api.resolve_backend("auto", torch.device("cuda")) == "torch"
        assert api.resolve_backend("auto", torch.device("cuda")) == "torch"
    msgs = [str(x.message) for x in w if "FALLING BACK" in str(x.message)]
    assert len(msgs) == 1


def test_sim3_fit_of_non_finite_cameras_falls_back_to_identity_instead_of_raising():
    from anycity.lit.evaluation import fit_gt_to_pred

    gt = torch.eye(4).repeat(2, 3, 1, 1)
    gt[:, :, 0, 3] = torch.tensor([0.0, 0.5, 1.0])
    pred = gt.clone()
    pred[1] = float("nan")  # one scene's predicted cameras are NaN (a NaN batch on one DDP rank)
    s, R, t = fit_gt_to_pred(pred, gt, "sim3")
    assert s[1] == 1 and torch.equal(R[1], torch.eye(3)) and torch.equal(t[1], torch.zeros(3))
    assert torch.isfinite(s).all() and abs(s[0].item() - 1) < 1e-4


def test_a_non_finite_forward_gives_a_nan_loss_reaching_every_trainable_parameter_instead_of_raising():
    # (NaN images are refused by the network's input check; an overflow inside the network is what remains)
    from anycity.geometry import make_intrinsics
    from anycity.structures import ViewBatch, Views

    def views(n):
        w2c = torch.eye(4).repeat(1, n, 1, 1)
        w2c[..., 0, 3] = torch.linspace(0, 0.3, n)
        K = make_intrinsics(30.0, 30.0, 16.0, 16.0).expand(1, n, 3, 3).clone()
        return Views(images=torch.full((1, n, 3, 32, 32), 0.5), w2c=w2c, K=K)

    m = ScaffoldModule(preset="tiny", render_backend="torch")
    m.log = lambda *a, **k: None
    with torch.no_grad():
        m.net.aggregator.camera_token.fill_(float("inf"))  # every token non-finite after the first attention
    loss = m.training_step(ViewBatch(context=views(2), target=views(1)), 0)  # the renderer would raise on NaN
    assert torch.isnan(loss)
    loss.backward()
    assert all(p.grad is not None for p in m.parameters() if p.requires_grad)  # DDP's reducer sees every param


def test_stage1_loads_an_older_checkpoint_that_still_has_a_completion_branch():
    old = build_network("tiny")  # completion branch built, as Stage I did before
    ckpt = {"state_dict": {f"net.{k}": v for k, v in old.state_dict().items()}}
    m = ScaffoldModule(preset="tiny")
    m.on_load_checkpoint(ckpt)
    m.load_state_dict(ckpt["state_dict"], strict=True)
    torch.testing.assert_close(m.net.aggregator.camera_token, old.aggregator.camera_token)


def test_pretrained_lr_scale_applies_to_pretrained_weights_only_and_patterns_must_match(tmp_path):
    """stage1.yaml's pretrained_patterns slowed the backbone to 0.1x the LR even when it trained from random init
    (pretrained: null), with nothing said; a typo in a pattern silently left the pretrained layers at the full
    rate."""
    from types import SimpleNamespace

    from anycity.models import build_network

    def lrs(m):
        m._trainer = SimpleNamespace(max_steps=10)
        opt = m.configure_optimizers()["optimizer"]
        return sorted({(g["initial_lr"], any(p is m.net.aggregator.camera_token for p in g["params"]))
                       for g in opt.param_groups})

    pats = ["aggregator.*", "camera_head.*"]
    scratch = ScaffoldModule(preset="tiny", lr=1e-3, pretrained_patterns=pats)
    assert {lr for lr, _ in lrs(scratch)} == {1e-3}
    path = tmp_path / "model.pt"
    torch.save(build_network("tiny", completion=False).state_dict(), path)
    tuned = ScaffoldModule(preset="tiny", lr=1e-3, pretrained=str(path), pretrained_patterns=pats)
    assert [lr for lr, agg in lrs(tuned) if agg] == [pytest.approx(1e-4)]  # the backbone's group: 0.1x
    assert len(tuned.configure_optimizers()["optimizer"].param_groups) == len(
        scratch.configure_optimizers()["optimizer"].param_groups)  # same groups: a resumed run's state fits
    with pytest.raises(ValueError, match="pretrained_patterns: 'net.agregator.\\*' matches no parameter"):
        lrs(ScaffoldModule(preset="tiny", pretrained_patterns=["agregator.*"]))


def test_adamw_is_fused_in_full_precision_and_foreach_under_mixed_precision():
    """Full precision steps with torch's fused AdamW (about 20 ms less per quickstart step on 2 cores). Under mixed
    precision Lightning refuses to clip gradients for an optimiser that unscales inside its step, so foreach stays,
    also for a resumed optimiser whose checkpoint came from a fused run (torch restores the saved flags)."""
    def optimiser(m, precision):
        m._trainer = SimpleNamespace(max_steps=10, precision=precision)
        return m.configure_optimizers()["optimizer"]

    def kernels(opt):
        return {(bool(g["fused"]), bool(g["foreach"])) for g in opt.param_groups}

    m = ScaffoldModule(preset="tiny")
    fused = optimiser(m, "32-true")
    assert kernels(fused) == {(True, False)}
    mixed = optimiser(m, "bf16-mixed")
    assert kernels(mixed) == {(False, True)}
    mixed.load_state_dict(fused.state_dict())
    assert kernels(mixed) == {(True, False)}
    m._trainer.optimizers = [mixed]
    m.on_train_start()
    assert kernels(mixed) == {(False, True)}
    for p in m.parameters():
        p.grad = torch.ones_like(p)
    mixed.step()  # the flipped groups step with foreach


@pytest.mark.parametrize("cls, precision", [(ScaffoldModule, "64"), (ScaffoldModule, "bf16-true"),
                                            (RefinementModule, "16-true")])
def test_a_precision_that_casts_the_whole_module_is_refused_in_one_line(cls, precision):
    """Lightning's "*-true" precisions other than 32-true cast every weight and input; the heads, losses and
    renderer run in float32, so the first step failed with a dtype traceback (and 64-true was listed as a fused
    AdamW precision). Refused when the trainer sets the module up, before it is cast."""
    import lightning.pytorch as pl

    from anycity.lit.base import FUSED_ADAMW_PRECISIONS

    trainer = pl.Trainer(precision=precision, accelerator="cpu", max_steps=1, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False)
    name = trainer.precision  # "64" reads "64-true"
    with pytest.raises(ValueError, match=f"^trainer.precision {name}: the heads, losses and renderer run in float32; "
                                         "use bf16-mixed \\(GPU\\) or 32-true$"):
        trainer.fit(cls(preset="tiny"), train_dataloaders=torch.utils.data.DataLoader([0]))
    assert "64-true" not in FUSED_ADAMW_PRECISIONS
    m = cls(preset="tiny")
    for ok in ("32-true", "bf16-mixed", "16-mixed"):
        m._trainer = SimpleNamespace(precision=ok, ckpt_path=None,
                                     strategy=SimpleNamespace(restore_checkpoint_after_setup=False))
        m.setup("test")


class _Stream(torch.utils.data.IterableDataset):
    """A stream with no length, as the shard pipeline: Lightning cannot count its batches."""

    def __iter__(self):
        yield from (torch.zeros(1) for _ in range(3))


def _zero_loss(module, batch, batch_idx):
    return sum(p.sum() for p in module.parameters() if p.requires_grad) * 0.0


@pytest.mark.parametrize("cls", ["ScaffoldModule", "PosePriorModule"])
@pytest.mark.parametrize("max_epochs", [2, -1])
def test_the_lr_schedule_is_sized_by_max_steps_and_refuses_a_run_ended_by_epochs(cls, max_epochs, monkeypatch):
    """The schedule's length came from Lightning's estimated_stepping_batches, which for a stream with no length is
    max_steps: -1 under ``--trainer.max_steps -1 --trainer.max_epochs N`` (the cosine dropped to its floor right after
    warm-up, silently) and int(inf), a traceback, under max_epochs -1. Now it is max_steps, refused in one line when
    unset."""
    import lightning.pytorch as pl

    from anycity.lit.pose_prior import PosePriorModule

    module_cls = {"ScaffoldModule": ScaffoldModule, "PosePriorModule": PosePriorModule}[cls]
    monkeypatch.setattr(module_cls, "training_step", _zero_loss)
    module = module_cls(preset="tiny") if cls == "ScaffoldModule" else module_cls()

    def fit(max_steps):
        trainer = pl.Trainer(max_steps=max_steps, max_epochs=max_epochs, accelerator="cpu", logger=False,
                             enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)
        trainer.fit(module, train_dataloaders=torch.utils.data.DataLoader(_Stream(), batch_size=1))
        return trainer

    with pytest.raises(ValueError, match=r"^trainer.max_steps is -1: the LR schedule is sized by it \(the shard "
                                         r"stream has no length, so max_epochs cannot size it\); set "
                                         r"--trainer.max_steps N$"):
        fit(-1)
    trainer = fit(5)  # ends with max_epochs 2 (6 samples) or max_steps: the schedule spans max_steps either way
    sched = trainer.lr_scheduler_configs[0].scheduler
    if cls == "ScaffoldModule":
        total = dict(zip(sched.lr_lambdas[0].__code__.co_freevars,
                         (c.cell_contents for c in sched.lr_lambdas[0].__closure__)))["total"]
    else:
        total = sched.total_steps
    assert total == 5


def test_the_pose_prior_rre_is_gathered_by_every_rank_even_one_without_evaluation_samples(monkeypatch):
    """``self.log(..., sync_dist=True)`` in the step leaves a rank that held no validation sample out of the
    epoch-end reduction (the others then wait in it forever); every rank now joins one all-gather of (sum, count)."""
    from types import SimpleNamespace

    from anycity.lit.pose_prior import PosePriorModule
    from anycity.structures import ViewBatch

    m = PosePriorModule()
    logged, gathered = {}, []
    monkeypatch.setattr(m, "log", lambda name, value, **k: logged.__setitem__(name, float(value)))
    other_rank = torch.tensor([3.0 * 2, 2.0])  # two samples at a mean error of 3 degrees
    monkeypatch.setattr(m, "all_gather", lambda t: gathered.append(t) or torch.stack([t, other_rank]))
    m._trainer = SimpleNamespace(world_size=2)
    m.on_validation_epoch_start()  # this rank gets no batch
    m.on_validation_epoch_end()
    assert len(gathered) == 1 and logged == {"val/rre": pytest.approx(3.0)}

    m._trainer, logged = SimpleNamespace(world_size=1), {}
    w2c = torch.eye(4).repeat(1, 3, 1, 1)
    w2c[:, 1:, 0, 3] = torch.tensor([0.5, 1.0])
    batch = ViewBatch(context=SimpleNamespace(images=torch.rand(1, 3, 3, 32, 32), w2c=w2c), target=None)
    from anycity.metrics.pose import relative_pose_errors

    with torch.no_grad():  # as Lightning runs test_step
        m.on_test_epoch_start()
        m.test_step(batch, 0)
        m.on_test_epoch_end()
        expected = float(relative_pose_errors(m.net(batch.context.images), w2c)[0].mean())
    assert logged["test/rre"] == pytest.approx(expected)
    logged.clear()
    m.on_test_epoch_start()
    m.on_test_epoch_end()  # no rank had a sample: nothing logged
    assert logged == {}


def test_auto_backend_on_cuda_with_a_gsplat_without_kernels_falls_back_and_gsplat_is_one_line(monkeypatch):
    """gsplat 1.x imports without its CUDA kernels (no wheel for this torch, no nvcc) and sets ``_C = None``: 'auto'
    chose it and the first render died with "'NoneType' object has no attribute ..."."""
    import sys
    import types

    from anycity.render import api

    stub = {name: types.ModuleType(name) for name in ("gsplat", "gsplat.cuda", "gsplat.cuda._backend")}
    stub["gsplat.cuda._backend"]._C = None
    for name, module in stub.items():
        monkeypatch.setitem(sys.modules, name, module)
    for f in (api._module_available, api._gsplat_kernels, api._warn_gsplat_without_kernels):
        f.cache_clear()
    try:
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            assert api.resolve_backend("auto", torch.device("cuda")) == "torch"
            assert api.resolve_backend("auto", torch.device("cuda")) == "torch"
        assert len([x for x in w if "without its CUDA kernels" in str(x.message)]) == 1
        with pytest.raises(ValueError, match=r"^backend='gsplat': gsplat is installed without its CUDA kernels"):
            api._load("gsplat")
        stub["gsplat.cuda._backend"]._C = object()  # kernels present
        api._gsplat_kernels.cache_clear()
        assert api.resolve_backend("auto", torch.device("cuda")) == "gsplat"
    finally:
        for f in (api._module_available, api._gsplat_kernels, api._warn_gsplat_without_kernels):
            f.cache_clear()


def test_adamw_betas_and_weight_decay_groups_follow_the_documented_defaults():
    """AdamW betas (0.9, 0.95), weight decay 0.05 on matrices only: biases, norms and every other tensor of fewer
    than 2 dimensions (LayerScale gammas, tokens' scales) get none; the cosine ends at min_lr_ratio 0.1."""
    m = ScaffoldModule(warmup_steps=2)
    assert (m.hparams.weight_decay, m.hparams.min_lr_ratio) == (0.05, 0.1)
    m._trainer = SimpleNamespace(max_steps=10, precision="32-true")
    cfg = m.configure_optimizers()
    opt = cfg["optimizer"]
    decay_of = {id(p): g["weight_decay"] for g in opt.param_groups for p in g["params"]}
    assert all(g["betas"] == (0.9, 0.95) for g in opt.param_groups)
    named = [(n, p) for n, p in m.named_parameters() if p.requires_grad]
    assert any(p.ndim < 2 and "norm" not in n and not n.endswith(".bias") for n, p in named)  # e.g. gammas
    for n, p in named:
        no_decay = p.ndim < 2 or "norm" in n or n.endswith(".bias")
        assert decay_of[id(p)] == (0.0 if no_decay else 0.05), n
    assert cfg["lr_scheduler"]["scheduler"].lr_lambdas[0](10) == pytest.approx(0.1)


def test_a_metric_updated_on_any_rank_is_reported_by_every_rank():
    """The flags of the ranks are OR-ed: a metric only another rank updated is still computed and logged."""
    from anycity.lit.distributed import updated_anywhere

    mod = SimpleNamespace(device=torch.device("cpu"), _trainer=SimpleNamespace(world_size=2),
                          all_gather=lambda t: torch.stack([t, torch.tensor([0.0, 1.0])]))
    mets = {"a": SimpleNamespace(update_called=True), "b": SimpleNamespace(update_called=False)}
    assert updated_anywhere(mod, mets) == ["a", "b"]
