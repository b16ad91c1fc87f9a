"""Numba kernels for the fused CPU backend: tile binning, forward compositing, backward compositing.

Tiles are 8 px wide x 16 px tall (8 float32 lanes per row, see shared/research/fused_cpu.md). Per tile the
forward walks its depth-sorted pair list once, Gaussian-major, with one flat vectorised loop over the pixel rows
the Gaussian can reach. The backward walks the same list back to front, rebuilding T_i = T_{i+1} / (1 - α_i),
and writes one gradient row per (tile, Gaussian) pair into a slot owned by that pair, so no atomics are needed
and the per-Gaussian sums (done in the projection backward) are bitwise independent of the thread count.

Vectorisation rules that matter here (each was worth 2-5x): unsigned loop indices, one flat scratch array with
compile-time offsets, a polynomial ``exp`` instead of ``math.exp`` (no SVML in pip's llvmlite),
``error_model="numpy"``, and float32 constants only (a Python float literal promotes the loop to float64).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core.dispatcher import Dispatcher
from numba.extending import intrinsic

from anycity.render._numba_cache import stamp_constants
from anycity.render.projection import ALPHA_MAX, ALPHA_MIN, T_MIN

TX, TY = 8, 16  # tile width (one 8-lane vector per pixel row) and height, in pixels
NPIX = TX * TY
QBASE = 6  # pair row: mx, my (tile-relative), conic a, b, c, opacity; then D features; then row range r0, r1

_F = np.float32
_U = np.uint64
F0, F1, HALF = _F(0.0), _F(1.0), _F(0.5)
AMIN, AMAX, TMIN = _F(ALPHA_MIN), _F(ALPHA_MAX), _F(T_MIN)
EPS_ALPHA = _F(1e-10)
_LOG2E, _LN2_HI, _LN2_LO = _F(1.4426950408889634), _F(0.693145751953125), _F(1.428606765330187e-06)
_EXP_MIN = _F(-87.0)
_P2, _P3, _P4, _P5, _P6 = _F(1 / 2), _F(1 / 6), _F(1 / 24), _F(1 / 120), _F(1 / 720)


@intrinsic
def _bits_to_f32(typingctx, x):
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


@njit(inline="always", fastmath=True, error_model="numpy", cache=True)
def fexp(x):
    """float32 e^x for x <= 0 (relative error ~2e-7); vectorises, unlike math.exp."""
    x = max(x, _EXP_MIN)
    n = np.int32(x * _LOG2E - HALF)  # round(x·log2 e) for x <= 0 (truncation towards zero)
    nf = _F(n)
    r = x - nf * _LN2_HI - nf * _LN2_LO
    p = F1 + r * (F1 + r * (_P2 + r * (_P3 + r * (_P4 + r * (_P5 + r * _P6)))))
    return p * _bits_to_f32((n + np.int32(127)) << np.int32(23))


# ------------------------------------------------------------------------------------------------ binning


@njit(cache=True)
def depth_order(z, ntiles):
    """Entries with ntiles > 0, sorted by z (stable LSD radix sort on the float bits; z > 0)."""
    m = 0
    for e in range(z.shape[0]):
        if ntiles[e] > 0:
            m += 1
    order = np.empty(m, np.int64)
    keys = np.empty(m, np.uint32)
    bits = z.view(np.uint32)
    k = 0
    for e in range(z.shape[0]):
        if ntiles[e] > 0:
            order[k] = e
            keys[k] = bits[e]
            k += 1
    tmp_o = np.empty(m, np.int64)
    tmp_k = np.empty(m, np.uint32)
    for shift in (0, 11, 22):
        count = np.zeros(2049, np.int64)
        for i in range(m):
            count[((keys[i] >> shift) & 2047) + 1] += 1
        for d in range(2048):
            count[d + 1] += count[d]
        for i in range(m):
            d = (keys[i] >> shift) & 2047
            pos = count[d]
            count[d] += 1
            tmp_o[pos] = order[i]
            tmp_k[pos] = keys[i]
        order, tmp_o = tmp_o, order
        keys, tmp_k = tmp_k, keys
    return order


@njit(parallel=True, cache=True)
def bin_pairs(order, rect, ntiles, P, ext_y, n_cams, n_per_cam, tiles_x, tiles_y, n_chunks):
    """Counting sort of (tile, Gaussian) pairs by tile, stable, so each tile's run stays depth-sorted.

    Args:
        order: ``[M]`` depth-sorted entry ids (entry e = camera * N + gaussian).
        rect: ``[C*N, 4]`` int32 tile box x0, x1, y0, y1 (half-open); ntiles ``[C*N]`` its area.
        P: ``[C*N, 6+D]`` projected rows (mx, my, conic a b c, opacity, features); ext_y ``[C*N]`` the y
            half-extent of the footprint in px (pixel rows outside it cannot reach α >= 1/255).
    Returns:
        Q ``[n_pairs, 6+D+2]`` float32 pair rows (mean relative to the tile, ..., row range r0, r1),
        tile_off ``[C*tiles+1]``, slot ``[n_pairs]`` (each pair's row in the per-entry layout: entry e owns
        rows pstart[e]:pstart[e+1]), pstart ``[C*N+1]``.
    """
    ce = P.shape[0]
    tpc = tiles_x * tiles_y
    n_tiles = n_cams * tpc
    m = order.shape[0]
    width = P.shape[1]
    # gather the entries in depth order once, so that the passes below read sequentially
    Ps = np.empty((m, width), np.float32)
    Is = np.empty((m, 6), np.int64)  # tile base, x0, x1, y0, y1, pstart
    ys = np.empty(m, np.float32)
    pstart = np.zeros(ce + 1, np.int64)
    for e in range(ce):
        pstart[e + 1] = pstart[e] + ntiles[e]
    n_pairs = pstart[ce]
    for s in prange(m):
        e = order[s]
        for d in range(width):
            Ps[s, d] = P[e, d]
        Is[s, 0] = (e // n_per_cam) * tpc
        for d in range(4):
            Is[s, 1 + d] = rect[e, d]
        Is[s, 5] = pstart[e]
        ys[s] = ext_y[e]
    step = (m + n_chunks - 1) // n_chunks
    hist = np.zeros((n_chunks, n_tiles), np.int64)
    for k in prange(n_chunks):
        for s in range(k * step, min(m, (k + 1) * step)):
            for ty in range(Is[s, 3], Is[s, 4]):
                row = Is[s, 0] + ty * tiles_x
                for tx in range(Is[s, 1], Is[s, 2]):
                    hist[k, row + tx] += 1
    tile_off = np.zeros(n_tiles + 1, np.int64)
    for t in range(n_tiles):
        run = tile_off[t]
        for k in range(n_chunks):
            c = hist[k, t]
            hist[k, t] = run
            run += c
        tile_off[t + 1] = run
    qw = width + 2
    Q = np.empty((n_pairs, qw), np.float32)
    slot = np.empty(n_pairs, np.int64)
    for k in prange(n_chunks):
        for s in range(k * step, min(m, (k + 1) * step)):
            kk = Is[s, 5]
            mx, my, ry = Ps[s, 0], Ps[s, 1], ys[s]
            for ty in range(Is[s, 3], Is[s, 4]):
                oy = np.float32(ty * TY)
                r0 = max(0, math.ceil(max(my - ry - 0.5 - oy, -1.0)))
                r1 = min(TY, math.floor(min(my + ry - 0.5 - oy, TY + 1.0)) + 1)
                row = Is[s, 0] + ty * tiles_x
                for tx in range(Is[s, 1], Is[s, 2]):
                    j = hist[k, row + tx]
                    hist[k, row + tx] = j + 1
                    Q[j, 0] = mx - np.float32(tx * TX)
                    Q[j, 1] = my - oy
                    for d in range(2, width):
                        Q[j, d] = Ps[s, d]
                    Q[j, qw - 2] = r0
                    Q[j, qw - 1] = r1
                    slot[j] = kk
                    kk += 1
    return Q, tile_off, slot, pstart


# ------------------------------------------------------------------------------------------- compositing


def make_raster_kernels(D: int):
    """Forward and backward compositing kernels for D feature channels (rgb, z[, normal]); D is a compile-time
    constant so that the scratch offsets are too."""
    O_T, O_L, O_A = _U(0), _U(NPIX), _U(2 * NPIX)  # forward scratch: T | last | D accumulators
    O_S, O_G = _U(2 * NPIX), _U(3 * NPIX)  # backward scratch: T | last | suffix S | D pixel grads
    NF = 3 + D
    U7, U3 = _U(TX - 1), _U(3)
    QW = QBASE + D + 2
    NORMALS = D == 7

    def raster_fwd(Q, tile_off, tiles_x, tiles_y, width, height, bg, rgb, depth, alpha, normal, t_final, last):
        """Composite every tile. Writes rgb/depth/alpha/normal ``[C,ch,H,W]``, t_final and last ``[C,H,W]``
        (last = index within the tile's run of the last blended pair, -1 if none)."""
        tpc = tiles_x * tiles_y
        for t in prange(tile_off.shape[0] - 1):
            c = t // tpc
            ty = (t - c * tpc) // tiles_x
            tx = t - c * tpc - ty * tiles_x
            x0, y0 = tx * TX, ty * TY
            sc = np.empty(NF * NPIX, np.float32)
            ndone = 0
            for i in range(NPIX):
                inside = (x0 + (i & (TX - 1)) < width) and (y0 + (i >> 3) < height)
                sc[i] = F1 if inside else -F1
                ndone += 0 if inside else 1
                sc[NPIX + i] = -F1
                for d in range(D):
                    sc[(2 + d) * NPIX + i] = F0
            start = tile_off[t]
            for j in range(start, tile_off[t + 1]):
                if ndone >= NPIX:
                    break
                mx, my, a, b, cc, o = Q[j, 0], Q[j, 1], Q[j, 2], Q[j, 3], Q[j, 4], Q[j, 5]
                f0, f1, f2, f3 = Q[j, 6], Q[j, 7], Q[j, 8], Q[j, 9]
                if NORMALS:
                    f4, f5, f6 = Q[j, 10], Q[j, 11], Q[j, 12]
                jl = np.float32(j - start)
                nstop = 0
                for i in range(_U(Q[j, QW - 2]) * _U(TX), _U(Q[j, QW - 1]) * _U(TX)):
                    dx = np.float32(i & U7) + HALF - mx
                    dy = np.float32(i >> U3) + HALF - my
                    sig = HALF * (a * dx * dx + cc * dy * dy) + b * dx * dy
                    al = min(AMAX, o * fexp(-sig))
                    T = sc[O_T + i]
                    ok = (sig >= F0) & (al >= AMIN) & (T > F0)
                    Tn = T * (F1 - al)
                    stop = ok & (Tn <= TMIN)
                    use = ok & (Tn > TMIN)
                    w = al * T if use else F0
                    sc[O_A + i] += w * f0
                    sc[O_A + _U(NPIX) + i] += w * f1
                    sc[O_A + _U(2 * NPIX) + i] += w * f2
                    sc[O_A + _U(3 * NPIX) + i] += w * f3
                    if NORMALS:
                        sc[O_A + _U(4 * NPIX) + i] += w * f4
                        sc[O_A + _U(5 * NPIX) + i] += w * f5
                        sc[O_A + _U(6 * NPIX) + i] += w * f6
                    sc[O_T + i] = Tn if use else (-T if stop else T)
                    sc[O_L + i] = jl if use else sc[O_L + i]
                    nstop += np.int64(stop)
                ndone += nstop
            for i in range(NPIX):
                px, py = x0 + (i & (TX - 1)), y0 + (i >> 3)
                if px < width and py < height:
                    T = abs(sc[i])
                    al = F1 - T
                    for ch in range(3):
                        rgb[c, ch, py, px] = sc[(2 + ch) * NPIX + i] + T * bg[c, ch]
                    depth[c, 0, py, px] = sc[5 * NPIX + i] / max(al, EPS_ALPHA)
                    alpha[c, 0, py, px] = al
                    if NORMALS:
                        for ch in range(3):
                            normal[c, ch, py, px] = sc[(6 + ch) * NPIX + i]
                    t_final[c, py, px] = T
                    last[c, py, px] = sc[NPIX + i]

    def raster_bwd(Q, tile_off, slot, tiles_x, tiles_y, width, height, bg, t_final, last, depth,
                   g_rgb, g_depth, g_alpha, g_normal, G):
        """Per pair, dL/d(mx, my, conic a, b, c, opacity, features) summed over the tile's pixels -> G[slot]."""
        tpc = tiles_x * tiles_y
        for t in prange(tile_off.shape[0] - 1):
            start, stop_ = tile_off[t], tile_off[t + 1]
            if stop_ == start:
                continue
            c = t // tpc
            ty = (t - c * tpc) // tiles_x
            tx = t - c * tpc - ty * tiles_x
            x0, y0 = tx * TX, ty * TY
            sc = np.empty(NF * NPIX, np.float32)
            jmax = -1.0
            for i in range(NPIX):
                px, py = x0 + (i & (TX - 1)), y0 + (i >> 3)
                if px < width and py < height:
                    T = t_final[c, py, px]
                    al = F1 - T
                    gz = g_depth[c, 0, py, px]
                    ga = g_alpha[c, 0, py, px]
                    if al > EPS_ALPHA:
                        ga -= gz * depth[c, 0, py, px] / al
                    gT = -ga
                    for ch in range(3):
                        g = g_rgb[c, ch, py, px]
                        gT += g * bg[c, ch]
                        sc[(3 + ch) * NPIX + i] = g
                    sc[6 * NPIX + i] = gz / max(al, EPS_ALPHA)
                    if NORMALS:
                        for ch in range(3):
                            sc[(7 + ch) * NPIX + i] = g_normal[c, ch, py, px]
                    sc[i] = T
                    sc[NPIX + i] = last[c, py, px]
                    sc[2 * NPIX + i] = gT * T
                    jmax = max(jmax, last[c, py, px])
                else:
                    for k in range(NF):
                        sc[k * NPIX + i] = F0
                    sc[NPIX + i] = -F1
            for j in range(start + np.int64(jmax) + 1, stop_):  # pairs behind every pixel's last: no gradient
                for d in range(QBASE + D):
                    G[slot[j], d] = F0
            for j in range(start + np.int64(jmax), start - 1, -1):
                mx, my, a, b, cc, o = Q[j, 0], Q[j, 1], Q[j, 2], Q[j, 3], Q[j, 4], Q[j, 5]
                f0, f1, f2, f3 = Q[j, 6], Q[j, 7], Q[j, 8], Q[j, 9]
                if NORMALS:
                    f4, f5, f6 = Q[j, 10], Q[j, 11], Q[j, 12]
                jl = np.float32(j - start)
                s_mx = s_my = s_a = s_b = s_c = s_o = F0
                s_f0 = s_f1 = s_f2 = s_f3 = s_f4 = s_f5 = s_f6 = F0
                for i in range(_U(Q[j, QW - 2]) * _U(TX), _U(Q[j, QW - 1]) * _U(TX)):
                    dx = np.float32(i & U7) + HALF - mx
                    dy = np.float32(i >> U3) + HALF - my
                    sig = HALF * (a * dx * dx + cc * dy * dy) + b * dx * dy
                    e = fexp(-sig)
                    oe = o * e
                    al = min(AMAX, oe)
                    use = (sig >= F0) & (al >= AMIN) & (jl <= sc[O_L + i])
                    inv = F1 / (F1 - al)
                    Ti = sc[O_T + i] * inv
                    w = al * Ti if use else F0
                    g0, g1, g2, g3 = sc[O_G + i], sc[O_G + _U(NPIX) + i], sc[O_G + _U(2 * NPIX) + i], \
                        sc[O_G + _U(3 * NPIX) + i]
                    Gi = g0 * f0 + g1 * f1 + g2 * f2 + g3 * f3
                    if NORMALS:
                        g4, g5, g6 = sc[O_G + _U(4 * NPIX) + i], sc[O_G + _U(5 * NPIX) + i], \
                            sc[O_G + _U(6 * NPIX) + i]
                        Gi += g4 * f4 + g5 * f5 + g6 * f6
                    S = sc[O_S + i]
                    dal = Gi * Ti - S * inv
                    free = use & (oe < AMAX)  # the 0.99 clamp stops σ and opacity gradients
                    gsig = -al * dal if free else F0
                    s_o += e * dal if free else F0
                    s_f0 += g0 * w
                    s_f1 += g1 * w
                    s_f2 += g2 * w
                    s_f3 += g3 * w
                    if NORMALS:
                        s_f4 += g4 * w
                        s_f5 += g5 * w
                        s_f6 += g6 * w
                    s_mx -= gsig * (a * dx + b * dy)
                    s_my -= gsig * (b * dx + cc * dy)
                    s_a += gsig * dx * dx
                    s_b += gsig * dx * dy
                    s_c += gsig * dy * dy
                    sc[O_T + i] = Ti if use else sc[O_T + i]
                    sc[O_S + i] = S + Gi * w
                row = slot[j]
                G[row, 0] = s_mx
                G[row, 1] = s_my
                G[row, 2] = HALF * s_a
                G[row, 3] = s_b
                G[row, 4] = HALF * s_c
                G[row, 5] = s_o
                G[row, 6] = s_f0
                G[row, 7] = s_f1
                G[row, 8] = s_f2
                G[row, 9] = s_f3
                if NORMALS:
                    G[row, 10] = s_f4
                    G[row, 11] = s_f5
                    G[row, 12] = s_f6

    kernels = tuple(_jit_per_channel_count(fn, D) for fn in (raster_fwd, raster_bwd))
    stamp_constants(kernels)
    return kernels


def _jit_per_channel_count(fn, D: int) -> Dispatcher:
    """``fn`` compiled with a cache file of its own per ``D``: numba names a kernel's cache index after its qualname,
    which both channel counts' closures share; two processes compiling D = 4 and D = 7 at once then both write data
    file 1 of one index, and a later process loaded one D's machine code for the other (silently wrong renders)."""
    fn.__qualname__ = f"{fn.__name__}_d{D}"
    return njit(parallel=True, fastmath=True, error_model="numpy", cache=True)(fn)


# cached kernels go stale when a constant of this module (imported ones included) changes: see stamp_constants
stamp_constants([v for v in list(globals().values()) if isinstance(v, Dispatcher)])
