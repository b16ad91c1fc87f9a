"""benchmarks/stage2_headroom.py's perfect-knowledge fit starts at the given Gaussians and fits the views it reads."""

from types import SimpleNamespace

import torch
from helpers.scenes import make_cameras, make_gaussians
from helpers.scripts import load_script

from anycity.render import render


def _bench():
    return load_script("stage2_headroom", "benchmarks")


def _module():
    def _render(g, w2c, K, hw, context):
        return render(g, w2c, K, hw[1], hw[0], background=torch.zeros(3), backend="torch")

    return SimpleNamespace(render=_render)


def test_fit_starts_at_the_gaussians_and_fits_the_views():
    bench, module = _bench(), _module()
    g = make_gaussians(N=200, dtype=torch.float32, seed=0)
    w2c, K = make_cameras(1, 3, 24, 16, dtype=torch.float32)
    target = make_gaussians(N=200, dtype=torch.float32, seed=5)  # another scene: the views to fit
    images = render(target, w2c, K, 24, 16, background=torch.zeros(3), backend="torch").rgb.detach()
    views = [(w2c, K, images)]

    same = bench.fit_gaussians(module, g, views, images, steps=0)
    for a, b in zip((same.means, same.scales, same.opacities, same.sh), (g.means, g.scales, g.opacities, g.sh)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)

    def mse(gauss):
        return ((module.render(gauss, w2c, K, (16, 24), images).rgb - images) ** 2).mean().item()

    fitted = bench.fit_gaussians(module, g, views, images, steps=30)
    assert mse(fitted) < 0.5 * mse(g)
    assert not fitted.means.requires_grad and fitted.valid is g.valid
