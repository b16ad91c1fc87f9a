"""Provenance: obs_views by depth test, completion vs the scaffold, and the PLY columns that carry them."""

from __future__ import annotations

import numpy as np
import torch
from helpers.raycast_scenes import H, W, intrinsics, look_at, render_depth
from plyfile import PlyData

from anycity.export import load_ply, load_ply_extras, save_ply
from anycity.export.provenance import completion_score, provenance, summary
from anycity.export.smoothing import sampling_rate
from anycity.structures import Gaussians

BOX = ((-0.5, -0.5, 0.0), (0.5, 0.5, 1.0))


def _gaussians(means: torch.Tensor) -> Gaussians:
    n = means.shape[1]
    return Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4).clone(),
                     scales=torch.full((1, n, 3), 0.01), opacities=torch.full((1, n), 0.5),
                     sh=torch.zeros(1, n, 1, 3))


def test_obs_views_and_completion():
    w2c = torch.stack([look_at(e, (0.0, 0.0, 0.0)) for e in [(0.3, -0.2, 5.0), (4.0, 0.0, 3.0)]])[None]
    K = intrinsics().expand(1, 2, 3, 3)
    depth = render_depth(w2c, K, boxes=[BOX])
    pts = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.2, -1.0, 0.0]]])  # roof, hidden ground, ground
    scaffold = _gaussians(pts)
    refined = _gaussians(pts.clone())
    pixel = 1 / sampling_rate(pts, w2c, K, W, H)  # world size of one input pixel (the 0.01 std is below it)
    refined.means[0, 2, 0] -= 3 * pixel[0, 2]  # a 3-pixel shift: completion 1
    refined.means[0, 1, 0] += 0.3 * pixel[0, 1]  # 0.3 px, no photo resolves it: 0.1, not 1 as 30 stds would say
    refined.opacities[0, 0] = 0.6  # opacity change 0.1
    prov = provenance(refined, scaffold, depth, w2c, K)
    torch.testing.assert_close(prov["obs_views"], torch.tensor([[2.0, 0.0, 2.0]]))
    torch.testing.assert_close(prov["completion"], torch.tensor([[0.1, 0.1, 1.0]]), atol=1e-5, rtol=0)
    share = summary(prov)
    assert share == {"supported": 1 / 3, "completed": 1 / 3, "unsupported": 1 / 3}
    assert (completion_score(scaffold, scaffold) == 0).all()  # Stage I: nothing completed


def test_provenance_columns_in_ply(tmp_path):
    g = _gaussians(torch.randn(1, 5, 3))
    g.quats[0, 1] = 0  # dropped row: the extra columns must drop it too
    prov = {"obs_views": torch.arange(5.0)[None], "completion": torch.linspace(0, 1, 5)[None]}
    assert save_ply(g, tmp_path / "s.ply", extra=prov) == 1
    extras = load_ply_extras(tmp_path / "s.ply")
    np.testing.assert_array_equal(extras["obs_views"], [0, 2, 3, 4])
    np.testing.assert_allclose(extras["completion"], [0, 0.5, 0.75, 1])
    names = PlyData.read(str(tmp_path / "s.ply"))["vertex"].data.dtype.names
    assert names[-2:] == ("obs_views", "completion") and names[:3] == ("x", "y", "z")
    assert load_ply(tmp_path / "s.ply").num_gaussians == 4  # the standard reader ignores them
