"""Aligning chunk reconstructions into one frame: robust pairwise Sim(3) on shared views (the pose graph over them
is :mod:`anycity.city.posegraph`).

A Sim(3) is a ``[4, 4]`` matrix ``[[s R, t], [0, 1]]`` mapping points ``p -> s R p + t``. Chunk ``i`` has the
transform ``S_i`` (chunk frame -> world); an edge ``(a, b)`` holds ``T_ab`` with ``p_a = T_ab p_b`` for the same
3-D point seen in chunks ``a`` and ``b``, so ``S_a T_ab = S_b``. Everything runs in float64 on CPU (the
problems are tiny: a few hundred points per edge, 7 unknowns per chunk).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import torch
from torch import Tensor

from anycity.city.plan import MIN_SHARED
from anycity.geometry.alignment import sim3_matrix, umeyama
from anycity.geometry.cameras import camera_centers


def sim3_parts(T: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``[..., 4, 4]`` Sim(3) -> s ``[...]``, R ``[..., 3, 3]``, t ``[..., 3]``."""
    A = T[..., :3, :3]
    s = torch.linalg.det(A).clamp_min(1e-300) ** (1 / 3)
    return s, A / s[..., None, None], T[..., :3, 3]


def sim3_inverse(T: Tensor) -> Tensor:
    """``[..., 4, 4]`` Sim(3) ``p -> s R p + t`` -> its inverse ``p -> (1/s) Rᵀ (p - t)``, ``[..., 4, 4]``, in closed
    form (no general matrix inverse); e.g. chunk frame -> world becomes world -> chunk frame."""
    s, R, t = sim3_parts(T)
    Ri = R.transpose(-1, -2)
    return sim3_matrix(1 / s, Ri, -(Ri @ t[..., None])[..., 0] / s[..., None])


def apply_sim3(T: Tensor, p: Tensor) -> Tensor:
    """``T [4, 4]`` applied to points ``p [..., 3]``."""
    return p @ T[:3, :3].transpose(0, 1) + T[:3, 3]


def w2c_to_world(w2c: Tensor, S: Tensor) -> Tensor:
    """Cameras ``w2c [V, 4, 4]`` of a chunk frame -> rigid cameras of the world frame where ``S`` maps the chunk
    frame to the world (camera-frame coordinates, hence depths, are scaled by s)."""
    s, _, _ = sim3_parts(S)
    D = torch.diag(torch.stack([s, s, s, torch.ones_like(s)]))
    return D @ w2c @ sim3_inverse(S)


@dataclass
class Sim3Fit:
    """A robust Sim(3) fit ``dst ≈ T src``: inliers ``[N]`` bool, residuals in dst units."""

    T: Tensor
    inliers: Tensor
    rms: float
    median: float
    threshold: float

    @property
    def num_inliers(self) -> int:
        return int(self.inliers.sum())


def _spread(p: Tensor) -> float:
    """Median distance of points ``p [N, 3]`` to their coordinate-wise median.

    About the median, not the mean: a few far points that disagree between chunks (sky or horizon pixels of
    oblique photos, which each chunk's pass puts at its own depth) drag the mean away, and the inflated spread let
    them in as inliers (5 % of it is the inlier threshold) and blinded the pose graph's check."""
    return float((p - p.median(0).values).norm(dim=-1).median())


def robust_sim3(src: Tensor, dst: Tensor, rel_threshold: float = 0.05, trials: int = 256, refits: int = 4,
                min_inliers: int = 6, seed: int = 0) -> Sim3Fit:
    """RANSAC over minimal 3-point Umeyama fits, then least-squares refits on the inliers.

    Args:
        src, dst: ``[N, 3]`` corresponding points (N >= 3).
        rel_threshold: inlier residual as a fraction of the median distance of ``dst`` to its coordinate-wise
            median (:func:`_spread`).
        trials: random 3-point samples (batched).
        refits: rounds of "refit on inliers, recompute inliers".
        min_inliers: fewer inliers than this is a failure.
    Raises:
        ValueError: too few points, a degenerate configuration (collinear, zero spread, non-finite) or too few
        inliers; the message says which.
    """
    src, dst = src.double().cpu(), dst.double().cpu()
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"robust_sim3: {n} corresponding points, need at least 3")
    if not (torch.isfinite(src).all() and torch.isfinite(dst).all()):
        raise ValueError("robust_sim3: non-finite points (NaN/inf depth or cameras)")
    scale = _spread(dst)
    sv = torch.linalg.svdvals(dst - dst.mean(0))
    if scale <= 0 or sv[1] <= 1e-9 * max(float(sv[0]), 1e-300) or _spread(src) <= 0:
        raise ValueError("robust_sim3: degenerate point set (all points on one line or one point)")
    thr = rel_threshold * scale
    g = torch.Generator().manual_seed(seed)
    idx = torch.stack([torch.randperm(n, generator=g)[:3] for _ in range(trials)])  # [T, 3]
    s, R, t = umeyama(src[idx], dst[idx])
    pred = s[:, None, None] * torch.einsum("kij,nj->kni", R, src) + t[:, None]
    res = (pred - dst).norm(dim=-1)  # [T, N]
    ok = torch.isfinite(res).all(-1) & (s > 0)
    counts = torch.where(ok, (res < thr).sum(-1), torch.full_like(ok, -1, dtype=torch.long))
    inl = res[counts.argmax()] < thr
    T = None
    for _ in range(refits):
        if int(inl.sum()) < max(3, min_inliers):
            break
        s1, R1, t1 = umeyama(src[inl], dst[inl])
        T = sim3_matrix(s1, R1, t1)
        r = (apply_sim3(T, src) - dst).norm(dim=-1)
        new = r < thr
        if torch.equal(new, inl):
            break
        inl = new
    if T is not None and int(inl.sum()) >= 3:  # the fit that goes with the final inlier set
        s1, R1, t1 = umeyama(src[inl], dst[inl])
        T = sim3_matrix(s1, R1, t1)
    if T is None or int(inl.sum()) < min_inliers:
        raise ValueError(f"robust_sim3: {int(inl.sum())} of {n} points agree within {thr:.3g} (need "
                         f"{min_inliers}); the two reconstructions disagree on their shared views")
    r = (apply_sim3(T, src) - dst).norm(dim=-1)
    s_fit = float(sim3_parts(T)[0])
    if not math.isfinite(s_fit) or s_fit <= 1e-8:
        raise ValueError(f"robust_sim3: degenerate scale {s_fit:.3g}")
    return Sim3Fit(T, inl, float(r[inl].pow(2).mean().sqrt()), float(r[inl].median()), thr)


@dataclass
class ChunkGeometry:
    """What alignment needs of one chunk, all in the chunk's own frame.

    Attributes:
        views: global photo indices of the chunk's views, in chunk order.
        w2c: ``[V, 4, 4]`` predicted cameras.
        points: ``[V, P, 3]`` 3-D points of a fixed pixel subset of each view (the pixel-aligned Gaussian centres,
            i.e. the depth back-projected), the same pixels in every chunk.
    """

    views: list[int]
    w2c: Tensor
    points: Tensor


@dataclass
class Edge:
    """Pairwise alignment of chunks ``a`` and ``b`` (``p_a = T p_b``) on their shared views."""

    a: int
    b: int
    shared: list[int]
    fit: Sim3Fit
    src: Tensor = field(repr=False)  # inlier points in b's frame [M, 3]
    dst: Tensor = field(repr=False)  # the same points in a's frame [M, 3]
    graph_rms: float = math.nan  # rms of |dst - S_a^-1 S_b src| under the final transforms, in a's frame


def correspondences(ca: ChunkGeometry, cb: ChunkGeometry, shared: list[int]) -> tuple[Tensor, Tensor]:
    """Points of the shared views in chunk b's frame (src) and chunk a's frame (dst): camera centres plus the
    views' depth points (same pixels), ``[M, 3]`` each."""
    ia = [ca.views.index(v) for v in shared]
    ib = [cb.views.index(v) for v in shared]
    dst = torch.cat([camera_centers(ca.w2c[ia].double()), ca.points[ia].double().reshape(-1, 3)])
    src = torch.cat([camera_centers(cb.w2c[ib].double()), cb.points[ib].double().reshape(-1, 3)])
    keep = torch.isfinite(src).all(-1) & torch.isfinite(dst).all(-1)
    return src[keep], dst[keep]


def pairwise_edges(chunks: list[ChunkGeometry], names: list[str] | None = None, min_shared: int = MIN_SHARED,
                   skipped: list[list[int]] | None = None, **fit_kw) -> list[Edge]:
    """A robust Sim(3) for every pair of chunks sharing at least one view.

    A failed fit of an extra (non-consecutive) pair is skipped: the chain still holds. So is a failed fit of the
    loop-closure chunk to chunk 0 (:func:`_is_loop`), with a warning: the loop chunk owns no photo, so the scene is
    aligned without its cycle (its edge to the last chunk keeps it placed); its other extra pairs go too. The
    loop chunk's skipped pairs ``[a, b]`` are appended to ``skipped``.

    Raises:
        ValueError: a pair of consecutive chunks sharing fewer than ``min_shared`` views, or its failed fit, naming
        the chunks, their photos and the fix.
    """
    loop = len(chunks) - 1 if _is_loop(chunks) else None
    edges, loop_dropped = [], False
    for a in range(len(chunks)):
        for b in range(a + 1, len(chunks)):
            shared = sorted(set(chunks[a].views) & set(chunks[b].views))
            consecutive = b == a + 1 or (a == 0 and b == loop)
            if len(shared) < min_shared:
                if consecutive:
                    raise ValueError(_chunk_error(a, b, shared, names, f"share {len(shared)} views, need "
                                                  f"{min_shared}"))
                continue
            if loop_dropped and in_loop_cycle(a, b, loop):  # the rest of the dropped loop chunk's cycle
                if skipped is not None:
                    skipped.append([a, b])
                continue
            src, dst = correspondences(chunks[a], chunks[b], shared)
            try:
                fit = robust_sim3(src, dst, **fit_kw)
            except ValueError as e:
                why = str(e).removeprefix("robust_sim3: ")
                if not consecutive:  # an extra edge; the chain still holds
                    continue
                if b != loop or a != 0:
                    raise ValueError(_chunk_error(a, b, shared, names, why)) from None
                shown = ", ".join(names[v] if names else str(v) for v in shared[:4])
                warnings.warn(loop_dropped_warning(chunks, names, f"cannot be aligned with chunk 0 (shared photos: "
                                                                  f"{shown}): {why}; "), stacklevel=3)
                loop_dropped = True
                if skipped is not None:
                    skipped.append([a, b])
                continue
            edges.append(Edge(a, b, shared, fit, src[fit.inliers], dst[fit.inliers]))
    return edges


def loop_dropped_warning(chunks: list[ChunkGeometry], names: list[str] | None, problem: str) -> str:
    """The warning for a loop-closure chunk (the last of ``chunks``) left out of the alignment; ``problem`` says why
    and ends where "so the scene is aligned without its cycle" goes on."""
    loop, views = len(chunks) - 1, chunks[-1].views
    ends = ", ".join(names[v] if names else str(v) for v in (views[0], views[-1]))
    return (f"city alignment: the loop-closure chunk {loop} (photos {ends}, both ends of the flight) {problem}so the "
            "scene is aligned without its cycle, as without --data.predict_loop. Drop --data.predict_loop if the "
            "flight's last photos do not see its first ones, or raise --data.predict_chunk_size so that the loop "
            "chunk holds more of both ends")


def in_loop_cycle(a: int, b: int, loop: int) -> bool:
    """Pair ``(a, b)`` (a < b) closes the cycle of the loop-closure chunk ``loop``: any of its pairs but its edge to
    the last chunk, which keeps it placed on a tree."""
    return b == loop and a != loop - 1


def _is_loop(chunks: list[ChunkGeometry]) -> bool:
    """The last chunk is a loop-closure chunk (it wraps around the photo order)."""
    return len(chunks) > 2 and chunks[-1].views[0] > chunks[-1].views[-1]


def _chunk_error(a: int, b: int, shared: list[int], names: list[str] | None, why: str) -> str:
    shown = ", ".join(names[v] if names else str(v) for v in shared[:4]) or "none"
    return (f"city alignment: chunks {a} and {b} (shared photos: {shown}) cannot be aligned: {why}; raise "
            "--data.predict_chunk_overlap (more shared photos) or --data.predict_chunk_size, or check that "
            "consecutive photos overlap")


def _exp_so3(w: Tensor) -> Tensor:
    """Axis-angle ``[..., 3]`` -> rotation ``[..., 3, 3]`` (Rodrigues, smooth at 0)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    W = torch.zeros(*w.shape[:-1], 3, 3, dtype=w.dtype, device=w.device)
    W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    W = W - W.transpose(-1, -2)
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-12
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * W + b * (W @ W)
