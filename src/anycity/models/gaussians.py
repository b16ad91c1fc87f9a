"""Raw Gaussian-head channels -> :class:`anycity.structures.Gaussians` (AnySplat's adapter, our conventions).

Raw layout per pixel (``C_raw = 9 + 3K``, K = (d+1)^2): ``[opacity logit, scale (3), quaternion xyzw (4),
SH (3*K, channel-major: all K of R, then G, then B), merge confidence]``. Activations: opacity sigmoid,
scale ``0.001 * softplus`` clamped at 0.3 (normalised scene units), quaternion normalised and converted to
wxyz here (the Gaussian head's xyzw boundary), SH band d scaled by ``0.1 * 0.25^d`` for d >= 1.

Two optional per-pixel inputs change the activations (``NetConfig.color_mode`` / ``scale_mode``):
``rgb`` adds the pixel's own colour to the SH DC term (``(rgb - 0.5) / C0``), so the head predicts a residual;
``footprint`` (depth / focal, the pixel's size in scene units) replaces the absolute ``0.001`` scale factor,
so ``softplus(0)`` gives a Gaussian about 0.7 pixels wide in its own view at any depth.

Centres are the predicted depth unprojected with the predicted cameras (world = first camera). The
optional voxel merge averages raw features and centres inside each voxel with per-voxel softmax weights of
the confidence channel (plain torch: ``scatter_reduce`` + ``index_add``), then activates; batches with
different voxel counts are padded and carry a ``valid`` mask.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from anycity.geometry import unproject_depth, xyzw_to_wxyz
from anycity.structures import Gaussians

SCALE_FACTOR, SCALE_MAX = 0.001, 0.3
SH_C0 = 0.28209479177387814  # degree-0 SH basis; colour = 0.5 + C0 * dc


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """RGB in [0, 1] -> the SH DC coefficient that renders it (``(rgb - 0.5) / C0``)."""
    return (rgb - 0.5) / SH_C0


def pixel_footprint(depth: Tensor, K: Tensor) -> Tensor:
    """``depth [B, V, 1, H, W]``, ``K [B, V, 3, 3]`` -> ``[B, V, 1, H, W]``: a pixel's width in scene units at
    that depth (``depth / mean(fx, fy)``)."""
    focal = 0.5 * (K[..., 0, 0] + K[..., 1, 1])
    return depth.float() / focal.float().clamp_min(1e-6)[..., None, None, None]


def sh_band_mask(sh_degree: int, device=None) -> Tensor:
    """``[K]`` damping per SH coefficient: 1 for degree 0, ``0.1 * 0.25^d`` for degree d."""
    w = [1.0] + [0.1 * 0.25 ** d for d in range(1, sh_degree + 1) for _ in range(2 * d + 1)]
    return torch.tensor(w, device=device)


def activate_raw(raw: Tensor, sh_degree: int, rgb: Tensor | None = None,
                 footprint: Tensor | None = None) -> dict[str, Tensor]:
    """``[..., C_raw - 1]`` (no confidence) -> opacities ``[...]``, scales ``[..., 3]``, quats wxyz ``[..., 4]``,
    sh ``[..., K, 3]``. ``rgb [..., 3]`` (optional) is added to the DC term as colour; ``footprint [...]``
    (optional, scene units per pixel) makes scales ``footprint * softplus`` instead of ``0.001 * softplus``."""
    k = (sh_degree + 1) ** 2
    if raw.shape[-1] != 8 + 3 * k:
        raise ValueError(f"raw gaussians: expected {8 + 3 * k} channels for SH degree {sh_degree}, got {raw.shape[-1]}")
    opacity, scale, quat, sh = raw.split((1, 3, 4, 3 * k), dim=-1)
    quat = quat / (quat.norm(dim=-1, keepdim=True) + 1e-8)
    sh = sh.unflatten(-1, (3, k)).transpose(-1, -2) * sh_band_mask(sh_degree, raw.device)[:, None]
    if rgb is not None:
        sh = torch.cat([sh[..., :1, :] + rgb_to_sh_dc(rgb)[..., None, :], sh[..., 1:, :]], dim=-2)
    factor = SCALE_FACTOR if footprint is None else footprint[..., None]
    scales = (factor * F.softplus(scale)).clamp_max(SCALE_MAX)
    return {"opacities": torch.sigmoid(opacity[..., 0]), "scales": scales, "quats": xyzw_to_wxyz(quat), "sh": sh}


def pixel_centres(depth: Tensor, K: Tensor, w2c: Tensor, offset: Tensor | None = None) -> Tensor:
    """``depth [B, V, 1, H, W]`` -> world centres ``[B, V, H, W, 3]`` (float32).

    ``offset [B, V, 3, H, W]`` (optional) moves each centre off its pixel's ray: ``depth * offset`` in the source
    camera's frame (x right, y down, z forward), so an offset of 0.1 is a tenth of the pixel's depth whatever the
    scene's scale. Zero offsets give exactly the unprojected depth.
    """
    means = unproject_depth(depth.float(), K.float(), w2c.float())
    if offset is None:
        return means
    d_cam = (depth.float() * offset.float()).permute(0, 1, 3, 4, 2)  # [B, V, H, W, 3]
    R_c2w = w2c.float()[..., :3, :3].transpose(-1, -2)
    return means + torch.einsum("bvij,bvhwj->bvhwi", R_c2w, d_cam)


def voxel_merge(means: Tensor, feats: Tensor, conf: Tensor, voxel_size: float) -> tuple[Tensor, Tensor]:
    """Merge points of one scene per voxel. ``means [N, 3]``, ``feats [N, C]``, ``conf [N]`` raw logits ->
    ``(means [M, 3], feats [M, C])``, weights = softmax of ``conf`` within each voxel."""
    idx = torch.round(means.detach() / voxel_size).long()
    _, inv = torch.unique(idx, dim=0, return_inverse=True)
    m = int(inv.max()) + 1
    cmax = torch.full((m,), float("-inf"), device=conf.device, dtype=conf.dtype)
    cmax = cmax.scatter_reduce(0, inv, conf.detach(), reduce="amax", include_self=True)
    e = torch.exp(conf - cmax[inv])
    denom = torch.zeros(m, device=conf.device, dtype=conf.dtype).index_add(0, inv, e)
    wgt = (e / (denom[inv] + 1e-6))[:, None]
    out_means = torch.zeros(m, 3, device=means.device, dtype=means.dtype).index_add(0, inv, wgt * means)
    out_feats = torch.zeros(m, feats.shape[-1], device=feats.device, dtype=feats.dtype).index_add(0, inv, wgt * feats)
    return out_means, out_feats


def _pad(x: Tensor, n: int, value: float) -> Tensor:
    return torch.cat([x, x.new_full((n - x.shape[0], *x.shape[1:]), value)], dim=0)


def _flat(x: Tensor) -> Tensor:
    """``[B, V, C, H, W]`` -> ``[B, V*H*W, C]`` (float32)."""
    return x.float().permute(0, 1, 3, 4, 2).reshape(x.shape[0], -1, x.shape[2])


def raw_to_gaussians(raw: Tensor, means: Tensor, sh_degree: int, voxel_size: float | None = None,
                     rgb: Tensor | None = None, footprint: Tensor | None = None) -> Gaussians:
    """Raw head output ``[B, V, C_raw, H, W]`` and centres ``[B, V, H, W, 3]`` -> Gaussians.

    ``rgb [B, V, 3, H, W]`` (pixel colours added to the DC term) and ``footprint [B, V, 1, H, W]`` (pixel-relative
    scales) are optional, see :func:`activate_raw`; a voxel merge averages them with the same weights.
    Without ``voxel_size``: N = V*H*W in (view, row, column) order, ``valid`` None. With it: N = the largest
    voxel count in the batch; padded entries have opacity 0, unit quaternion, scale 1e-4 and ``valid`` False.
    """
    b = raw.shape[0]
    feats = _flat(raw)
    conf, body = feats[..., -1], feats[..., :-1]
    aux = [x for x in (rgb, footprint) if x is not None]
    c = body.shape[-1]
    if aux:
        body = torch.cat([body, *(_flat(x) for x in aux)], dim=-1)

    def act(f: Tensor) -> dict[str, Tensor]:
        extra = f[..., c:]
        col = extra[..., :3] if rgb is not None else None
        fp = extra[..., -1] if footprint is not None else None
        return activate_raw(f[..., :c], sh_degree, col, fp)

    pts = means.reshape(b, -1, 3)
    if voxel_size is None:
        return Gaussians(means=pts, **act(body))
    if voxel_size <= 0:
        raise ValueError(f"voxel_size: expected a positive float (scene units) or None, got {voxel_size}")
    merged = [voxel_merge(pts[i], body[i], conf[i], voxel_size) for i in range(b)]
    n = max(m.shape[0] for m, _ in merged)
    acts = [act(f) for _, f in merged]
    counts = [m.shape[0] for m, _ in merged]
    pad = {"opacities": 0.0, "scales": 1e-4, "sh": 0.0}
    out = {key: torch.stack([_pad(a[key], n, pad[key]) if key in pad else
                             torch.cat([a[key], a[key].new_tensor([1.0, 0, 0, 0]).expand(n - a[key].shape[0], 4)])
                             for a in acts]) for key in acts[0]}
    valid = torch.stack([torch.arange(n, device=raw.device) < c for c in counts])
    return Gaussians(means=torch.stack([_pad(m, n, 0.0) for m, _ in merged]), valid=valid, **out)
