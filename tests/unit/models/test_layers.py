import math

import pytest
import torch

from anycity.geometry import make_intrinsics
from anycity.geometry.pose_encoding import (
    blend_pose_encoding,
    extri_intri_to_pose_encoding,
    pose_encoding_to_extri_intri,
)
from anycity.geometry.rotations import quat_to_rotmat
from anycity.models.layers import Attention, Block, DinoViT, RoPE2D, patch_positions


def test_rope_scores_depend_only_on_relative_position():
    torch.manual_seed(0)
    rope = RoPE2D(100.0)
    q, k = torch.randn(1, 2, 1, 16), torch.randn(1, 2, 1, 16)

    def score(pq, pk):
        rq = rope(q, torch.tensor([[pq]]))
        rk = rope(k, torch.tensor([[pk]]))
        return (rq * rk).sum(-1)

    base = score((3, 5), (1, 2))
    assert torch.allclose(score((13, 25), (11, 22)), base, atol=1e-5)  # same offset (2, 3)
    assert not torch.allclose(score((3, 5), (1, 7)), base, atol=1e-3)  # different offset


def test_rope_is_a_rotation_and_identity_at_origin():
    rope = RoPE2D(100.0)
    x = torch.randn(2, 4, 6, 32)
    pos = torch.randint(0, 20, (2, 6, 2))
    assert torch.allclose(rope(x, pos).norm(dim=-1), x.norm(dim=-1), atol=1e-5)
    assert torch.allclose(rope(x, torch.zeros_like(pos)), x)
    # y rotates the first half only, x the second half only
    moved = rope(x, torch.stack([pos[..., 0], torch.zeros_like(pos[..., 1])], -1))
    assert torch.allclose(moved[..., 16:], x[..., 16:])


def _rope_before(x, pos, base=100.0):
    """RoPE2D as it was: angles cast to x's dtype before cos/sin."""
    def rot(x, p):
        d = x.shape[-1]
        inv_freq = 1.0 / base ** (torch.arange(0, d, 2).float() / d)
        a = (p.float()[..., None] * inv_freq).to(x.dtype)
        a = torch.cat([a, a], dim=-1)[:, None]
        x1, x2 = x.chunk(2, dim=-1)
        return x * a.cos() + torch.cat([-x2, x1], dim=-1) * a.sin()
    y, z = x.chunk(2, dim=-1)
    return torch.cat([rot(y, pos[..., 0]), rot(z, pos[..., 1])], dim=-1)


def test_rope_computes_cos_sin_in_float32_for_low_precision_and_keeps_float32_exact():
    torch.manual_seed(0)
    x = torch.randn(1, 4, 1 + 32 * 32, 64)
    pos = patch_positions(1, 32, 32, num_special=1)  # a 448 image: angles up to 32 rad
    rope = RoPE2D(100.0)
    assert torch.equal(rope(x, pos), _rope_before(x, pos))  # float32 and float64 bit for bit as before
    assert torch.equal(rope(x.double(), pos), _rope_before(x.double(), pos))
    ref = rope(x.double(), pos)
    xb = x.bfloat16()
    err = (rope(xb, pos).double() - ref).abs().max().item()
    err_before = (_rope_before(xb, pos).double() - ref).abs().max().item()
    assert rope(xb, pos).dtype == torch.bfloat16
    assert err < 0.08 and err < err_before / 3  # bf16 angles of ~32 rad were off by up to 0.125 rad


def test_block_norm_eps_reaches_the_qk_norm():
    b = Block(64, 4, qk_norm=True, norm_eps=1e-6)
    assert (b.norm1.eps, b.norm2.eps, b.attn.q_norm.eps, b.attn.k_norm.eps) == (1e-6,) * 4
    assert Block(64, 4, qk_norm=True).attn.k_norm.eps == 1e-5


def test_patch_positions_layout():
    pos = patch_positions(2, 3, 4, num_special=5)
    assert pos.shape == (2, 5 + 12, 2)
    assert (pos[:, :5] == 0).all()
    assert pos[0, 5].tolist() == [1, 1] and pos[0, 5 + 4].tolist() == [2, 1] and pos[0, -1].tolist() == [3, 4]


def test_vit_interpolates_position_embedding_to_any_grid():
    vit = DinoViT(img_size=56, patch_size=14, embed_dim=32, depth=1, num_heads=2).eval()
    assert vit(torch.rand(2, 3, 28, 70)).shape == (2, 2 * 5, 32)
    assert vit(torch.rand(1, 3, 56, 56)).shape == (1, 16, 32)


def test_pose_encoding_round_trip():
    torch.manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(2, 3, 4), dim=-1)
    w2c = torch.eye(4).repeat(2, 3, 1, 1)
    w2c[..., :3, :3] = quat_to_rotmat(q)
    w2c[..., :3, 3] = torch.randn(2, 3, 3)
    K = make_intrinsics(torch.full((2, 3), 100.0), torch.full((2, 3), 90.0), 64.0, 48.0)
    enc = extri_intri_to_pose_encoding(w2c, K, (96, 128))
    assert enc.shape == (2, 3, 9)
    assert torch.allclose(enc[..., 7], 2 * torch.atan(torch.tensor(48 / 90.0)))
    w2c2, K2 = pose_encoding_to_extri_intri(enc, (96, 128))
    assert torch.allclose(w2c2, w2c, atol=1e-5) and torch.allclose(K2, K, atol=1e-4)
    # xyzw order: identity rotation is (0, 0, 0, 1)
    ident = extri_intri_to_pose_encoding(torch.eye(4)[None], K[0, :1], (96, 128))
    assert torch.allclose(ident[0, 3:7], torch.tensor([0.0, 0, 0, 1]))
    # unnormalised quaternions are accepted (the camera head does not normalise them)
    enc2 = enc.clone()
    enc2[..., 3:7] *= 3.0
    assert torch.allclose(pose_encoding_to_extri_intri(enc2, (96, 128))[0], w2c, atol=1e-5)
    with pytest.raises(ValueError, match="last dim 9"):
        pose_encoding_to_extri_intri(enc[..., :8], (96, 128))
    assert math.isclose(float(K2[0, 0, 0, 2]), 64.0)


@pytest.mark.parametrize("mode", ["vggt", "anysplat"])
def test_pose_decoding_clamps_the_field_of_view_and_leaves_ordinary_ones_bit_identical(mode):
    # The camera head's FoV is a ReLU: 0 is reachable (infinite focal, -inf gradient) and FoV >= pi gives a focal
    # length <= 0 that render() refuses. Both must decode to finite, positive focal lengths with finite gradients.
    enc = torch.zeros(5, 9)
    enc[:, 6] = 1.0
    enc[:, 7] = enc[:, 8] = torch.tensor([0.0, 1e-8, math.pi, 3.3, -0.5])
    enc.requires_grad_(True)
    _, K = pose_encoding_to_extri_intri(enc, (64, 96), focal_decode=mode)
    fx, fy = K[:, 0, 0], K[:, 1, 1]
    assert torch.isfinite(fx).all() and (fx > 0).all() and torch.isfinite(fy).all() and (fy > 0).all()
    (fx.sum() + fy.sum()).backward()
    assert torch.isfinite(enc.grad).all()
    # ordinary fields of view decode exactly as the unclamped formula (VGGT's cameras are unchanged)
    fov = torch.linspace(0.05, 3.1, 97)
    enc = torch.zeros(97, 9)
    enc[:, 6], enc[:, 7], enc[:, 8] = 1.0, fov, fov
    _, K = pose_encoding_to_extri_intri(enc, (64, 96), focal_decode=mode)
    ref = 96 / (2 * torch.tan(fov / 2)) if mode == "vggt" else 48 / (torch.tan(fov / 2) + 1e-3)
    assert torch.equal(K[:, 0, 0], ref)


def test_blend_pose_encoding_moves_translation_and_rotation_towards_a_pose():
    K = make_intrinsics(torch.full((1, 2), 100.0), torch.full((1, 2), 90.0), 64.0, 48.0)
    start = torch.eye(4).repeat(1, 2, 1, 1)
    start[..., :3, 3] = torch.tensor([1.0, 0, 0])
    enc = extri_intri_to_pose_encoding(start, K, (96, 128))
    enc[..., 3:7] *= -2.0  # the camera head's quaternions: any sign, any norm
    goal = torch.eye(4).repeat(1, 2, 1, 1)
    goal[..., :3, :3] = quat_to_rotmat(torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]))  # 90° z
    goal[..., :3, 3] = torch.tensor([0.0, 2, 0])
    assert torch.equal(blend_pose_encoding(enc, goal, torch.zeros(1, 2, 2)), enc)  # weight 0: exactly the start
    reached, K2 = pose_encoding_to_extri_intri(blend_pose_encoding(enc, goal, torch.ones(1, 2, 2)), (96, 128))
    torch.testing.assert_close(reached, goal, atol=1e-5, rtol=0)
    torch.testing.assert_close(K2, K, atol=1e-4, rtol=0)  # the fields of view are kept
    # per view and per part: view 0 moves half its rotation (45° about z), view 1 half its translation only
    w = torch.tensor([[[0.0, 0.5], [0.5, 0.0]]], requires_grad=True)
    half = pose_encoding_to_extri_intri(blend_pose_encoding(enc, goal, w), (96, 128))[0]
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    torch.testing.assert_close(half[0, 0, :3, :3], torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), atol=1e-5,
                               rtol=0)
    torch.testing.assert_close(half[0, 0, :3, 3], torch.tensor([1.0, 0, 0]))
    torch.testing.assert_close(half[0, 1, :3, :3], torch.eye(3))
    torch.testing.assert_close(half[0, 1, :3, 3], torch.tensor([0.5, 1, 0]))
    (half * torch.randn(half.shape, generator=torch.Generator().manual_seed(0))).sum().backward()
    assert (w.grad.abs() > 0).all()
    with pytest.raises(ValueError, match="weight \\[..., 2\\]"):
        blend_pose_encoding(enc, goal, torch.zeros(1, 2, 1))


def test_block_applies_rope_to_queries_and_keys():
    """RoPE reaches the block's attention and rotates both q and k: shifting every position changes nothing
    (scores depend on relative positions only), collapsing the positions does."""
    torch.manual_seed(0)
    blk = Block(32, 2, qk_norm=True, rope=RoPE2D(100.0), init_values=1.0).eval()
    x, pos = torch.randn(1, 6, 32), torch.randint(1, 9, (1, 6, 2))
    with torch.no_grad():
        a, shifted, flat = blk(x, pos=pos), blk(x, pos=pos + torch.tensor([3, 5])), blk(x, pos=torch.zeros_like(pos))
    assert torch.allclose(a, shifted, atol=1e-5)
    assert not torch.allclose(a, flat, atol=1e-4)


def test_aggregator_global_blocks_get_every_views_positions():
    """The global attention sees all V*T tokens of a sample with their patch positions, as the frame attention does."""
    from anycity.models.aggregator import Aggregator

    agg = Aggregator(img_size=32, patch_size=8, embed_dim=32, depth=1, num_heads=2, patch_embed="conv").eval()
    seen = {}

    def hook(module, args, kwargs):
        seen["pos"] = kwargs.get("pos", args[1] if len(args) > 1 else None)

    agg.global_blocks[0].register_forward_pre_hook(hook, with_kwargs=True)
    with torch.no_grad():
        agg(torch.rand(1, 2, 3, 16, 16))
    t = agg.patch_start_idx + 2 * 2
    assert seen["pos"] is not None and tuple(seen["pos"].shape) == (1, 2 * t, 2)
    frame = patch_positions(2, 2, 2, agg.patch_start_idx, None)
    assert torch.equal(seen["pos"], frame.reshape(1, 2 * t, 2))


def test_attention_k_norm_normalises_the_keys():
    """qk-norm uses k_norm for the keys: a k_norm with zero weight and bias makes every key 0, so attention is
    uniform and each output is the projection of the mean value."""
    torch.manual_seed(0)
    att = Attention(32, 2, qk_norm=True).eval()
    with torch.no_grad():
        att.k_norm.weight.zero_()
        att.k_norm.bias.zero_()
        x = torch.randn(1, 5, 32)
        v = att.qkv(x)[..., 64:]
        ref = att.proj(v.mean(1, keepdim=True).expand(1, 5, 32))
        out = att(x)
    assert torch.allclose(out, ref, atol=1e-5)


def test_vit_stretches_its_square_position_grid_to_a_wide_grid_of_as_many_patches():
    """A 2x8 patch grid has as many patches as the native 4x4 one, yet its position embedding is the 4x4 grid
    resized to 2x8, not the 16 entries read row-wrapped: with channel 0 the native column and channel 1 the row,
    each row of the 2x8 embedding has one row value and increasing columns."""
    vit = DinoViT(img_size=56, patch_size=14, embed_dim=32, depth=1, num_heads=2).eval()
    with torch.no_grad():
        rows, cols = torch.meshgrid(torch.arange(4.0), torch.arange(4.0), indexing="ij")
        vit.pos_embed[0, 1:, 0] = cols.flatten()
        vit.pos_embed[0, 1:, 1] = rows.flatten()
        wide = vit._pos_embed(2, 8, torch.float32)[0, 1:].reshape(2, 8, -1)
    assert not torch.equal(vit._pos_embed(2, 8, torch.float32), vit._pos_embed(4, 4, torch.float32))
    for r in range(2):
        assert torch.allclose(wide[r, :, 1], wide[r, :1, 1].expand(8), atol=1e-5), r
        assert (wide[r, 1:, 0] >= wide[r, :-1, 0] - 1e-5).all(), r
    assert wide[1, 0, 1] > wide[0, 0, 1] + 0.5
