"""The region diagnostic (AnyCity, "Diagnostic evaluation"): which target pixels the sparse context observes.

Each target pixel is back-projected with the target's depth and reprojected into every context view; a view sees it
when it passes the depth test of :func:`anycity.geometry.visibility.visible_views` against that view's depth.

* **observation-supported**: seen by at least ``min_views`` context views whose rays to the point span at least
  ``min_parallax_deg`` (the largest angle between two seeing views' rays), and not on a depth discontinuity;
* **weak**: every other pixel with valid depth: seen by fewer views, too little parallax, out of every context frame
  or occluded in all of them, or on a depth edge (relative depth jump to a 4-neighbour above ``edge_thresh``, or a
  neighbour without depth);
* pixels without valid target depth (sky) are in neither.

Defaults, from the quickstart's test cities (48x48 orbit views, 4 context views spread over the 7 nearest trajectory
views of each held-out view, 96 target views of 8 unseen cities; `python benchmarks/regions.py`): ``min_views=2``,
``min_parallax_deg=5``, ``depth_tol=0.03``, ``edge_thresh=0.1`` give about three quarters observed and one quarter
weak (the exact shares are printed by that script and logged as ``region_obs`` / ``region_weak``). Stricter
parallax moves pixels seen from nearly the same direction to weak; the paper's point is that weak content (facades,
far buildings, thin and self-occluded structure) is where completion should help.

``masked_psnr`` / ``masked_ssim`` score one region per image; ``lpips_or_none`` builds torchmetrics' LPIPS only when
it can run offline.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics.functional.image import structural_similarity_index_measure

from anycity.geometry import camera_centers, unproject_depth
from anycity.geometry.visibility import visible_views

CHUNK = 16384  # target pixels per parallax step


def depth_edges(depth: Tensor, valid: Tensor, edge_thresh: float) -> Tensor:
    """``[..., 1, H, W]`` bool: a relative depth jump above ``edge_thresh`` to a 4-neighbour, or a neighbour without
    valid depth (a silhouette against the sky)."""
    d = torch.where(valid, depth.float(), torch.zeros_like(depth, dtype=torch.float32))
    lead = d.shape[:-3]
    d = d.reshape(-1, 1, *d.shape[-2:])
    m = valid.reshape(-1, 1, *valid.shape[-2:]).float()
    dp = F.pad(d, (1, 1, 1, 1), mode="replicate")
    mp = F.pad(m, (1, 1, 1, 1), mode="replicate")
    h, w = d.shape[-2:]
    edge = torch.zeros_like(d, dtype=torch.bool)
    for dy, dx in ((0, 1), (1, 0), (1, 2), (2, 1)):
        nd, nm = dp[..., dy:dy + h, dx:dx + w], mp[..., dy:dy + h, dx:dx + w]
        edge |= (nm < 0.5) | ((d - nd).abs() > edge_thresh * d.clamp_min(1e-9))
    return edge.reshape(*lead, 1, h, w) & valid


def _max_parallax(points: Tensor, centres: Tensor, seen: Tensor) -> Tensor:
    """``points [B, N, 3]``, camera ``centres [B, V, 3]``, ``seen [B, V, N]`` -> ``[B, N]`` largest angle (degrees)
    between the rays of two seeing views (0 when fewer than two see the point)."""
    out = []
    for s in range(0, points.shape[1], CHUNK):
        rays = points[:, None, s:s + CHUNK] - centres[:, :, None]  # [B, V, n, 3]
        rays = rays / rays.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cos = torch.einsum("bvnc,bunc->bnvu", rays, rays).clamp(-1, 1)
        sn = seen[:, :, s:s + CHUNK].transpose(1, 2)  # [B, n, V]
        pair = sn[..., :, None] & sn[..., None, :]
        ang = torch.where(pair, torch.rad2deg(torch.acos(cos)), torch.zeros_like(cos))
        out.append(ang.flatten(-2).amax(-1))
    return torch.cat(out, dim=1)


def region_masks(target_depth: Tensor, target_w2c: Tensor, target_K: Tensor, context_depth: Tensor,
                 context_w2c: Tensor, context_K: Tensor, *, min_views: int = 2, min_parallax_deg: float = 5.0,
                 depth_tol: float = 0.05, edge_thresh: float = 0.3, target_valid: Tensor | None = None,
                 context_valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Observation-supported and weak target pixels (see the module docstring).

    Args:
        target_depth: ``[B, T, 1, H, W]`` z-depth of the targets (ground truth, or a teacher's render).
        target_w2c, target_K: ``[B, T, 4, 4]``, ``[B, T, 3, 3]``.
        context_depth: ``[B, V, 1, H', W']``; context_w2c, context_K: ``[B, V, 4, 4]``, ``[B, V, 3, 3]`` (same
            world frame and units as the targets).
        target_valid, context_valid: bool masks of usable depth (same shapes as the depths), or None.
    Returns:
        ``(observed, weak)``: bool ``[B, T, 1, H, W]``, disjoint; neither where the target depth is invalid.
    """
    if target_depth.dim() != 5 or context_depth.dim() != 5:
        raise ValueError(f"region_masks: depths must be [B, T|V, 1, H, W], got {tuple(target_depth.shape)} and "
                         f"{tuple(context_depth.shape)}")
    b, t, _, h, w = target_depth.shape
    td = target_depth.float()
    valid = torch.isfinite(td) & (td > 0)
    if target_valid is not None:
        valid = valid & target_valid.bool()
    points = unproject_depth(torch.where(valid, td, torch.ones_like(td)), target_K.float(), target_w2c.float())
    points = points.reshape(b, -1, 3)  # [B, T*H*W, 3]
    seen = visible_views(points, context_depth, context_w2c, context_K, depth_tol=depth_tol, valid=context_valid)
    count = seen.sum(1)
    parallax = _max_parallax(points, camera_centers(context_w2c.float()), seen)
    supported = ((count >= min_views) & (parallax >= min_parallax_deg)).reshape(b, t, 1, h, w)
    observed = supported & valid & ~depth_edges(td, valid, edge_thresh)
    return observed, valid & ~observed


def _mask_weights(mask: Tensor, like: Tensor) -> Tensor:
    if mask.shape[0] != like.shape[0] or mask.shape[-2:] != like.shape[-2:]:
        raise ValueError(f"masked metric: mask {tuple(mask.shape)} does not match images {tuple(like.shape)}")
    return mask.float().expand_as(like)


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """``[M]`` PSNR (dB, data range 1) of ``[M, 3, H, W]`` images over the pixels of ``mask [M, 1, H, W]``; NaN
    where the mask is empty."""
    m = _mask_weights(mask, pred)
    n = m.sum(dim=(1, 2, 3))
    mse = ((pred.float().clamp(0, 1) - target.float()).square() * m).sum(dim=(1, 2, 3)) / n.clamp_min(1)
    out = -10 * torch.log10(mse.clamp_min(1e-10))
    return torch.where(n > 0, out, torch.full_like(out, float("nan")))


def masked_ssim(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """``[M]`` mean of the SSIM map (Gaussian window 11, sigma 1.5) over ``mask [M, 1, H, W]``; NaN where empty."""
    _, full = structural_similarity_index_measure(pred.float().clamp(0, 1), target.float(), data_range=1.0,
                                                  reduction="none", return_full_image=True)
    m = _mask_weights(mask, full)
    n = m.sum(dim=(1, 2, 3))
    out = (full * m).sum(dim=(1, 2, 3)) / n.clamp_min(1)
    return torch.where(n > 0, out, torch.full_like(out, float("nan")))


def masked_lpips(lpips, pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """``[M]`` LPIPS of one region: torchmetrics' LPIPS gives one number per image pair, so the region is scored as the
    LPIPS between the target and a composite that is the prediction inside ``mask`` and the target outside it
    (0 outside the region by construction); NaN where the mask is empty. ``lpips(a [1, 3, H, W], b) -> scalar``."""
    m = _mask_weights(mask, pred)
    comp = pred.float().clamp(0, 1) * m + target.float() * (1 - m)
    out = torch.stack([torch.as_tensor(lpips(comp[i:i + 1], target[i:i + 1].float())).float().reshape(())
                       for i in range(pred.shape[0])])
    return torch.where(m.flatten(1).sum(1) > 0, out, torch.full_like(out, float("nan")))


def lpips_or_none(net_type: str = "alex") -> tuple[object | None, str]:
    """torchmetrics' LPIPS when it can be built offline (torchvision installed and the backbone weights already in
    the torch hub cache), else None. Returns ``(metric or None, one line saying which and why)``; never downloads."""
    import os

    try:
        import torchvision  # noqa: F401
    except Exception:  # ImportError, or torchvision built for another torch
        return None, ("LPIPS: left out (torchvision is not installed); install torchvision matching torch and put "
                      f"the {net_type} backbone weights in the torch hub cache to get it")
    old = {k: os.environ.get(k) for k in ("HF_HUB_OFFLINE", "TORCH_HOME")}
    os.environ["HF_HUB_OFFLINE"] = "1"
    try:
        import torch.hub
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        hub = os.path.join(torch.hub.get_dir(), "checkpoints")
        if not os.path.isdir(hub) or not os.listdir(hub):
            return None, (f"LPIPS: left out (no backbone weights in {hub}); put the {net_type} weights there to get it"
                          " (this never downloads)")
        return LearnedPerceptualImagePatchSimilarity(net_type=net_type, normalize=True), "LPIPS: on"
    except Exception as err:  # noqa: BLE001 - any failure to build offline means: leave the figure out
        return None, f"LPIPS: left out ({type(err).__name__}: {str(err).splitlines()[0][:120]})"
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
