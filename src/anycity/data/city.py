"""Procedural city layout: a road grid of blocks holding buildings, parks and plazas, as ray-castable primitives.

World frame: metres, +z up, ground plane z = 0, the city centred on the origin. Everything here is numpy and
deterministic from the ``numpy.random.Generator`` passed in; :mod:`anycity.data.raycast` renders it.

Primitives:
    * Buildings are axis-aligned boxes ``[lo, hi]`` intersected with up to four sloped roof half-spaces
      ``n_k . x <= d_k`` whose normals come from the fixed set :data:`ROOF_NORMALS` (one roof pitch per city), so
      flat roofs, gables (ridge along x or y) and hip roofs are all convex and exactly ray-castable.
    * Tree crowns are spheres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ROOF_PITCH_DEG = 32.0
_S, _C = math.sin(math.radians(ROOF_PITCH_DEG)), math.cos(math.radians(ROOF_PITCH_DEG))
#: ``[4, 3]`` outward normals of the sloped roof planes: facing +x, -x, +y, -y.
ROOF_NORMALS = np.array([[_S, 0, _C], [-_S, 0, _C], [0, _S, _C], [0, -_S, _C]], dtype=np.float32)
INACTIVE = 1e9  # plane offset of an unused roof half-space (always satisfied)

# Block kinds.
BUILDINGS, PARK, PLAZA, PARKING = 0, 1, 2, 3
# Box styles (how the shader paints the facade).
FACADE, GLASS, PLAIN = 0, 1, 2

_FACADES = np.array([[0.80, 0.74, 0.62], [0.66, 0.36, 0.28], [0.72, 0.72, 0.70], [0.90, 0.88, 0.84],
                     [0.82, 0.66, 0.46], [0.55, 0.52, 0.50], [0.78, 0.58, 0.52]], dtype=np.float32)
_GLASS = np.array([[0.42, 0.55, 0.66], [0.36, 0.44, 0.50], [0.50, 0.60, 0.58]], dtype=np.float32)
_FLAT_ROOFS = np.array([[0.45, 0.45, 0.47], [0.62, 0.60, 0.56], [0.30, 0.31, 0.33], [0.70, 0.70, 0.72]],
                       dtype=np.float32)
_SLOPED_ROOFS = np.array([[0.62, 0.24, 0.16], [0.30, 0.30, 0.34], [0.34, 0.50, 0.44], [0.52, 0.30, 0.22]],
                         dtype=np.float32)


@dataclass
class City:
    """A procedural city (all arrays numpy float32 unless stated).

    Attributes:
        box_lo, box_hi: ``[Nb, 3]`` building box corners in metres.
        roof_d: ``[Nb, 4]`` offsets of the roof half-spaces ``ROOF_NORMALS[k] . x <= roof_d[:, k]``.
        eave: ``[Nb]`` height where the walls end (windows stop below it).
        wall, roof: ``[Nb, 3]`` albedos of the walls and of the roof/top faces.
        style: ``[Nb]`` int, FACADE / GLASS / PLAIN.
        floor_h, bay_w: ``[Nb]`` storey height and window bay width in metres.
        sph_c: ``[Ns, 3]`` tree crown centres; sph_r ``[Ns]`` radii; sph_col ``[Ns, 3]`` albedos.
        n_blocks: blocks per side; block, road: block side and road width in metres.
        block_kind: ``[n_blocks, n_blocks]`` int kind of each block (indexed [ix, iy]).
        sun: ``[3]`` unit direction towards the sun.
    """

    box_lo: np.ndarray
    box_hi: np.ndarray
    roof_d: np.ndarray
    eave: np.ndarray
    wall: np.ndarray
    roof: np.ndarray
    style: np.ndarray
    floor_h: np.ndarray
    bay_w: np.ndarray
    sph_c: np.ndarray
    sph_r: np.ndarray
    sph_col: np.ndarray
    n_blocks: int
    block: float
    road: float
    block_kind: np.ndarray
    sun: np.ndarray

    @property
    def pitch(self) -> float:
        """Distance between consecutive block origins (block + road) in metres."""
        return self.block + self.road

    @property
    def half_extent(self) -> float:
        """Half the side of the square city (roads included) in metres."""
        return self.n_blocks * self.pitch / 2

    @property
    def max_height(self) -> float:
        return float(self.box_hi[:, 2].max()) if len(self.box_hi) else 0.0


class _Builder:
    def __init__(self) -> None:
        self.boxes: list[tuple] = []
        self.trees: list[tuple] = []

    def box(self, lo, hi, wall, roof, style, floor_h=3.2, bay_w=2.6, roof_kind="flat"):
        lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
        d = np.full(4, INACTIVE, np.float32)
        eave = float(hi[2])
        if roof_kind != "flat":
            # roof height above the eave at the ridge: half the span (across the ridge) times tan(pitch)
            tan = _S / _C
            span_x, span_y = (hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2
            ridge_along_x = span_x >= span_y
            rise = tan * (span_y if ridge_along_x or roof_kind == "hip" else span_x)
            if roof_kind == "hip":
                rise = tan * min(span_x, span_y)
            top = eave + rise
            c = (lo + hi) / 2
            planes = ([2, 3] if ridge_along_x else [0, 1]) if roof_kind == "gable" else [0, 1, 2, 3]
            for k in planes:
                n = ROOF_NORMALS[k]
                axis = 0 if k < 2 else 1
                half = span_x if axis == 0 else span_y
                edge = c.copy()
                edge[axis] += half * np.sign(n[axis])
                edge[2] = eave
                d[k] = float(n @ edge)
            hi = hi.copy()
            hi[2] = top
        self.boxes.append((lo, hi, d, eave, np.asarray(wall, np.float32), np.asarray(roof, np.float32),
                           style, floor_h, bay_w))

    def tree(self, x, y, r, col):
        self.trees.append(((x, y, 2.5 + r), r, col))  # crown on a 2.5 m trunk


def _building(b: _Builder, rng: np.random.Generator, x0, y0, x1, y1, downtown: float) -> None:
    """One building on the lot [x0, x1] x [y0, y1]; downtown in [0, 1] raises heights."""
    m = rng.uniform(0.8, 2.5)
    x0, y0, x1, y1 = x0 + m, y0 + m, x1 - m, y1 - m
    if x1 - x0 < 4 or y1 - y0 < 4:
        return
    u = rng.random()
    floor_h = rng.uniform(3.0, 3.6)
    if u < 0.35 * (1 - downtown) + 0.05:  # low-rise house with a sloped roof
        h = floor_h * rng.integers(2, 4)
        kind = "gable" if rng.random() < 0.6 else "hip"
        b.box((x0, y0, 0), (x1, y1, h), _FACADES[rng.integers(len(_FACADES))],
              _SLOPED_ROOFS[rng.integers(len(_SLOPED_ROOFS))], FACADE, floor_h, rng.uniform(2.4, 3.2), kind)
    elif u < 0.75 - 0.45 * downtown:  # mid-rise, flat roof with a plant room
        h = floor_h * rng.integers(4, 9)
        b.box((x0, y0, 0), (x1, y1, h), _FACADES[rng.integers(len(_FACADES))],
              _FLAT_ROOFS[rng.integers(len(_FLAT_ROOFS))], FACADE, floor_h, rng.uniform(2.2, 3.0))
        w, d = (x1 - x0) * rng.uniform(0.2, 0.4), (y1 - y0) * rng.uniform(0.2, 0.4)
        cx, cy = rng.uniform(x0 + w, x1 - w), rng.uniform(y0 + d, y1 - d)
        b.box((cx - w / 2, cy - d / 2, h), (cx + w / 2, cy + d / 2, h + rng.uniform(1.5, 3.0)),
              (0.75, 0.75, 0.74), (0.55, 0.56, 0.58), PLAIN)
    else:  # tower with setbacks
        h = floor_h * rng.integers(12, 18 + int(14 * downtown))
        glass = rng.random() < 0.6
        wall = _GLASS[rng.integers(len(_GLASS))] if glass else _FACADES[rng.integers(len(_FACADES))]
        roof = _FLAT_ROOFS[rng.integers(len(_FLAT_ROOFS))]
        style = GLASS if glass else FACADE
        z = 0.0
        tiers = rng.integers(1, 4)
        for t in range(tiers):
            top = h * (t + 1) / tiers
            b.box((x0, y0, z), (x1, y1, top), wall, roof, style, floor_h, rng.uniform(1.8, 2.6))
            shrink_x, shrink_y = (x1 - x0) * rng.uniform(0.1, 0.2), (y1 - y0) * rng.uniform(0.1, 0.2)
            x0, x1, y0, y1, z = x0 + shrink_x, x1 - shrink_x, y0 + shrink_y, y1 - shrink_y, top


def make_city(rng: np.random.Generator, n_blocks: int | None = None) -> City:
    """A random city of ``n_blocks x n_blocks`` blocks (4..6 when None)."""
    n = int(rng.integers(4, 7)) if n_blocks is None else int(n_blocks)
    block, road = float(rng.uniform(38, 50)), float(rng.uniform(11, 15))
    pitch = block + road
    origin = -n * pitch / 2 + road / 2
    kinds = rng.choice([BUILDINGS, PARK, PLAZA, PARKING], size=(n, n), p=[0.72, 0.14, 0.07, 0.07])
    b = _Builder()
    walk = 3.0
    for ix in range(n):
        for iy in range(n):
            bx0, by0 = origin + ix * pitch, origin + iy * pitch
            bx1, by1 = bx0 + block, by0 + block
            r = math.hypot((bx0 + bx1) / 2, (by0 + by1) / 2) / (n * pitch / 2)
            downtown = float(np.clip(1.2 - r, 0, 1))
            kind = kinds[ix, iy]
            if kind == BUILDINGS:
                nx, ny = rng.integers(1, 4), rng.integers(1, 4)
                xs = np.linspace(bx0 + walk, bx1 - walk, nx + 1)
                ys = np.linspace(by0 + walk, by1 - walk, ny + 1)
                for i in range(nx):
                    for j in range(ny):
                        _building(b, rng, xs[i], ys[j], xs[i + 1], ys[j + 1], downtown)
                for _ in range(rng.integers(0, 4)):  # street trees on the sidewalk
                    side = rng.integers(4)
                    t = rng.uniform(bx0 + 3, bx1 - 3)
                    x, y = [(t, by0 + 1.5), (t, by1 - 1.5), (bx0 + 1.5, t), (bx1 - 1.5, t)][side]
                    b.tree(x, y, rng.uniform(1.8, 2.6), _tree_colour(rng))
            elif kind == PARK:
                for _ in range(rng.integers(8, 20)):
                    r_ = rng.uniform(2.2, 4.5)
                    b.tree(rng.uniform(bx0 + r_ + 1, bx1 - r_ - 1), rng.uniform(by0 + r_ + 1, by1 - r_ - 1), r_,
                           _tree_colour(rng))
            elif kind == PLAZA and rng.random() < 0.7:  # a low pavilion
                cx, cy = (bx0 + bx1) / 2, (by0 + by1) / 2
                s = block * rng.uniform(0.12, 0.2)
                b.box((cx - s, cy - s, 0), (cx + s, cy + s, rng.uniform(4, 7)), (0.85, 0.82, 0.75),
                      _SLOPED_ROOFS[rng.integers(len(_SLOPED_ROOFS))], PLAIN, roof_kind="hip")
    el, az = math.radians(rng.uniform(35, 65)), rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)], np.float32)
    boxes = list(zip(*b.boxes)) if b.boxes else [[] for _ in range(9)]
    trees = list(zip(*b.trees)) if b.trees else [[], [], []]
    f32 = lambda x, shape: np.asarray(x, np.float32).reshape(shape)  # noqa: E731
    nb, ns = len(b.boxes), len(b.trees)
    return City(
        box_lo=f32(boxes[0], (nb, 3)), box_hi=f32(boxes[1], (nb, 3)), roof_d=f32(boxes[2], (nb, 4)),
        eave=f32(boxes[3], (nb,)), wall=f32(boxes[4], (nb, 3)), roof=f32(boxes[5], (nb, 3)),
        style=np.asarray(boxes[6], np.int64).reshape(nb), floor_h=f32(boxes[7], (nb,)), bay_w=f32(boxes[8], (nb,)),
        sph_c=f32(trees[0], (ns, 3)), sph_r=f32(trees[1], (ns,)), sph_col=f32(trees[2], (ns, 3)),
        n_blocks=n, block=block, road=road, block_kind=kinds.astype(np.int64), sun=sun,
    )


def _tree_colour(rng: np.random.Generator) -> np.ndarray:
    base = np.array([0.22, 0.42, 0.16], np.float32)
    return np.clip(base * rng.uniform(0.75, 1.25, 3).astype(np.float32), 0, 1)
