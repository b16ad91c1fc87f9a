import math

import pytest
import torch

from anycity.models.gaussians import (
    activate_raw,
    pixel_centres,
    pixel_footprint,
    raw_to_gaussians,
    sh_band_mask,
    voxel_merge,
)
from anycity.models.heads.activations import activate_dense, activate_pose


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


def test_centre_offset_is_depth_times_offset_rotated_into_the_world():
    """An offset is in the source camera's frame and in units of the pixel's depth: offset (0.1, 0, 0) at depth 2
    moves the centre 0.2 along the camera's x axis, which for a camera looking along world +x (camera x = world -z)
    is (0, 0, -0.2) in the world; R_c2w = R_w2c^T, not R_w2c."""
    depth = torch.full((1, 1, 1, 1, 1), 2.0)
    K = torch.tensor([[10.0, 0, 0.5], [0, 10.0, 0.5], [0, 0, 1]]).view(1, 1, 3, 3)  # the pixel centre is on the axis
    R_c2w = torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # camera z -> world +x, camera x -> world -z
    w2c = torch.eye(4)
    w2c[:3, :3] = R_c2w.T
    w2c = w2c.view(1, 1, 4, 4)
    offset = torch.zeros(1, 1, 3, 1, 1)
    offset[:, :, 0] = 0.1
    base = pixel_centres(depth, K, w2c)[0, 0, 0, 0]
    moved = pixel_centres(depth, K, w2c, offset)[0, 0, 0, 0]
    assert torch.allclose(base, torch.tensor([2.0, 0, 0]), atol=1e-6)
    assert torch.allclose(moved - base, torch.tensor([0.0, 0, -0.2]), atol=1e-6)


def test_sh_channels_are_channel_major():
    """The raw SH channels hold all K coefficients of R, then of G, then of B: setting the first K raw SH channels
    gives red coefficients only (band 1 damped by 0.1 * 0.25), not one coefficient of each colour."""
    raw = torch.zeros(1, 8 + 3 * 4)
    raw[0, 8:12] = 1.0
    sh = activate_raw(raw, sh_degree=1)["sh"]  # [1, K, 3]
    assert torch.allclose(sh[0, :, 0], torch.tensor([1.0, 0.025, 0.025, 0.025]))
    assert not sh[0, :, 1:].any()


def test_voxel_merge_softmax_is_stable_for_large_confidences():
    """The per-voxel softmax subtracts the voxel's largest confidence: logits of 100 (exp overflows float32) still
    give the weights 1/4 and 3/4 of logits 0 and ln 3, not NaN."""
    means = torch.tensor([[0.0, 0, 0], [0.1, 0, 0]])
    feats = torch.tensor([[1.0], [3.0]])
    conf = torch.tensor([100.0, 100.0 + math.log(3.0)])
    m, f = voxel_merge(means, feats, conf, voxel_size=1.0)
    assert torch.allclose(f, torch.tensor([[0.25 * 1 + 0.75 * 3]]), atol=1e-4)
    assert torch.allclose(m, torch.tensor([[0.75 * 0.1, 0, 0]]), atol=1e-4)


def test_a_zero_voxel_size_is_refused_not_taken_for_no_merge():
    """None is the documented "no merge"; a voxel size of 0 is an error, not a silent pixel-aligned output."""
    with pytest.raises(ValueError, match="voxel_size"):
        raw_to_gaussians(torch.zeros(1, 1, 12, 2, 2), torch.zeros(1, 1, 2, 2, 3), 0, voxel_size=0.0)


def test_pose_activation_relus_the_field_of_view_by_default():
    """VGGT's pose activation is linear for translation and quaternion and ReLU for the field of view."""
    enc = torch.tensor([0.1, -0.2, 0.3, 0, 0, 0, 1, -0.3, 0.5])
    out = activate_pose(enc)
    assert torch.equal(out[:7], enc[:7])
    assert torch.equal(out[7:], torch.tensor([0.0, 0.5]))
