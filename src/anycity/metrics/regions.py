"""Region diagnostic: which target pixels the sparse context views support (*observed*) and which they do not
(*weak*), and image metrics restricted to each region.

Definition (the paper's region diagnostic): every target pixel with valid target depth is back-projected to a
world point and reprojected into each context view. A context view *sees* the point when it lands in its frame,
in front of it, and passes a depth test against that view's depth map (:func:`~anycity.geometry.visible_views`:
``z <= depth_ref * (1 + depth_tol)`` with the 2x2-neighbourhood minimum as ``depth_ref``, so an occluded point
never leaks through a depth edge). A pixel is **observed** when

- at least ``min_views`` context views see it, and
- the largest angle between the viewing rays (context camera centre -> point) of two seeing views is at least
  ``min_parallax_deg`` (enough baseline to triangulate it; asked only when ``min_views >= 2``: with
  ``min_views=1`` one seeing view is enough), and
- it is not at a depth discontinuity of the target depth (:func:`depth_edges`: relative second difference of
  inverse depth along rows and columns at most ``edge_thresh``; ~ the relative size of a depth step, and zero on
  any plane, so oblique ground and facades seen at grazing angles are not called edges).

**weak** = valid target depth and not observed (low visibility, weak parallax, out of every frame or occluded,
or a depth edge). Pixels without valid target depth (sky: ``<= 0``, non-finite or ``target_valid`` False) are in
neither mask. The masks are disjoint.

Defaults, chosen on the quickstart's synthetic test cities (``orbit`` trajectory, 96 views per city at 48x48,
4 context + 2 targets per sample chosen by ``data.views.select_eval``, ray-cast true depth for targets and
context). Fractions of the valid target pixels (no sky in these cities), ``python benchmarks/regions.py`` at
stop 57: 8 cities, whole scenes, 96 target views (the defaults were chosen on 24-view windows of an earlier data
set, 64 target views, where they gave 0.665 / 0.335):

=========  ========  =========  ====  ========  ====
min_views  parallax  depth_tol  edge  observed  weak
=========  ========  =========  ====  ========  ====
2          2 deg     0.05       0.2   0.562     0.437
2          1 deg     0.10       0.3   0.650     0.350
2          2 deg     0.10       0.3   0.644     0.356   <- defaults (the quickstart's metrics.json: 64.4 / 35.6 %)
2          5 deg     0.10       0.3   0.601     0.399
2          2 deg     0.15       0.5   0.702     0.298
3          2 deg     0.10       0.3   0.502     0.498
=========  ========  =========  ====  ========  ====

On the 24-view windows, the depth edges alone marked 29 / 21 / 17 / 11 % of the pixels at ``edge_thresh``
0.1 / 0.2 / 0.3 / 0.5 (dense cities at 48 px are mostly building outlines), hence 0.3: depth steps of 30 % and
more. ``depth_tol`` 0.1 (looser than :func:`~anycity.geometry.visible_views`' 0.05): at 48 px the 2x2-minimum
reference of an oblique surface is several per cent nearer than the surface (with no edge test and no parallax,
55 / 73 / 79 / 92 % of the pixels were seen by two views at tolerance 0.02 / 0.05 / 0.1 / unlimited). Parallax
matters little on these orbits (the four context views span ~30 deg); 2 deg rules out near-coincident cameras.
With teacher-rendered or predicted depth, expect more weak pixels (noisier depth fails the depth test more often).
"""

from __future__ import annotations

import math
import os
from contextlib import contextmanager
from pathlib import Path

import torch
import torchmetrics
from torch import Tensor

from anycity.geometry import camera_centers, unproject_depth, visible_views
from anycity.metrics.image import SSIM_BORDER, ssim_map, ssim_window_fits

DEFAULT_MIN_VIEWS = 2
DEFAULT_PARALLAX_DEG = 2.0
DEFAULT_DEPTH_TOL = 0.1
DEFAULT_EDGE_THRESH = 0.3

_PAIR_BUDGET = 2**22  # elements of the [B, V, V, n] cosine tensor per parallax chunk (16 MiB in float32)


def _valid_depth(depth: Tensor, valid: Tensor | None) -> Tensor:
    ok = torch.isfinite(depth) & (depth > 0)
    return ok if valid is None else ok & valid.bool()


def depth_edges(depth: Tensor, edge_thresh: float, valid: Tensor | None = None) -> Tensor:
    """``[..., 1, H, W]`` z-depth -> bool mask of pixels at a depth discontinuity.

    The measure is scale-free and zero on any plane however oblique: inverse depth is affine in pixel
    coordinates on a plane, so a pixel b with neighbours a, c along a row or column scores
    ``|1/d_a - 2/d_b + 1/d_c| * max(d_a, d_b, d_c)`` (the second difference of inverse depth relative to the
    smallest inverse depth of the triple). A depth step from d to d (1 + r) between two pixels scores r on both
    of its sides. Triples with an invalid pixel (sky) are ignored; the image border is never marked.
    """
    ok = _valid_depth(depth, valid)
    d = torch.where(ok, depth, torch.ones_like(depth)).float()
    edge = torch.zeros_like(ok)
    for dim in (-1, -2):
        n = d.shape[dim]
        if n < 3:
            continue
        a, b, c = (d.narrow(dim, k, n - 2) for k in range(3))
        trip = ok.narrow(dim, 0, n - 2) & ok.narrow(dim, 1, n - 2) & ok.narrow(dim, 2, n - 2)
        score = (1 / a - 2 / b + 1 / c).abs() * torch.maximum(torch.maximum(a, b), c)
        edge.narrow(dim, 1, n - 2).logical_or_(trip & (score > edge_thresh))
    return edge


def _parallax_chunk(b: int, v: int) -> int:
    """Points per parallax chunk for ``b`` images and ``v`` context views: the ``[b, v, v, n]`` cosine tensor
    stays within ``_PAIR_BUDGET`` elements whatever b and v."""
    return max(1, _PAIR_BUDGET // max(1, b * v * v))


def _max_parallax_cos(points: Tensor, centres: Tensor, vis: Tensor) -> Tensor:
    """Cosine of the largest angle between viewing rays of two seeing views: ``[B, N]`` (1 where < 2 views).

    points ``[B, N, 3]``, centres ``[B, V, 3]``, vis ``[B, V, N]``.
    """
    b, v = vis.shape[:2]
    if v == 0:
        return points.new_ones(points.shape[:2])
    n = _parallax_chunk(b, v)
    out = []
    for s in range(0, points.shape[1], n):
        p, seen = points[:, s:s + n], vis[..., s:s + n]
        rays = p[:, None] - centres[:, :, None]  # [B, V, n, 3]
        rays = rays / rays.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cos = torch.einsum("bvnc,bwnc->bvwn", rays, rays)  # [B, V, V, n], no [B, V, V, n, 3] product
        cos.masked_fill_(~(seen[:, :, None] & seen[:, None]), 1.0)
        out.append(cos.flatten(1, 2).amin(1))
    return torch.cat(out, dim=-1) if out else points.new_ones(points.shape[:2])


def region_masks(target_depth: Tensor, target_w2c: Tensor, target_K: Tensor, context_depth: Tensor,
                 context_w2c: Tensor, context_K: Tensor, *, min_views: int = DEFAULT_MIN_VIEWS,
                 min_parallax_deg: float = DEFAULT_PARALLAX_DEG, depth_tol: float = DEFAULT_DEPTH_TOL,
                 edge_thresh: float = DEFAULT_EDGE_THRESH, target_valid: Tensor | None = None,
                 context_valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Observed and weak target pixels (module docstring has the definition).

    Args:
        target_depth: ``[B, T, 1, H, W]`` z-depth of the targets (ground truth, or teacher-rendered).
        target_w2c, target_K: ``[B, T, 4, 4]``, ``[B, T, 3, 3]`` (pixels of the target depth).
        context_depth: ``[B, V, 1, H', W']`` z-depth of the context views (same world units).
        context_w2c, context_K: ``[B, V, 4, 4]``, ``[B, V, 3, 3]`` (pixels of the context depth).
        min_views: context views that must see a pixel's point.
        min_parallax_deg: largest viewing-ray angle among the seeing views must reach this (degrees); only with
            ``min_views >= 2``: with ``min_views=1`` a pixel seen by one context view and off a depth edge is
            observed.
        depth_tol: relative depth-test tolerance (see :func:`~anycity.geometry.visible_views`).
        edge_thresh: relative depth step above which a target pixel is a depth discontinuity.
        target_valid, context_valid: optional bool masks shaped like the depths (False = no depth).
    Returns:
        ``(observed, weak)``: disjoint bool ``[B, T, 1, H, W]``.
    """
    if target_depth.dim() != 5 or target_depth.shape[2] != 1:
        raise ValueError(f"region_masks: target_depth must be [B, T, 1, H, W], got {tuple(target_depth.shape)}")
    b, t, _, h, w = target_depth.shape
    if target_w2c.shape != (b, t, 4, 4) or target_K.shape != (b, t, 3, 3):
        raise ValueError(f"region_masks: expected target_w2c [{b}, {t}, 4, 4] and target_K [{b}, {t}, 3, 3], got "
                         f"{tuple(target_w2c.shape)}, {tuple(target_K.shape)}")
    if target_valid is not None and target_valid.shape != target_depth.shape:
        raise ValueError(f"region_masks: target_valid must match target_depth {tuple(target_depth.shape)}, got "
                         f"{tuple(target_valid.shape)}")
    if min_views < 1:
        raise ValueError(f"region_masks: min_views must be >= 1, got {min_views}")
    depth = target_depth.float()
    valid = _valid_depth(depth, target_valid)
    d = torch.where(valid, depth, torch.ones_like(depth))
    points = unproject_depth(d, target_K.float(), target_w2c.float()).reshape(b, t * h * w, 3)
    vis = visible_views(points, context_depth, context_w2c, context_K, depth_tol=depth_tol, valid=context_valid)
    vis = vis & valid.reshape(b, 1, -1)
    enough = vis.sum(1) >= min_views
    if min_views >= 2 and min_parallax_deg > 0:  # one view has no parallax: min_views=1 asks for none
        cos = _max_parallax_cos(points, camera_centers(context_w2c.float()), vis)
        enough = enough & (cos <= math.cos(math.radians(min_parallax_deg)))
    observed = enough.reshape(b, t, 1, h, w) & valid & ~depth_edges(depth, edge_thresh, target_valid)
    return observed, valid & ~observed


def _flat(x: Tensor, c: int | None, name: str) -> Tensor:
    if x.dim() < 4 or (c is not None and x.shape[-3] != c):
        raise ValueError(f"{name}: expected [..., {c or 'C'}, H, W] with a leading dim, got {tuple(x.shape)}")
    return x.reshape(-1, *x.shape[-3:])


def masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Per-image mean of ``values [M, C, h, w]`` over the pixels of ``mask [M, 1, h, w]`` (all channels) -> ``[M]``;
    NaN where the mask is empty."""
    m = mask.to(values.dtype)
    n = m.sum(dim=(1, 2, 3))
    out = (values * m).sum(dim=(1, 2, 3)) / (n * values.shape[1]).clamp_min(1)
    return torch.where(n > 0, out, torch.full_like(out, float("nan")))


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Per-image PSNR (dB, images in [0, 1]) over the masked pixels and all channels: ``[..., 3, H, W]`` images,
    ``[..., 1, H, W]`` bool mask -> ``[M]``; NaN where the mask is empty."""
    p, g = _flat(pred, 3, "masked_psnr").float().clamp(0, 1), _flat(target, 3, "masked_psnr").float()
    return -10 * torch.log10(masked_mean((p - g) ** 2, _flat(mask, 1, "masked_psnr")))


def masked_ssim(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Per-image mean of the SSIM map (:func:`anycity.metrics.image.ssim_map`: the pixels 5 px and more inside the
    image) over the masked pixels and channels -> ``[M]``; NaN where the mask is empty there. The window still
    reads unmasked neighbours. NaN for images of 10 px or less on a side (no window fits)."""
    if not ssim_window_fits(pred):
        return torch.full((_flat(pred, 3, "masked_ssim").shape[0],), float("nan"), device=pred.device)
    smap = ssim_map(_flat(pred, 3, "masked_ssim"), _flat(target, 3, "masked_ssim"))
    b = SSIM_BORDER
    return masked_mean(smap, _flat(mask, 1, "masked_ssim")[..., b:-b, b:-b])


def lpips_map(net: torch.nn.Module, pred: Tensor, target: Tensor) -> Tensor:
    """Spatial LPIPS (from :func:`lpips_or_none`) of ``[..., 3, H, W]`` images in [0, 1] -> ``[M, 1, H, W]``."""
    p, g = _flat(pred, 3, "lpips").float().clamp(0, 1), _flat(target, 3, "lpips").float()
    return net(p, g, normalize=True)


def masked_lpips(net: torch.nn.Module, pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Per-image mean of a spatial LPIPS map (from :func:`lpips_or_none`) over the mask -> ``[M]`` (NaN if empty)."""
    return masked_mean(lpips_map(net, pred, target), _flat(mask, 1, "masked_lpips"))


@contextmanager
def _no_downloads():
    """Make every torch.hub download (what torchvision's weight loading falls back to) raise instead."""
    import torch.hub as hub

    def refuse(url, *args, **kwargs):
        raise RuntimeError(f"offline: {url} is not in the torch hub cache {hub.get_dir()}")

    saved = hub.download_url_to_file
    env = {k: os.environ.get(k) for k in ("HF_HUB_OFFLINE", "TORCH_HUB_OFFLINE")}
    hub.download_url_to_file = refuse
    os.environ.update(HF_HUB_OFFLINE="1", TORCH_HUB_OFFLINE="1")
    try:
        yield
    finally:
        hub.download_url_to_file = saved
        for k, v in env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# torchvision's ImageNet weights behind torchmetrics' LPIPS backbones, as torch.hub caches them
_LPIPS_BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth",
                         "squeeze": "squeezenet1_1-b8a52dc0.pth"}


def lpips_or_none(net: str = "vgg") -> tuple[torch.nn.Module | None, str]:
    """A spatial LPIPS network (torchmetrics' ``_LPIPS``, ``spatial=True``: ``[M, 1, H, W]`` maps) built fully
    offline, or ``(None, reason)`` with one line saying why and how to enable it. Never downloads anything.

    ``net`` is the backbone: ``"vgg"`` (default) as the feed-forward papers' evaluation (pixelSplat's
    ``LPIPS(net="vgg")``, used by NoPoSplat and AnySplat), ``"alex"`` or ``"squeeze"``. The figures of different
    backbones are not comparable, so the returned line names it (``LPIPS-vgg``)."""
    if net not in _LPIPS_BACKBONE_FILES:
        raise ValueError(f"lpips_or_none: net must be one of {', '.join(_LPIPS_BACKBONE_FILES)}, got {net!r}")
    name = f"LPIPS-{net}"
    cached = Path(torch.hub.get_dir()) / "checkpoints" / _LPIPS_BACKBONE_FILES[net]
    how = (f"install torchvision matching your torch and put its ImageNet {net} weights at {cached} "
           f"to score {name} (whole image and per region)")
    try:
        from torchmetrics.functional.image.lpips import _LPIPS
        from torchmetrics.utilities.imports import _TORCHVISION_AVAILABLE
    except Exception as e:  # noqa: BLE001 - any import failure means "absent"
        return None, f"{name} left out: torchmetrics LPIPS unavailable ({type(e).__name__}); {how}"
    if not _TORCHVISION_AVAILABLE:
        return None, f"{name} left out: torchvision is not installed; {how}"
    if not cached.is_file():  # checked first: torch.hub would print "Downloading: ..." before _no_downloads refuses
        return None, f"{name} left out: {net} backbone weights are not in the torch hub cache; {how}"
    try:
        with _no_downloads():
            model = _LPIPS(pretrained=True, net=net, spatial=True).eval()
    except Exception as e:  # noqa: BLE001 - missing weights or any backbone failure
        msg = " ".join(str(e).split())[:120]
        return None, f"{name} left out: {net} backbone weights not found offline ({msg}); {how}"
    return model, f"{name} (whole image and per region): torchmetrics {net} backbone, loaded offline from {cached}"


class RegionMetric(torchmetrics.Metric):
    """DDP-safe mean over images of masked PSNR (dB) and of the region's pixel fraction.

    ``update(pred [..., 3, H, W], target, mask [..., 1, H, W], valid [..., 1, H, W] | None)``: images whose mask
    is empty are skipped for PSNR (counted for the fraction); the fraction is mask pixels / valid pixels (all
    pixels when ``valid`` is None). ``compute()`` -> ``{"psnr": mean, "fraction": mean}`` (NaN when no image).
    """

    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        for name in ("psnr_sum", "psnr_count", "frac_sum", "frac_count"):
            self.add_state(name, default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor, mask: Tensor, valid: Tensor | None = None) -> None:
        v = masked_psnr(pred, target, mask).double()
        keep = ~torch.isnan(v)  # empty masks; a perfect region (+inf dB) is kept, as plain PSNR would
        self.psnr_sum += v[keep].sum()
        self.psnr_count += keep.sum()
        m = _flat(mask, 1, "RegionMetric").float()
        denom = m[:, 0].new_full((m.shape[0],), float(m[0].numel())) if valid is None else \
            _flat(valid, 1, "RegionMetric").float().sum(dim=(1, 2, 3))
        frac = m.sum(dim=(1, 2, 3)) / denom.clamp_min(1)
        ok = denom > 0
        self.frac_sum += frac[ok].double().sum()
        self.frac_count += ok.sum()

    def compute(self) -> dict[str, Tensor]:
        nan = torch.tensor(float("nan"), dtype=torch.float64, device=self.psnr_sum.device)
        return {
            "psnr": self.psnr_sum / self.psnr_count if self.psnr_count > 0 else nan,
            "fraction": self.frac_sum / self.frac_count if self.frac_count > 0 else nan,
        }
