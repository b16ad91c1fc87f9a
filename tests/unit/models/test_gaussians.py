import math

import pytest
import torch

from anycity.models.gaussians import activate_raw, pixel_footprint, raw_to_gaussians, sh_band_mask, voxel_merge
from anycity.models.heads.activations import activate_dense


def test_activations_and_xyzw_to_wxyz():
    raw = torch.zeros(2, 8 + 3 * 4)
    raw[:, 0] = torch.tensor([0.0, 100.0])  # opacity logits
    raw[:, 1:4] = torch.tensor([[0.0], [1e4]])  # scale: softplus(0)*1e-3, then the 0.3 clamp
    raw[:, 4:8] = torch.tensor([0.0, 0.0, 0.0, 2.0])  # xyzw identity, not normalised
    raw[:, 8:] = 1.0
    a = activate_raw(raw, sh_degree=1)
    assert torch.allclose(a["opacities"], torch.tensor([0.5, 1.0]))
    assert torch.allclose(a["scales"][0], torch.full((3,), 0.001 * torch.log(torch.tensor(2.0))))
    assert torch.allclose(a["scales"][1], torch.full((3,), 0.3))
    assert torch.allclose(a["quats"], torch.tensor([1.0, 0, 0, 0]).expand(2, 4), atol=1e-6)
    assert a["sh"].shape == (2, 4, 3)
    assert torch.allclose(a["sh"][0, :, 0], torch.tensor([1.0, 0.025, 0.025, 0.025]))
    with pytest.raises(ValueError, match="channels"):
        activate_raw(raw[:, :-1], sh_degree=1)


def test_sh_band_mask_matches_anysplat():
    m = sh_band_mask(4)
    assert m.shape == (25,)
    assert torch.allclose(m[[0, 1, 4, 9, 16]], torch.tensor([1.0, 0.025, 0.00625, 0.0015625, 0.000390625]))


def test_voxel_merge_softmax_weights():
    means = torch.tensor([[0.0, 0, 0], [0.2, 0, 0], [5.0, 5, 5]])
    feats = torch.tensor([[1.0], [3.0], [7.0]])
    conf = torch.tensor([0.0, torch.log(torch.tensor(3.0)), 2.0])
    m, f = voxel_merge(means, feats, conf, voxel_size=1.0)
    assert m.shape == (2, 3)
    order = m[:, 0].argsort()
    assert torch.allclose(f[order, 0], torch.tensor([0.25 * 1 + 0.75 * 3, 7.0]), atol=1e-5)
    assert torch.allclose(m[order][0], torch.tensor([0.15, 0, 0]), atol=1e-5)


def test_voxel_merge_ragged_batch_valid_mask_and_gradients():
    torch.manual_seed(0)
    raw = torch.randn(2, 1, 9 + 3, 4, 4, requires_grad=True)
    means = torch.randn(2, 1, 4, 4, 3)
    means[1] = 0.0  # every pixel of sample 1 falls in one voxel
    g = raw_to_gaussians(raw, means, sh_degree=0, voxel_size=0.5).validate()
    assert g.valid is not None and g.valid[1].sum() == 1 and g.valid[0].sum() == g.num_gaussians
    assert (g.opacities[1, 1:] == 0).all()
    g.opacities[g.valid].sum().backward()
    assert raw.grad[:, :, 0].abs().sum() > 0 and raw.grad[:, :, -1].abs().sum() > 0  # opacity and confidence


def test_pixel_aligned_order():
    raw = torch.zeros(1, 2, 12, 3, 4)
    means = torch.arange(2 * 3 * 4 * 3, dtype=torch.float32).reshape(1, 2, 3, 4, 3)
    g = raw_to_gaussians(raw, means, sh_degree=0)
    assert g.num_gaussians == 24 and g.valid is None
    assert torch.equal(g.means[0, 5], means[0, 0, 1, 1])
    with pytest.raises(ValueError, match="voxel_size"):
        raw_to_gaussians(raw, means, sh_degree=0, voxel_size=-1.0)


def test_rgb_and_footprint_survive_voxel_merge():
    raw = torch.zeros(1, 1, 9 + 3, 2, 2)  # SH degree 0
    means = torch.zeros(1, 1, 2, 2, 3)  # one voxel
    rgb = torch.tensor([[0.2, 0.4], [0.6, 0.8]]).expand(1, 1, 3, 2, 2)
    fp = torch.full((1, 1, 1, 2, 2), 0.02)
    g = raw_to_gaussians(raw, means, sh_degree=0, voxel_size=1.0, rgb=rgb, footprint=fp)
    assert g.num_gaussians == 1
    assert torch.allclose(0.5 + 0.28209479177387814 * g.sh[0, 0, 0], torch.full((3,), 0.5), atol=1e-5)
    assert torch.allclose(g.scales[0, 0], torch.full((3,), 0.02 * torch.log(torch.tensor(2.0))), atol=1e-6)


def test_pixel_footprint_divides_depth_by_the_mean_focal():
    """fx = 100, fy = 50: a pixel at depth d is d / 75 scene units wide (the mean of its two sides), not d / 100;
    one focal alone would size every Gaussian of a non-square-pixel camera for one axis only."""
    K = torch.tensor([[100.0, 0, 2], [0, 50.0, 2], [0, 0, 1]]).expand(1, 2, 3, 3)
    depth = torch.tensor([1.5, 3.0, 7.5, 30.0]).reshape(1, 1, 1, 2, 2).expand(1, 2, 1, 2, 2)
    torch.testing.assert_close(pixel_footprint(depth, K), depth / 75.0)


def test_depth_confidence_is_one_plus_exp():
    """VGGT's "expp1" confidence is 1 + exp(raw) >= 1: a plain exp would shift every confidence by 1, so a
    ``depth_conf_threshold`` (or VGGT weights) set on VGGT's scale would keep or drop the wrong pixels."""
    raw = torch.tensor([-30.0, -1.0, 0.0, 2.0]).reshape(1, 1, 1, 4).expand(1, 2, 1, 4).clone()  # [N, C, H, W]
    raw[:, 0] = 7.0  # the depth channel
    values, conf = activate_dense(raw)
    torch.testing.assert_close(conf, 1 + torch.tensor([[[math.exp(-30.0), math.exp(-1.0), 1.0, math.exp(2.0)]]]))
    assert conf.min() >= 1.0
    torch.testing.assert_close(values, torch.full((1, 1, 4, 1), math.exp(7.0)))
