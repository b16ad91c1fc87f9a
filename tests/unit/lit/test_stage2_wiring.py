"""Stage II and protocol wiring a plausible one-line bug would break silently: D2S trains the completion branch
(its student is the final model), and camrefine moves each view's Gaussians with its camera."""

import pytest
import torch

from anycity.geometry import make_intrinsics, project_points
from anycity.lit import RefinementModule, ScaffoldModule
from anycity.structures import ViewBatch, Views

H = W = 32


def _views(n, seed, index=None):
    g = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4).repeat(1, n, 1, 1)
    w2c[..., 0, 3] = torch.linspace(0, 0.3, n)
    K = make_intrinsics(30.0, 30.0, 16.0, 16.0).expand(1, n, 3, 3).clone()
    return Views(images=torch.rand(1, n, 3, H, W, generator=g), w2c=w2c, K=K,
                 depth=torch.rand(1, n, 1, H, W, generator=g) + 1, mask=torch.ones(1, n, 1, H, W, dtype=torch.bool),
                 index=None if index is None else torch.tensor([index]))


@pytest.fixture(scope="module")
def batch():
    return ViewBatch(context=_views(2, 0, [1, 3]), target=_views(1, 1, [2]), dense=_views(3, 2))


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
