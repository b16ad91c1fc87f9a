"""Numba kernels for the fused CPU backend: projection + SH colour (forward) and their backward.

Same maths as ``projection.project_gaussians`` (the reference), per (camera, Gaussian) entry ``e = c * N + n`` with
``c = b * V + v``. Arithmetic is float64 inside (scalar code, no cost), stored as float32. The backward loops over
Gaussians and, inside, over their V cameras and their (tile, Gaussian) pairs, so every sum has a fixed order.

Camera table ``cams [C, 23]`` (float64): R (9, row-major), t (3), fx, fy, cx, cy, camera centre (3), and the
clamp limits on x/z and y/z: x_lo, x_hi, y_lo, y_hi.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.core.dispatcher import Dispatcher

from anycity.render._cpu_raster import QBASE, TX, TY
from anycity.render._numba_cache import stamp_constants
from anycity.render.projection import ALPHA_MIN, EPS2D, RADIUS_SIGMAS
from anycity.render.sh import C0, C1, C2, C3, C4

_C2, _C3, _C4 = np.array(C2), np.array(C3), np.array(C4)
N_CHUNKS = 64  # fixed work split: results do not depend on the thread count


@njit(inline="always", cache=True)
def _quat_rot(q0, q1, q2, q3, rot):
    """Normalised wxyz quaternion -> rot (3x3, row-major, float64 [9]); returns the norm."""
    nrm = max(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), 1e-12)
    inv = 1.0 / nrm
    w, x, y, z = q0 * inv, q1 * inv, q2 * inv, q3 * inv
    rot[0], rot[1], rot[2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    rot[3], rot[4], rot[5] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    rot[6], rot[7], rot[8] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return nrm


@njit(inline="always", cache=True)
def _sh_basis(x, y, z, K, out):
    xx, yy, zz = x * x, y * y, z * z
    out[0] = C0
    if K > 1:
        out[1], out[2], out[3] = -C1 * y, C1 * z, -C1 * x
    if K > 4:
        out[4], out[5], out[6] = _C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2 * zz - xx - yy)
        out[7], out[8] = _C2[3] * x * z, _C2[4] * (xx - yy)
    if K > 9:
        out[9] = _C3[0] * y * (3 * xx - yy)
        out[10] = _C3[1] * x * y * z
        out[11] = _C3[2] * y * (4 * zz - xx - yy)
        out[12] = _C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
        out[13] = _C3[4] * x * (4 * zz - xx - yy)
        out[14] = _C3[5] * z * (xx - yy)
        out[15] = _C3[6] * x * (xx - 3 * yy)
    if K > 16:
        out[16] = _C4[0] * x * y * (xx - yy)
        out[17] = _C4[1] * y * z * (3 * xx - yy)
        out[18] = _C4[2] * x * y * (7 * zz - 1)
        out[19] = _C4[3] * y * z * (7 * zz - 3)
        out[20] = _C4[4] * (zz * (35 * zz - 30) + 3)
        out[21] = _C4[5] * x * z * (7 * zz - 3)
        out[22] = _C4[6] * (xx - yy) * (7 * zz - 1)
        out[23] = _C4[7] * x * z * (xx - 3 * yy)
        out[24] = _C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))


@njit(inline="always", cache=True)
def _sh_dir_grad(x, y, z, K, s):
    """Σ_k s[k] ∇Y_k at the unit direction (x, y, z) -> (gx, gy, gz)."""
    gx = gy = gz = 0.0
    xx, yy, zz = x * x, y * y, z * z
    if K > 1:
        gx -= C1 * s[3]
        gy -= C1 * s[1]
        gz += C1 * s[2]
    if K > 4:
        a, b, c, d, e = _C2[0] * s[4], _C2[1] * s[5], _C2[2] * s[6], _C2[3] * s[7], _C2[4] * s[8]
        gx += a * y - 2 * c * x + d * z + 2 * e * x
        gy += a * x + b * z - 2 * c * y - 2 * e * y
        gz += b * y + 4 * c * z + d * x
    if K > 9:
        k9, k10, k11, k12 = _C3[0] * s[9], _C3[1] * s[10], _C3[2] * s[11], _C3[3] * s[12]
        k13, k14, k15 = _C3[4] * s[13], _C3[5] * s[14], _C3[6] * s[15]
        gx += (k9 * 6 * x * y + k10 * y * z - k11 * 2 * x * y - k12 * 6 * x * z + k13 * (4 * zz - 3 * xx - yy)
               + k14 * 2 * x * z + k15 * 3 * (xx - yy))
        gy += (k9 * 3 * (xx - yy) + k10 * x * z + k11 * (4 * zz - xx - 3 * yy) - k12 * 6 * y * z
               - k13 * 2 * x * y - k14 * 2 * y * z - k15 * 6 * x * y)
        gz += k10 * x * y + k11 * 8 * y * z + k12 * (6 * zz - 3 * xx - 3 * yy) + k13 * 8 * x * z + k14 * (xx - yy)
    if K > 16:
        k16, k17, k18, k19, k20 = _C4[0] * s[16], _C4[1] * s[17], _C4[2] * s[18], _C4[3] * s[19], _C4[4] * s[20]
        k21, k22, k23, k24 = _C4[5] * s[21], _C4[6] * s[22], _C4[7] * s[23], _C4[8] * s[24]
        gx += (k16 * (3 * xx * y - yy * y) + k17 * 6 * x * y * z + k18 * y * (7 * zz - 1) + k21 * z * (7 * zz - 3)
               + k22 * 2 * x * (7 * zz - 1) + k23 * z * (3 * xx - 3 * yy) + k24 * (4 * xx * x - 12 * x * yy))
        gy += (k16 * (xx * x - 3 * x * yy) + k17 * (3 * xx * z - 3 * yy * z) + k18 * x * (7 * zz - 1)
               + k19 * z * (7 * zz - 3) - k22 * 2 * y * (7 * zz - 1) - k23 * 6 * x * y * z
               + k24 * (4 * yy * y - 12 * xx * y))
        gz += (k17 * (3 * xx * y - yy * y) + k18 * 14 * x * y * z + k19 * y * (21 * zz - 3)
               + k20 * (140 * zz * z - 60 * z) + k21 * x * (21 * zz - 3) + k22 * 14 * z * (xx - yy)
               + k23 * x * (xx - 3 * yy))
    return gx, gy, gz


@njit(inline="always", cache=True)
def _cov2d(cams, c, rot, s0, s1, s2, j00, j02, j11, j12):
    """Upper triangle (a, b, c) of Σ2D = A Aᵀ + eps2d·I, A = J W M with M = rot·diag(s) and J's nonzero entries
    (j00, j02; j11, j12); W is camera c's rotation in ``cams[c, :9]``."""
    ca = cb = cc = 0.0
    for k in range(3):  # column k of M: A[:, k] = (J W) M[:, k]
        sk = s0 if k == 0 else (s1 if k == 1 else s2)
        w0 = (cams[c, 0] * rot[k] + cams[c, 1] * rot[3 + k] + cams[c, 2] * rot[6 + k]) * sk
        w1 = (cams[c, 3] * rot[k] + cams[c, 4] * rot[3 + k] + cams[c, 5] * rot[6 + k]) * sk
        w2 = (cams[c, 6] * rot[k] + cams[c, 7] * rot[3 + k] + cams[c, 8] * rot[6 + k]) * sk
        a0 = j00 * w0 + j02 * w2
        a1 = j11 * w1 + j12 * w2
        ca += a0 * a0
        cb += a0 * a1
        cc += a1 * a1
    return ca + EPS2D, cb, cc + EPS2D


@njit(cache=True)
def _project_fwd_chunk(chunk, step, total, means, quats, scales, opac, sh, valid, cams, V, width, height, near, far,
                       P, z_out, rect, ntiles, ext_y):
    """Entries ``chunk * step`` up to ``(chunk + 1) * step`` of :func:`project_fwd`: a serial function that its
    parallel loop calls, which numba compiles several times faster than the same body inlined in the loop."""
    N = means.shape[1]
    K = sh.shape[2]
    normals = P.shape[1] - QBASE == 7
    rot = np.empty(9)
    basis = np.empty(25)
    for e in range(chunk * step, min(total, (chunk + 1) * step)):
        c = e // N
        n = e - c * N
        b = c // V
        ntiles[e] = 0
        z_out[e] = 1.0
        m0, m1, m2 = means[b, n, 0], means[b, n, 1], means[b, n, 2]
        x = cams[c, 0] * m0 + cams[c, 1] * m1 + cams[c, 2] * m2 + cams[c, 9]
        y = cams[c, 3] * m0 + cams[c, 4] * m1 + cams[c, 5] * m2 + cams[c, 10]
        z = cams[c, 6] * m0 + cams[c, 7] * m1 + cams[c, 8] * m2 + cams[c, 11]
        o = opac[b, n]
        z32 = np.float32(z)  # cull on the float32 z against float32 planes, as the torch backend and gsplat do
        if not (valid[b, n] and z > 0 and z32 >= near and z32 <= far and o >= ALPHA_MIN):
            continue
        fx, fy, cx, cy = cams[c, 12], cams[c, 13], cams[c, 14], cams[c, 15]
        _quat_rot(quats[b, n, 0], quats[b, n, 1], quats[b, n, 2], quats[b, n, 3], rot)
        s0, s1, s2 = scales[b, n, 0], scales[b, n, 1], scales[b, n, 2]
        iz = 1.0 / z
        u = min(max(x * iz, cams[c, 19]), cams[c, 20])
        v = min(max(y * iz, cams[c, 21]), cams[c, 22])
        # rows of J R (J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]])
        j00, j02, j11, j12 = fx * iz, -fx * u * iz, fy * iz, -fy * v * iz
        ca, cb, cc = _cov2d(cams, c, rot, s0, s1, s2, j00, j02, j11, j12)
        det = ca * cc - cb * cb
        if not det > 0:
            continue
        mx, my = fx * x * iz + cx, fy * y * iz + cy
        ext = min(RADIUS_SIGMAS, math.sqrt(2.0 * math.log(255.0 * o))) * 1.001 + 1e-3
        rx, ry = ext * math.sqrt(ca) + 1e-3, ext * math.sqrt(cc) + 1e-3
        # pixels whose centre (p + 0.5) lies within [m - r, m + r], clamped to the image
        px0 = max(math.ceil(max(mx - rx - 0.5, -1.0)), 0)
        px1 = min(math.floor(min(mx + rx - 0.5, width + 1.0)), width - 1)
        py0 = max(math.ceil(max(my - ry - 0.5, -1.0)), 0)
        py1 = min(math.floor(min(my + ry - 0.5, height + 1.0)), height - 1)
        if px1 < px0 or py1 < py0:
            continue
        rect[e, 0], rect[e, 1] = px0 // TX, px1 // TX + 1
        rect[e, 2], rect[e, 3] = py0 // TY, py1 // TY + 1
        ntiles[e] = (rect[e, 1] - rect[e, 0]) * (rect[e, 3] - rect[e, 2])
        ext_y[e] = ry
        z_out[e] = z
        P[e, 0], P[e, 1] = mx, my
        idet = 1.0 / det
        P[e, 2], P[e, 3], P[e, 4] = cc * idet, -cb * idet, ca * idet
        P[e, 5] = o
        if K == 1:
            for ch in range(3):
                P[e, 6 + ch] = max(C0 * sh[b, n, 0, ch] + 0.5, 0.0)
        else:
            d0, d1, d2 = m0 - cams[c, 16], m1 - cams[c, 17], m2 - cams[c, 18]
            dn = max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-12)
            _sh_basis(d0 / dn, d1 / dn, d2 / dn, K, basis)
            for ch in range(3):
                acc = 0.5
                for k in range(K):
                    acc += basis[k] * sh[b, n, k, ch]
                P[e, 6 + ch] = max(acc, 0.0)
        P[e, 9] = z
        if normals:
            k = 0 if (s0 <= s1 and s0 <= s2) else (1 if s1 <= s2 else 2)
            nx = cams[c, 0] * rot[k] + cams[c, 1] * rot[3 + k] + cams[c, 2] * rot[6 + k]
            ny = cams[c, 3] * rot[k] + cams[c, 4] * rot[3 + k] + cams[c, 5] * rot[6 + k]
            nz = cams[c, 6] * rot[k] + cams[c, 7] * rot[3 + k] + cams[c, 8] * rot[6 + k]
            sgn = -1.0 if nx * x + ny * y + nz * z > 0 else 1.0
            P[e, 10], P[e, 11], P[e, 12] = sgn * nx, sgn * ny, sgn * nz


@njit(parallel=True, cache=True)
def project_fwd(means, quats, scales, opac, sh, valid, cams, V, width, height, near, far, tiles_x, tiles_y,
                P, z_out, rect, ntiles, ext_y):
    """Fill P ``[C*N, 6+D]`` (mx, my, conic a b c, opacity, rgb, z[, normal]), z_out, the tile box rect,
    ntiles (its area; 0 = culled) and ext_y, the footprint's y half-extent in px. Footprints use the
    opacity-aware extent min(3.33, sqrt(2 ln(255 o))) σ: outside it α < 1/255, so it culls exactly what
    compositing would skip. ``near``/``far``: the culling planes, float32 values (the float32 z is compared)."""
    B, N = means.shape[:2]
    total = B * V * N
    step = (total + N_CHUNKS - 1) // N_CHUNKS
    for chunk in prange(N_CHUNKS):
        _project_fwd_chunk(np.int64(chunk), step, total, means, quats, scales, opac, sh, valid, cams, V, width,
                           height, near, far, P, z_out, rect, ntiles, ext_y)


@njit(cache=True)
def _project_bwd_chunk(chunk, step, total, means, quats, scales, opac, sh, cams, V, pstart, G, g_means, g_quats,
                       g_scales, g_opac, g_sh, cam_grad, g_cam):
    """Entries ``chunk * step`` up to ``(chunk + 1) * step`` of :func:`project_bwd`: a serial function that its
    parallel loop calls, which numba compiles several times faster than the same body inlined in the loop."""
    N = means.shape[1]
    K = sh.shape[2]
    D = G.shape[1] - QBASE
    rot = np.empty(9)
    grot = np.empty(9)
    basis = np.empty(25)
    s = np.empty(25)
    g = np.empty(QBASE + 7)
    gcam = g_cam[chunk]
    gcam[:] = 0.0
    for bn in range(chunk * step, min(total, (chunk + 1) * step)):
        b = bn // N
        n = bn - b * N
        for k in range(K):
            for ch in range(3):
                g_sh[b, n, k, ch] = 0.0
        gm0 = gm1 = gm2 = gs0 = gs1 = gs2 = go = 0.0
        for k in range(9):
            grot[k] = 0.0
        qn = _quat_rot(quats[b, n, 0], quats[b, n, 1], quats[b, n, 2], quats[b, n, 3], rot)
        m0, m1, m2 = means[b, n, 0], means[b, n, 1], means[b, n, 2]
        sc = (scales[b, n, 0], scales[b, n, 1], scales[b, n, 2])
        for v in range(V):
            c = b * V + v
            e = c * N + n
            if pstart[e + 1] == pstart[e]:
                continue
            for d in range(QBASE + D):
                g[d] = 0.0
            for row in range(pstart[e], pstart[e + 1]):
                for d in range(QBASE + D):
                    g[d] += G[row, d]
            x = cams[c, 0] * m0 + cams[c, 1] * m1 + cams[c, 2] * m2 + cams[c, 9]
            y = cams[c, 3] * m0 + cams[c, 4] * m1 + cams[c, 5] * m2 + cams[c, 10]
            z = cams[c, 6] * m0 + cams[c, 7] * m1 + cams[c, 8] * m2 + cams[c, 11]
            fx, fy = cams[c, 12], cams[c, 13]
            iz = 1.0 / z
            xz, yz = x * iz, y * iz
            u = min(max(xz, cams[c, 19]), cams[c, 20])
            vv = min(max(yz, cams[c, 21]), cams[c, 22])
            j00, j02, j11, j12 = fx * iz, -fx * u * iz, fy * iz, -fy * vv * iz
            ca, cb, cc = _cov2d(cams, c, rot, sc[0], sc[1], sc[2], j00, j02, j11, j12)  # forward again
            det = ca * cc - cb * cb
            idet = 1.0 / det
            qa, qb, qc = cc * idet, -cb * idet, ca * idet
            # conic -> Σ2D: H = -Q Gq Q with Gq = [[ga, gb/2], [gb/2, gc]]
            ga, gb, gc = g[2], 0.5 * g[3], g[4]
            t00, t01 = qa * ga + qb * gb, qa * gb + qb * gc
            t10, t11 = qb * ga + qc * gb, qb * gb + qc * gc
            h00, h01, h11 = -(t00 * qa + t01 * qb), -(t00 * qb + t01 * qc), -(t10 * qb + t11 * qc)
            gj00 = gj02 = gj11 = gj12 = 0.0
            for k in range(3):
                r0 = cams[c, 0] * rot[k] + cams[c, 1] * rot[3 + k] + cams[c, 2] * rot[6 + k]
                r1 = cams[c, 3] * rot[k] + cams[c, 4] * rot[3 + k] + cams[c, 5] * rot[6 + k]
                r2 = cams[c, 6] * rot[k] + cams[c, 7] * rot[3 + k] + cams[c, 8] * rot[6 + k]
                w0, w1, w2 = r0 * sc[k], r1 * sc[k], r2 * sc[k]
                a0, a1 = j00 * w0 + j02 * w2, j11 * w1 + j12 * w2
                ga0, ga1 = 2 * (h00 * a0 + h01 * a1), 2 * (h01 * a0 + h11 * a1)  # dL/dA = 2 H A
                gj00 += ga0 * w0
                gj02 += ga0 * w2
                gj11 += ga1 * w1
                gj12 += ga1 * w2
                gw0, gw1, gw2 = j00 * ga0, j11 * ga1, j02 * ga0 + j12 * ga1
                if k == 0:
                    gs0 += r0 * gw0 + r1 * gw1 + r2 * gw2
                elif k == 1:
                    gs1 += r0 * gw0 + r1 * gw1 + r2 * gw2
                else:
                    gs2 += r0 * gw0 + r1 * gw1 + r2 * gw2
                for i in range(3):  # d rot[i, k] += s_k (Rᵀ gw)_i
                    grot[3 * i + k] += sc[k] * (cams[c, i] * gw0 + cams[c, 3 + i] * gw1 + cams[c, 6 + i] * gw2)
                if cam_grad:  # d W[i, j] += gw_i M[j, k], M = rot diag(s)
                    for j in range(3):
                        mjk = rot[3 * j + k] * sc[k]
                        gcam[c, j] += gw0 * mjk
                        gcam[c, 3 + j] += gw1 * mjk
                        gcam[c, 6 + j] += gw2 * mjk
            gx = g[0] * fx * iz
            gy = g[1] * fy * iz
            gz = -(g[0] * fx * x + g[1] * fy * y) * iz * iz + g[9]
            gz += -(gj00 * fx + gj11 * fy) * iz * iz + (gj02 * fx * u + gj12 * fy * vv) * iz * iz
            gu, gv = -gj02 * fx * iz, -gj12 * fy * iz
            if cams[c, 19] <= xz <= cams[c, 20]:
                gx += gu * iz
                gz -= gu * x * iz * iz
            elif cam_grad:  # u sits on a clamp limit, -(cx + 0.15 W)/fx or (1.15 W - cx)/fx: d/dfx = -u/fx
                gcam[c, 12] -= gu * u / fx
                gcam[c, 14] -= gu / fx
            if cams[c, 21] <= yz <= cams[c, 22]:
                gy += gv * iz
                gz -= gv * y * iz * iz
            elif cam_grad:
                gcam[c, 13] -= gv * vv / fy
                gcam[c, 15] -= gv / fy
            if cam_grad:  # mean2d = f x/z + c; J's entries f/z and -f u/z
                gcam[c, 12] += g[0] * xz + (gj00 - gj02 * u) * iz
                gcam[c, 13] += g[1] * yz + (gj11 - gj12 * vv) * iz
                gcam[c, 14] += g[0]
                gcam[c, 15] += g[1]
            go += g[5]
            # colour (SH + 0.5, clamped at 0)
            if K == 1:
                for ch in range(3):
                    if C0 * sh[b, n, 0, ch] + 0.5 >= 0.0:
                        g_sh[b, n, 0, ch] += C0 * g[6 + ch]
            else:
                d0, d1, d2 = m0 - cams[c, 16], m1 - cams[c, 17], m2 - cams[c, 18]
                dn = max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-12)
                d0, d1, d2 = d0 / dn, d1 / dn, d2 / dn
                _sh_basis(d0, d1, d2, K, basis)
                for k in range(K):
                    s[k] = 0.0
                for ch in range(3):
                    acc = 0.5
                    for k in range(K):
                        acc += basis[k] * sh[b, n, k, ch]
                    gcol = g[6 + ch] if acc >= 0.0 else 0.0
                    for k in range(K):
                        g_sh[b, n, k, ch] += basis[k] * gcol
                        s[k] += gcol * sh[b, n, k, ch]
                gd0, gd1, gd2 = _sh_dir_grad(d0, d1, d2, K, s)
                dot = gd0 * d0 + gd1 * d1 + gd2 * d2
                gd0, gd1, gd2 = (gd0 - d0 * dot) / dn, (gd1 - d1 * dot) / dn, (gd2 - d2 * dot) / dn
                gm0 += gd0
                gm1 += gd1
                gm2 += gd2
                if cam_grad:  # the view direction's origin, the camera centre -Rᵀ t, takes -gd
                    for i in range(3):
                        ti = cams[c, 9 + i]
                        gcam[c, 3 * i] += gd0 * ti
                        gcam[c, 3 * i + 1] += gd1 * ti
                        gcam[c, 3 * i + 2] += gd2 * ti
                        gcam[c, 9 + i] += cams[c, 3 * i] * gd0 + cams[c, 3 * i + 1] * gd1 + cams[c, 3 * i + 2] * gd2
            if D == 7:
                k = 0 if (sc[0] <= sc[1] and sc[0] <= sc[2]) else (1 if sc[1] <= sc[2] else 2)
                nx = cams[c, 0] * rot[k] + cams[c, 1] * rot[3 + k] + cams[c, 2] * rot[6 + k]
                ny = cams[c, 3] * rot[k] + cams[c, 4] * rot[3 + k] + cams[c, 5] * rot[6 + k]
                nz = cams[c, 6] * rot[k] + cams[c, 7] * rot[3 + k] + cams[c, 8] * rot[6 + k]
                sgn = -1.0 if nx * x + ny * y + nz * z > 0 else 1.0
                for i in range(3):
                    grot[3 * i + k] += sgn * (cams[c, i] * g[10] + cams[c, 3 + i] * g[11] + cams[c, 6 + i] * g[12])
                if cam_grad:  # normal = sgn W rot[:, k]
                    for i in range(3):
                        for j in range(3):
                            gcam[c, 3 * i + j] += sgn * g[10 + i] * rot[3 * j + k]
            if cam_grad:  # camera-frame point p = W m + t
                for j in range(3):
                    mj = m0 if j == 0 else (m1 if j == 1 else m2)
                    gcam[c, j] += gx * mj
                    gcam[c, 3 + j] += gy * mj
                    gcam[c, 6 + j] += gz * mj
                gcam[c, 9] += gx
                gcam[c, 10] += gy
                gcam[c, 11] += gz
            # camera-frame point -> world mean: Rᵀ (gx, gy, gz)
            gm0 += cams[c, 0] * gx + cams[c, 3] * gy + cams[c, 6] * gz
            gm1 += cams[c, 1] * gx + cams[c, 4] * gy + cams[c, 7] * gz
            gm2 += cams[c, 2] * gx + cams[c, 5] * gy + cams[c, 8] * gz
        g_means[b, n, 0], g_means[b, n, 1], g_means[b, n, 2] = gm0, gm1, gm2
        g_scales[b, n, 0], g_scales[b, n, 1], g_scales[b, n, 2] = gs0, gs1, gs2
        g_opac[b, n] = go
        # rotation matrix -> normalised quaternion -> raw quaternion
        w, qx, qy, qz = quats[b, n, 0] / qn, quats[b, n, 1] / qn, quats[b, n, 2] / qn, quats[b, n, 3] / qn
        r = grot
        gw = 2 * (-qz * r[1] + qy * r[2] + qz * r[3] - qx * r[5] - qy * r[6] + qx * r[7])
        gx_ = 2 * (qy * r[1] + qz * r[2] + qy * r[3] - 2 * qx * r[4] - w * r[5] + qz * r[6] + w * r[7]
                   - 2 * qx * r[8])
        gy_ = 2 * (-2 * qy * r[0] + qx * r[1] + w * r[2] + qx * r[3] + qz * r[5] - w * r[6] + qz * r[7]
                   - 2 * qy * r[8])
        gz_ = 2 * (-2 * qz * r[0] - w * r[1] + qx * r[2] + w * r[3] - 2 * qz * r[4] + qy * r[5] + qx * r[6]
                   + qy * r[7])
        dot = gw * w + gx_ * qx + gy_ * qy + gz_ * qz
        g_quats[b, n, 0] = (gw - w * dot) / qn
        g_quats[b, n, 1] = (gx_ - qx * dot) / qn
        g_quats[b, n, 2] = (gy_ - qy * dot) / qn
        g_quats[b, n, 3] = (gz_ - qz * dot) / qn


@njit(parallel=True, cache=True)
def project_bwd(means, quats, scales, opac, sh, cams, V, pstart, G,
                g_means, g_quats, g_scales, g_opac, g_sh, cam_grad, g_cam):
    """Chain the per-pair 2-D gradients G ``[n_pairs, 6+D]`` (rows of entry e at pstart[e]:pstart[e+1])
    back through projection and SH into the per-Gaussian gradients (overwritten). With ``cam_grad``, also into
    ``g_cam [N_CHUNKS, C, 16]`` (float64, overwritten): each work chunk's camera gradients, R (9, row-major), t (3),
    fx, fy, cx, cy; the caller sums the chunks, so the result does not depend on the thread count either."""
    B, N = means.shape[:2]
    total = B * N
    step = (total + N_CHUNKS - 1) // N_CHUNKS
    for chunk in prange(N_CHUNKS):
        _project_bwd_chunk(np.int64(chunk), step, total, means, quats, scales, opac, sh, cams, V, pstart, G,
                           g_means, g_quats, g_scales, g_opac, g_sh, cam_grad, g_cam)


# cached kernels go stale when a constant of this module (imported ones included) changes: see stamp_constants
stamp_constants([v for v in list(globals().values()) if isinstance(v, Dispatcher)])
