"""View selection (context / dense / target), resizing with K updates, and per-sample world normalisation.

Selection works on trajectory positions ``0..n-1``:

* training: a sliding window of consecutive views; the context is stratified over the window, targets are drawn
  from the other window views, the dense teacher set from the window minus the targets;
* evaluation (``llffhold=8``): the view at scene position ``i`` is a target when ``i % 8 == 0`` (positions are the
  views' ``index`` in the scene, so a trajectory window holds out the same views as its whole scene, and only the
  targets in the window's own range are scored: overlapping windows score each once); targets are cut into chunks
  of T (the last chunk repeats its own views), and each chunk's context views are spread evenly over the
  ``2 x num_context`` non-held-out views nearest to it (whatever ``num_dense``), its dense views over the
  ``max(2 x num_context, num_dense)`` nearest. Deterministic. A sample with fewer non-held-out views than context
  views is refused (:class:`TooFewViews`): its context would repeat views.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from anycity.geometry import camera_centers, crop_intrinsics, invert_rigid, rescale_intrinsics, unproject_depth


class SettingsError(ValueError):
    """A sample the settings cannot build (not a corrupt one): every such sample would fail alike, so
    ``skip_corrupt`` raises it instead of skipping the sample out of training."""


class TooFewViews(SettingsError):
    """A training window too short for the distinct context + target views asked of it, or an evaluation sample with
    fewer non-held-out views than context views."""


@dataclass
class Selection:
    """Trajectory positions of one sample's views."""

    context: list[int]
    target: list[int]
    dense: list[int]


def _pick(rng: np.random.Generator, pool: list[int], k: int) -> list[int]:
    """k distinct items of pool when possible, else with replacement (fixed-V batches)."""
    if k <= 0:
        return []
    if not pool:
        raise ValueError("view selection: no candidate views left; the scene has too few views for the request")
    return sorted(int(i) for i in rng.choice(pool, size=k, replace=len(pool) < k))


def _spread(pool: list[int], k: int) -> list[int]:
    """k items evenly spread over pool (deterministic; repeats when pool is shorter than k)."""
    if k <= 0:
        return []
    return [pool[i] for i in np.linspace(0, len(pool) - 1, k).round().astype(int)]


def select_train(n: int, num_context: int, num_targets: int, num_dense: int, rng: np.random.Generator,
                 window: int | None = None) -> Selection:
    """Random selection inside a sliding window of ``window`` consecutive views (default 2 x the largest set).

    Context and target views are always distinct (a target is a novel view); the dense set may repeat views. Raises
    :class:`TooFewViews` when the window cannot hold ``num_context + num_targets`` distinct views.
    """
    if n < 2:
        raise ValueError(f"view selection: a sample needs >= 2 views, got {n}")
    L = min(n, window or 2 * max(num_context + num_targets, num_dense))
    if num_context + num_targets > L:
        raise TooFewViews(f"view selection: a {L}-view training window cannot hold {num_context} context + "
                         f"{num_targets} target views, all distinct; use at most {L - num_targets} context views "
                         f"(num_context / train_num_context), fewer num_targets, or longer windows (data.window; "
                         f"anycity data synth --window, convert --max_views)")
    start = int(rng.integers(0, n - L + 1))
    win = list(range(start, start + L))
    edges = np.linspace(0, L, num_context + 1)
    ctx = sorted({win[int(rng.integers(int(a), max(int(a) + 1, int(b))))] for a, b in zip(edges[:-1], edges[1:])})
    ctx = ctx + _pick(rng, [i for i in win if i not in ctx], num_context - len(ctx)) if len(ctx) < num_context else ctx
    rest = [i for i in win if i not in ctx]
    tgt = _pick(rng, rest, num_targets)
    dense = _pick(rng, [i for i in win if i not in tgt] or win, num_dense)
    return Selection(sorted(ctx), tgt, dense)


def llffhold_split(n: int, hold: int = 8) -> tuple[list[int], list[int]]:
    """(train, test) positions: position i is a test view when ``i % hold == 0``."""
    test = [i for i in range(n) if i % hold == 0]
    return [i for i in range(n) if i % hold != 0], test


def select_eval(n: int, num_context: int, num_targets: int, num_dense: int, hold: int = 8,
                index: list[int] | None = None, own: tuple[int, int] | None = None) -> list[Selection]:
    """Deterministic llffhold selections covering every held-out view of an n-view sample (positions 0..n-1).

    Each chunk's context is spread over the ``2 x num_context`` non-held-out views nearest its targets whatever
    ``num_dense``, so runs with and without dense views (Stage I and II configs) test from the same context views;
    the dense views are spread over the ``max(2 x num_context, num_dense)`` nearest.

    Args:
        index: trajectory position of each of the n views in its scene (default ``0..n-1``); llffhold applies to
            it, so a window of a longer trajectory holds out the same views as the whole scene would.
        own: ``[lo, hi)`` scene positions whose held-out views this sample scores (overlapping windows of a
            scene own disjoint ranges, so every held-out view is scored once); default all.
    Returns:
        selections in sample positions; empty when the sample owns no held-out view.
    """
    index = list(range(n)) if index is None else [int(i) for i in index]
    lo, hi = own if own is not None else (min(index, default=0), max(index, default=0) + 1)
    train = [i for i in range(n) if index[i] % hold != 0]
    test = [i for i in range(n) if index[i] % hold == 0 and lo <= index[i] < hi]
    if not train:
        raise ValueError(f"view selection: a {n}-view sample has no non-held-out views for llffhold={hold}")
    if len(train) < num_context:  # _spread would repeat context views: a repeated pair scores rte 90 deg
        raise TooFewViews(f"view selection: a {n}-view evaluation sample keeps {len(train)} views after "
                          f"data.llffhold {hold} holds out every {hold}th, fewer than data.num_context {num_context}, "
                          f"so context views would repeat; set data.num_context <= {len(train)}, or evaluate "
                          "samples with more views (anycity data convert --max_views)")
    out = []
    for c in range(0, len(test), num_targets):
        part = test[c:c + num_targets]
        chunk = [part[j % len(part)] for j in range(num_targets)]  # pad the last chunk with its own views
        centre = float(np.mean(chunk))
        near = sorted(train, key=lambda i: (abs(i - centre), i))
        ctx, dense = sorted(near[:2 * num_context]), sorted(near[:max(2 * num_context, num_dense)])
        out.append(Selection(_spread(ctx, num_context), chunk, _spread(dense, num_dense)))
    return out


def jpeg_reduction(h: int, w: int, nh: int, nw: int) -> int:
    """Largest JPEG DCT scale-down (8, 4, 2) that keeps at least ``nh x nw`` pixels and divides ``h x w`` (so the
    decoded image covers exactly the same field of view); 1 when none does."""
    for r in (8, 4, 2):
        if h % r == 0 and w % r == 0 and h // r >= nh and w // r >= nw:
            return r
    return 1


def resize_plan(h: int, w: int, size: tuple[int, int], mode: str = "crop", patch: int = 14
                ) -> tuple[int, int, int, int]:
    """Resized size ``(nh, nw)`` before the centre crop and the output size ``(H, W)`` (see :func:`resize_view`).

    ``"keep"``: the output has about ``H*W`` pixels, the photo's aspect ratio to the nearest patch multiple on each
    side; the photo is scaled uniformly to cover it and the remainder (under one patch) centre-cropped, so pixels
    stay square. Scaling each side to its multiple separately stretched them (a 16:9 photo at the quickstart's 48 px
    budget and patch 8: 64x32, 12 % wider), which the network, which predicts square pixels, cannot represent."""
    H, W = size
    if mode == "keep":
        s = (H * W / (h * w)) ** 0.5
        H, W = max(patch, round(h * s / patch) * patch), max(patch, round(w * s / patch) * patch)
    elif mode != "crop":
        raise ValueError(f"resize mode: expected 'crop' or 'keep', got {mode!r}")
    s = max(H / h, W / w)
    return max(H, round(h * s)), max(W, round(w * s)), H, W


def resize_view(image: np.ndarray, K: np.ndarray, size: tuple[int, int], mode: str = "crop", patch: int = 14,
                depth: np.ndarray | None = None, normal: np.ndarray | None = None, mask: np.ndarray | None = None,
                src_hw: tuple[int, int] | None = None):
    """Resize (and centre-crop) a view to ``size = (H, W)``, updating K.

    Args:
        image: ``[h, w, 3]`` uint8; K: ``[3, 3]`` pixels of the ``src_hw`` image.
        mode: "crop" scales to cover ``size`` then centre-crops (exact output size); "keep" keeps the aspect
            ratio with about ``H*W`` pixels and both sides multiples of ``patch`` (cropping under one patch).
        depth/normal/mask: ``[h, w]``, ``[h, w, 3]``, ``[h, w]`` resampled with nearest neighbours (the source
            pixel under each output pixel's centre).
        src_hw: the ``(h, w)`` that K describes (default: the image's); arrays of another size covering the same
            field of view (a JPEG decoded at 1/2, 1/4 or 1/8 scale) are resampled from their own size.
    Returns:
        image, K (float64 numpy), depth, normal, mask at the new size.
    """
    h, w = src_hw if src_hw is not None else image.shape[:2]
    nh, nw, H, W = resize_plan(h, w, size, mode, patch)
    Kt = torch.as_tensor(np.asarray(K, np.float64))
    if (nw, nh) != (w, h):
        Kt = rescale_intrinsics(Kt, nw / w, nh / h)

    # nearest neighbours with pixel centres aligned (INTER_NEAREST_EXACT), as K is rescaled; plain INTER_NEAREST
    # samples source pixel floor(x * scale), which puts depth, normals and mask a fraction of a pixel off
    def fit(a, interp=cv2.INTER_NEAREST_EXACT):
        if a is None or a.shape[:2] == (nh, nw):
            return a
        if interp != cv2.INTER_NEAREST_EXACT:
            interp = cv2.INTER_AREA if a.shape[1] > nw else cv2.INTER_LINEAR
        return cv2.resize(a, (nw, nh), interpolation=interp)

    image, depth, normal = fit(image, cv2.INTER_LINEAR), fit(depth), fit(normal)
    mask = None if mask is None else fit(mask.view(np.uint8) if mask.dtype == bool else mask).astype(bool)
    x0, y0 = (nw - W) // 2, (nh - H) // 2
    if (x0, y0) != (0, 0) or (nw, nh) != (W, H):
        Kt = crop_intrinsics(Kt, x0, y0)
        crop = lambda a: None if a is None else a[y0:y0 + H, x0:x0 + W]  # noqa: E731
        image, depth, normal, mask = crop(image), crop(depth), crop(normal), crop(mask)
    return np.ascontiguousarray(image), Kt.numpy(), depth, normal, mask


def normalise(w2c: torch.Tensor, K: torch.Tensor, num_context: int, depth: torch.Tensor | None = None,
              mask: torch.Tensor | None = None, stride: int | None = None
              ) -> tuple[torch.Tensor, float, torch.Tensor]:
    """Re-express poses in the first context camera and normalise the scale (DESIGN section 3).

    Args:
        w2c: ``[V, 4, 4]`` float64 poses, context views first. K: ``[V, 3, 3]``.
        num_context: how many leading views are context views.
        depth, mask: ``[V, 1, H, W]`` z-depth (source units) and validity, or None.
    Returns:
        new ``w2c [V, 4, 4]``, ``s`` (source units per normalised unit: divide depths by it) and the
        ``[4, 4]`` similarity ``world_from_source`` (``p_norm = T @ p_src``).
    """
    w2c = w2c.to(torch.float64)
    T0 = w2c[0].clone()
    rel = w2c @ invert_rigid(T0)
    s = 0.0
    if depth is not None:
        stride = stride or max(1, min(depth.shape[-2:]) // 96)
        d = depth[:num_context, :, ::stride, ::stride].to(torch.float64)
        k = rescale_intrinsics(K[:num_context].to(torch.float64), 1 / stride, 1 / stride)
        k = crop_intrinsics(k, 0.5 / stride - 0.5, 0.5 / stride - 0.5)  # pixel i of the subsample = i*stride
        pts = unproject_depth(d, k, rel[:num_context])
        valid = (d[:, 0] > 0) if mask is None else (mask[:num_context, :, ::stride, ::stride][:, 0] & (d[:, 0] > 0))
        if bool(valid.any()):
            s = float(pts[valid].norm(dim=-1).mean())
    if s <= 1e-9:
        c = camera_centers(rel[:num_context])
        s = float(c.norm(dim=-1).mean() * num_context / max(num_context - 1, 1)) if num_context > 1 else 0.0
    if s <= 1e-9 or not np.isfinite(s):
        s = 1.0
    rel[:, :3, 3] /= s
    S = torch.diag(torch.tensor([1 / s, 1 / s, 1 / s, 1.0], dtype=torch.float64))
    return rel, s, S @ T0
