"""Stage I / Stage II LightningModules on a constructed batch (tiny preset, 32x32 images)."""

import warnings

import pytest
import torch
from helpers.scenes import make_views

from anycity.lit import RefinementModule, ScaffoldModule
from anycity.structures import Gaussians, ViewBatch, Views

H = W = 32


@pytest.fixture(scope="module")
def batch():
    return ViewBatch(context=make_views(2, 0, [1, 3]), target=make_views(1, 1, [2]), dense=make_views(3, 2))


def _no_log(module):
    module.log = lambda *a, **k: None
    return module


def test_scaffold_step_trains_scaffold_only(batch):
    torch.manual_seed(0)
    m = _no_log(ScaffoldModule(depth_warmup_steps=0, normal_weight=0.1, render_backend="torch"))
    loss = m.training_step(batch, 0)
    assert torch.isfinite(loss)
    loss.backward()
    grads = {n: p.grad for n, p in m.named_parameters()}
    assert grads["net.aggregator.camera_token"] is not None
    assert any(g is not None and g.abs().sum() > 0 for n, g in grads.items() if n.startswith("net.depth_head"))
    assert all(g is None for n, g in grads.items() if n.startswith("net.completion"))


def test_scaffold_normal_term_skips_the_sky(batch):
    """ctx.mask (sky / invalid = 0) reached the depth terms but not L_normal."""
    from dataclasses import replace

    def normal_term(context):
        torch.manual_seed(0)
        m = ScaffoldModule(depth_warmup_steps=0, normal_weight=0.1, flat_weight=0.1, render_backend="torch")
        terms = {}
        m.log_terms = lambda t, *a, **k: terms.update(t)
        m.training_step(replace(batch, context=context), 0)
        return terms["normal"]

    assert normal_term(batch.context).item() > 0
    sky = replace(batch.context, mask=torch.zeros_like(batch.context.mask))
    assert normal_term(sky).item() == 0.0  # the flatness term too: the sky's Gaussians are not pressed flat


def test_refinement_freezes_scaffold_starts_at_scaffold_and_loads_stage1(batch, tmp_path):
    torch.manual_seed(0)
    stage1 = ScaffoldModule()
    ckpt = tmp_path / "stage1.ckpt"
    torch.save({"state_dict": stage1.state_dict()}, ckpt)
    m = _no_log(RefinementModule(init_from=str(ckpt), render_backend="torch"))
    m.load_stage1(str(ckpt))
    torch.testing.assert_close(m.net.depth_head.state_dict(), stage1.net.depth_head.state_dict())
    assert not any(p.requires_grad for p in m.net.scaffold_parameters())
    loss = m.training_step(batch, 0)
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in m.net.refinement_parameters())
    m.evaluate(batch, m.val_metrics, want_preview=False)
    res = {k: v.compute() for k, v in m.val_metrics.items() if v.update_called}
    # P_delta is zero-initialised: before training the refined model renders exactly the scaffold
    assert res["psnr_refined"].item() == pytest.approx(res["psnr_scaffold"].item(), abs=1e-4)
    assert {"psnr_baseline", "psnr_nearest", "ssim_refined", "abs_rel_refined", "delta1_scaffold"} <= set(res)
    # the nearest-view reference copies context view 0 (trajectory position 1 vs 3; ties go to the first)
    from anycity.metrics import psnr
    expected = psnr(batch.context.images[:, :1], batch.target.images).mean()
    assert res["psnr_nearest"].item() == pytest.approx(expected.item(), abs=1e-4)


def _start_fit(m, ckpt_path=None):
    """What Lightning calls of the module when a fit starts: setup, the checkpoint restore (not done here), then
    on_fit_start, when trainer.ckpt_path says whether it resumed."""
    from types import SimpleNamespace

    m._trainer = SimpleNamespace(ckpt_path=ckpt_path, strategy=SimpleNamespace(restore_checkpoint_after_setup=False))
    m.setup("fit")
    m.on_fit_start()


def test_refinement_rejects_missing_init_and_bad_gate_mode(tmp_path):
    m = RefinementModule(init_from=str(tmp_path / "nope.ckpt"))  # checked when fitting starts (test/predict: unused)
    with pytest.raises(FileNotFoundError, match="init_from"):
        _start_fit(m)
    _start_fit(m, "last.ckpt")  # a resumed fit reads its checkpoint, not the Stage I file
    # no Stage I at all: Stage II trained silently on a random, frozen scaffold
    m = RefinementModule(init_from=None)
    with pytest.raises(ValueError, match="model.init_from: Stage II freezes the scaffold, and none was given"):
        _start_fit(m)
    m.setup("test")  # test/predict take the weights from a checkpoint
    _start_fit(m, "last.ckpt")  # a resumed fit too
    _start_fit(RefinementModule(init_from=None, freeze_scaffold=False))  # everything trains: nothing stays random
    with pytest.raises(ValueError, match="gate_mode"):
        RefinementModule(gate_mode="max")
    with pytest.raises(ValueError, match="d2s_depth_scale"):
        RefinementModule(d2s_depth_scale="gt")


def _scaffold_file(path, prefixes, rename=lambda k: k):
    """A pretrained-weights file holding the tiny scaffold's ``prefixes`` (``rename`` maps to the file's layout)."""
    from safetensors.torch import save_file

    sd = {rename(k): v.contiguous() for k, v in ScaffoldModule().net.state_dict().items() if k.startswith(prefixes)}
    save_file(sd, str(path)) if path.suffix == ".safetensors" else torch.save(sd, path)
    return str(path)


def test_reg_weight_with_a_voxel_merge_is_refused_when_fitting_only():
    """L_reg pairs the scaffold's and the final Gaussians one to one, which a voxel merge breaks: a training rule.
    net.voxel_size is a test-time key (cli.NET_TEST_TIME_KEYS), and `anycity test`/`predict` of a Stage II
    checkpoint with it were refused at construction."""
    from types import SimpleNamespace

    m = RefinementModule(net={"voxel_size": 0.1})  # reg_weight 0.01
    m._trainer = SimpleNamespace(ckpt_path=None, strategy=SimpleNamespace(restore_checkpoint_after_setup=False))
    m.setup("test")
    m.setup("predict")
    with pytest.raises(ValueError, match="model.reg_weight: .*voxel merge"):  # it would pair unrelated Gaussians
        m.setup("fit")
    ok = RefinementModule(net={"voxel_size": 0.1}, reg_weight=0.0)
    ok._trainer = m._trainer
    ok.setup("fit")


@pytest.mark.parametrize("cls, kw", [
    (ScaffoldModule, dict(camera_weight=0.0)),
    (ScaffoldModule, dict(camera_weight=0.0, depth_weight=0.0, normal_weight=0.0, context_rgb_weight=0.0,
                          depth_warmup_steps=0, render_pose_grad=False)),
    (RefinementModule, dict(freeze_scaffold=False)),  # Stage II's camera_weight is 0 by default
], ids=["stage1", "stage1_rgb_only", "stage2_unfrozen"])
def test_every_trainable_parameter_gets_a_gradient_when_a_loss_weight_is_0(batch, cls, kw):
    """DDP with find_unused_parameters: false (stage1.yaml) stops at the second step when a trainable parameter
    got no gradient: with camera_weight 0, camera_head.empty_pose_tokens fed only the camera loss."""
    torch.manual_seed(0)
    m = _no_log(cls(render_backend="torch", **kw))
    m.training_step(batch, 0).backward()
    assert [n for n, p in m.named_parameters() if p.requires_grad and p.grad is None] == []
    assert not m.net.camera_head.empty_pose_tokens.requires_grad  # frozen, not trained by something else


def test_the_pose_token_keeps_training_where_something_reaches_it():
    assert ScaffoldModule(camera_weight=1.0).net.camera_head.empty_pose_tokens.requires_grad
    # one camera iteration: the final cameras, which place the Gaussians, read it
    one = ScaffoldModule(camera_weight=0.0, net={"camera_iterations": 1})
    assert one.net.camera_head.empty_pose_tokens.requires_grad


def test_refinement_rejects_a_pretrained_file_that_leaves_the_frozen_scaffold_random(tmp_path):
    """Stage II from a VGGT file and no init_from trained on a random, frozen Gaussian head (VGGT has none)."""
    vggt = _scaffold_file(tmp_path / "model.pt", ("aggregator.", "camera_head.", "depth_head."))
    m = RefinementModule(pretrained=vggt, pretrained_kind="vggt")
    with pytest.raises(ValueError, match=r"model.init_from: Stage II freezes the scaffold, and model.pretrained .*"
                                         r"model.pt leaves \d+ of its weights random \(e.g. gaussian_head\..*"
                                         r"--model.init_args.init_from"):
        _start_fit(m)
    _start_fit(m, "last.ckpt")  # a resumed fit reads its checkpoint
    _start_fit(RefinementModule(pretrained=vggt, freeze_scaffold=False))  # the Gaussian head trains
    # an AnySplat file fills the whole scaffold (its Gaussian head under another name; no centre offset, zero-init)
    def anysplat_name(k):
        return k.replace("gaussian_head.", "gaussian_param_head.") if k.startswith("gaussian_head.") else f"encoder.{k}"

    for name in ("anysplat.safetensors", "anysplat.ckpt"):
        anysplat = _scaffold_file(tmp_path / name, ("aggregator.", "camera_head.", "depth_head.", "gaussian_head."),
                                  anysplat_name)
        _start_fit(RefinementModule(pretrained=anysplat, pretrained_kind="anysplat"))
    with pytest.raises(ValueError, match=r"leaves \d+ of its weights random \(e.g. gaussian_head\."):  # other SH
        _start_fit(RefinementModule(pretrained=anysplat, pretrained_kind="anysplat", net={"sh_degree": 0}))


def test_stage1_mismatch_names_the_overrides_that_rebuild_its_scaffold(tmp_path):
    """The fix load_stage1 named ('-c the Stage I config -c the Stage II config') cannot work: the Stage II config's
    net dict replaces the Stage I one. It names overrides built from the checkpoint's hyperparameters and this Stage II
    net (tests/integration/test_configs.py runs them)."""
    import json
    import shlex

    stage1 = ScaffoldModule(net={"sh_degree": 0, "head_layers": None})
    ckpt = tmp_path / "stage1.ckpt"
    torch.save({"state_dict": stage1.state_dict(), "hyper_parameters": dict(stage1.hparams)}, ckpt)
    with pytest.raises(ValueError, match=r"does not fit .* after its config: --model.init_args.preset tiny "
                                         r"--model.init_args.net '\{.*\}'$") as err:
        RefinementModule(net={"video_prior": "none"}).load_stage1(str(ckpt))
    flags = shlex.split(str(err.value).split("after its config: ")[1])
    assert json.loads(flags[-1]) == {"video_prior": "none", "sh_degree": 0, "head_layers": None}
    torch.save({"state_dict": stage1.state_dict()}, ckpt)  # no hyperparameters: the rule, not the values
    with pytest.raises(ValueError, match=r"--model.init_args.preset PRESET and --model.init_args.net.KEY VALUE"):
        RefinementModule().load_stage1(str(ckpt))


@pytest.mark.parametrize("option, aligned", [("median", True), ("cameras", False)])
def test_d2s_depth_scale_reaches_the_loss(batch, monkeypatch, option, aligned):
    import anycity.lit.refinement as refinement

    seen = []
    real = refinement.d2s_loss

    def spy(student, teacher, **kw):
        seen.append(kw.get("scale_align", True))
        return real(student, teacher, **kw)

    monkeypatch.setattr(refinement, "d2s_loss", spy)
    torch.manual_seed(0)
    m = _no_log(RefinementModule(d2s_depth_scale=option, render_backend="torch"))
    assert torch.isfinite(m.training_step(batch, 0))
    assert seen == [aligned]


def test_context_mean_background_fills_uncovered_pixels(batch):
    from anycity.structures import Gaussians

    m = ScaffoldModule(background_mode="context_mean", render_backend="torch")
    n = 4
    empty = Gaussians(means=torch.zeros(1, n, 3) + torch.tensor([0.0, 0.0, 2.0]), quats=torch.tensor([[1.0, 0, 0, 0]]).
                      expand(1, n, 4), scales=torch.full((1, n, 3), 0.01), opacities=torch.zeros(1, n),
                      sh=torch.zeros(1, n, 1, 3))
    tgt = batch.target
    r = m.render(empty, tgt.w2c, tgt.K, tgt.hw, batch.context.images)
    mean = batch.context.images.mean(dim=(1, 3, 4))
    torch.testing.assert_close(r.rgb[0, 0, :, 5, 7], mean[0])


def test_test_step_aligns_target_poses_when_asked(batch):
    torch.manual_seed(0)
    m = _no_log(ScaffoldModule(eval_pose_align_steps=20, eval_align="none", render_backend="torch")).eval()
    m.validation_step(batch, 1)
    assert not m.val_metrics.metrics["psnr_scaffold_targetalign"].update_called  # validation never aligns
    with torch.inference_mode():  # as in Lightning's test loop: the batch itself holds inference tensors
        m.test_step(ViewBatch(context=make_views(2, 0, [1, 3]), target=make_views(1, 1, [2])), 1)
    res = {k: v.compute().item() for k, v in m.test_metrics.items() if v.update_called}
    assert {"psnr_scaffold", "psnr_scaffold_targetalign", "ssim_scaffold", "rre", "rte", "pose_auc30"} <= set(res)
    assert "psnr_scaffold_camrefine" not in res  # no camera refinement asked
    assert 0 <= res["rre"] <= 180 and 0 <= res["rte"] <= 90 and 0 <= res["pose_auc30"] <= 1
    # photometric alignment against the target image does not make the render worse than feed-forward
    assert res["psnr_scaffold_targetalign"] >= res["psnr_scaffold"] - 0.05


def test_test_and_predict_refine_the_context_cameras_when_asked(batch):
    torch.manual_seed(0)
    m = _no_log(ScaffoldModule(camera_refine_steps=5, camera_refine_lr=0.05, eval_align="none",
                               render_backend="torch")).eval()
    m.validation_step(batch, 1)
    assert not m.val_metrics.metrics["rre_scaffold_camrefine"].update_called  # validation scores feed-forward only
    with torch.inference_mode():
        m.test_step(ViewBatch(context=make_views(2, 0, [1, 3]), target=make_views(1, 1, [2])), 1)
        pred = m.predict_step(batch.context.images, 0)
    res = {k: v.compute().item() for k, v in m.test_metrics.items() if v.update_called}
    assert {"psnr_scaffold", "psnr_scaffold_camrefine", "rre", "rre_scaffold_camrefine",
            "rte_scaffold_camrefine"} <= set(res)
    assert "psnr_scaffold_targetalign" not in res  # no target alignment asked
    raw = m.net(batch.context.images)["w2c"]
    moved = (pred["w2c"] - raw).abs().amax(dim=(-1, -2))
    assert moved[0, 0] < 1e-5 and moved[0, 1] > 1e-4  # the reference view stays, the other one was refined
    assert pred["gaussians"].means.shape == (1, 2 * H * W, 3)


def test_provenance_of_re_placed_cameras_counts_content_changes_only(batch):
    """With net.refine_cameras Stage II re-places the views. A camera move alone completes nothing, so predict hands
    the export the scaffold's decoding at the same (re-placed) cameras: the completion score is what it is without
    the move."""
    from anycity.export.provenance import completion_score

    torch.manual_seed(0)
    m = RefinementModule(net={"refine_cameras": True}, render_backend="torch").eval()
    images = batch.context.images

    def completion():
        with torch.inference_mode():
            pred = m.predict_step(images, 0)
        return completion_score(pred["gaussians"], pred["scaffold"])

    torch.testing.assert_close(completion(), torch.zeros(1, 2 * H * W))  # dZ = 0, cameras kept: nothing
    with torch.no_grad():
        m.net.completion.camera_proj.bias.normal_(0, 0.5)  # the cameras move; dZ stays zero
    with torch.inference_mode():
        out = m.net(images)
    assert (out["w2c"] - out["scaffold_w2c"]).abs().amax() > 0.1
    assert completion_score(out["gaussians"], out["scaffold_gaussians"]).mean() > 0.5  # as placed: all "moved"
    torch.testing.assert_close(completion(), torch.zeros(1, 2 * H * W), atol=1e-4, rtol=0)
    with torch.no_grad():
        for proj in m.net.completion.delta_proj:  # the content changes too
            proj.bias.normal_(0, 5.0)
        moved = completion()
        m.net.completion.camera_proj.bias.zero_()
    kept = completion()
    assert kept.mean() > 0.02
    torch.testing.assert_close(moved, kept, atol=5e-3, rtol=0)  # the same whether the cameras moved or not


def test_protocols_that_must_not_read_target_images_cannot(batch):
    """feedforward and camrefine get target cameras only: they run with target images that hold no data at all
    (meta tensors) and give the same renders; targetalign, which reads them, cannot run on such targets."""
    from anycity.lit import protocols as P

    torch.manual_seed(0)
    m = ScaffoldModule(camera_refine_steps=3, eval_pose_align_steps=3, eval_align="none",
                       render_backend="torch").eval()
    ctx, tgt = batch.context, batch.target
    sealed = Views(images=torch.empty(tgt.images.shape, device="meta"), w2c=tgt.w2c, K=tgt.K)
    with torch.no_grad():
        out, variants = m.predict_variants(ctx.images)
        scene = P.Scene(variants["scaffold"], out["w2c"], out["K"])
        r_sealed, _ = P.feedforward(m, scene, ctx, P.TargetCameras.of(sealed))
        r_open, _ = P.feedforward(m, scene, ctx, P.TargetCameras.of(tgt))
        torch.testing.assert_close(r_sealed.rgb, r_open.rgb)
        r_ref, _, refined = P.camrefine(m, scene, ctx, P.TargetCameras.of(sealed), steps=3)
        assert torch.isfinite(r_ref.rgb).all() and r_ref.rgb.device.type == "cpu"
        with pytest.raises((NotImplementedError, RuntimeError)):
            P.targetalign(m, refined, ctx, sealed, steps=3)


def test_joint_protocol_scores_and_region_metrics_are_logged(batch):
    torch.manual_seed(0)
    m = _no_log(RefinementModule(eval_joint=True, eval_align="none", render_backend="torch")).eval()
    with torch.inference_mode():
        m.test_step(ViewBatch(context=make_views(2, 0, [1, 3]), target=make_views(1, 1, [2])), 1)
    res = {k: v.compute().item() for k, v in m.test_metrics.items() if v.update_called}
    assert {"psnr_scaffold_joint", "psnr_refined_joint", "region_obs", "region_weak"} <= set(res)
    assert res["region_obs"] + res["region_weak"] == pytest.approx(1.0, abs=1e-6)  # no sky in these targets
    for name in ("scaffold", "refined", "baseline"):
        present = [k for k in (f"psnr_obs_{name}", f"psnr_weak_{name}") if k in res]
        assert present, name  # at least one region is non-empty


def _sample(v: Views, i: int, views=slice(None)) -> Views:
    """Sample ``i`` of ``v`` (batch of 1), at ``views``."""
    return Views(*(None if x is None else x[i:i + 1, views] for x in (v.images, v.w2c, v.K, v.depth, v.mask,
                                                                      v.normal, v.index)))


def test_joint_renders_of_a_padded_chunk_do_not_depend_on_the_padding():
    """Evaluation pads a sample's last chunk with its own targets ([2, 4, 2]); joint fed the repeats through the
    network as extra input images, so the scores of the distinct targets depended on the padding."""
    from anycity.lit import protocols as P

    torch.manual_seed(0)
    m = RefinementModule(eval_align="none", render_backend="torch").eval()
    two = [make_views(2, 0, [1, 3]), make_views(2, 5, [1, 3])]
    ctx = Views(*(torch.cat([getattr(v, f) for v in two]) for f in ("images", "w2c", "K", "depth", "mask")),
                index=torch.tensor([[1, 3], [1, 3]]))
    tgt = make_views(3, 1, [2, 4, 5])
    tgt = Views(*(torch.cat([x[:, [0, 1, 0]], x]) for x in (tgt.images, tgt.w2c, tgt.K, tgt.depth, tgt.mask)),
                index=torch.tensor([[2, 4, 2], [2, 4, 5]]))  # sample 0 padded with its first target
    with torch.no_grad():
        padded, s = P.joint(m, ctx, tgt)
        alone = [P.joint(m, _sample(ctx, 0), _sample(tgt, 0, slice(0, 2))), P.joint(m, _sample(ctx, 1),
                                                                                      _sample(tgt, 1))]
    assert set(padded) == {"scaffold", "refined"} and s.shape == (2,)
    for name, r in padded.items():
        assert r.rgb.shape == (2, 3, 3, H, W) and r.depth.shape == (2, 3, 1, H, W)
        assert torch.equal(r.rgb[0, :2], alone[0][0][name].rgb[0]) and torch.equal(r.rgb[1], alone[1][0][name].rgb[0])
        assert torch.equal(r.depth[0, :2], alone[0][0][name].depth[0])
        assert torch.equal(r.rgb[0, 2], r.rgb[0, 0])  # the repeat: the render of its first occurrence
    torch.testing.assert_close(s, torch.cat([alone[0][1], alone[1][1]]))


def test_joint_depth_scale_is_the_ratio_of_camera_spreads_wherever_the_predicted_world_sits():
    from types import SimpleNamespace

    from anycity.lit import protocols as P

    ctx, tgt = make_views(3, 0, [1, 3, 5]), make_views(1, 1, [2])
    ctx.w2c[0, :, 1, 3] = torch.tensor([0.0, 0.2, -0.1])
    w2c = torch.cat([ctx.w2c, tgt.w2c], 1).clone()  # the network's cameras: the truth, 2x larger, moved by 5 units
    w2c[..., :3, 3] = 2 * w2c[..., :3, 3] - (w2c[..., :3, :3] @ torch.tensor([5.0, -1.0, 2.0]))
    out = {"w2c": w2c, "K": torch.cat([ctx.K, tgt.K], 1)}
    g = Gaussians(torch.zeros(1, 4, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(1, 4, 1), torch.ones(1, 4, 3),
                  torch.ones(1, 4), torch.zeros(1, 4, 1, 3))
    module = SimpleNamespace(predict_variants=lambda images: (out, {"scaffold": g}),
                             variant_cameras=lambda o, name: (o["w2c"], o["K"]), render=lambda *a: None)
    _, s = P.joint(module, ctx, tgt)
    torch.testing.assert_close(s, torch.tensor([2.0]))


def test_hparams_hold_the_subclass_and_base_arguments():
    m = ScaffoldModule(lr=3e-3, depth_weight=0.5, eval_align="none")
    assert (m.hparams.lr, m.hparams.depth_weight, m.hparams.eval_align) == (3e-3, 0.5, "none")
    assert m.hparams.preset == "tiny" and m.hparams.warmup_steps == 100 and "base" not in m.hparams
    d = ScaffoldModule().hparams  # the paper's loss weights (Stage I lambda_depth, lambda_normal)
    assert (d.depth_weight, d.normal_weight) == (0.1, 0.1)
    r = RefinementModule()
    assert r.hparams.lr == 1e-4 and r.hparams.d2s_weight == 1.0 and r.hparams.eval_pose_align_steps == 0
    assert (r.hparams.pres_weight, r.hparams.reg_weight) == (0.1, 0.01)  # Stage II lambda_pres, lambda_reg
    with pytest.raises(TypeError, match="depht_weight"):
        ScaffoldModule(depht_weight=0.1)


def test_far_views_keeps_the_dense_cameras_farthest_from_the_context():
    from anycity.lit.refinement import far_views

    ctx, dense = make_views(2, 0, [0, 1]), make_views(5, 2, [0, 1, 2, 3, 4])
    dense.w2c[..., 0, 3] = torch.tensor([0.0, 0.9, 0.1, 0.5, 0.3])  # camera centres at x = -t
    ctx.w2c[..., 0, 3] = torch.tensor([0.0, 0.1])
    far = far_views(dense, ctx, 2)
    assert far.index.tolist() == [[1, 3]]  # 0.9 and 0.5 away; order kept
    torch.testing.assert_close(far.images, dense.images[:, [1, 3]])
    torch.testing.assert_close(far.depth, dense.depth[:, [1, 3]])
    assert far_views(dense, ctx, None) is dense and far_views(dense, ctx, 9) is dense
    with pytest.raises(ValueError, match="d2s_views"):
        far_views(dense, ctx, 0)


def test_d2s_views_renders_the_far_cameras_of_a_teacher_that_read_every_dense_view(batch):
    torch.manual_seed(0)
    m = _no_log(RefinementModule(d2s_views=1, render_backend="torch"))
    seen, forward = [], m.forward_net

    def recording(images, **kw):
        seen.append(images.shape[1])
        return forward(images, **kw)

    m.forward_net = recording
    rendered, render = [], m.render
    m.render = lambda g, w2c, *a, **k: rendered.append(w2c.shape[1]) or render(g, w2c, *a, **k)
    m.training_step(batch, 0)
    assert batch.dense.num_views == 3 and 3 in seen  # the teacher: every dense view, not the one rendered
    assert rendered.count(1) >= 2  # the teacher and the student, each at the one far camera


def test_stage2_camera_option_trains_the_camera_residual_and_scores_each_variant_at_its_own_cameras(batch):
    """``net.refine_cameras`` + ``camera_weight`` (beyond the paper): the camera loss reaches the camera residual,
    the preservation term renders the scaffold at the scaffold's cameras, and evaluation places each variant with the
    cameras its Gaussians were built with (the scaffold's figures do not change when the refined cameras move)."""
    with pytest.raises(ValueError, match="refine_cameras"):
        RefinementModule(camera_weight=1.0)
    torch.manual_seed(0)
    m = _no_log(RefinementModule(net={"refine_cameras": True}, camera_weight=20.0, render_backend="torch"))
    seen = {}
    m.log_terms = lambda terms, *a, **k: seen.update(terms)
    m.training_step(batch, 0).backward()
    assert seen["cam"] > 0 and seen["pres"] == 0  # zero-init: final renders equal the scaffold's at its cameras
    assert m.net.completion.camera_proj.weight.grad.abs().sum() > 0

    def scores(module):
        for _, metric in module.val_metrics.items():
            metric.reset()
        module.evaluate(batch, module.val_metrics, want_preview=False)
        return {k: v.compute().item() for k, v in module.val_metrics.items() if v.update_called}

    m.eval()
    before = scores(m)
    assert {"rre", "rre_scaffold"} <= set(before) and before["rre"] == pytest.approx(before["rre_scaffold"])
    with torch.no_grad():
        m.net.completion.camera_proj.bias.normal_(0, 0.5)
    after = scores(m)
    assert after["psnr_scaffold"] == pytest.approx(before["psnr_scaffold"], abs=1e-5)
    assert after["rre_scaffold"] == pytest.approx(before["rre_scaffold"], abs=1e-5)
    assert after["rre"] != pytest.approx(before["rre"], abs=1e-3)
    assert after["psnr_refined"] != pytest.approx(before["psnr_refined"], abs=1e-4)


def test_a_configured_loss_term_the_batch_cannot_feed_is_said(batch):
    """Stage II with d2s_weight > 0 but data.num_dense: 0 skipped L_d2s (the paper's weight 1.0 term) with nothing
    said; Stage I's depth term on shards without depth was skipped silently too (a data matter: said once)."""
    from dataclasses import replace

    m = _no_log(RefinementModule(render_backend="torch"))
    no_dense = replace(batch, dense=None)
    with pytest.raises(ValueError, match="model.d2s_weight is 1.0, but the batches hold no dense views"):
        m.training_step(no_dense, 0)
    assert torch.isfinite(_no_log(RefinementModule(render_backend="torch", d2s_weight=0.0)).training_step(no_dense, 0))
    s = _no_log(ScaffoldModule(depth_warmup_steps=0, render_backend="torch"))
    no_depth = replace(batch, context=replace(batch.context, depth=None, mask=None))
    with pytest.warns(UserWarning, match="model.depth_weight is .* no ground-truth depth"):
        s.training_step(no_depth, 0)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="model.depth_weight")  # once per run
        s.training_step(no_depth, 1)


def test_bf16_autocast_reaches_the_trunk_only(batch, monkeypatch):
    """Under ``precision: bf16-mixed`` Lightning runs each step in autocast. The network's trunk keeps it; the losses,
    the metrics (SSIM's convolutions) and the geometry (ray anchoring's reprojection) run in float32."""
    import anycity.lit.evaluation as evaluation
    import anycity.lit.refinement as refinement
    import anycity.lit.scaffold as scaffold

    seen = {}

    def spy(where, fn):
        def wrapped(*a, **k):
            seen.setdefault(where, []).append(torch.is_autocast_enabled("cpu"))
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(scaffold, "rgb_loss", spy("loss", scaffold.rgb_loss))
    monkeypatch.setattr(scaffold, "ray_anchor_loss", spy("loss", scaffold.ray_anchor_loss))
    monkeypatch.setattr(refinement, "d2s_loss", spy("loss", refinement.d2s_loss))
    monkeypatch.setattr(evaluation.EvalMetrics, "update", spy("metrics", evaluation.EvalMetrics.update))
    torch.manual_seed(0)
    for m in (ScaffoldModule(depth_warmup_steps=0, render_backend="torch"), RefinementModule(render_backend="torch")):
        m = _no_log(m)
        trunk = m.net.aggregator.forward
        monkeypatch.setattr(m.net.aggregator, "forward", spy("trunk", trunk))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert torch.isfinite(m.training_step(batch, 0))
            m.evaluate(batch, m.val_metrics, want_preview=False)
            assert torch.is_autocast_enabled("cpu")  # the step's own autocast is given back
    assert seen["trunk"] and all(seen["trunk"])
    assert seen["loss"] and not any(seen["loss"])
    assert seen["metrics"] and not any(seen["metrics"])
    assert m.forward_net is not None and getattr(m, "_net_autocast", None) is None  # no state left after a step


def test_a_resumed_stage2_fit_needs_no_stage1_file(batch, tmp_path):
    """Lightning tells a module that a fit resumes only after setup; the Stage I file (moved aside by a fresh Stage I
    run, say) must not be needed by a resume, and a fresh fit without it must still stop."""
    import lightning.pytorch as pl
    from torch.utils.data import DataLoader

    stage1 = tmp_path / "stage1.ckpt"
    torch.save({"state_dict": ScaffoldModule().state_dict()}, stage1)

    def fit(steps, ckpt_path=None):
        m = _no_log(RefinementModule(init_from=str(stage1), render_backend="torch", camera_refine_steps=0))
        trainer = pl.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                             enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
        trainer.fit(m, DataLoader([batch], batch_size=None, collate_fn=lambda b: b), ckpt_path=ckpt_path)
        return trainer

    fit(1).save_checkpoint(tmp_path / "stage2.ckpt")
    stage1.unlink()
    assert fit(2, str(tmp_path / "stage2.ckpt")).global_step == 2
    with pytest.raises(FileNotFoundError, match="model.init_from: .*stage1.ckpt not found"):
        fit(1)
    torch.save({"state_dict": ScaffoldModule(net={"sh_degree": 0}).state_dict()}, stage1)  # another network's
    assert fit(2, str(tmp_path / "stage2.ckpt")).global_step == 2
    with pytest.raises(ValueError, match="model.init_from: .*stage1.ckpt does not fit this network's scaffold"):
        fit(1)


def test_a_padded_chunk_scores_each_held_out_view_once(batch):
    """select_eval pads a sample's last chunk of held-out views with its own views (so batches stack): [32, 40] ->
    [32, 40, 32]. The repeated view must not weigh twice in any figure."""
    import dataclasses

    from anycity.lit.evaluation import EvalMetrics, scored_targets

    assert scored_targets(torch.tensor([[32, 40, 32, 40], [8, 16, 24, 0]])).tolist() == [
        True, True, False, False, True, True, True, True]
    two = make_views(2, 5, [2, 5])
    two.images[:, 1] = two.images[:, 1] * 0.2  # two targets that score differently
    padded = dataclasses.replace(two, **{f: getattr(two, f)[:, [0, 1, 0]] for f in
                                         ("images", "w2c", "K", "depth", "mask", "index")})
    torch.manual_seed(0)
    m = ScaffoldModule(render_backend="torch", camera_refine_steps=0)
    res = []
    for target in (two, padded):
        metrics = EvalMetrics(m.variants)
        m.evaluate(dataclasses.replace(batch, target=target), metrics, want_preview=False)
        res.append({k: v.compute().item() for k, v in metrics.metrics.items() if v.update_called})
    assert res[0].keys() == res[1].keys()
    assert {"psnr_scaffold", "psnr_weak_scaffold", "abs_rel_scaffold"} <= res[0].keys()
    for k in res[0]:
        assert res[1][k] == pytest.approx(res[0][k], rel=1e-5, abs=1e-6), k


def test_training_gives_the_same_gradients_on_the_fused_cpu_kernels_as_on_the_torch_backend(batch, monkeypatch):
    """The render loss reaches the predicted poses on every backend (the fused kernels give camera gradients), and
    never the intrinsics (gsplat, the GPU training backend, gives K none): CPU training trains as GPU training."""
    import anycity.render as render_pkg
    from anycity.render.api import _cpu_backend_available

    if not _cpu_backend_available():
        pytest.skip("numba is not installed")
    seen = []
    real = render_pkg.render

    def spy(gaussians, w2c, K, *args, **kwargs):
        seen.append((w2c.requires_grad, K.requires_grad))
        return real(gaussians, w2c, K, *args, **kwargs)

    monkeypatch.setattr(render_pkg, "render", spy)
    grads = {}
    for backend in ("cpu", "torch"):
        torch.manual_seed(0)
        m = _no_log(ScaffoldModule(depth_warmup_steps=0, render_backend=backend))
        m.training_step(batch, 0).backward()
        grads[backend] = {n: p.grad for n, p in m.named_parameters() if n.startswith("net.camera_head")}
    assert (True, False) in seen and not any(k for _, k in seen)  # poses with gradient, intrinsics without
    assert any(g is not None and g.abs().sum() > 0 for g in grads["cpu"].values())
    for n, g in grads["torch"].items():
        if g is None:
            assert grads["cpu"][n] is None, n
        else:
            torch.testing.assert_close(grads["cpu"][n], g, rtol=1e-3, atol=1e-6, msg=n)
    torch.manual_seed(0)
    assert torch.isfinite(_no_log(RefinementModule(render_backend="cpu")).training_step(batch, 0))
    seen.clear()  # render_pose_grad=False: the poses render detached too (the quickstart's setting)
    _no_log(ScaffoldModule(depth_warmup_steps=0, render_backend="cpu", render_pose_grad=False)).training_step(batch, 0)
    assert seen and set(seen) == {(False, False)}


def test_pretrained_gaps_of_a_weights_folder_read_names_only(tmp_path, monkeypatch):
    """A folder holding ``model.safetensors`` (a downloaded snapshot) is a valid ``pretrained`` since the loader
    reads its one weights file; the Stage II gap check then read the whole file (gigabytes for VGGT-1B) instead of
    the names and shapes safetensors gives."""
    from safetensors.torch import save_file

    import anycity.models.pretrained as pretrained
    from anycity.lit.refinement import pretrained_scaffold_gaps
    from anycity.models import build_network

    net = build_network("tiny")
    sd = {k: v.detach().clone().contiguous() for k, v in net.state_dict().items() if k.startswith("aggregator.")}
    (tmp_path / "snapshot").mkdir()
    save_file(sd, str(tmp_path / "snapshot" / "model.safetensors"))
    expected = pretrained_scaffold_gaps(net, str(tmp_path / "snapshot" / "model.safetensors"), "vggt")

    def no_full_read(path):
        raise AssertionError(f"read the whole file {path}")

    monkeypatch.setattr(pretrained, "read_state_dict", no_full_read)
    assert pretrained_scaffold_gaps(net, str(tmp_path / "snapshot"), "vggt") == expected
    assert expected and all(not k.startswith("aggregator.") for k in expected)


def test_a_non_finite_d2s_teacher_gives_the_nan_loss_every_rank_skips_instead_of_raising(batch):
    """The D2S teacher (the frozen scaffold on the dense views) skipped the student's finiteness check: a NaN in its
    Gaussians made render() raise on that rank alone, while the other DDP ranks waited in backward."""
    from dataclasses import replace

    torch.manual_seed(0)
    m = _no_log(RefinementModule(render_backend="torch"))
    forward = m.net.forward

    def nan_teacher(images, refine=True):
        out = forward(images, refine=refine)
        if refine:  # the student's forward stays finite
            return out
        g = out["gaussians"]
        g = replace(g, means=g.means.clone().index_fill_(1, torch.tensor([0]), float("nan")))
        return {**out, "gaussians": g, "scaffold_gaussians": g}

    m.net.forward = nan_teacher
    loss = m.training_step(batch, 0)
    assert torch.isnan(loss)
    loss.backward()  # built with grad enabled: DDP's reducer sees every trainable parameter
    assert all(p.grad is not None for p in m.parameters() if p.requires_grad)


# D2S trains the completion branch (its student is the final model), and camrefine moves each view's Gaussians
# with its camera: one-line bugs there left every figure finite and plausible (mutation testing, stop 52)
def test_d2s_trains_the_completion_branch(batch, monkeypatch):
    import anycity.lit.refinement as refinement

    seen = []
    real = refinement.d2s_loss
    monkeypatch.setattr(refinement, "d2s_loss", lambda s, t, **kw: seen.append(real(s, t, **kw)) or seen[-1])
    torch.manual_seed(0)
    m = RefinementModule(render_backend="torch")
    m.log = lambda *a, **k: None
    m.training_step(batch, 0)
    params = [p for p in m.net.completion.parameters() if p.requires_grad]
    grads = torch.autograd.grad(seen[0]["total"], params, allow_unused=True)
    assert any(g is not None and g.abs().sum() > 0 for g in grads)


def test_camrefine_moves_each_views_gaussians_with_its_camera(batch):
    from anycity.geometry import project_points
    from anycity.lit import protocols as P

    torch.manual_seed(0)
    m = ScaffoldModule(camera_refine_steps=3, eval_align="none", render_backend="torch").eval()
    ctx, tgt = batch.context, batch.target
    with torch.no_grad():
        out, variants = m.predict_variants(ctx.images)
        scene = P.Scene(variants["scaffold"], out["w2c"], out["K"])
        _, _, refined = P.camrefine(m, scene, ctx, P.TargetCameras.of(tgt), steps=3)
    assert not torch.allclose(refined.w2c[:, 1], scene.w2c[:, 1])  # the camera moved
    v, n = scene.w2c.shape[1], scene.gaussians.means.shape[1]
    for i in range(v):  # view i's Gaussians project through its refined camera as before through the predicted one
        sl = slice(i * n // v, (i + 1) * n // v)
        before, _ = project_points(scene.gaussians.means[:, sl], scene.w2c[:, i], scene.K[:, i])
        after, _ = project_points(refined.gaussians.means[:, sl], refined.w2c[:, i], refined.K[:, i])
        torch.testing.assert_close(after, before, atol=1e-3, rtol=0)


def test_a_module_called_on_images_runs_its_network(batch):
    """``RefinementModule.load_from_checkpoint(path)(images)`` raised torch's "missing the required forward"."""
    torch.manual_seed(0)
    m = ScaffoldModule(render_backend="torch").eval()
    with torch.inference_mode():
        out, ref = m(batch.context.images), m.net(batch.context.images)
    assert torch.equal(out["depth"], ref["depth"]) and torch.equal(out["w2c"], ref["w2c"])


# The loss each stage optimises, pinned term by term against the paper's weights (Stage I: lambda_depth 0.1,
# lambda_normal 0.1; Stage II: lambda_d2s 1.0, lambda_pres 0.1, lambda_reg 0.01): a dropped weight, a swapped
# width/height or a lost no_grad left every loss finite and decreasing (mutation testing, stop 56)
def _logged_terms(m, batch, step=0):
    """Run one training step and return the logged terms as floats."""
    terms = {}
    m.log_terms = lambda t, *a, **k: terms.update({name: v.item() for name, v in t.items()})
    torch.manual_seed(0)
    m.training_step(batch, step)
    return terms


def test_stage1_loss_is_the_paper_weighted_sum_of_its_terms(batch):
    """L = L_rgb + L_rgb_ctx + L_cam + 0.1 L_depth + 0.1 L_normal once the depth warm-up is over."""
    torch.manual_seed(0)
    t = _logged_terms(ScaffoldModule(depth_warmup_steps=0, render_backend="torch"), batch)
    assert t["depth"] > 0 and t["normal"] > 0
    expected = t["rgb"] + t["rgb_ctx"] + t["cam"] + 0.1 * t["depth"] + 0.1 * t["normal"]
    assert t["loss"] == pytest.approx(expected, abs=1e-5)


def test_stage2_loss_is_the_paper_weighted_sum_and_pres_compares_with_the_scaffold(batch):
    """P_delta starts at zero, so the refined render equals the scaffold's and L_pres is 0; once the refinement
    weights move, L_pres > 0 and L = L_rgb + L_rgb_ctx + 1.0 L_d2s + 0.1 L_pres + 0.01 L_reg."""
    torch.manual_seed(0)
    m = RefinementModule(render_backend="torch")
    assert _logged_terms(m, batch)["pres"] == 0.0
    with torch.no_grad():
        for p in m.net.refinement_parameters():
            p.add_(0.05 * torch.randn_like(p))
    t = _logged_terms(m, batch)
    assert t["pres"] > 0 and t["reg"] > 0 and t["d2s"] > 0
    expected = t["rgb"] + t["rgb_ctx"] + 1.0 * t["d2s"] + 0.1 * t["pres"] + 0.01 * t["reg"]
    assert t["loss"] == pytest.approx(expected, abs=1e-5)


def test_the_context_photometric_term_is_on_during_the_depth_warm_up_and_without_pres(batch):
    """L_rgb_ctx (weight 1) does not wait for the geometry terms (Stage I warm-up) nor need L_pres (Stage II)."""
    torch.manual_seed(0)
    t = _logged_terms(ScaffoldModule(render_backend="torch"), batch, step=0)  # step 0 < depth_warmup_steps
    assert "rgb_ctx" in t and "depth" not in t
    assert t["loss"] == pytest.approx(t["rgb"] + t["rgb_ctx"] + t["cam"], abs=1e-5)
    torch.manual_seed(0)
    t = _logged_terms(RefinementModule(pres_weight=0.0, render_backend="torch"), batch)
    assert "rgb_ctx" in t and "pres" not in t


def test_stage1_renders_and_encodes_non_square_views_at_their_height_and_width(monkeypatch):
    """Views of H=32 x W=48: every render is (32, 48) and the pose encoding reads hw = (32, 48)."""
    import anycity.lit.scaffold as scaffold

    h, w = 32, 48

    def views(n, seed):
        g = torch.Generator().manual_seed(seed)
        w2c = torch.eye(4).repeat(1, n, 1, 1)
        w2c[..., 0, 3] = torch.linspace(0, 0.3, n)
        K = torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]]).expand(1, n, 3, 3).clone()
        return Views(images=torch.rand(1, n, 3, h, w, generator=g), w2c=w2c, K=K,
                     depth=torch.rand(1, n, 1, h, w, generator=g) + 1,
                     mask=torch.ones(1, n, 1, h, w, dtype=torch.bool))

    seen_hw, shapes = [], []
    real = scaffold.extri_intri_to_pose_encoding
    monkeypatch.setattr(scaffold, "extri_intri_to_pose_encoding",
                        lambda w2c, K, hw, *a: seen_hw.append(tuple(hw)) or real(w2c, K, hw, *a))
    torch.manual_seed(0)
    m = _no_log(ScaffoldModule(depth_warmup_steps=0, render_backend="torch"))
    render = m.render
    m.render = lambda *a, **k: (lambda r: shapes.append(tuple(r.rgb.shape[-2:])) or r)(render(*a, **k))
    from anycity.structures import ViewBatch

    assert torch.isfinite(m.training_step(ViewBatch(context=views(2, 0), target=views(1, 1)), 0))
    assert shapes and set(shapes) == {(h, w)}
    assert seen_hw == [(h, w)]


def test_the_d2s_teacher_runs_without_autograd(batch):
    """The student reads the context views with autograd; the teacher (every dense view) under no_grad."""
    torch.manual_seed(0)
    m = _no_log(RefinementModule(render_backend="torch"))
    calls, forward = [], m.forward_net

    def spy(images, **kw):
        calls.append((images.shape[1], torch.is_grad_enabled()))
        return forward(images, **kw)

    m.forward_net = spy
    m.training_step(batch, 0)
    assert calls == [(batch.context.images.shape[1], True), (batch.dense.images.shape[1], False)]


def test_d2s_cameras_scale_converts_each_render_by_its_own_camera_fit(batch, monkeypatch):
    """d2s_depth_scale='cameras': the teacher's depth is divided by its camera-fit scale, the student's by the
    scale of the student's own cameras (target_cameras of its predicted poses against the dense views)."""
    import anycity.lit.refinement as refinement

    seen, real = [], refinement._scaled
    monkeypatch.setattr(refinement, "_scaled", lambda r, s: seen.append(s.detach().clone()) or real(r, s))
    torch.manual_seed(0)
    m = _no_log(RefinementModule(d2s_depth_scale="cameras", render_backend="torch"))
    outs, forward = [], m.forward_net
    m.forward_net = lambda images, **kw: outs.append(forward(images, **kw)) or outs[-1]
    m.training_step(batch, 0)
    assert len(seen) == 2
    teacher, student = seen
    assert not torch.allclose(teacher, student)
    shown = batch.dense  # only the far views are rendered, but the scale depends on the context fit alone
    expected = m.target_cameras(outs[0]["w2c"], batch.context, shown)[1]
    torch.testing.assert_close(student, expected)


def test_load_stage1_copies_the_scaffold_only(tmp_path):
    """A completion branch an older Stage I checkpoint holds (untrained) is not copied into Stage II."""
    from anycity.models import build_network

    torch.manual_seed(0)
    old = build_network("tiny")
    sd = {f"net.{k}": torch.full_like(v, 7.0) if k.startswith("completion") and v.is_floating_point() else v
          for k, v in old.state_dict().items()}
    assert any(k.startswith("net.completion") for k in sd)
    ckpt = tmp_path / "stage1.ckpt"
    torch.save({"state_dict": sd}, ckpt)
    m = RefinementModule()
    m.load_stage1(str(ckpt))
    assert not any(bool((p == 7.0).all()) for p in m.net.completion.parameters())


def test_the_absolute_depth_term_is_not_scale_aligned(batch, monkeypatch):
    """depth_abs_weight adds an unaligned depth L1 (align=False) to the aligned depth term."""
    import anycity.lit.scaffold as scaffold

    aligns, real = [], scaffold.depth_z_loss
    monkeypatch.setattr(scaffold, "depth_z_loss",
                        lambda *a, **kw: aligns.append(kw.get("align", True)) or real(*a, **kw))
    torch.manual_seed(0)
    _no_log(ScaffoldModule(depth_abs_weight=1.0, depth_warmup_steps=0, render_backend="torch")).training_step(batch, 0)
    assert aligns == [True, False]


def test_ssim_weight_reaches_every_photometric_term(batch, monkeypatch):
    import anycity.lit.scaffold as scaffold

    weights, real = [], scaffold.rgb_loss
    monkeypatch.setattr(scaffold, "rgb_loss", lambda *a, **kw: weights.append(kw["ssim_weight"]) or real(*a, **kw))
    torch.manual_seed(0)
    _no_log(ScaffoldModule(ssim_weight=0.2, render_backend="torch")).training_step(batch, 0)
    assert weights == [0.2, 0.2]  # target and context views


def test_the_depth_warm_up_defaults_to_200_steps():
    assert ScaffoldModule().hparams.depth_warmup_steps == 200


def test_load_stage1_refuses_a_scaffold_trained_with_other_decode_settings(tmp_path):
    """Settings that change what the scaffold's weights decode but not their shapes (scale_mode, color_mode, the
    head's slope, ...) were taken from the Stage II config: a Stage I trained with scale_mode absolute was frozen and
    decoded with pixel scales (mean scale 0.0007 in Stage I, 0.024 in Stage II), without a word."""
    from anycity.models import build_network

    net = build_network("tiny", scale_mode="absolute", color_mode="head")
    ckpt = tmp_path / "stage1.ckpt"
    torch.save({"state_dict": {f"net.{k}": v for k, v in net.state_dict().items()},
                "hyper_parameters": {"preset": "tiny", "net": {"scale_mode": "absolute", "color_mode": "head"}}}, ckpt)
    with pytest.raises(ValueError, match=r"^model.init_from: .*stage1.ckpt does not fit this network's scaffold: it "
                                         r"decodes its weights with other settings \(net.scale_mode: absolute there, "
                                         r"pixel here, net.color_mode: head there, pixel here\); give Stage II the "
                                         r"Stage I network after its config: --model.init_args.preset tiny "
                                         r".*\"scale_mode\": \"absolute\""):
        RefinementModule().load_stage1(str(ckpt))
    m = RefinementModule(net={"scale_mode": "absolute", "color_mode": "head"})
    m.load_stage1(str(ckpt))  # the same settings: loaded
    torch.testing.assert_close(m.net.gaussian_head.state_dict(), net.gaussian_head.state_dict())
    # a deeper trunk resolves its default head layers from its own depth, in both checkpoints alike
    deep = build_network("tiny", depth=8, completion=False)
    torch.save({"state_dict": {f"net.{k}": v for k, v in deep.state_dict().items()},
                "hyper_parameters": {"preset": "tiny", "net": {"depth": 8}}}, ckpt)
    RefinementModule(net={"depth": 8}).load_stage1(str(ckpt))


def test_training_on_scenes_with_and_without_depth_is_named_once(batch):
    """A frame with depth is scaled by its context's median depth, one without by its cameras' spread (views.py),
    so mixing synthetic and COLMAP shards teaches the camera head translations in two units, silently."""
    import dataclasses
    import warnings

    no_depth = ViewBatch(context=dataclasses.replace(batch.context, depth=None, mask=None), target=batch.target,
                         dense=batch.dense)
    torch.manual_seed(0)
    m = _no_log(ScaffoldModule(depth_weight=0.0, normal_weight=0.0, render_backend="torch"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m.training_step(batch, 0)
        m.training_step(batch, 1)
    assert not [w for w in caught if "two units" in str(w.message)]  # one kind: nothing to say
    with pytest.warns(UserWarning, match=r"^training mixes scenes with ground-truth depth and scenes without .*two "
                                         r"units; convert the depth-free scenes with depth, or train on one kind$"):
        m.training_step(no_depth, 2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m.training_step(batch, 3)
        m.training_step(no_depth, 4)
    assert not [w for w in caught if "two units" in str(w.message)]  # said once


def test_unscaled_placement_of_a_batch_without_depth_is_named_once(batch):
    """eval_align none takes the ground truth's scale as the network's: true of a frame scaled by median depth, not
    of a depth-free sample's (scaled by its cameras' spread); the zero-shot COLMAP figures carried it unsaid."""
    import dataclasses

    no_depth = ViewBatch(context=dataclasses.replace(batch.context, depth=None, mask=None),
                         target=dataclasses.replace(batch.target, depth=None, mask=None))
    torch.manual_seed(0)
    m = _no_log(ScaffoldModule(eval_align="none", render_backend="torch"))
    with pytest.warns(UserWarning, match=r"^eval_align none: a batch has no ground-truth depth, .*pass "
                                         r"--model.init_args.eval_align sim3"):
        m.evaluate(no_depth, m.val_metrics, want_preview=False)
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m.evaluate(no_depth, m.val_metrics, want_preview=False)  # once
        _no_log(ScaffoldModule(eval_align="sim3", render_backend="torch")).evaluate(no_depth, m.val_metrics, False)
        _no_log(ScaffoldModule(eval_align="none", render_backend="torch")).evaluate(batch, m.val_metrics, False)
    assert not [w for w in caught if "eval_align none" in str(w.message)]
