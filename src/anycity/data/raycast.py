"""Exact, vectorised ray casting of a :class:`~anycity.data.city.City` (torch, CPU or GPU).

Acceleration: every primitive is projected into the image and only tested against the rays of the pixels in its
screen bounding box (plus a one-pixel margin), as a flat list of (ray, primitive) pairs; the nearest hit per ray
is a ``scatter_reduce(amin)``. Ray directions are camera-frame ``[x, y, 1]`` rotated to the world, so the ray
parameter ``t`` *is* the OpenCV z-depth. Hits are exact (slab test against boxes intersected with sloped roof
half-spaces, quadratic for spheres, plane z = 0 for the ground).

Anti-aliasing is adaptive: pixels whose colour differs from a neighbour are re-traced with four sub-pixel rays
and averaged; depth, normals and the mask come from the pixel-centre ray.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from anycity.data import city as C

_INF = float("inf")
_EPS = 1e-4
_SKY_HORIZON = torch.tensor([0.82, 0.87, 0.92])
_SKY_ZENITH = torch.tensor([0.42, 0.60, 0.86])
_HAZE_M = 2500.0  # distance at which haze reaches 1 - 1/e


class SceneTensors:
    """The city's primitives as torch tensors on one device (built once per scene)."""

    def __init__(self, city: C.City, device: torch.device | str = "cpu") -> None:
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), device=device)  # noqa: E731
        self.city = city
        self.lo, self.hi, self.roof_d = t(city.box_lo), t(city.box_hi), t(city.roof_d)
        self.eave, self.wall, self.roof = t(city.eave), t(city.wall), t(city.roof)
        self.style, self.floor_h, self.bay_w = t(city.style), t(city.floor_h), t(city.bay_w)
        self.sph_c, self.sph_r, self.sph_col = t(city.sph_c), t(city.sph_r), t(city.sph_col)
        self.kinds = t(city.block_kind)
        self.sun = t(city.sun)
        self.roof_n = t(C.ROOF_NORMALS)
        self.device = torch.device(device)
        # corners of the primitives' bounding boxes, for screen-space culling
        lo = torch.cat([self.lo, self.sph_c - self.sph_r[:, None]], 0)
        hi = torch.cat([self.hi, self.sph_c + self.sph_r[:, None]], 0)
        sel = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], device=device, dtype=torch.bool)
        self.corners = torch.where(sel[None], hi[:, None], lo[:, None])  # [Nb + Ns, 8, 3]


def _screen_pairs(scene: SceneTensors, w2c: Tensor, K: Tensor, h: int, w: int) -> tuple[Tensor, Tensor]:
    """(pixel index, primitive index) pairs for every pixel inside a primitive's projected bounding box."""
    cam = scene.corners @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[..., 2]
    front = z > 1e-3
    uv = (cam @ K.T)[..., :2] / z.clamp_min(1e-3)[..., None]
    big = torch.tensor(1e9, device=uv.device)
    umin = torch.where(front[..., None], uv, big).amin(1)
    umax = torch.where(front[..., None], uv, -big).amax(1)
    partial = front.any(1) & ~front.all(1)  # straddles the camera plane: test the whole image
    x0 = torch.where(partial, 0, (umin[:, 0].floor() - 1).clamp(0, w)).long()
    x1 = torch.where(partial, w - 1, (umax[:, 0].floor() + 1).clamp(-1, w - 1)).long()
    y0 = torch.where(partial, 0, (umin[:, 1].floor() - 1).clamp(0, h)).long()
    y1 = torch.where(partial, h - 1, (umax[:, 1].floor() + 1).clamp(-1, h - 1)).long()
    bw, bh = (x1 - x0 + 1).clamp_min(0), (y1 - y0 + 1).clamp_min(0)
    area = torch.where(front.any(1), bw * bh, 0)
    prim = torch.repeat_interleave(torch.arange(len(area), device=uv.device), area)
    start = torch.cumsum(area, 0) - area
    off = torch.arange(len(prim), device=uv.device) - start[prim]
    pix = (y0[prim] + off // bw[prim]) * w + x0[prim] + off % bw[prim]
    return pix, prim


def _trace(scene: SceneTensors, o: Tensor, d: Tensor, s_idx: Tensor, prim: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest hit of rays ``o + t d`` (``d [S, 3]``) over the candidate pairs.

    Returns ``t [S]`` (inf for no hit), ``kind [S]`` (0 sky, 1 ground, 2 box, 3 sphere) and ``pid [S]`` (the box
    or sphere index, -1 otherwise).
    """
    S, nb = d.shape[0], scene.lo.shape[0]
    dev = d.device
    dsafe = torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    inv = 1.0 / dsafe
    den = d @ scene.roof_n.T  # [S, 4]
    tab = torch.cat([scene.lo - o, scene.hi - o, scene.roof_d - scene.roof_n @ o], 1)  # [Nb, 10]
    isbox = prim < nb
    bs, bp = s_idx[isbox], prim[isbox]
    g, gi, dn = tab[bp], inv[bs], den[bs]
    t1, t2 = g[:, 0:3] * gi, g[:, 3:6] * gi
    tn, tf = torch.minimum(t1, t2).amax(1), torch.maximum(t1, t2).amin(1)
    tr = g[:, 6:10] / dn
    tn = torch.maximum(tn, torch.where(dn < 0, tr, -_INF).amax(1))
    tf = torch.minimum(tf, torch.where(dn > 0, tr, _INF).amin(1))
    tb = torch.where((tn <= tf) & (tn > _EPS), tn, _INF)
    t_box = torch.full((S,), _INF, device=dev).scatter_reduce_(0, bs, tb, "amin")
    win = (tb == t_box[bs]) & torch.isfinite(tb)
    id_box = torch.full((S,), -1, device=dev, dtype=torch.long).scatter_reduce_(0, bs[win], bp[win], "amax")

    ss, sp = s_idx[~isbox], prim[~isbox] - nb
    oc = o - scene.sph_c[sp]
    dd = d[ss]
    a = (dd * dd).sum(1)
    b = (dd * oc).sum(1)
    disc = b * b - a * ((oc * oc).sum(1) - scene.sph_r[sp] ** 2)
    ts = (-b - disc.clamp_min(0).sqrt()) / a
    ts = torch.where((disc > 0) & (ts > _EPS), ts, _INF)
    t_sph = torch.full((S,), _INF, device=dev).scatter_reduce_(0, ss, ts, "amin")
    win = (ts == t_sph[ss]) & torch.isfinite(ts)
    id_sph = torch.full((S,), -1, device=dev, dtype=torch.long).scatter_reduce_(0, ss[win], sp[win], "amax")

    t_gnd = torch.where(d[:, 2] < 0, -o[2] / d[:, 2].clamp_max(-1e-12), _INF)
    ts_all = torch.stack([t_gnd, t_box, t_sph], 1)
    t, k = ts_all.min(1)
    kind = torch.where(torch.isfinite(t), k + 1, 0)
    pid = torch.where(kind == 2, id_box, torch.where(kind == 3, id_sph, -1))
    return t, kind, pid


def _hash(ix: Tensor, iy: Tensor, salt: float = 0.0) -> Tensor:
    """Deterministic pseudo-random value in [0, 1) per integer cell."""
    v = torch.sin(ix.float() * 12.9898 + iy.float() * 78.233 + salt) * 43758.5453
    return v - v.floor()


def _box_normals(scene: SceneTensors, o: Tensor, d: Tensor, bid: Tensor) -> tuple[Tensor, Tensor]:
    """World normals ``[S, 3]`` and face ids ``[S]`` (0..2 axis faces, 3..6 roof planes) of box hits."""
    lo, hi = scene.lo[bid] - o, scene.hi[bid] - o
    dsafe = torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    t_axis = torch.minimum(lo / dsafe, hi / dsafe)
    dn = d @ scene.roof_n.T
    tr = torch.where(dn < 0, (scene.roof_d[bid] - scene.roof_n @ o) / dn, -_INF)
    face = torch.cat([t_axis, tr], 1).argmax(1)
    sgn = torch.where(d < 0, -1.0, 1.0)
    axis_n = -sgn * torch.nn.functional.one_hot(face.clamp_max(2), 3).to(d.dtype)
    roof_n = scene.roof_n[(face - 3).clamp(0, 3)]
    return torch.where((face < 3)[:, None], axis_n, roof_n), face


def _ground_albedo(scene: SceneTensors, p: Tensor) -> Tensor:
    c = scene.city
    P, n = c.pitch, c.n_blocks
    gx, gy = p[:, 0] + n * P / 2, p[:, 1] + n * P / 2
    ix, iy = torch.floor(gx / P), torch.floor(gy / P)
    lx, ly = gx - ix * P, gy - iy * P
    inside = (gx >= 0) & (gy >= 0) & (gx < n * P) & (gy < n * P)
    half = c.road / 2
    road_x, road_y = (lx < half) | (lx > half + c.block), (ly < half) | (ly > half + c.block)
    col = torch.empty(p.shape[0], 3, device=p.device)
    # countryside fields
    fx, fy = torch.floor(p[:, 0] / 37.0), torch.floor(p[:, 1] / 29.0)
    palette = torch.tensor([[0.42, 0.52, 0.25], [0.60, 0.56, 0.33], [0.33, 0.45, 0.21], [0.52, 0.43, 0.28]],
                           device=p.device)
    fc = palette[(_hash(fx, fy) * 4).long().clamp_max(3)]
    col[:] = fc * (0.93 + 0.07 * torch.sin(p[:, 0] * 1.3 + p[:, 1] * 0.4))[:, None]
    # block interiors
    kinds = scene.kinds[ix.long().clamp(0, n - 1), iy.long().clamp(0, n - 1)]
    bx, by = lx - half, ly - half
    edge = torch.minimum(torch.minimum(bx, c.block - bx), torch.minimum(by, c.block - by))
    noise = 0.9 + 0.2 * _hash(torch.floor(p[:, 0] / 1.5), torch.floor(p[:, 1] / 1.5), 3.0)
    interior = torch.tensor([0.60, 0.58, 0.54], device=p.device).expand_as(col).clone()
    grass = torch.tensor([0.30, 0.50, 0.20], device=p.device) * noise[:, None]
    path = ((bx - c.block / 2).abs() < 1.4) | ((by - c.block / 2).abs() < 1.4)
    park = torch.where(path[:, None], torch.tensor([0.76, 0.71, 0.60], device=p.device), grass)
    tiles = ((bx % 4.0 < 0.15) | (by % 4.0 < 0.15))[:, None]
    plaza = torch.where(tiles, torch.tensor([0.62, 0.58, 0.52], device=p.device),
                        torch.tensor([0.80, 0.76, 0.68], device=p.device))
    stall = ((bx % 2.7) < 0.14) & ((by % 12.0) > 2.0) & ((by % 12.0) < 7.0)
    parking = torch.where(stall[:, None], torch.tensor([0.92, 0.92, 0.90], device=p.device),
                          torch.tensor([0.34, 0.34, 0.36], device=p.device))
    interior = torch.where((kinds == C.PARK)[:, None], park, interior)
    interior = torch.where((kinds == C.PLAZA)[:, None], plaza, interior)
    interior = torch.where((kinds == C.PARKING)[:, None], parking, interior)
    interior = torch.where((edge < 3.0)[:, None], torch.tensor([0.70, 0.69, 0.66], device=p.device), interior)
    # roads with dashed centre lines
    asphalt = torch.tensor([0.27, 0.27, 0.29], device=p.device) * (0.95 + 0.1 * noise[:, None] - 0.1)
    dash_x = (torch.minimum(lx, P - lx) < 0.18) & (torch.remainder(gy, 6.0) < 3.0) & ~road_y
    dash_y = (torch.minimum(ly, P - ly) < 0.18) & (torch.remainder(gx, 6.0) < 3.0) & ~road_x
    road = torch.where((dash_x | dash_y)[:, None], torch.tensor([0.92, 0.86, 0.45], device=p.device), asphalt)
    city_col = torch.where((road_x | road_y)[:, None], road, interior)
    return torch.where(inside[:, None], city_col, col)


def _box_albedo(scene: SceneTensors, p: Tensor, bid: Tensor, face: Tensor) -> Tensor:
    wall, roof = scene.wall[bid], scene.roof[bid]
    lo, hi, eave = scene.lo[bid], scene.hi[bid], scene.eave[bid]
    fh, bay, style = scene.floor_h[bid], scene.bay_w[bid], scene.style[bid]
    z = p[:, 2]
    s = torch.where(face == 0, p[:, 1] - lo[:, 1], p[:, 0] - lo[:, 0])
    fu, fv = torch.remainder(s / bay, 1.0), torch.remainder(z / fh, 1.0)
    glass = style == C.GLASS
    win = torch.where(glass, (fu > 0.06) & (fu < 0.94) & (fv > 0.1) & (fv < 0.9),
                      (fu > 0.2) & (fu < 0.8) & (fv > 0.3) & (fv < 0.82))
    win = win & (z > fh) & (z < eave - 0.4) & (style != C.PLAIN)
    shade = 0.75 + 0.5 * _hash(torch.floor(s / bay) + bid * 7.0, torch.floor(z / fh))
    pane = torch.where(glass[:, None], wall * 0.72, torch.tensor([0.20, 0.24, 0.30], device=p.device))
    facade = torch.where(win[:, None], pane * shade[:, None], wall)
    facade = torch.where(((z < fh) & (style != C.PLAIN))[:, None], wall * 0.72, facade)
    border = torch.minimum(torch.minimum(p[:, 0] - lo[:, 0], hi[:, 0] - p[:, 0]),
                           torch.minimum(p[:, 1] - lo[:, 1], hi[:, 1] - p[:, 1]))
    flat = torch.where((border < 0.6)[:, None], wall * 0.9, roof)
    sloped = roof * (0.86 + 0.14 * (torch.remainder(z / 0.45, 1.0) > 0.5).float())[:, None]
    out = torch.where((face < 2)[:, None], facade, flat)
    return torch.where((face >= 3)[:, None], sloped, out)


def _shade(scene: SceneTensors, o: Tensor, d: Tensor, t: Tensor, kind: Tensor, pid: Tensor) -> tuple[Tensor, Tensor]:
    """Colour ``[S, 3]`` in [0, 1] and world normals ``[S, 3]`` (zero for sky)."""
    S, dev = d.shape[0], d.device
    tt = torch.where(torch.isfinite(t), t, torch.zeros_like(t))
    p = o + tt[:, None] * d
    col = torch.zeros(S, 3, device=dev)
    nrm = torch.zeros(S, 3, device=dev)
    g = kind == 1
    col[g] = _ground_albedo(scene, p[g])
    nrm[g] = torch.tensor([0.0, 0.0, 1.0], device=dev)
    b = kind == 2
    if b.any():
        nb_, face = _box_normals(scene, o, d[b], pid[b])
        nrm[b] = nb_
        col[b] = _box_albedo(scene, p[b], pid[b], face)
    s = kind == 3
    if s.any():
        sp = pid[s]
        n = p[s] - scene.sph_c[sp]
        nrm[s] = n / n.norm(dim=1, keepdim=True).clamp_min(1e-9)
        q = p[s]
        leaf = 0.8 + 0.35 * _hash(torch.floor(q[:, 0] / 0.8) + torch.floor(q[:, 2] / 0.8) * 31.0,
                                  torch.floor(q[:, 1] / 0.8), 5.0)
        col[s] = scene.sph_col[sp] * leaf[:, None]
    lam = (nrm @ scene.sun).clamp_min(0)
    col = col * (0.5 + 0.62 * lam)[:, None]
    # sky and haze
    dn = d / d.norm(dim=1, keepdim=True)
    a = dn[:, 2].clamp(0, 1).sqrt()[:, None]
    sky = _SKY_HORIZON.to(dev) * (1 - a) + _SKY_ZENITH.to(dev) * a
    dist = tt * d.norm(dim=1)
    fog = (1 - torch.exp(-dist / _HAZE_M))[:, None]
    col = col * (1 - fog) + _SKY_HORIZON.to(dev) * fog
    col = torch.where((kind == 0)[:, None], sky, col)
    return col.clamp(0, 1), nrm


def _rays(w2c: Tensor, K: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """World directions ``[S, 3]`` with camera-frame z = 1 through pixel coordinates (u, v)."""
    cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], 1)
    return cam @ w2c[:3, :3]  # R^T applied to row vectors


@torch.no_grad()
def render(scene: SceneTensors, w2c: Tensor, K: Tensor, height: int, width: int, aa: bool = True) -> dict[str, Tensor]:
    """Ray-cast one view.

    Args:
        scene: the city as tensors.
        w2c: ``[4, 4]`` world-to-camera (OpenCV); K: ``[3, 3]`` intrinsics in pixels.
        height, width: image size in pixels.
        aa: re-trace high-contrast pixels with 4 sub-pixel rays.
    Returns:
        ``rgb [H, W, 3]`` float in [0, 1], ``depth [H, W]`` z-depth in metres (0 on sky), ``normal [H, W, 3]``
        unit normals in the camera frame (0 on sky), ``mask [H, W]`` bool (True where a surface was hit).
    """
    dev = scene.device
    w2c, K = w2c.to(dev, torch.float32), K.to(dev, torch.float32)
    o = -w2c[:3, :3].T @ w2c[:3, 3]
    vv, uu = torch.meshgrid(torch.arange(height, device=dev, dtype=torch.float32) + 0.5,
                            torch.arange(width, device=dev, dtype=torch.float32) + 0.5, indexing="ij")
    u, v = uu.reshape(-1), vv.reshape(-1)
    d = _rays(w2c, K, u, v)
    pix, prim = _screen_pairs(scene, w2c, K, height, width)
    t, kind, pid = _trace(scene, o, d, pix, prim)
    col, nrm = _shade(scene, o, d, t, kind, pid)
    if aa:
        img = col.view(height, width, 3)
        diff = torch.zeros(height, width, device=dev)
        dx = (img[:, 1:] - img[:, :-1]).abs().sum(-1)
        dy = (img[1:] - img[:-1]).abs().sum(-1)
        diff[:, 1:] = torch.maximum(diff[:, 1:], dx)
        diff[:, :-1] = torch.maximum(diff[:, :-1], dx)
        diff[1:] = torch.maximum(diff[1:], dy)
        diff[:-1] = torch.maximum(diff[:-1], dy)
        edge = (diff > 0.1).view(-1)
        e_idx = edge.nonzero()[:, 0]
        if len(e_idx):
            remap = torch.full((height * width,), -1, device=dev, dtype=torch.long)
            remap[e_idx] = torch.arange(len(e_idx), device=dev)
            keep = edge[pix]
            ps, pp = remap[pix[keep]], prim[keep]
            offs = ((-0.125, -0.375), (0.375, -0.125), (0.125, 0.375), (-0.375, 0.125))  # rotated grid
            n = len(e_idx)
            ds = torch.cat([_rays(w2c, K, u[e_idx] + a, v[e_idx] + b) for a, b in offs])
            s_all = torch.cat([ps + k * n for k in range(4)])
            t2, k2, p2 = _trace(scene, o, ds, s_all, pp.repeat(4))
            c2, _ = _shade(scene, o, ds, t2, k2, p2)
            col[e_idx] = (col[e_idx] + c2.view(4, n, 3).sum(0)) / 5
    hit = kind > 0
    depth = torch.where(hit, t, torch.zeros_like(t))
    n_cam = nrm @ w2c[:3, :3].T
    return {"rgb": col.view(height, width, 3), "depth": depth.view(height, width),
            "normal": n_cam.view(height, width, 3), "mask": hit.view(height, width)}


def look_at(eye, target, up=(0.0, 0.0, 1.0), heading=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV world-to-camera ``[4, 4]`` of a camera at ``eye`` looking at ``target`` (z-up world).

    For (near-)vertical views, ``heading`` gives the direction the top of the image points to.
    """
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    f = target - eye
    f /= np.linalg.norm(f)
    hint = np.asarray(up, np.float64) if abs(f[2]) < 0.999 else np.asarray(heading, np.float64)
    r = np.cross(f, hint) if abs(f[2]) < 0.999 else np.cross(f, hint)
    r /= np.linalg.norm(r)
    dn = np.cross(f, r)
    R = np.stack([r, dn, f])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def fov_intrinsics(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """``[3, 3]`` pinhole K with square pixels, horizontal field of view ``hfov_deg`` and centred principal point."""
    f = width / (2 * math.tan(math.radians(hfov_deg) / 2))
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float64)
