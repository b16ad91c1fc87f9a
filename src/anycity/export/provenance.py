"""Provenance of each Gaussian: which ones the photos support and which ones the model completed.

- ``obs_views [B, N]``: how many context views see the Gaussian's centre (in frame, in front, and not behind
  that view's predicted depth; :func:`anycity.geometry.visibility.count_visible`). A pixel-aligned Gaussian is
  always seen by its own view, so *observation-supported* means seen by at least two.
- ``completion [B, N]`` in [0, 1]: how much Stage II changed the Gaussian from its scaffold (the Stage I
  decoding of the same pixel): the largest of the centre shift in units of 3 × its size, the opacity change and
  the DC colour change (RGB distance / sqrt 3), each clipped to 1. The size is the scaffold's mean std, but at
  least one input pixel at the Gaussian (``1 / ν``, ν the highest sampling rate of a context camera): most
  predicted Gaussians are far below a pixel, and a shift no photo could resolve is not a completion. 0 for a
  Stage I model. NaN (unknown) when the two sets are not pixel-aligned one to one: a test-time voxel merge
  (``net.voxel_size``) merges the scaffold and the refined Gaussians separately, so their rows do not pair up even
  when the counts agree. NaN Gaussians count neither as supported nor as completed.
"""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.export.smoothing import sampling_rate
from anycity.geometry.visibility import count_visible
from anycity.structures import Gaussians

SH_C0 = 0.28209479177387814
SUPPORT_VIEWS = 2  # seen by its own view and at least one other
COMPLETED = 0.25  # completion above this: Stage II moved/recoloured it noticeably


def completion_score(refined: Gaussians, scaffold: Gaussians, pixel: Tensor | None = None) -> Tensor:
    """``[B, N]`` in [0, 1]; zeros when the two are the same object, NaN when their Gaussians do not pair up one
    to one: a voxel merge made them (it alone sets ``valid``; merged separately, row i of one is not row i of the
    other even at the same N) or N differs. ``pixel [B, N]``: the world size of one input pixel at each scaffold
    centre (the smallest shift that counts; None = the std alone)."""
    if refined is scaffold:
        return torch.zeros_like(refined.opacities)
    if not pixel_aligned_pair(refined, scaffold):
        return torch.full_like(refined.opacities, float("nan"))
    size = scaffold.scales.mean(-1)
    if pixel is not None:
        size = torch.maximum(size, pixel.to(size))
    size = size.clamp_min(1e-12)
    pos = (refined.means - scaffold.means).norm(dim=-1) / (3 * size)
    opa = (refined.opacities - scaffold.opacities).abs()
    rgb = lambda g: (0.5 + SH_C0 * g.sh[..., 0, :]).clamp(0, 1)  # noqa: E731
    col = (rgb(refined) - rgb(scaffold)).norm(dim=-1) / 3 ** 0.5
    return torch.stack([pos, opa, col], -1).clamp(0, 1).amax(-1)


def pixel_aligned_pair(refined: Gaussians, scaffold: Gaussians) -> bool:
    """Whether row i of ``refined`` and of ``scaffold`` decode the same pixel: the same shape and no ``valid`` mask
    (:func:`anycity.models.gaussians.raw_to_gaussians` sets one exactly when it voxel-merges)."""
    return refined.means.shape == scaffold.means.shape and refined.valid is None and scaffold.valid is None


def provenance(refined: Gaussians, scaffold: Gaussians, depth: Tensor, w2c: Tensor, K: Tensor,
               depth_tol: float = 0.05) -> dict[str, Tensor]:
    """``{"obs_views": [B, N] float, "completion": [B, N]}`` for the final Gaussians; ``depth [B, V, 1, H, W]``,
    ``w2c [B, V, 4, 4]``, ``K [B, V, 3, 3]`` of the context views (the cameras the Gaussians live with)."""
    obs = count_visible(refined.means.float(), depth.float(), w2c.float(), K.float(), depth_tol=depth_tol)
    nu = sampling_rate(scaffold.means.float(), w2c.float(), K.float(), depth.shape[-1], depth.shape[-2])
    pixel = torch.where(nu > 0, 1 / nu.clamp_min(1e-12), torch.zeros_like(nu))
    return {"obs_views": obs.float(), "completion": completion_score(refined, scaffold, pixel).float()}


def summary(prov: dict[str, Tensor], valid: Tensor | None = None) -> dict[str, float]:
    """Shares over (valid) Gaussians: ``supported`` (>= 2 views and known not completed), ``completed``
    (completion > :data:`COMPLETED`), ``unsupported`` (fewer than 2 views see it), ``unknown`` (completion NaN:
    voxel-merged, see :func:`completion_score`; counted as neither supported nor completed)."""
    obs, comp = prov["obs_views"], prov["completion"]
    keep = torch.ones_like(obs, dtype=torch.bool) if valid is None else valid
    n = keep.sum().clamp_min(1).item()
    unknown = comp.isnan()
    completed = comp > COMPLETED  # False for NaN
    few = obs < SUPPORT_VIEWS
    return {"supported": ((~completed & ~unknown & ~few) & keep).sum().item() / n,
            "completed": (completed & keep).sum().item() / n, "unsupported": (few & keep).sum().item() / n,
            "unknown": (unknown & keep).sum().item() / n}
