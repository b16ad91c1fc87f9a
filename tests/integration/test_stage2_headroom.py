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


def test_the_perfect_knowledge_section_reads_test_samples_with_their_dense_views(tmp_path, monkeypatch):
    # Evaluation samples decode no dense views unless data.eval_dense: section 3 fits to them, so it must ask.
    bench = _bench()
    (tmp_path / "index.json").write_text("{}")
    (tmp_path / "last.ckpt").write_bytes(b"")
    seen = []
    monkeypatch.setattr(bench, "load_module", lambda ckpt: None)
    monkeypatch.setattr(bench, "headroom", lambda module, dm: None)
    monkeypatch.setattr(bench, "teacher_vs_student", lambda module, dm, batches: None)
    monkeypatch.setattr(bench, "perfect_knowledge", lambda module, dm, steps: seen.append(dm))
    monkeypatch.setattr("sys.argv", ["stage2_headroom.py", str(tmp_path / "last.ckpt"), "--data", str(tmp_path),
                                     "--fit-steps", "1"])
    bench.main()
    assert len(seen) == 1 and seen[0].hp.eval_dense and seen[0].hp.num_dense == 8
