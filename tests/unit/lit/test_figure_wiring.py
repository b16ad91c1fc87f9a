"""Which render, camera and metric each logged evaluation figure is wired to (protocols and ``evaluate``)."""

import math
from types import SimpleNamespace

import pytest
import torch
from helpers.scenes import make_views
from torchmetrics.image import PeakSignalNoiseRatio

from anycity.geometry import make_intrinsics, quat_to_rotmat
from anycity.lit import ScaffoldModule
from anycity.lit import protocols as P
from anycity.lit.base import AnyCityModule
from anycity.lit.distributed import log_eval_metrics
from anycity.lit.evaluation import EvalMetrics, cameras_in_pred_frame, fit_gt_to_pred
from anycity.metrics.pose import pose_auc
from anycity.structures import Gaussians, RenderOutput, ViewBatch, Views

H = W = 32


def _gaussians(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(torch.randn(1, n, 3, generator=g), torch.tensor([[1.0, 0, 0, 0]]).repeat(1, n, 1),
                     torch.rand(1, n, 3, generator=g), torch.rand(1, n, generator=g), torch.rand(1, n, 1, 3,
                                                                                                  generator=g))


def _rot_w2c(deg, axis=(0.0, 1.0, 0.0), t=(0.0, 0.0, 0.0)):
    half = math.radians(deg) / 2
    q = torch.tensor([math.cos(half), *(math.sin(half) * a for a in axis)])
    T = torch.eye(4)
    T[:3, :3] = quat_to_rotmat(q)
    T[:3, 3] = torch.tensor(t)
    return T


@pytest.fixture(scope="module")
def module():
    torch.manual_seed(0)
    m = ScaffoldModule(camera_refine_steps=1, eval_align="none", render_backend="torch").eval()
    m.log = lambda *a, **k: None
    return m


def _spy_updates(metrics, monkeypatch):
    """Record every ``metrics.update(name, pred, ...)`` call's prediction, then run the real update."""
    seen = {}
    real = metrics.update

    def update(name, pred, *a, **k):
        seen[name] = pred.detach().clone()
        return real(name, pred, *a, **k)

    monkeypatch.setattr(metrics, "update", update)
    return seen


# ------------------------------------------------------------------------------------------------ protocols


def test_joint_renders_the_context_views_gaussians_at_the_networks_target_cameras():
    """joint scored every input view's Gaussians (targets see themselves) or the wrong predicted cameras."""
    v, t, per_view = 2, 1, 5
    w2c = torch.stack([_rot_w2c(5.0 * i, t=(0.1 * i, 0.0, 0.0)) for i in range(v + t)])[None]
    K = make_intrinsics(30.0, 30.0, 16.0, 16.0).expand(1, v + t, 3, 3).clone()
    out = {"w2c": w2c, "K": K}
    g = _gaussians((v + t) * per_view)
    calls = []
    module = SimpleNamespace(predict_variants=lambda images: (out, {"scaffold": g}),
                             variant_cameras=lambda o, name: (o["w2c"], o["K"]),
                             render=lambda gs, c, k, hw, ctx: calls.append((gs, c, k, hw)))
    P.joint(module, make_views(v, 0), make_views(t, 1))
    (gs, c, k, hw), = calls
    assert torch.equal(gs.means, g.means[:, :v * per_view]) and torch.equal(gs.sh, g.sh[:, :v * per_view])
    assert torch.equal(c, w2c[:, v:]) and torch.equal(k, K[:, v:]) and hw == (H, W)


def test_targetalign_renders_at_the_aligned_target_cameras():
    """targetalign scored the placed (unaligned) cameras while its name says the target was aligned."""
    ctx, tgt = make_views(2, 0), make_views(1, 1)
    placed = tgt.w2c.clone()
    aligned = placed.clone()
    aligned[..., 1, 3] += 0.25
    seen = []
    module = SimpleNamespace(target_cameras=lambda *a, **k: (placed, torch.ones(1)),
                             align_targets=lambda g, w, target, images, steps: aligned,
                             render=lambda g, w, *a: seen.append(w) or "render")
    scene = P.Scene(_gaussians(4), ctx.w2c, ctx.K)
    render, _ = P.targetalign(module, scene, ctx, tgt, steps=3)
    assert render == "render" and len(seen) == 1 and torch.equal(seen[0], aligned)


def test_place_anchors_the_first_ground_truth_camera_at_the_networks_first_camera():
    """With eval_align='none' the targets were placed relative to the origin, not the first camera as predicted."""
    ctx, tgt = make_views(3, 0), make_views(2, 1)
    tgt.w2c[0, 1, 1, 3] = 0.2
    pred = ctx.w2c.clone()
    pred[0] = torch.stack([_rot_w2c(4.0, t=(0.05, -0.02, 0.1)), _rot_w2c(-3.0, axis=(1.0, 0, 0)), _rot_w2c(2.0)])
    ns = SimpleNamespace(hparams=SimpleNamespace(eval_align="none"))
    ns.target_cameras = lambda *a, **k: AnyCityModule.target_cameras(ns, *a, **k)
    got, s = P.place(ns, P.Scene(_gaussians(3), pred, ctx.K), ctx, P.TargetCameras.of(tgt))
    want = cameras_in_pred_frame(tgt.w2c, *fit_gt_to_pred(pred, ctx.w2c, "none", anchor_first=True))
    torch.testing.assert_close(got, want)
    torch.testing.assert_close(s, torch.ones(1))
    # the first ground-truth context camera lands on the predicted first camera
    here = cameras_in_pred_frame(ctx.w2c, *fit_gt_to_pred(pred, ctx.w2c, "none", anchor_first=True))
    torch.testing.assert_close(here[:, 0], pred[:, 0], atol=1e-6, rtol=0)



def test_camrefine_renders_the_gaussians_moved_with_the_refined_cameras():
    """camrefine renders each view's Gaussians moved by its refinement transform (the refined scene), not the
    network's unrefined Gaussians, which would make the _camrefine figures score the feed-forward picture."""
    from anycity.lit.evaluation import transform_gaussians

    v = 2
    g = _gaussians(v * 4)
    w2c, K = torch.eye(4).repeat(1, v, 1, 1), torch.eye(3).repeat(1, v, 1, 1)
    A = torch.eye(4).repeat(1, v, 1, 1)
    A[0, 1, :3, 3] = torch.tensor([0.3, 0.0, 0.0])  # view 1's Gaussians move; view 0 is the reference
    refined_w2c = w2c.clone()
    refined_w2c[0, 1, :3, 3] = torch.tensor([-0.3, 0.0, 0.0])
    seen = []
    module = SimpleNamespace(refine_cameras=lambda gs, w, k, images, steps: (refined_w2c, A),
                             target_cameras=lambda pw, ctx, q, anchor_first: (pw[:, :1].clone(), torch.ones(1)),
                             render=lambda gs, w, *a: seen.append((gs, w)) or "render")
    ctx = Views(make_views(v, 0).images, w2c, K)
    cams = P.TargetCameras(torch.eye(4)[None, None], torch.eye(3)[None, None], (H, W))
    render, _, refined = P.camrefine(module, P.Scene(g, w2c, K), ctx, cams, steps=3)
    (gs, cam), = seen
    assert render == "render"
    torch.testing.assert_close(gs.means, transform_gaussians(g, A).means)
    assert not torch.allclose(gs.means, g.means)
    assert torch.equal(cam, refined_w2c[:, :1])  # placed through the refined cameras
    assert torch.equal(refined.w2c, refined_w2c)


def test_feedforward_and_targetalign_render_with_the_targets_own_intrinsics():
    """A target with other intrinsics than the context (here a zoomed one, focal 45 against 30) is rendered with
    its own K, not the context's."""
    K_ctx = make_intrinsics(30.0, 30.0, 16.0, 16.0).expand(1, 2, 3, 3)
    K_tgt = make_intrinsics(45.0, 45.0, 16.0, 16.0).expand(1, 1, 3, 3)
    ctx, tgt = make_views(2, 0), make_views(1, 1)
    ctx, tgt = Views(ctx.images, ctx.w2c, K_ctx), Views(tgt.images, tgt.w2c, K_tgt)
    seen = []
    module = SimpleNamespace(target_cameras=lambda pw, c, q, anchor_first: (q.w2c, torch.ones(1)),
                             align_targets=lambda g, w, target, images, steps: w,
                             render=lambda g, w, k, hw, images: seen.append(k) or "render")
    scene = P.Scene(_gaussians(4), ctx.w2c, K_ctx)
    P.feedforward(module, scene, ctx, P.TargetCameras.of(tgt))
    P.targetalign(module, scene, ctx, tgt, steps=2)
    assert len(seen) == 2 and all(torch.equal(k, K_tgt) for k in seen)


# ------------------------------------------------------------------------------------------------- evaluate


def test_camrefine_figures_score_the_camrefine_render(module, monkeypatch):
    """psnr_*_camrefine scored the feed-forward render, so camrefine looked exactly as good as feed-forward."""
    batch = ViewBatch(context=make_views(2, 0), target=make_views(1, 1))
    known = torch.full((1, 1, 3, H, W), 0.25)

    def camrefine(mod, scene, ctx, cams, steps):
        z = torch.zeros(1, 1, 1, H, W)
        return RenderOutput(known, z, z), torch.ones(1), scene

    monkeypatch.setattr(P, "camrefine", camrefine)
    metrics = EvalMetrics(("scaffold",))
    seen = _spy_updates(metrics, monkeypatch)
    module.evaluate(batch, metrics, want_preview=False, protocols=("feedforward", "camrefine"))
    torch.testing.assert_close(seen["scaffold_camrefine"], known.flatten(0, 1))
    assert not torch.equal(seen["scaffold"], seen["scaffold_camrefine"])


def test_depth_figures_divide_the_render_by_the_depth_scale(module, monkeypatch):
    """A render whose depth is exactly s x ground truth (pred = s * gt) must score AbsRel 0 and delta1 1."""
    batch = ViewBatch(context=make_views(2, 0), target=make_views(1, 1))

    def feedforward(mod, scene, ctx, cams):
        d = 2.0 * batch.target.depth
        return RenderOutput(torch.rand(1, 1, 3, H, W), d, torch.ones_like(d)), torch.tensor([2.0])

    monkeypatch.setattr(P, "feedforward", feedforward)
    metrics = EvalMetrics(("scaffold",))
    module.evaluate(batch, metrics, want_preview=False)
    assert metrics.metrics["abs_rel_scaffold"].compute().item() == pytest.approx(0.0, abs=1e-6)
    assert metrics.metrics["delta1_scaffold"].compute().item() == pytest.approx(1.0)


def test_region_shares_use_the_default_region_masks_and_the_targets_validity(module):
    """region_obs / region_weak counted other thresholds than documented, or the targets' sky as a region."""
    from anycity.metrics.regions import region_masks

    ctx, tgt = make_views(2, 0, plane=2.0), make_views(2, 1, plane=2.0)
    metrics = EvalMetrics(("scaffold",))
    module.evaluate(ViewBatch(context=ctx, target=tgt), metrics, want_preview=False)
    obs, weak = region_masks(tgt.depth, tgt.w2c, tgt.K, ctx.depth, ctx.w2c, ctx.K)
    share_obs = metrics.metrics["region_obs"].compute().item()
    assert share_obs == pytest.approx(obs.float().mean().item(), abs=1e-6)
    assert metrics.metrics["region_weak"].compute().item() == pytest.approx(weak.float().mean().item(), abs=1e-6)
    assert 0 < share_obs < 1  # both regions are present: the thresholds matter

    tgt.mask[..., : W // 2] = False  # half of every target is sky
    metrics = EvalMetrics(("scaffold",))
    module.evaluate(ViewBatch(context=ctx, target=tgt), metrics, want_preview=False)
    total = metrics.metrics["region_obs"].compute().item() + metrics.metrics["region_weak"].compute().item()
    assert total == pytest.approx(0.5, abs=1e-6)


# -------------------------------------------------------------------------------------------------- metrics


def test_a_second_evaluation_logs_its_own_batch_only():
    """log_eval_metrics must reset: the second validation logged the mean of both."""
    g = torch.Generator().manual_seed(0)
    gt1, gt2 = torch.rand(2, 3, 8, 8, generator=g), torch.rand(2, 3, 8, 8, generator=g)
    pred1, pred2 = (gt1 + 0.05).clamp(0, 1), (gt2 - 0.2).clamp(0, 1)
    stub = SimpleNamespace(device=torch.device("cpu"), log=lambda *a, **k: None)
    m = EvalMetrics(("scaffold",))
    m.update("scaffold", pred1, gt1)
    log_eval_metrics(stub, m, "val")
    m.update("scaffold", pred2, gt2)
    second = log_eval_metrics(stub, m, "val")
    fresh = EvalMetrics(("scaffold",))
    fresh.update("scaffold", pred2, gt2)
    alone = log_eval_metrics(stub, fresh, "val")
    assert second == pytest.approx(alone)


def test_pose_auc30_is_the_auc_at_30_degrees():
    """pose_auc30 was the AUC at another threshold: a view 20 degrees off scores 0 at 15."""
    gt = torch.stack([torch.eye(4), _rot_w2c(0.0, t=(-1.0, 0.0, 0.0))])[None]
    pred = gt.clone()
    pred[0, 1] = _rot_w2c(20.0) @ gt[0, 1]  # the second camera turned 20 degrees about its own centre
    m = EvalMetrics(("scaffold",))
    m.update_pose(pred, gt)
    rre = m.metrics["rre"].compute()
    assert rre.item() == pytest.approx(20.0, abs=1e-3)
    rte = m.metrics["rte"].compute()
    want = pose_auc(rre.reshape(1), rte.reshape(1), 30).mean().item()
    err = max(rre.item(), rte.item())
    assert want == pytest.approx(sum(err < th for th in range(1, 31)) / 30)  # the definition, by hand
    assert m.metrics["pose_auc30"].compute().item() == pytest.approx(want) and want > 0


def test_pose_metrics_log_the_translation_error_under_rte():
    """rte is the translation-direction error: cameras with exact rotations and translations 90 degrees apart
    score rre 0 and rte 90."""
    gt = torch.eye(4).repeat(1, 2, 1, 1)
    gt[0, 1, :3, 3] = torch.tensor([-1.0, 0.0, 0.0])
    pred = gt.clone()
    pred[0, 1, :3, 3] = torch.tensor([0.0, -1.0, 0.0])
    m = EvalMetrics(("scaffold",))
    m.update_pose(pred, gt)
    assert m.metrics["rre"].compute().item() == pytest.approx(0.0, abs=1e-3)
    assert m.metrics["rte"].compute().item() == pytest.approx(90.0, abs=1e-3)


def test_psnr_scores_the_prediction_clamped_to_the_image_range():
    """An unclamped render (the rasteriser's rgb may exceed 1) scored lower than the image it shows."""
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(2, 3, 8, 8, generator=g)
    pred = gt + 0.3
    m = EvalMetrics(("scaffold",))
    m.update("scaffold", pred, gt)
    ref = PeakSignalNoiseRatio(data_range=1.0, dim=(1, 2, 3), reduction="elementwise_mean")
    want = ref(pred.clamp(0, 1), gt)
    torch.testing.assert_close(m.metrics["psnr_scaffold"].compute(), want)


# ------------------------------------------------------------------------------------------- training losses


def _train_batch():
    return ViewBatch(context=make_views(2, 0, [1, 3]), target=make_views(1, 1, [2]), dense=make_views(3, 2))


def _recording(m, monkeypatch):
    """Spy on ``m``: the network outputs, every render call ``(gaussians, w2c, K, raw render)`` and the terms."""
    rec = {"renders": [], "terms": {}}
    real_net, real_render = m.forward_net, m.render

    def forward_net(images, **kw):
        out = real_net(images, **kw)
        rec.setdefault("outs", []).append(out)
        return out

    def render(g, w2c, K, *a, **k):
        r = real_render(g, w2c, K, *a, **k)
        rec["renders"].append((g, w2c.detach().clone(), K, r))
        return r

    monkeypatch.setattr(m, "forward_net", forward_net)
    monkeypatch.setattr(m, "render", render)
    m.log_terms = lambda t, *a, **k: rec["terms"].update(t)
    return rec


def _moved_off_zero_init(m, cameras=False):
    """Stage II starts exactly at the scaffold (zero-initialised residuals): move it so final != scaffold."""
    with torch.no_grad():
        for proj in m.net.completion.delta_proj:
            proj.bias.normal_(0, 0.5)
        if cameras:
            m.net.completion.camera_proj.bias.normal_(0, 0.3)


def test_stage1_depth_term_holds_the_ray_anchoring():
    """L_xy (ray anchoring) was left out of the depth term, so the centre offsets trained on nothing."""
    from anycity.losses.depth import ray_anchor_loss

    def depth_term(ray_weight, monkeypatch):
        torch.manual_seed(0)
        m = ScaffoldModule(depth_warmup_steps=0, ray_weight=ray_weight, render_backend="torch")
        with torch.no_grad():
            m.net.gaussian_head.offset_conv.bias.normal_(0, 0.05)
        rec = _recording(m, monkeypatch)
        m.training_step(_train_batch(), 0)
        return rec["terms"]["depth"].item(), rec["outs"][0]

    with pytest.MonkeyPatch.context() as mp:
        without, _ = depth_term(0.0, mp)
    with pytest.MonkeyPatch.context() as mp:
        with_xy, out = depth_term(2.0, mp)
    ctx = _train_batch().context
    dxy = ray_anchor_loss(out["pixel_means"], out["w2c"], out["K"], ctx.mask).item()
    assert dxy > 1e-3
    assert with_xy - without == pytest.approx(2.0 * dxy, rel=1e-4, abs=1e-6)


def test_stage2_loss_is_the_weighted_sum_of_its_terms(monkeypatch):
    """A term multiplied by another term's weight trains Stage II with other balances than configured."""
    from anycity.lit import RefinementModule

    torch.manual_seed(0)
    w = dict(context_rgb_weight=0.9, pres_weight=0.3, d2s_weight=0.7, reg_weight=0.05)
    m = RefinementModule(render_backend="torch", **w)
    _moved_off_zero_init(m)
    rec = _recording(m, monkeypatch)
    loss = m.training_step(_train_batch(), 0)
    t = {k: v.item() for k, v in rec["terms"].items()}
    assert all(t[k] > 0 for k in ("rgb", "rgb_ctx", "pres", "d2s", "reg"))
    want = t["rgb"] + 0.9 * t["rgb_ctx"] + 0.3 * t["pres"] + 0.7 * t["d2s"] + 0.05 * t["reg"]
    assert loss.item() == pytest.approx(want, rel=1e-5)


def test_stage2_target_rgb_renders_the_completed_gaussians(monkeypatch):
    """L_rgb on the targets rendered the frozen scaffold: the main photometric term never reached the completion."""
    from anycity.lit import RefinementModule

    torch.manual_seed(0)
    m = RefinementModule(render_backend="torch")
    _moved_off_zero_init(m)
    rec = _recording(m, monkeypatch)
    m.training_step(_train_batch(), 0)
    assert rec["renders"][0][0] is rec["outs"][0]["gaussians"]  # the first render: the targets
    assert rec["terms"]["rgb"].requires_grad  # the scaffold is frozen: a render of it carries no gradient
    params = [p for p in m.net.completion.parameters() if p.requires_grad]
    grads = torch.autograd.grad(rec["terms"]["rgb"], params, allow_unused=True)
    assert sum(float(g.abs().sum()) for g in grads if g is not None) > 0


def test_d2s_teacher_and_student_render_the_same_far_dense_camera(monkeypatch):
    """The teacher rendered another dense camera than the student, so L_d2s compared two different views."""
    from anycity.lit import RefinementModule

    torch.manual_seed(0)
    m = RefinementModule(d2s_views=1, eval_align="none", render_backend="torch")
    rec = _recording(m, monkeypatch)
    batch = _train_batch()
    m.training_step(batch, 0)
    teacher, student = rec["renders"][-2], rec["renders"][-1]
    assert student[0] is rec["outs"][0]["gaussians"] and teacher[0] is not student[0]
    # dense views at x = 0, 0.15, 0.3 and context at 0, 0.3: the far one is dense view 1. Both frames put
    # the first view (at x = 0) at the origin, so each renders the ground-truth camera itself.
    far = batch.dense.w2c[:, 1:2]
    torch.testing.assert_close(teacher[1], far)
    torch.testing.assert_close(student[1], far)


def test_pres_renders_the_scaffold_at_the_scaffolds_own_cameras(monkeypatch):
    """With re-placed cameras L_pres rendered the scaffold at the final cameras: a camera move counted as a change."""
    from anycity.lit import RefinementModule

    torch.manual_seed(0)
    m = RefinementModule(net={"refine_cameras": True}, render_backend="torch")
    _moved_off_zero_init(m, cameras=True)
    rec = _recording(m, monkeypatch)
    m.training_step(_train_batch(), 0)
    out = rec["outs"][0]
    assert not torch.allclose(out["scaffold_w2c"], out["w2c"], atol=1e-3)
    scaf = rec["renders"][2]  # the target, the final context and then the scaffold's context render
    assert torch.equal(scaf[0].means, out["scaffold_gaussians"].means.detach())
    torch.testing.assert_close(scaf[1], out["scaffold_w2c"].detach())
    torch.testing.assert_close(scaf[2], out["scaffold_K"])


def test_d2s_divides_each_sides_depth_by_its_own_scale(monkeypatch):
    """Each render's depth goes to ground-truth units with its own frame's scale; one side's s mis-scales the other."""
    import anycity.lit.refinement as refinement
    from anycity.lit import RefinementModule

    torch.manual_seed(0)
    m = RefinementModule(d2s_depth_scale="cameras", render_backend="torch")
    real_place = m.target_cameras
    batch = _train_batch()

    def target_cameras(pred_w2c, context, query, **k):  # known scales: 2 in the teacher's frame, 0.5 in the student's
        w2c, _ = real_place(pred_w2c, context, query, **k)
        return w2c, torch.tensor([2.0 if context is batch.dense else 0.5])

    monkeypatch.setattr(m, "target_cameras", target_cameras)
    seen = []
    real_d2s = refinement.d2s_loss
    monkeypatch.setattr(refinement, "d2s_loss", lambda s, t, **k: seen.append((s, t)) or real_d2s(s, t, **k))
    rec = _recording(m, monkeypatch)
    m.training_step(batch, 0)
    (student, teacher), = seen
    raw_teacher, raw_student = rec["renders"][-2][3], rec["renders"][-1][3]
    torch.testing.assert_close(teacher.depth, raw_teacher.depth / 2.0)
    torch.testing.assert_close(student.depth, raw_student.depth / 0.5)
