"""Fused CPU backend (``backend="cpu"``): numba kernels for projection + SH, binning, compositing and backward.

One ``torch.autograd.Function`` runs, on float32 CPU tensors:

1. ``project_fwd``: 3-D Gaussians -> per (camera, Gaussian) screen-space rows, tile boxes, depths.
2. ``depth_order`` + ``bin_pairs``: radix sort by depth, counting sort of (tile, Gaussian) pairs by tile.
3. ``raster_fwd``: per 8x16 tile, front-to-back blending of rgb, z (and normals); writes the final images.
4. backward: ``raster_bwd`` (back to front, one gradient row per pair) then ``project_bwd`` (per Gaussian, sums
   its pairs in a fixed order and chains through projection and SH). No atomics: gradients are bitwise identical
   for any thread count.

Semantics, gradients included, are those of ``anycity.render.api.render`` (the torch backend is the reference):
the Gaussians, ``w2c`` (its top three rows), ``K`` (fx, fy, cx, cy) and ``background`` all get theirs. Camera
gradients are summed over fixed work chunks, so they too are bitwise identical for any thread count. Outputs are
ordinary tensors (in-place ops on them work) and backward keeps its own copies, so editing them cannot change
gradients.
Kernels compile on first use (a few seconds, announced once on stderr) and are cached next to this file's
``__pycache__`` or in ``NUMBA_CACHE_DIR``; a cache compiled with other values of the constants the kernels read
(``projection.ALPHA_MAX``, ``sh.C1``, ...) counts as stale (``_numba_cache.stamp_constants``). Threads follow
``torch.get_num_threads()``. Kernel launches are serialised across Python threads (a module lock): numba's
"workqueue" threading layer, the one left where neither OpenMP nor TBB is installed, aborts the process when two
threads launch at once, and on the others two launches would only fight over the same cores. numba's OpenMP pool
is not fork-safe, so calling this in a child forked after the kernels ran (e.g. ``DataLoader(num_workers>0)``
workers) raises instead of hanging.
"""

from __future__ import annotations

import logging
import math
import os
import threading

# numba's OpenMP pool (the system libgomp, loaded on the first parallel launch) spins between parallel regions by
# default; on a shared 2-core machine that spinning made a 2-thread render 5-10x slower than 1 thread. Sleeping
# workers cost ~0.1 ms per call. An explicit user setting wins; torch's own libgomp is already loaded and unaffected.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
import numpy as np
import torch
from torch import Tensor

from anycity.render import _cpu_project as _proj
from anycity.render import _cpu_raster as _rast
from anycity.render import projection as _projection
from anycity.render._numba_cache import repair_cache

_log = logging.getLogger(__name__)
_BIN_CHUNKS = 8  # fixed split of the binning work: results do not depend on the thread count
_kernels: dict[int, tuple] = {}
_lock = threading.Lock()
_first_use_lock = threading.Lock()
_launch_lock = threading.Lock()  # one thread in the kernels at a time (see the module docstring)
_state = {"pid": None, "announced": False, "checked": set()}


def raster_kernels(D: int):
    """(forward, backward) compositing kernels for D feature channels (4: rgb+z, 7: + normals)."""
    with _lock:
        if D not in _kernels:
            _kernels[D] = _rast.make_raster_kernels(D)
        return _kernels[D]


def _dispatchers(D: int) -> list:
    return [_proj.project_fwd, _proj.project_bwd, _rast.depth_order, _rast.bin_pairs, *raster_kernels(D)]


def _all_dispatchers(D: int) -> list:
    """The entry kernels and the jitted helpers they call (each has its own cache file)."""
    found = {id(d): d for d in _dispatchers(D)}
    for module in (_proj, _rast):
        found.update({id(v): v for v in vars(module).values() if isinstance(v, numba.core.dispatcher.Dispatcher)})
    return list(found.values())


def _first_use(D: int) -> None:
    """Once per process and channel count (reading the dispatchers' caches and signatures costs more than a small
    render's kernels): repair the kernels' cache, then say whether they are about to be compiled."""
    if D in _state["checked"]:
        return
    with _first_use_lock:
        if D not in _state["checked"]:
            repair_cache(_all_dispatchers(D))
            _announce_compile(D)
            _state["checked"].add(D)


def _announce_compile(D: int) -> None:
    """Tell the user once when the kernels are about to be compiled rather than loaded from the cache."""
    if _state["announced"]:
        return
    cold = []
    for disp in _dispatchers(D):
        if disp.signatures:
            continue
        try:  # an index of another source or constants stamp reads as empty: numba compiles
            cached = bool(disp._cache._cache_file._load_index())
        except Exception:  # noqa: BLE001 (numba internals moved, or a damaged index): say nothing rather than guess
            cached = True
        if not cached:
            cold.append(disp.__name__)
    if cold:
        _state["announced"] = True
        _log.warning("anycity: compiling the fused CPU render kernels (%s); first use only, up to about 40 s on 2 "
                     "cores, cached afterwards", ", ".join(cold))


def _guard_process() -> None:
    """numba's OpenMP thread pool does not survive fork(): refuse to run in a child forked after the kernels ran
    in its parent (e.g. ``DataLoader(num_workers>0)`` workers). Spawned processes start clean and are fine."""
    pid = os.getpid()
    if _state["pid"] is not None and _state["pid"] != pid:
        worker = torch.utils.data.get_worker_info()
        where = f"DataLoader worker {worker.id}" if worker is not None else "a child process"
        raise RuntimeError(
            f"render(backend='cpu') called in {where} forked after the fused kernels ran in its parent: numba's "
            "OpenMP thread pool is not fork-safe. Render in the main process, pass backend='torch' inside "
            "workers, or use multiprocessing_context='spawn'")
    _state["pid"] = pid


def _set_threads() -> None:
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    if numba.get_num_threads() != n:
        numba.set_num_threads(n)


def _camera_table(w2c: Tensor, K: Tensor, width: int, height: int) -> np.ndarray:
    """``[C, 23]`` float64: R (9), t (3), fx, fy, cx, cy, camera centre (3), x/z and y/z clamp limits (4)."""
    w2c = w2c.detach().double().reshape(-1, 4, 4)
    K = K.detach().double().reshape(-1, 3, 3)
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    fx, fy, cx, cy = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2]
    centre = -torch.einsum("cji,cj->ci", R, t)
    clamp = _projection.FOV_CLAMP  # read per call, as the torch backend does: an edited value reaches both
    hx, hy = clamp * 0.5 * width / fx, clamp * 0.5 * height / fy
    lims = torch.stack([-cx / fx - hx, (width - cx) / fx + hx, -cy / fy - hy, (height - cy) / fy + hy], -1)
    table = torch.cat([R.reshape(-1, 9), t, torch.stack([fx, fy, cx, cy], -1), centre, lims], -1)
    return np.ascontiguousarray(table.numpy())


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _FusedRender(torch.autograd.Function):
    """means, quats, scales, opacities, sh -> rgb, depth, alpha, normal (see the module docstring)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, valid, w2c, K, width, height, background, near, far,
                normals):
        B, N = means.shape[:2]
        V = w2c.shape[1]
        C, D = B * V, (7 if normals else 4)
        tiles_x, tiles_y = math.ceil(width / _rast.TX), math.ceil(height / _rast.TY)
        cams = _camera_table(w2c, K, width, height)
        arrays = [_np(t) for t in (means, quats, scales, opacities, sh)]
        P = np.empty((C * N, _rast.QBASE + D), np.float32)
        z = np.empty(C * N, np.float32)
        rect = np.empty((C * N, 4), np.int32)
        ntiles = np.empty(C * N, np.int64)
        ext_y = np.empty(C * N, np.float32)
        # torch-owned [B, V, ...] outputs (not views: in-place ops on them work as with the torch backend); the
        # kernels write through [C, ...] numpy views of the same memory
        img3, img1 = (3, height, width), (1, height, width)
        out = [torch.empty(B, V, *s, dtype=torch.float32) for s in (img3, img1, img1, img3 if normals else (3, 1, 1))]
        rgb, depth, alpha, normal = [o.numpy().reshape(C, *o.shape[2:]) for o in out]  # normal (C,3,1,1): unused
        t_final = np.empty((C, height, width), np.float32)
        last = np.empty((C, height, width), np.float32)
        bg = _np(background.reshape(C, 3)).copy()  # backward reads it too: never share the caller's memory
        fwd, _ = raster_kernels(D)
        with np.errstate(over="ignore"):  # the torch backend compares in float32 too; far > 3.4e38: inf
            near32, far32 = float(np.float32(near)), float(np.float32(far))
        with _launch_lock:
            _proj.project_fwd(*arrays, _np(valid), cams, V, width, height, near32, far32, tiles_x, tiles_y,
                              P, z, rect, ntiles, ext_y)
            order = _rast.depth_order(z, ntiles)
            Q, tile_off, slot, pstart = _rast.bin_pairs(order, rect, ntiles, P, ext_y, C, max(N, 1), tiles_x,
                                                        tiles_y, _BIN_CHUNKS)
            fwd(Q, tile_off, tiles_x, tiles_y, width, height, bg, rgb, depth, alpha, normal, t_final, last)

        ctx.save_for_backward(means, quats, scales, opacities, sh)
        # backward reads depth: keep a private copy, so that edits of the returned depth (or a detached view of it)
        # cannot change the gradients
        ctx.state = (cams, V, D, tiles_x, tiles_y, width, height, pstart, Q, tile_off, slot, bg, t_final,
                     last, depth.copy() if any(ctx.needs_input_grad) else None)
        if not normals:
            ctx.mark_non_differentiable(out[3])
        return tuple(out)

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_alpha, g_normal):
        cams, V, D, tiles_x, tiles_y, width, height, pstart, Q, tile_off, slot, bg, t_final, last, depth = \
            ctx.state
        means, quats, scales, opacities, sh = ctx.saved_tensors
        C = cams.shape[0]

        def grad(g, shape):
            return np.zeros(shape, np.float32) if g is None else _np(g.float()).reshape(shape)

        img3, img1 = (C, 3, height, width), (C, 1, height, width)
        G = np.empty((Q.shape[0], _rast.QBASE + D), np.float32)
        _, bwd = raster_kernels(D)
        _set_threads()
        pixel_grads = (grad(g_rgb, img3), grad(g_depth, img1), grad(g_alpha, img1),
                       grad(g_normal, img3) if D == 7 else grad(None, (1, 3, 1, 1)))
        # contiguous like the inputs _np gives: numba compiles a kernel again for each new array layout (the model's
        # sh is a transposed view, and empty_like would keep its strides)
        fields = (means, quats, scales, opacities, sh)
        outs = [torch.empty_like(t, memory_format=torch.contiguous_format) for t in fields]
        want_w2c, want_K, want_bg = (ctx.needs_input_grad[i] for i in (6, 7, 10))
        g_cam = np.empty((_proj.N_CHUNKS, C, 16) if want_w2c or want_K else (_proj.N_CHUNKS, 1, 16))
        with _launch_lock:
            bwd(Q, tile_off, slot, tiles_x, tiles_y, width, height, bg, t_final, last, depth, *pixel_grads, G)
            _proj.project_bwd(*[_np(t) for t in fields], cams, V, pstart, G,
                              *[o.numpy() for o in outs], want_w2c or want_K, g_cam)
        g_w2c = g_K = g_bg = None
        if want_w2c or want_K:
            g_cam = torch.from_numpy(g_cam.sum(0)).float()  # [C, 16]: R (9), t (3), fx, fy, cx, cy
            B = means.shape[0]
            if want_w2c:
                g_w2c = torch.zeros(C, 4, 4)
                g_w2c[:, :3, :3] = g_cam[:, :9].reshape(C, 3, 3)
                g_w2c[:, :3, 3] = g_cam[:, 9:12]
                g_w2c = g_w2c.reshape(B, V, 4, 4)
            if want_K:
                g_K = torch.zeros(C, 3, 3)
                g_K[:, 0, 0], g_K[:, 1, 1], g_K[:, 0, 2], g_K[:, 1, 2] = g_cam[:, 12:].unbind(-1)
                g_K = g_K.reshape(B, V, 3, 3)
        if want_bg and g_rgb is not None:  # rgb = ... + T_final * background
            g_bg = torch.einsum("ckhw,chw->ck", g_rgb.float().reshape(C, 3, height, width),
                                torch.from_numpy(t_final)).reshape(-1, V, 3)
        return (*outs, None, g_w2c, g_K, None, None, g_bg, None, None, None)


def render_cpu(means, quats, scales, opacities, sh, valid, w2c, K, width, height, background, near, far,
               render_normals):
    """Backend entry point (contract in ``anycity.render.api``); float32 CPU tensors only."""
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities), ("sh", sh),
                    ("w2c", w2c)):
        if t.device.type != "cpu" or t.dtype != torch.float32:
            raise ValueError(f"backend='cpu': {name} must be a float32 CPU tensor, got {t.dtype} on {t.device}; "
                             "use backend='torch' for other dtypes or devices")
    if sh.shape[2] > 25:
        raise ValueError(f"backend='cpu': sh has K={sh.shape[2]} coefficients, at most 25 (degree 4) are supported; "
                         "use backend='torch' or a lower SH degree")
    _guard_process()
    _set_threads()
    D = 7 if render_normals else 4
    _first_use(D)
    rgb, depth, alpha, normal = _FusedRender.apply(
        means, quats, scales, opacities, sh, valid, w2c, K, width, height, background, near, far, render_normals)
    return rgb, depth, alpha, (normal if render_normals else None)
