"""An oracle in place of the network, for testing the alignment: ground-truth cameras and depth points given to
each chunk in its own random Sim(3) frame (optionally perturbed), and camera errors up to one global Sim(3)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from anycity.city.align import ChunkGeometry, apply_sim3, w2c_to_world
from anycity.geometry.alignment import sim3_matrix, umeyama
from anycity.geometry.cameras import camera_centers
from anycity.metrics.pose import rotation_angle_deg


def random_rotation(gen: torch.Generator, n: int | None = None) -> Tensor:
    q = torch.randn(*(() if n is None else (n,)), 4, generator=gen, dtype=torch.float64)
    from anycity.geometry.rotations import quat_to_rotmat

    return quat_to_rotmat(q)


def small_rotation(gen: torch.Generator, n: int, deg: float) -> Tensor:
    """``[n, 3, 3]`` rotations about random axes by angles ~ N(0, deg) degrees."""
    from anycity.city.align import _exp_so3

    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    return _exp_so3(axis * torch.randn(n, 1, generator=gen, dtype=torch.float64) * math.radians(deg))


def random_sim3(gen: torch.Generator) -> Tensor:
    s = torch.exp(torch.empty((), dtype=torch.float64).uniform_(-1.5, 1.5, generator=gen))
    return sim3_matrix(s, random_rotation(gen), torch.randn(3, generator=gen, dtype=torch.float64) * 20)


def orbit_scene(n: int, points_per_view: int = 64, radius: float = 10.0, height: float = 6.0, seed: int = 0,
                arc: float = 0.9) -> tuple[Tensor, Tensor]:
    """Ground truth: ``w2c [n, 4, 4]`` on an orbit looking at the origin and ``points [n, P, 3]``, each view's
    points (what its depth map would back-project to) scattered around the ground it looks at."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n * arc  # arc = 1: a closed loop
    centres = torch.stack([radius * ang.cos(), radius * ang.sin(), torch.full_like(ang, height)], -1)
    fwd = torch.nn.functional.normalize(-centres, dim=-1)
    right = torch.nn.functional.normalize(torch.cross(fwd, torch.tensor([0, 0, 1.0], dtype=torch.float64)
                                                      .expand_as(fwd), dim=-1), dim=-1)
    down = torch.cross(fwd, right, dim=-1)
    R = torch.stack([right, down, fwd], -2)  # rows: camera axes in world
    w2c = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    w2c[:, :3, :3], w2c[:, :3, 3] = R, -(R @ centres[..., None])[..., 0]
    look = centres + fwd * (centres[:, 2:] / -fwd[:, 2:])  # where the optical axis meets z = 0
    pts = look[:, None] + torch.randn(n, points_per_view, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [2.0, 2.0, 0.5], dtype=torch.float64)
    return w2c, pts


def oracle_chunks(w2c: Tensor, points: Tensor, plan: list[list[int]], seed: int = 0, rot_deg: float = 0.0,
                  centre_noise: float = 0.0, depth_noise: float = 0.0) -> tuple[list[ChunkGeometry], Tensor]:
    """Each chunk sees its views' ground truth in its own random Sim(3) frame ``G_k`` (world -> chunk), then
    perturbed in that frame: camera rotations by ~``rot_deg`` degrees, camera centres by ``centre_noise`` x the
    scene extent, each depth point along its ray by a factor ``1 + N(0, depth_noise)``.

    Returns:
        the chunks and ``G [C, 4, 4]``.
    """
    g = torch.Generator().manual_seed(seed + 1)
    extent = float((camera_centers(w2c) - camera_centers(w2c).mean(0)).norm(dim=-1).max())
    out, G = [], []
    for views in plan:
        Gk = random_sim3(g)
        cams, pts = w2c[views].clone(), points[views].clone()
        c = camera_centers(cams)
        ray = pts - c[:, None]
        pts = c[:, None] + ray * (1 + depth_noise * torch.randn(pts.shape[:2], generator=g, dtype=torch.float64))[
            ..., None]
        if rot_deg > 0 or centre_noise > 0:
            c_new = c + centre_noise * extent * torch.randn(c.shape, generator=g, dtype=torch.float64)
            Rn = small_rotation(g, len(views), rot_deg) @ cams[:, :3, :3]
            cams[:, :3, :3], cams[:, :3, 3] = Rn, -(Rn @ c_new[..., None])[..., 0]
        out.append(ChunkGeometry(list(views), w2c_to_world(cams, Gk), apply_sim3(Gk, pts)))
        G.append(Gk)
    return out, torch.stack(G)


def camera_errors(w2c: Tensor, w2c_gt: Tensor) -> dict:
    """Errors of cameras ``w2c [V, 4, 4]`` against ``w2c_gt`` after one global Sim(3) fit of the camera centres:
    rotation (degrees: mean, max), position (mean, max, relative to the extent = largest distance of a ground-truth
    centre from their centroid), and the largest absolute difference of the aligned w2c matrices in extent units.
    Centres on one line (a straight strip) leave the roll about it free: the fit then also matches a point one
    spread ahead of each camera and one above it, along its own axes."""
    w2c, w2c_gt = w2c.double(), w2c_gt.double()
    c, c_gt = camera_centers(w2c), camera_centers(w2c_gt)
    sv = torch.linalg.svdvals(c_gt - c_gt.mean(0))
    if len(c) >= 2 and sv[1] <= 1e-3 * sv[0]:
        s, R, t = umeyama(_with_axes(w2c, c), _with_axes(w2c_gt, c_gt))
    else:
        s, R, t = umeyama(c, c_gt)
    aligned = w2c_to_world(w2c, sim3_matrix(s, R, t))
    extent = float((c_gt - c_gt.mean(0)).norm(dim=-1).max())
    Rrel = aligned[:, :3, :3] @ w2c_gt[:, :3, :3].transpose(-1, -2)
    rot = rotation_angle_deg(Rrel)
    pos = (camera_centers(aligned) - c_gt).norm(dim=-1) / extent
    # the global rotation fitted to the camera orientations alone (chordal mean), which a poor set of centres
    # (the tiny model's) cannot throw off
    U, _, Vh = torch.linalg.svd((w2c_gt[:, :3, :3].transpose(-1, -2) @ w2c[:, :3, :3]).sum(0))
    Q = U @ torch.diag(torch.tensor([1.0, 1.0, float(torch.det(U @ Vh))], dtype=U.dtype)) @ Vh
    Rq = w2c[:, :3, :3] @ Q.T @ w2c_gt[:, :3, :3].transpose(-1, -2)
    rot_q = rotation_angle_deg(Rq)
    diff = (aligned - w2c_gt).abs()
    diff[:, :3, 3] /= extent
    return {"rot_deg_mean": float(rot.mean()), "rot_deg_max": float(rot.max()),
            "rot_deg_mean_rotfit": float(rot_q.mean()), "pos_rel_mean": float(pos.mean()),
            "pos_rel_max": float(pos.max()), "w2c_max_abs": float(diff.max())}


def _with_axes(w2c: Tensor, c: Tensor) -> Tensor:
    """Camera centres ``c [V, 3]``, then points one spread (largest distance from their centroid) ahead of each
    camera and one spread above it (``-y``), ``[3V, 3]``: a set that fixes a rotation even when ``c`` is a line."""
    spread = (c - c.mean(0)).norm(dim=-1).max().clamp_min(1e-12)
    return torch.cat([c, c + spread * w2c[:, 2, :3], c - spread * w2c[:, 1, :3]])
