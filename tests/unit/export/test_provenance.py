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
    assert share == {"supported": 1 / 3, "completed": 1 / 3, "unsupported": 1 / 3, "unknown": 0.0}
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


def _voxel_merged(raw: torch.Tensor, means: torch.Tensor) -> Gaussians:
    from anycity.models.gaussians import raw_to_gaussians

    return raw_to_gaussians(raw, means, 0, voxel_size=0.05)


def test_voxel_merged_completion_is_unknown_even_at_the_same_count():
    """A test-time voxel merge merges the scaffold and the refined Gaussians separately: row i of one is not row i of
    the other. The score was NaN (other counts) or paired voxels by their order (same count); it is NaN (unknown)
    either way, and NaN counts neither as supported nor as completed (it counted as "kept")."""
    gen = torch.Generator().manual_seed(0)
    raw = torch.randn(1, 1, 12, 16, 16, generator=gen)
    means = torch.rand(1, 1, 16, 16, 3, generator=gen)
    recoloured = raw.clone()
    recoloured[:, :, 8:11] += 2.0  # Stage II recolours every Gaussian: the same voxels, so the same count
    scaffold, refined = _voxel_merged(raw, means), _voxel_merged(recoloured, means)
    assert refined.num_gaussians == scaffold.num_gaussians and scaffold.valid is not None
    comp = completion_score(refined, scaffold)
    assert comp.isnan().all()
    moved = _voxel_merged(recoloured, means + 0.03 * torch.randn(means.shape, generator=gen))
    assert completion_score(moved, scaffold).isnan().all()  # another count: NaN as before
    assert (completion_score(scaffold, scaffold) == 0).all()  # a Stage I model: nothing completed, merged or not
    share = summary({"obs_views": torch.full_like(comp, 3.0), "completion": comp})
    assert share == {"supported": 0.0, "completed": 0.0, "unsupported": 0.0, "unknown": 1.0}


def test_summary_counts_nan_completion_as_unknown():
    prov = {"obs_views": torch.tensor([[3.0, 3.0, 0.0, 3.0]]),
            "completion": torch.tensor([[0.0, float("nan"), float("nan"), 0.9]])}
    assert summary(prov) == {"supported": 0.25, "completed": 0.25, "unsupported": 0.25, "unknown": 0.5}
