"""Tiled, vectorised rasterisation in pure PyTorch (CPU and CUDA, float32 and float64); autograd backward.

Stages (one function each):
1. ``project_gaussians`` (projection.py): 3D -> 2D Gaussians per camera.
2. ``bin_gaussians``: enumerate (tile, Gaussian) pairs from each footprint, sort them by one int64 key
   ``tile << 32 | float32-bits(z)`` (positive float bits sort like the floats), and count pairs per tile.
3. ``composite``: tiles ordered by pair count and processed in chunks padded to the chunk's largest count, so no
   per-pair intermediate exceeds ``chunk_elements`` (large tensors leave glibc's small-block pool and get page-faulted
   afresh on every op). Per chunk, σ comes from one matmul: ``σ(p) - log o`` is a quadratic polynomial in the pixel
   offset p from the tile centre, so pixel monomials ``[tile², 6]`` times per-Gaussian coefficients ``[6, P]`` give
   every (pixel, Gaussian) pair at once. Offsets are tile-centre-relative so every term stays small (≲ 50 where α
   matters), keeping float32 exact to ~1e-6. Transmittance is a cumprod over the depth-sorted Gaussians and
   features are blended by a batched matmul, so depth, alpha and normal channels cost almost nothing extra.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from anycity.render.projection import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected, project_gaussians

DEFAULT_TILE = {"cpu": 4, "cuda": 8}
DEFAULT_CHUNK_ELEMENTS = {"cpu": 1 << 20, "cuda": 1 << 25}


def render_torch(means, quats, scales, opacities, sh, valid, w2c, K, width, height, background, near, far,
                 render_normals, *, tile_size: int | None = None, chunk_elements: int | None = None):
    """Backend entry point (contract in ``anycity.render.api``)."""
    B, V = w2c.shape[:2]
    dev = means.device.type
    tile = tile_size or DEFAULT_TILE.get(dev, 8)
    chunk = chunk_elements or DEFAULT_CHUNK_ELEMENTS.get(dev, 1 << 22)
    proj = project_gaussians(means, quats, scales, opacities, sh, valid, w2c, K, width, height, near, far,
                             render_normals)
    acc = rasterize(proj, width, height, tile, chunk)  # [C, D+1, H, W]; last channel = alpha
    acc = acc.unflatten(0, (B, V))
    alpha = acc[:, :, -1:]
    rgb = acc[:, :, :3] + (1 - alpha) * background[..., None, None]
    depth = acc[:, :, 3:4] / alpha.clamp_min(1e-10)
    normal = acc[:, :, 4:7] if render_normals else None
    return rgb, depth, alpha, normal


def tile_ranges(proj: Projected, tile: int, tiles_x: int, tiles_y: int):
    """Per visible Gaussian: flat index into [C*N], and its tile box [x0, x1) x [y0, y1)."""
    vis = proj.visible.flatten().nonzero()[:, 0]
    mean2d = proj.mean2d.detach().flatten(0, 1).index_select(0, vis)
    radius = proj.radius.flatten(0, 1).index_select(0, vis).to(mean2d.dtype)
    lo = torch.floor((mean2d - radius) / tile).long()
    hi = torch.ceil((mean2d + radius) / tile).long()
    x0, x1 = lo[:, 0].clamp(0, tiles_x), hi[:, 0].clamp(0, tiles_x)
    y0, y1 = lo[:, 1].clamp(0, tiles_y), hi[:, 1].clamp(0, tiles_y)
    return vis, x0, x1, y0, y1


@torch.no_grad()
def bin_gaussians(proj: Projected, tile: int, tiles_x: int, tiles_y: int):
    """Sorted (tile, Gaussian) pairs.

    Visible Gaussians are first sorted by camera z (as int32: positive float32 bits sort like the floats), their
    pairs enumerated in that order, and the pairs then stably sorted by an int32 tile id, which leaves each tile's
    run in depth order. (Two int32 sorts beat one int64 (tile << 32 | z) sort by ~2x on CPU.)

    Returns:
        vis ``[M]``: flat [C*N] index of each visible Gaussian.
        pair_gauss ``[P]``: index into ``vis`` of each pair, sorted by (camera, tile, z).
        counts ``[C*tiles]``: pairs per tile; offsets ``[C*tiles]``: start of each tile's run in the sorted pairs.
    """
    C, N = proj.visible.shape
    n_tiles_total = C * tiles_x * tiles_y
    if n_tiles_total >= 2**31:
        raise ValueError(f"too many tiles ({n_tiles_total}) for int32 tile ids; render fewer or smaller images")
    vis, x0, x1, y0, y1 = tile_ranges(proj, tile, tiles_x, tiles_y)
    z_bits = proj.features[..., 3].detach().flatten().index_select(0, vis).float().view(torch.int32)
    by_depth = torch.sort(z_bits, stable=True).indices
    x0, x1, y0, y1 = (v.index_select(0, by_depth).int() for v in (x0, x1, y0, y1))
    w = x1 - x0
    n_tiles = w * (y1 - y0)
    first_tile = torch.div(vis.index_select(0, by_depth), N, rounding_mode="floor").int() * (tiles_x * tiles_y)
    first_tile += y0 * tiles_x + x0
    starts = torch.cumsum(n_tiles, 0, dtype=torch.int32) - n_tiles
    pair_gauss = torch.repeat_interleave(by_depth, n_tiles)  # pairs in depth order
    k = torch.arange(pair_gauss.numel(), dtype=torch.int32, device=vis.device)
    k -= torch.repeat_interleave(starts, n_tiles)  # index of the pair within its Gaussian's tile box
    wg = torch.repeat_interleave(w, n_tiles)
    row = torch.div(k, wg, rounding_mode="floor")
    tile_id = torch.repeat_interleave(first_tile, n_tiles) + row * tiles_x + (k - row * wg)
    tile_id, order = torch.sort(tile_id, stable=True)
    pair_gauss = pair_gauss.index_select(0, order)
    counts = torch.bincount(tile_id, minlength=n_tiles_total)
    offsets = torch.cumsum(counts, 0) - counts
    return vis, pair_gauss, counts, offsets


def _pixel_monomials(tile: int, dtype, device) -> Tensor:
    """``[tile², 6]`` rows (1, px, py, px², px·py, py²) of pixel-centre offsets from the tile centre."""
    r = torch.arange(tile, dtype=dtype, device=device) + 0.5 - tile / 2
    py, px = torch.meshgrid(r, r, indexing="ij")
    px, py = px.flatten(), py.flatten()
    return torch.stack([torch.ones_like(px), px, py, px * px, px * py, py * py], -1)


def rasterize(proj: Projected, width: int, height: int, tile: int = 4, chunk_elements: int = 1 << 20) -> Tensor:
    """Composite projected Gaussians front to back. Returns ``[C, D+1, H, W]``: blended features and alpha."""
    C, N, D = proj.features.shape
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    vis, pair_gauss, counts, offsets = bin_gaussians(proj, tile, tiles_x, tiles_y)
    dtype, device = proj.mean2d.dtype, proj.mean2d.device

    # One channel-major parameter table of the visible Gaussians, [6 + D, M + 1]: gathering columns with
    # index_select(1, ·) has a backward (index_add_ along dim 1) ~4x faster on CPU than gathering rows. The last
    # column is the padding slot every padded pair points at.
    table = torch.cat([proj.mean2d, proj.conic, proj.opacity[..., None], proj.features], -1).flatten(0, 1)
    table = table.index_select(0, vis).t()
    table = torch.cat([table, table.new_zeros(table.shape[0], 1)], 1)
    pair_gauss = torch.cat([pair_gauss, pair_gauss.new_full((1,), vis.numel())])
    pad_slot = pair_gauss.numel() - 1

    neg_monomials = -_pixel_monomials(tile, dtype, device)
    active = counts.nonzero()[:, 0]
    active = active[torch.argsort(counts[active], descending=True, stable=True)]
    active_counts = counts[active].tolist()
    per_tile = tile * tile
    tile_ids, outputs = [], []
    s = 0
    while s < len(active_counts):
        P = active_counts[s]
        e = min(len(active_counts), s + max(1, chunk_elements // (per_tile * P)))
        tiles = active[s:e]
        outputs.append(_composite_chunk(table, pair_gauss, tiles, offsets, counts, P, pad_slot, neg_monomials, tile,
                                        tiles_x, tiles_y, D))
        tile_ids.append(tiles)
        s = e

    acc = table.new_zeros(C * tiles_x * tiles_y, per_tile, D + 1)
    if outputs:
        acc = acc.index_copy(0, torch.cat(tile_ids), torch.cat(outputs))
    elif table.requires_grad:
        acc = acc + 0 * table.sum()  # keep the graph connected when nothing is visible
    acc = acc.view(C, tiles_y, tiles_x, tile, tile, D + 1).permute(0, 5, 1, 3, 2, 4)
    return acc.reshape(C, D + 1, tiles_y * tile, tiles_x * tile)[:, :, :height, :width]


def _composite_chunk(table, pair_gauss, tiles, offsets, counts, P, pad_slot, neg_monomials, tile, tiles_x, tiles_y,
                     D):
    """Blend one chunk of t tiles with at most P pairs each -> ``[t, tile², D+1]``."""
    slot = torch.arange(P, device=tiles.device)
    idx = offsets[tiles, None] + slot
    idx = torch.where(slot < counts[tiles, None], idx, pad_slot)  # [t, P]
    g = pair_gauss.index_select(0, idx.flatten())
    rows = table.index_select(1, g).view(-1, *idx.shape)  # [6 + D, t, P]
    mx, my, a, b, c, opacity = rows[:6]

    local = tiles % (tiles_x * tiles_y)
    centre_x = ((local % tiles_x).to(rows.dtype) + 0.5) * tile
    centre_y = (torch.div(local, tiles_x, rounding_mode="floor").to(rows.dtype) + 0.5) * tile
    mx, my = mx - centre_x[:, None], my - centre_y[:, None]  # mean relative to the tile centre, [t, P]
    # σ(p) - log(o) = σ0 + g·p + ½ pᵀ conic p with σ0 = ½ mᵀ conic m - log o and g = -conic m.
    sigma0 = 0.5 * (a * mx * mx + c * my * my) + b * mx * my - torch.log(opacity.clamp_min(ALPHA_MIN))
    sigma0 = torch.where(idx == pad_slot, torch.full_like(sigma0, math.inf), sigma0)
    coeffs = torch.stack([sigma0, -(a * mx + b * my), -(b * mx + c * my), 0.5 * a, b, 0.5 * c], 1)  # [t, 6, P]
    feats = rows[6:].transpose(0, 1)  # [t, D, P]
    feats_t = torch.cat([feats, torch.ones_like(feats[:, :1])], 1)  # [t, D+1, P]; alpha = Σ w rides along
    return _Composite.apply(coeffs, feats_t, neg_monomials)


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of one chunk with a hand-written backward.

    Forward: ``α = min(0.99, e)`` where ``e = exp(-(M @ coeffs)) = o·e^(-σ)`` and ``e >= 1/255`` (else 0),
    ``w_i = α_i T_i`` with ``T_i = Π_{j<i} (1 - α_j)``, for the Gaussians before the one that brings T to <= 1e-4;
    ``out = w @ feats``. Since T is non-increasing the kept Gaussians are a prefix, and for them
    ``T_i = T_{i+1} / (1 - α_i)``, so ``u = T · keep = threshold(cumprod(1 - α), 1e-4) / (1 - α)``.

    Backward, with g = dL/dw and S_k = Σ_{i>k} g_i w_i: ``dL/dα_k = g_k u_k - S_k / (1 - α_k)`` and dα/dσ = -α where
    α is neither clamped nor cut (α' = that α, else 0), so ``dL/dσ_k = α'_k (S_k / (1 - α_k) - g_k u_k)``.

    CPU notes (per 1M-element chunk, 1 thread): in-place elementwise ops cost ~0.1 ms but building a bool mask and
    multiplying by it ~1.1 ms, and ``masked_fill_`` ~3.8 ms, so every cut here is a ``threshold``. The small-output
    batched matmuls are ~4x faster with the P-long operand transposed (``[t, D+1, P] @ [t, P, tile²]``).
    """

    @staticmethod
    def forward(ctx, coeffs: Tensor, feats_t: Tensor, neg_monomials: Tensor) -> Tensor:
        alpha = torch.matmul(neg_monomials, coeffs).exp_()  # [t, tile², P]
        F.threshold(alpha, _below(ALPHA_MIN, alpha.dtype), 0.0, inplace=True)
        # α' (α where neither cut nor clamped, else 0) before clamping: -threshold(-e, -0.99) keeps e < 0.99.
        alpha_active = F.threshold(alpha.neg(), -ALPHA_MAX, 0.0, inplace=True).neg_()
        alpha.clamp_max_(ALPHA_MAX)
        one_minus = 1 - alpha
        u = F.threshold(torch.cumprod(one_minus, -1), T_MIN, 0.0, inplace=True).div_(one_minus)
        w = u * alpha
        ctx.save_for_backward(alpha, alpha_active, u, feats_t, neg_monomials)
        return torch.bmm(feats_t, w.transpose(1, 2)).transpose(1, 2)  # [t, tile², D+1]

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        alpha, alpha_active, u, feats_t, neg_monomials = ctx.saved_tensors
        grad_out = grad_out.contiguous()
        gu = torch.bmm(grad_out, feats_t).mul_(u)  # g_k u_k, [t, tile², P]
        gw = gu * alpha
        suffix = gw.cumsum(-1).neg_().add_(gw.sum(-1, keepdim=True))  # S_k = Σ_{i>k} g_i w_i
        grad_sigma = suffix.div_(1 - alpha).sub_(gu).mul_(alpha_active)  # dL/d(σ - log o)
        grad_coeffs = torch.matmul(neg_monomials.t(), grad_sigma).neg_()  # M = -neg_monomials
        grad_feats_t = torch.bmm(grad_out.transpose(1, 2), u * alpha)  # saved tensors stay intact: w = u α
        return grad_coeffs, grad_feats_t, None


def _below(x: float, dtype: torch.dtype) -> float:
    """The largest value of ``dtype`` below x, so that ``threshold(v, _below(x))`` keeps exactly v >= x."""
    t = torch.tensor(x, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))
