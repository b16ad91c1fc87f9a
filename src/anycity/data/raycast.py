"""Exact, vectorised ray casting of a :class:`~anycity.data.city.City` (torch, CPU or GPU).

Acceleration: every primitive is projected into the image and only tested against the rays of the pixels in its
screen bounding box (plus a one-pixel margin), as a flat list of (ray, primitive) pairs; the nearest hit per ray
is a ``scatter_reduce(amin)``. Ray directions are camera-frame ``[x, y, 1]`` rotated to the world, so the ray
parameter ``t`` *is* the OpenCV z-depth. Hits are exact (slab test against boxes intersected with sloped roof
half-spaces, quadratic for spheres, plane z = 0 for the ground).

Anti-aliasing is adaptive: pixels whose colour differs from a neighbour are re-traced with four sub-pixel rays
and averaged; depth, normals and the mask come from the pixel-centre ray. At geometric edges (a neighbour hit
another primitive) the sub-pixel rays test all the pixel's candidates; inside one primitive (texture contrast:
windows, road marks, noise) they test only that convex primitive and the ground, which is most edge pixels.

Speed (CPU, one thread): gathers are ``index_select`` (advanced indexing is several times slower), min/max over
the 3 slab axes and 4 roof planes are column-wise ``minimum``/``maximum`` (tiny-dimension reductions are slow),
boxes and spheres are traced as separate pair lists, and per-box shading attributes come from one table.
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
_DARK_GLASS = torch.tensor([0.20, 0.24, 0.30])


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
        self.nb = len(self.lo)
        eye = torch.eye(3, device=device)
        self.face_normals = torch.cat([torch.stack([eye[i // 2] * (1 - 2 * (i % 2)) for i in range(6)]),
                                       self.roof_n], 0)  # [10, 3], see _box_normals
        self.ground_palette = _GROUND_PALETTE.to(device)
        # per-box shading attributes in one table (one gather per shaded batch)
        self.box_attr = torch.cat([self.lo, self.hi, self.wall, self.roof, self.eave[:, None], self.floor_h[:, None],
                                   self.bay_w[:, None], self.style[:, None].float()], 1)  # [Nb, 16]
        # corners of the primitives' bounding boxes, for screen-space culling
        lo = torch.cat([self.lo, self.sph_c - self.sph_r[:, None]], 0)
        hi = torch.cat([self.hi, self.sph_c + self.sph_r[:, None]], 0)
        sel = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], device=device, dtype=torch.bool)
        self.corners = torch.where(sel[None], hi[:, None], lo[:, None])  # [Nb + Ns, 8, 3]


class Pairs:
    """Candidate (ray, primitive) pairs, boxes and spheres apart: ``bs/bp`` ray and box indices, ``ss/sp`` ray and
    sphere indices (all int64 ``[P]``)."""

    def __init__(self, bs: Tensor, bp: Tensor, ss: Tensor, sp: Tensor) -> None:
        self.bs, self.bp, self.ss, self.sp = bs, bp, ss, sp

    def repeat(self, k: int, n: int) -> Pairs:
        """The pairs of ``k`` ray sets of ``n`` rays stacked one after the other (ray ``i`` of set ``j`` is
        ``i + j n``)."""
        off = lambda s: (s[None] + n * torch.arange(k, device=s.device)[:, None]).reshape(-1)  # noqa: E731
        return Pairs(off(self.bs), self.bp.repeat(k), off(self.ss), self.sp.repeat(k))


def _screen_pairs(scene: SceneTensors, w2c: Tensor, K: Tensor, h: int, w: int) -> Pairs:
    """(pixel index, primitive index) pairs for every pixel inside a primitive's projected bounding box."""
    cam = scene.corners @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[..., 2]
    front = z > 1e-3
    uv = (cam @ K.T)[..., :2] / z.clamp_min(1e-3)[..., None]
    umin = uv.masked_fill(~front[..., None], 1e9).amin(1)
    umax = uv.masked_fill(~front[..., None], -1e9).amax(1)
    partial = front.any(1) & ~front.all(1)  # straddles the camera plane: test the whole image
    x0 = torch.where(partial, 0, (umin[:, 0].floor() - 1).clamp(0, w)).long()
    x1 = torch.where(partial, w - 1, (umax[:, 0].floor() + 1).clamp(-1, w - 1)).long()
    y0 = torch.where(partial, 0, (umin[:, 1].floor() - 1).clamp(0, h)).long()
    y1 = torch.where(partial, h - 1, (umax[:, 1].floor() + 1).clamp(-1, h - 1)).long()
    bw, bh = (x1 - x0 + 1).clamp_min(0), (y1 - y0 + 1).clamp_min(0)
    area = torch.where(front.any(1), bw * bh, 0)
    n_box = int(area[: scene.nb].sum())
    total = int(area.sum())
    prim = torch.repeat_interleave(torch.arange(len(area), device=uv.device), area, output_size=total)
    rep = lambda a: torch.repeat_interleave(a, area, output_size=total)  # noqa: E731
    bw_r = rep(bw)
    off = torch.arange(total, device=uv.device) - rep(torch.cumsum(area, 0) - area)
    pix = (rep(y0) + off // bw_r) * w + rep(x0) + off % bw_r
    return Pairs(pix[:n_box], prim[:n_box], pix[n_box:], prim[n_box:] - scene.nb)


def _trace(scene: SceneTensors, o: Tensor, d: Tensor, pairs: Pairs) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest hit of rays ``o + t d`` (``d [S, 3]``) over the candidate pairs.

    Returns ``t [S]`` (inf for no hit), ``kind [S]`` (0 sky, 1 ground, 2 box, 3 sphere) and ``pid [S]`` (the box
    or sphere index, -1 otherwise).
    """
    S, nb, dev = d.shape[0], scene.nb, d.device
    # boxes: slab test on the three axes, clipped by the sloped roof half-spaces (dn = 0: parallel, ignored)
    inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    ray = torch.cat([inv, d @ scene.roof_n.T], 1)  # [S, 7]
    tab = torch.cat([scene.lo - o, scene.hi - o, scene.roof_d - scene.roof_n @ o], 1)  # [Nb, 10]
    g, r = tab.index_select(0, pairs.bp), ray.index_select(0, pairs.bs)
    t1, t2 = g[:, 0:3] * r[:, 0:3], g[:, 3:6] * r[:, 0:3]
    near, far = torch.minimum(t1, t2), torch.maximum(t1, t2)
    dn = r[:, 3:]
    tr = g[:, 6:] / dn
    enter, leave = tr.masked_fill(dn >= 0, -_INF), tr.masked_fill(dn <= 0, _INF)
    # column-wise max/min: reductions over tiny inner dimensions are slow on CPU
    tn, tf = near[:, 0], far[:, 0]
    for k in (1, 2):
        tn, tf = torch.maximum(tn, near[:, k]), torch.minimum(tf, far[:, k])
    for k in range(4):
        tn, tf = torch.maximum(tn, enter[:, k]), torch.minimum(tf, leave[:, k])
    tb = tn.masked_fill((tn > tf) | (tn <= _EPS), _INF)
    # spheres: nearest root of |o + t d - c|^2 = r^2 (rays starting inside a crown miss it)
    oc_tab = o - scene.sph_c  # [Ns, 3]
    c_tab = (oc_tab * oc_tab).sum(1) - scene.sph_r ** 2
    oc, dd = oc_tab.index_select(0, pairs.sp), d.index_select(0, pairs.ss)
    a = (dd * dd).sum(1)
    b = (dd * oc).sum(1)
    disc = b * b - a * c_tab.index_select(0, pairs.sp)
    ts = (-b - disc.clamp_min(0).sqrt()) / a
    ts = ts.masked_fill((disc <= 0) | (ts <= _EPS), _INF)
    # nearest primitive per ray (global id: boxes 0..Nb-1, spheres Nb..), then the ground plane z = 0
    s_all, t_all = torch.cat([pairs.bs, pairs.ss]), torch.cat([tb, ts])
    p_all = torch.cat([pairs.bp, pairs.sp + nb])
    t_prim = torch.full((S,), _INF, device=dev).scatter_reduce_(0, s_all, t_all, "amin")
    win = (t_all == t_prim.index_select(0, s_all)) & (t_all < _INF)
    gid = torch.full((S,), -1, device=dev, dtype=torch.long).scatter_reduce_(0, s_all[win], p_all[win], "amax")
    t_gnd = torch.where(d[:, 2] < 0, -o[2] / d[:, 2].clamp_max(-1e-12), _INF)
    prim_first = t_prim < t_gnd
    t = torch.where(prim_first, t_prim, t_gnd)
    kind = torch.where(prim_first, torch.where(gid < nb, 2, 3), torch.where(t_gnd < _INF, 1, 0))
    pid = torch.where(prim_first, torch.where(gid < nb, gid, gid - nb), -1)
    return t, kind, pid


def _hash(ix: Tensor, iy: Tensor, salt: float = 0.0) -> Tensor:
    """Deterministic pseudo-random value in [0, 1) per integer cell."""
    v = torch.sin(ix.float() * 12.9898 + iy.float() * 78.233 + salt) * 43758.5453
    return v - v.floor()


def _box_normals(scene: SceneTensors, o: Tensor, d: Tensor, attr: Tensor, bid: Tensor) -> tuple[Tensor, Tensor]:
    """World normals ``[S, 3]`` and face ids ``[S]`` (0..2 axis faces, 3..6 roof planes) of box hits.

    ``attr``: the hit boxes' rows of ``scene.box_attr``; the face is the one whose entry parameter is largest.
    """
    dsafe = torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    t_axis = torch.minimum((attr[:, 0:3] - o) / dsafe, (attr[:, 3:6] - o) / dsafe)
    dn = d @ scene.roof_n.T
    tr = ((scene.roof_d.index_select(0, bid) - scene.roof_n @ o) / dn).masked_fill(dn >= 0, -_INF)
    face = torch.cat([t_axis, tr], 1).argmax(1)
    # rows of _FACE_NORMALS: +x, -x, +y, -y, +z, -z (an axis face faces against the ray), then the 4 roof planes
    axis = face.clamp_max(2)
    away = d.gather(1, axis[:, None])[:, 0] >= 0
    row = torch.where(face < 3, 2 * axis + away.long(), face + 3)
    return scene.face_normals.index_select(0, row), face


_GROUND_PALETTE = torch.tensor([
    [0.42, 0.52, 0.25], [0.60, 0.56, 0.33], [0.33, 0.45, 0.21], [0.52, 0.43, 0.28],  # 0-3 countryside fields
    [0.60, 0.58, 0.54], [0.30, 0.50, 0.20], [0.76, 0.71, 0.60],  # 4 block interior, 5 grass, 6 park path
    [0.62, 0.58, 0.52], [0.80, 0.76, 0.68],  # 7 plaza tile joint, 8 plaza tile
    [0.92, 0.92, 0.90], [0.34, 0.34, 0.36],  # 9 parking stall line, 10 parking asphalt
    [0.70, 0.69, 0.66], [0.27, 0.27, 0.29], [0.92, 0.86, 0.45],  # 11 sidewalk, 12 road, 13 centre line
])


def _ground_albedo(scene: SceneTensors, p: Tensor) -> Tensor:
    """Ground colour ``[S, 3]``: a material id and a brightness per point, then one palette lookup."""
    c = scene.city
    P, n = c.pitch, c.n_blocks
    gx, gy = p[:, 0] + n * P / 2, p[:, 1] + n * P / 2
    ix, iy = torch.floor(gx / P), torch.floor(gy / P)
    lx, ly = gx - ix * P, gy - iy * P
    inside = (gx >= 0) & (gy >= 0) & (gx < n * P) & (gy < n * P)
    half = c.road / 2
    road_x, road_y = (lx < half) | (lx > half + c.block), (ly < half) | (ly > half + c.block)
    # countryside fields
    field = (_hash(torch.floor(p[:, 0] / 37.0), torch.floor(p[:, 1] / 29.0)) * 4).long().clamp_max(3)
    mult = 0.93 + 0.07 * torch.sin(p[:, 0] * 1.3 + p[:, 1] * 0.4)
    # block interiors
    cell = ix.long().clamp(0, n - 1) * n + iy.long().clamp(0, n - 1)
    kinds = scene.kinds.reshape(-1).index_select(0, cell)
    bx, by = lx - half, ly - half
    edge = torch.minimum(torch.minimum(bx, c.block - bx), torch.minimum(by, c.block - by))
    noise = 0.9 + 0.2 * _hash(torch.floor(p[:, 0] / 1.5), torch.floor(p[:, 1] / 1.5), 3.0)
    path = ((bx - c.block / 2).abs() < 1.4) | ((by - c.block / 2).abs() < 1.4)
    tiles = (bx % 4.0 < 0.15) | (by % 4.0 < 0.15)
    stall = ((bx % 2.7) < 0.14) & ((by % 12.0) > 2.0) & ((by % 12.0) < 7.0)
    interior = torch.full_like(field, 4)
    interior = torch.where(kinds == C.PARK, torch.where(path, 6, 5), interior)
    interior = torch.where(kinds == C.PLAZA, torch.where(tiles, 7, 8), interior)
    interior = torch.where(kinds == C.PARKING, torch.where(stall, 9, 10), interior)
    interior = torch.where(edge < 3.0, 11, interior)
    # roads with dashed centre lines
    dash_x = (torch.minimum(lx, P - lx) < 0.18) & (torch.remainder(gy, 6.0) < 3.0) & ~road_y
    dash_y = (torch.minimum(ly, P - ly) < 0.18) & (torch.remainder(gx, 6.0) < 3.0) & ~road_x
    road = torch.where(dash_x | dash_y, 13, 12)
    city = torch.where(road_x | road_y, road, interior)
    mat = torch.where(inside, city, field)
    city_mult = torch.where(mat == 5, noise, torch.where(mat == 12, 0.85 + 0.1 * noise, 1.0))  # grass, asphalt
    mult = torch.where(inside, city_mult, mult)
    return scene.ground_palette.index_select(0, mat) * mult[:, None]


def _box_albedo(p: Tensor, attr: Tensor, bid: Tensor, face: Tensor) -> Tensor:
    """Box colour ``[S, 3]``: the wall or roof albedo (or dark glass) of each hit times a brightness."""
    lo, hi, wall, roof = attr[:, 0:3], attr[:, 3:6], attr[:, 6:9], attr[:, 9:12]
    eave, fh, bay, style = attr[:, 12], attr[:, 13], attr[:, 14], attr[:, 15].long()
    z = p[:, 2]
    s = torch.where(face == 0, p[:, 1] - lo[:, 1], p[:, 0] - lo[:, 0])
    fu, fv = torch.remainder(s / bay, 1.0), torch.remainder(z / fh, 1.0)
    glass, plain = style == C.GLASS, style == C.PLAIN
    win = torch.where(glass, (fu > 0.06) & (fu < 0.94) & (fv > 0.1) & (fv < 0.9),
                      (fu > 0.2) & (fu < 0.8) & (fv > 0.3) & (fv < 0.82))
    win = win & (z > fh) & (z < eave - 0.4) & ~plain
    shade = 0.75 + 0.5 * _hash(torch.floor(s / bay) + bid * 7.0, torch.floor(z / fh))
    lobby = (z < fh) & ~plain
    # walls: window panes (tinted wall for glass, dark glass otherwise) x shade, ground floor 0.72, else wall
    wall_mult = torch.where(lobby, 0.72, torch.where(win, torch.where(glass, 0.72, 1.0) * shade, 1.0))
    dark = win & ~glass & ~lobby
    border = torch.minimum(torch.minimum(p[:, 0] - lo[:, 0], hi[:, 0] - p[:, 0]),
                           torch.minimum(p[:, 1] - lo[:, 1], hi[:, 1] - p[:, 1]))
    flat_wall = border < 0.6  # roof parapet
    stripe = 0.86 + 0.14 * (torch.remainder(z / 0.45, 1.0) > 0.5).float()
    side, top, sloped = face < 2, face == 2, face >= 3
    use_roof = (top & ~flat_wall) | sloped
    mult = torch.where(side, wall_mult, torch.where(sloped, stripe, torch.where(flat_wall, 0.9, 1.0)))
    col = torch.where(use_roof[:, None], roof, wall)
    col = torch.where((side & dark)[:, None], _DARK_GLASS.to(p.device), col)
    return col * mult[:, None]


def _shade(scene: SceneTensors, o: Tensor, d: Tensor, t: Tensor, kind: Tensor, pid: Tensor) -> tuple[Tensor, Tensor]:
    """Colour ``[S, 3]`` in [0, 1] and world normals ``[S, 3]`` (zero for sky)."""
    S, dev = d.shape[0], d.device
    tt = torch.where(kind > 0, t, torch.zeros_like(t))
    p = torch.addcmul(o, tt[:, None], d)
    col = torch.zeros(S, 3, device=dev)
    nrm = torch.zeros(S, 3, device=dev)
    g = (kind == 1).nonzero()[:, 0]
    if len(g):
        col.index_copy_(0, g, _ground_albedo(scene, p.index_select(0, g)))
        nrm[:, 2].masked_fill_(kind == 1, 1.0)
    b = (kind == 2).nonzero()[:, 0]
    if len(b):
        bid = pid.index_select(0, b)
        attr = scene.box_attr.index_select(0, bid)
        nb_, face = _box_normals(scene, o, d.index_select(0, b), attr, bid)
        nrm.index_copy_(0, b, nb_)
        col.index_copy_(0, b, _box_albedo(p.index_select(0, b), attr, bid, face))
    s = (kind == 3).nonzero()[:, 0]
    if len(s):
        sp = pid.index_select(0, s)
        q = p.index_select(0, s)
        n = q - scene.sph_c.index_select(0, sp)
        nrm.index_copy_(0, s, n / n.norm(dim=1, keepdim=True).clamp_min(1e-9))
        leaf = 0.8 + 0.35 * _hash(torch.floor(q[:, 0] / 0.8) + torch.floor(q[:, 2] / 0.8) * 31.0,
                                  torch.floor(q[:, 1] / 0.8), 5.0)
        col.index_copy_(0, s, scene.sph_col.index_select(0, sp) * leaf[:, None])
    lam = (nrm @ scene.sun).clamp_min(0)
    dnorm = d.norm(dim=1)
    # haze towards the horizon colour with distance; sky gradient from horizon to zenith
    fog = 1 - torch.exp(-(tt * dnorm) / _HAZE_M)
    horizon = _SKY_HORIZON.to(dev)
    col = torch.addcmul(horizon * fog[:, None], col, ((0.5 + 0.62 * lam) * (1 - fog))[:, None])
    a = (d[:, 2] / dnorm).clamp(0, 1).sqrt()[:, None]
    sky = torch.lerp(horizon, _SKY_ZENITH.to(dev), a)
    col = torch.where((kind == 0)[:, None], sky, col)
    return col.clamp(0, 1), nrm


def _rays(w2c: Tensor, K: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """World directions ``[S, 3]`` with camera-frame z = 1 through pixel coordinates (u, v)."""
    cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], 1)
    return cam @ w2c[:3, :3]  # R^T applied to row vectors


def _edges(img: Tensor, hit: Tensor) -> tuple[Tensor, Tensor]:
    """Pixels to anti-alias: colour contrast > 0.1 to a 4-neighbour; and among them the geometric edges (a
    4-neighbour hit another primitive, or the ground/sky)."""
    H, W = hit.shape
    dx = (img[:, 1:] - img[:, :-1]).abs().sum(-1) > 0.1
    dy = (img[1:] - img[:-1]).abs().sum(-1) > 0.1
    gx, gy = hit[:, 1:] != hit[:, :-1], hit[1:] != hit[:-1]
    edge = torch.zeros(H, W, dtype=torch.bool, device=img.device)
    geo = torch.zeros_like(edge)
    for m, a, b in ((edge, dx, dy), (geo, gx, gy)):
        m[:, 1:] |= a
        m[:, :-1] |= a
        m[1:] |= b
        m[:-1] |= b
    return edge.view(-1), (edge & geo).view(-1)


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
    pairs = _screen_pairs(scene, w2c, K, height, width)
    t, kind, pid = _trace(scene, o, d, pairs)
    col, nrm = _shade(scene, o, d, t, kind, pid)
    if aa:
        hit_id = torch.where(kind == 2, pid, torch.where(kind == 3, pid + scene.nb, -1 - kind))
        edge, geo = _edges(col.view(height, width, 3), hit_id.view(height, width))
        e_idx = edge.nonzero()[:, 0]
        n = len(e_idx)
        if n:
            # geometric edges: re-trace against all the pixel's candidates; inside one primitive (texture
            # contrast only) the sub-pixel rays hit the same convex primitive, so trace only that one
            remap = torch.full((height * width,), -1, device=dev, dtype=torch.long)
            remap[e_idx] = torch.arange(n, device=dev)
            kb, ks = geo.index_select(0, pairs.bs), geo.index_select(0, pairs.ss)
            tex = edge & ~geo
            tb = (tex & (kind == 2)).nonzero()[:, 0]
            ts = (tex & (kind == 3)).nonzero()[:, 0]
            sub = Pairs(torch.cat([remap.index_select(0, pairs.bs[kb]), remap.index_select(0, tb)]),
                        torch.cat([pairs.bp[kb], pid.index_select(0, tb)]),
                        torch.cat([remap.index_select(0, pairs.ss[ks]), remap.index_select(0, ts)]),
                        torch.cat([pairs.sp[ks], pid.index_select(0, ts)])).repeat(4, n)
            offs = ((-0.125, -0.375), (0.375, -0.125), (0.125, 0.375), (-0.375, 0.125))  # rotated grid
            ue, ve = u.index_select(0, e_idx), v.index_select(0, e_idx)
            ds = torch.cat([_rays(w2c, K, ue + a, ve + b) for a, b in offs])
            t2, k2, p2 = _trace(scene, o, ds, sub)
            c2, _ = _shade(scene, o, ds, t2, k2, p2)
            col.index_copy_(0, e_idx, (col.index_select(0, e_idx) + c2.view(4, n, 3).sum(0)) / 5)
    hit = kind > 0
    depth = torch.where(hit, t, torch.zeros_like(t))
    n_cam = nrm @ w2c[:3, :3].T
    return {"rgb": col.view(height, width, 3), "depth": depth.view(height, width),
            "normal": n_cam.view(height, width, 3), "mask": hit.view(height, width)}


def look_at(eye, target, up=(0.0, 0.0, 1.0), heading=(0.0, 1.0, 0.0)) -> np.ndarray:
    """OpenCV world-to-camera ``[4, 4]`` of a camera at ``eye`` looking at ``target`` (z-up world).

    The top of the image points to ``up`` (projected), or for (near-)vertical views (``|f_z| >= 0.999``, within
    2.6 deg of vertical) to ``heading``. A view that should keep a heading when tilted a few degrees off vertical
    passes it as ``up`` too (the synthetic nadir lawnmower does).
    """
    eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
    f = target - eye
    f /= np.linalg.norm(f)
    hint = np.asarray(up, np.float64) if abs(f[2]) < 0.999 else np.asarray(heading, np.float64)
    r = np.cross(f, hint)
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
