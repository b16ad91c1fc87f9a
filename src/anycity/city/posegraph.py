"""The pose graph over the pairwise Sim(3)s of :mod:`anycity.city.align`, and its cycle-consistency check.

Chunk ``i`` has the transform ``S_i`` (chunk frame -> world, chunk 0 the world); an edge ``(a, b)`` holds
``T_ab`` with ``S_a T_ab = S_b``. Float64 on CPU.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

from anycity.city.align import (
    ChunkGeometry,
    Edge,
    _exp_so3,
    _is_loop,
    _spread,
    in_loop_cycle,
    loop_dropped_warning,
    pairwise_edges,
    sim3_inverse,
    sim3_parts,
)
from anycity.metrics.pose import rotation_angle_deg


def _exp_sim3(p: Tensor) -> Tensor:
    """``[..., 7]`` (log scale, axis-angle, translation) -> Sim(3) ``[..., 4, 4]``."""
    top = torch.cat([_exp_so3(p[..., 1:4]) * torch.exp(p[..., :1])[..., None], p[..., 4:, None]], -1)
    bottom = torch.tensor([0.0, 0, 0, 1], dtype=p.dtype).expand(*p.shape[:-1], 1, 4)
    return torch.cat([top, bottom], -2)


def chain_init(num_chunks: int, edges: list[Edge]) -> Tensor:
    """``[C, 4, 4]`` chunk-to-world transforms by walking the edges from chunk 0 (breadth first)."""
    S: list[Tensor | None] = [None] * num_chunks
    S[0] = torch.eye(4, dtype=torch.float64)
    frontier = [0]
    while frontier:
        nxt = []
        for i in frontier:
            for e in edges:
                if e.a == i and S[e.b] is None:
                    S[e.b] = S[i] @ e.fit.T
                    nxt.append(e.b)
                elif e.b == i and S[e.a] is None:
                    S[e.a] = S[i] @ sim3_inverse(e.fit.T)
                    nxt.append(e.a)
        frontier = nxt
    missing = [i for i, s in enumerate(S) if s is None]
    if missing:
        raise ValueError(f"city alignment: chunks {missing} are not connected to chunk 0 by shared photos; raise "
                         "--data.predict_chunk_overlap")
    return torch.stack(S)


@dataclass
class _EdgePoints:
    """Every edge's inlier points, padded to the largest edge's count n: ``src``, ``dst [E, n, 3]`` in chunk b's
    and chunk a's frame; ``w [E, n]`` the weight ``1 / (spread_e sqrt(n_e))`` that makes each edge's squared term a
    mean in units of its points' spread (0 on padding); ``a``, ``b [E]`` the chunks of each edge."""

    src: Tensor
    dst: Tensor
    w: Tensor
    a: Tensor
    b: Tensor


def _stack_edges(edges: list[Edge]) -> _EdgePoints:
    """The edges' inlier points, padded, with their weights (:class:`_EdgePoints`)."""
    n = max(len(e.dst) for e in edges)
    src = torch.zeros(len(edges), n, 3, dtype=torch.float64)
    dst, w = torch.zeros_like(src), torch.zeros(len(edges), n, dtype=torch.float64)
    for i, e in enumerate(edges):
        m = len(e.dst)
        src[i, :m], dst[i, :m] = e.src, e.dst
        # each edge in its own frame (a) and units: measured in the world instead, shrinking the chunks far from
        # chunk 0 would lower the residuals (the scale drift of point-based pose graphs)
        w[i, :m] = 1 / (max(_spread(e.dst), 1e-12) * m ** 0.5)
    return _EdgePoints(src, dst, w, torch.tensor([e.a for e in edges]), torch.tensor([e.b for e in edges]))


def _point_residuals(Sa: Tensor, Sb: Tensor, P: _EdgePoints) -> Tensor:
    """``dst - Sa^-1 Sb src`` for every point, ``[E, n, 3]`` in chunk a's frame; ``Sa``, ``Sb``: ``[E, 4, 4]``."""
    T = sim3_inverse(Sa) @ Sb
    return P.dst - P.src @ T[:, :3, :3].transpose(-1, -2) - T[:, None, :3, 3]


def _weighted_residuals(X: Tensor, S0: Tensor, P: _EdgePoints, za: Tensor | None = None,
                        zb: Tensor | None = None) -> Tensor:
    """The pose graph's residuals ``[E, 3n]`` at perturbations ``X [C, 7]`` (row 0 zero) of ``S0 [C, 4, 4]``;
    ``za``, ``zb [7]``: added to every edge's own copy of its chunk a's / b's perturbation (for its Jacobian)."""
    Xa, Xb = X[P.a], X[P.b]
    if za is not None:
        Xa, Xb = Xa + za, Xb + zb
    Sa, Sb = _exp_sim3(Xa) @ S0[P.a], _exp_sim3(Xb) @ S0[P.b]
    return (_point_residuals(Sa, Sb, P) * P.w[..., None]).flatten(1)


def _normal_equations(X: Tensor, S0: Tensor, P: _EdgePoints) -> tuple[Tensor, Tensor]:
    """Gauss-Newton ``H [7(C-1), 7(C-1)]`` and ``g [7(C-1)]`` of the residuals at ``X``, accumulated edge by edge.

    An edge's residuals depend on its two chunks only, so its Jacobian has 14 columns: one forward-mode pass over
    14 tangents (each applied to every edge's own copy of its chunks) gives every edge's block, ``[E, 3n, 14]`` in
    all, linear in the chunk count (a dense Jacobian is ``[3nE, 7(C-1)]``)."""
    J = torch.autograd.functional.jacobian(lambda z: _weighted_residuals(X, S0, P, z[:7], z[7:]),
                                           torch.zeros(14, dtype=torch.float64), vectorize=True,
                                           strategy="forward-mode")  # [E, 3n, 14]
    r = _weighted_residuals(X, S0, P)
    cols = torch.cat([P.a[:, None] * 7 - 7, P.b[:, None] * 7 - 7], 1)[:, :, None] + torch.arange(7)
    cols = cols.flatten(1)  # [E, 14] unknowns of each edge's two chunks; < 0: chunk 0, fixed
    Hs, gs = J.transpose(1, 2) @ J, (J.transpose(1, 2) @ r[..., None])[..., 0]  # [E, 14, 14], [E, 14]
    n = 7 * (X.shape[0] - 1)
    ok = cols >= 0
    ij = ok[:, :, None] & ok[:, None, :]
    H = torch.zeros(n, n, dtype=torch.float64).index_put_(
        (cols[:, :, None].expand_as(Hs)[ij], cols[:, None, :].expand_as(Hs)[ij]), Hs[ij], accumulate=True)
    g = torch.zeros(n, dtype=torch.float64).index_put_((cols[ok],), gs[ok], accumulate=True)
    return H, g


def edge_rms(S: Tensor, edges: list[Edge]) -> Tensor:
    """``[E]`` rms distance of each edge's inlier points under chunk-to-world transforms ``S [C, 4, 4]``:
    ``|dst - S_a^-1 S_b src|`` in chunk a's frame (the units of its pairwise fit's rms and threshold)."""
    if not edges:
        return torch.zeros(0, dtype=torch.float64)
    P = _stack_edges(edges)
    d2 = _point_residuals(S[P.a], S[P.b], P).pow(2).sum(-1) * (P.w > 0)
    return (d2.sum(-1) / torch.tensor([len(e.dst) for e in edges], dtype=torch.float64)).sqrt()


def world_rms(S: Tensor, edges: list[Edge]) -> float:
    """The edges' rms residuals under ``S`` pooled (``sqrt(mean_e rms_e^2)``), each in world units of chunk 0's
    frame (scaled by its chunk a's scale ``s_a``, as chunks.json's pairs): on a chain, the pooled pairwise rms."""
    if not edges:
        return 0.0
    s_a = sim3_parts(S)[0][[e.a for e in edges]]
    return float((edge_rms(S, edges) * s_a).pow(2).mean().sqrt())


def pose_graph(num_chunks: int, edges: list[Edge], iters: int = 50) -> tuple[Tensor, dict]:
    """Global least squares over chunk transforms (chunk 0 fixed as the world frame).

    Minimises, over every edge, the mean squared distance between its inlier points and the same points carried
    over from chunk b by the current relative transform, ``|dst - S_a^-1 S_b src|^2`` (in chunk a's frame, in units
    of the edge's point spread), so a loop or a view shared by three chunks spreads the error instead of piling it
    up along the chain; on a chain (a tree) it keeps the pairwise fits as they are. Starts from
    :func:`chain_init` and runs Gauss-Newton (Levenberg damped) on a left perturbation ``exp(sigma), exp(omega),
    tau`` of every other chunk, with the normal equations built edge by edge (:func:`_normal_equations`).

    Returns:
        ``S [C, 4, 4]`` chunk-to-world Sim(3)s and a report ``{"initial_rms", "final_rms"}``: the edges' rms
        residuals before and after, pooled, in world units of chunk 0's frame (:func:`world_rms`).
    """
    S0 = chain_init(num_chunks, edges)
    if num_chunks == 1 or not edges:
        return S0, {"initial_rms": 0.0, "final_rms": 0.0}
    P = _stack_edges(edges)
    X = torch.zeros(num_chunks, 7, dtype=torch.float64)
    r = _weighted_residuals(X, S0, P)
    lam, H = 1e-6, None
    for _ in range(iters):
        if float(r.pow(2).sum()) < 1e-24:  # already exact (an oracle)
            break
        if H is None:
            H, g = _normal_equations(X, S0, P)
        step = torch.linalg.solve(H + lam * torch.diag(H.diagonal().clamp_min(1e-12)), -g)
        X_new = torch.cat([X[:1], X[1:] + step.reshape(-1, 7)])
        r_new = _weighted_residuals(X_new, S0, P)
        old, new = float(r.pow(2).sum()), float(r_new.pow(2).sum())
        if new < old:
            X, r, lam, H = X_new, r_new, lam * 0.3, None
            if old - new <= 1e-12 * old:
                break
        else:
            lam *= 10
            if lam > 1e4:
                break
    S = _exp_sim3(X) @ S0
    return S, {"initial_rms": world_rms(S0, edges), "final_rms": world_rms(S, edges)}


# An edge whose rms residual under the final transforms exceeds this many times its pairwise fit's inlier threshold
# disagrees with the rest of the graph: its shared points would land that far apart in the merged scene. Oracle
# orbits of 60 to 1000 photos in chunks of 16/4 with a loop chunk (docs/city.md, benchmarks/city.py --loop-check):
# consistent loops 0.4x to 0.8x (up to 3 % noise), 1.1x with every chunk also stretched 2 % along itself, 2x to 2.9x
# at 5 %; a loop chunk whose halves are a random Sim(3) apart 5x to 25x. A milder break (halves 20 degrees apart)
# spreads over the chain at 0.4x to 1.5x: the loop's correction (``_loop_correction``) shows it.
MAX_RESIDUAL = 2.0
# a loop chunk that turns or scales a chunk by more than this against the chain alone gets a warning
LOOP_WARN_DEG, LOOP_WARN_SCALE = 10.0, 1.2


def align_chunks(chunks: list[ChunkGeometry], names: list[str] | None = None, global_pass: bool = True,
                 **fit_kw) -> tuple[Tensor, list[Edge], dict]:
    """Pairwise robust fits on shared views, then the pose graph, checked: ``(S [C, 4, 4], edges, report)``.

    After the pose graph every edge's residual is measured again under the final transforms (``Edge.graph_rms``).
    If one ends above ``MAX_RESIDUAL`` x its inlier threshold, the graph's cycles cannot be closed, and edges that
    make them are dropped with a warning: the graph is solved without the loop-closure chunk's cycle
    (:func:`anycity.city.plan.plan_chunks`; it owns no photo, so the scene is then the one without it), else on the
    chain of consecutive chunks alone, which always passes (a tree keeps the pairwise fits). The report holds the
    pose graph's ``initial_rms``/``final_rms``, ``dropped_pairs`` (the loop chunk's pairs first when its fit to
    chunk 0 failed: :func:`~anycity.city.align.pairwise_edges`) and, with a loop chunk in use, how far it moved the
    chain (``loop_rotation_deg``, ``loop_scale``).

    Raises:
        ValueError: a failed pairwise fit (:func:`anycity.city.align.pairwise_edges`), naming the chunks.
    """
    skipped: list[list[int]] = []
    edges = pairwise_edges(chunks, names, skipped=skipped, **fit_kw)
    C = len(chunks)
    loop = C - 1 if _is_loop(chunks) and not skipped else None
    if not global_pass:
        S, rep = chain_init(C, edges), {}
    else:
        used = list(range(len(edges)))
        S, rep = pose_graph(C, edges)
        bad = _inconsistent(S, edges, used)
        steps = [st for st in _fallbacks(chunks, names, edges, loop) if len(st[0]) < len(edges)] if bad else []
        for n, (keep, why) in enumerate(steps):
            S_k, rep_k = pose_graph(C, [edges[i] for i in keep])
            if n == len(steps) - 1 or not _inconsistent(S_k, edges, keep):  # the last, the chain, is a tree
                warnings.warn(why(_describe(S, edges[bad[0]])), stacklevel=2)
                S, rep, used = S_k, rep_k, keep
                break
        rep["dropped_pairs"] = skipped + [[edges[i].a, edges[i].b] for i in range(len(edges)) if i not in used]
        if loop is not None and not rep["dropped_pairs"]:
            rep.update(_loop_correction(C, edges, loop, S))
    for e, r in zip(edges, edge_rms(S, edges).tolist()):
        e.graph_rms = r
    return S, edges, rep


def _fallbacks(chunks: list[ChunkGeometry], names: list[str] | None, edges: list[Edge], loop: int | None) -> list:
    """``[(kept edge indices, warning(residual text) -> str)]`` to try in turn: without the loop chunk's cycle,
    then the chain of consecutive chunks."""
    chain = [i for i, e in enumerate(edges) if e.b == e.a + 1]
    steps = [(chain, lambda res: (
        f"city alignment: chunks that share photos beyond the chain disagree with it: after the pose graph {res} "
        f"(more than {MAX_RESIDUAL:g}x), so the scene is aligned on consecutive chunks only (pairs "
        f"{', '.join(f'{edges[i].a}-{edges[i].b}' for i in range(len(edges)) if i not in chain)} dropped; see "
        "chunks.json's pairs). A chunk's reconstruction may be inconsistent with itself: if surfaces near those "
        "chunks' shared photos look doubled, try another --data.predict_chunk_size or --data.predict_chunk_overlap"))]
    if loop is None:
        return steps
    return [(_without_loop_cycle(edges, loop), lambda res: loop_dropped_warning(
        chunks, names, f"disagrees with the chain: after the pose graph {res} (more than {MAX_RESIDUAL:g}x), "))
        ] + steps


def _without_loop_cycle(edges: list[Edge], loop: int) -> list[int]:
    """Indices of the edges but the loop chunk's, except its edge to the last chunk (it stays placed, on a tree)."""
    return [i for i, e in enumerate(edges) if not in_loop_cycle(e.a, e.b, loop)]


def _inconsistent(S: Tensor, edges: list[Edge], used: list[int]) -> list[int]:
    """The used edges whose rms residual under ``S`` is above ``MAX_RESIDUAL`` x their inlier threshold, worst
    first."""
    ratio = edge_rms(S, edges) / torch.tensor([e.fit.threshold for e in edges], dtype=torch.float64)
    return sorted((i for i in used if ratio[i] > MAX_RESIDUAL), key=lambda i: -float(ratio[i]))


def _describe(S: Tensor, e: Edge) -> str:
    """Edge ``e``'s residual under ``S`` against its inlier threshold, in world units of chunk 0's frame."""
    s = float(sim3_parts(S[e.a])[0])
    return (f"the shared points of chunks {e.a} and {e.b} end {float(edge_rms(S, [e])[0]) * s:.3g} apart (rms) "
            f"against their pairwise fit's inlier threshold {e.fit.threshold * s:.3g}")


def _loop_correction(C: int, edges: list[Edge], loop: int, S: Tensor) -> dict:
    """How far the loop chunk moved the chain: the largest rotation (degrees) and scale factor between each chunk's
    transform in ``S`` and in the pose graph without the loop chunk's cycle. Warns above ``LOOP_WARN_*``: a loop
    chunk that bends the chain that far may be closing a loop the flight does not have."""
    chain = [edges[i] for i in _without_loop_cycle(edges, loop)]
    D = S[:loop] @ sim3_inverse(pose_graph(C, chain)[0][:loop])
    s, R, _ = sim3_parts(D)
    deg = rotation_angle_deg(R)
    k_rot, k_scale = int(deg.argmax()), int(s.log().abs().argmax())
    out = {"loop_rotation_deg": float(deg[k_rot]), "loop_scale": float(s[k_scale])}
    if out["loop_rotation_deg"] > LOOP_WARN_DEG or abs(math.log(out["loop_scale"])) > math.log(LOOP_WARN_SCALE):
        warnings.warn(f"city alignment: the loop-closure chunk {loop} turns chunk {k_rot} by "
                      f"{out['loop_rotation_deg']:.1f} degrees and scales chunk {k_scale} by {out['loop_scale']:.3g} "
                      "against the chain alone; if the flight's last photos do not see its first ones, drop "
                      "--data.predict_loop", stacklevel=3)
    return out
