"""``ChunkedScene``: collect chunk reconstructions one at a time, then align, merge and write one scene.

Memory stays bounded by the chunk size: of each chunk only its cameras and a sparse grid of depth points per view
stay in memory (the pose graph adds a dense ``7(C-1)`` square normal matrix for C chunks: 10 MB at 167); the
Gaussians of the views it owns (:func:`anycity.city.plan.owners`) go to a spill file, and :meth:`ChunkedScene.finish`
streams them through their chunk's Sim(3) into the PLY, deleting each spill file once its rows are written (the disk
then holds at most the PLY body and the PLY: 2x the scene).

Given the output folder, the spill files live in the hidden :func:`work_dir` beside it (on the disk the scene is
written to, not in ``$TMPDIR``, which is RAM on a tmpfs ``/tmp``); ``finish`` stages its outputs there too, so each
is published by a rename. The folder is removed when the scene is written or the run fails; one that a killed run
left is removed by the next run of that scene (its chunks came from another run, so they are never reused). A run
holds an exclusive ``flock`` on its folder, so a second run of the same scene started while the first is still
running is refused instead of deleting the first one's spill (the kernel drops the lock of a killed run).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import torch
from torch import Tensor

from anycity.atomic import HAS_FLOCK, atomic_write_bytes, publish, try_flock
from anycity.city.align import ChunkGeometry, sim3_parts, w2c_to_world
from anycity.city.merge import PlyStream, sim3_gaussians
from anycity.city.plan import owners
from anycity.city.posegraph import align_chunks
from anycity.export.cameras import save_cameras
from anycity.structures import Gaussians

WORK_SUFFIX = ".anycity_city_work"
VIEWS_SUFFIX = ".anycity_city_views"
_HELD: dict[str, int] = {}  # spill folder -> descriptor holding its lock, for this process's ChunkedScenes


def work_dir(folder: str | Path) -> Path:
    """The hidden work folder of the scene written to ``folder``: ``<parent>/.<name>.anycity_city_work``. Beside
    the scene, not in it: ``predict`` keeps an earlier run's scene folder by renaming it (:mod:`anycity.lit.keep`),
    and a killed run's spill must stay where the next run of the scene finds and removes it."""
    folder = Path(folder)
    return folder.parent / f".{folder.name}{WORK_SUFFIX}"


def views_dir(folder: str | Path) -> Path:
    """Where a chunked scene's renders and inputs wait until the scene is written: the hidden
    ``<parent>/.<name>.anycity_city_views`` beside the scene folder (its filesystem: they move in by a rename). It has
    no lock of its own: the run's lock on :func:`work_dir` covers it."""
    folder = Path(folder)
    return folder.parent / f".{folder.name}{VIEWS_SUFFIX}"


def remove_leftovers(folder: str | Path) -> list[Path]:
    """Remove the :func:`work_dir` and :func:`views_dir` that a killed chunked run of the scene ``folder`` left, each
    with a warning, for a run that writes ``folder`` in one pass (a chunked run removes them as it starts, in
    :class:`ChunkedScene` and the exporter). A work folder another run holds (its ``flock``, this process's own
    unfinished scene included) is a live run's: both stay. Returns the folders removed."""
    work, views = work_dir(folder), views_dir(folder)
    removed = []
    if work.exists():
        try:
            fd = _lock(work)
        except BlockingIOError:  # a chunked run of this scene still writing it: its spill and renders stay
            return removed
        try:
            warnings.warn(f"{work}: removing the spill folder an interrupted run left", stacklevel=2)
            shutil.rmtree(work, ignore_errors=True)
            removed.append(work)
        finally:
            if fd is not None:
                os.close(fd)
    if drop_views(folder):  # without a work folder no run is writing it (a live run locks its work folder first)
        removed.append(views)
    return removed


def drop_views(folder: str | Path, strict: bool = False) -> bool:
    """Remove, with a warning, the :func:`views_dir` renders an interrupted run of the scene ``folder`` left; whether
    there were any. The caller knows that no live run holds them. ``strict``: a removal that fails raises (a chunked
    run is about to write its own renders there)."""
    views = views_dir(folder)
    if not views.exists():
        return False
    warnings.warn(f"{views}: removing the renders an interrupted run left", stacklevel=3)
    shutil.rmtree(views, ignore_errors=not strict)
    return True


def grid_pixels(h: int, w: int, per_side: int = 8) -> Tensor:
    """Flat indices ``[P]`` of a ``per_side`` x ``per_side`` grid of pixel centres of an ``h`` x ``w`` view."""
    ys = torch.linspace(0, h - 1, min(per_side, h)).round().long()
    xs = torch.linspace(0, w - 1, min(per_side, w)).round().long()
    return (ys[:, None] * w + xs[None, :]).flatten()


class ChunkedScene:
    """Accumulate the chunks of one scene; :meth:`finish` aligns them and writes ``scene.ply``, ``cameras.json``
    and ``chunks.json``.

    Args:
        chunks: the plan, global photo indices per chunk (:func:`anycity.city.plan.plan_chunks`).
        names: photo names by global index.
        hw: ``(H, W)`` of the chunks' images (pixel-aligned Gaussians: N = V*H*W in view order).
        points_per_side: depth points per view side used for alignment.
        global_pass: run the pose graph after the pairwise fits (else chain them).
        out: the folder :meth:`finish` will write; the spill goes to :func:`work_dir` beside it (a killed run's
            one is removed first, with a warning; one that another running process holds is refused).
        workdir: without ``out``, where a new temporary spill folder is made; neither = ``$TMPDIR`` (RAM on a
            tmpfs ``/tmp``: pass ``out`` for a large scene).
        ordered_by: what ordered the photos ("time", "name", "tokens"), recorded in ``chunks.json``.
        fit: keyword options of :func:`anycity.city.align.robust_sim3`.
    """

    def __init__(self, chunks: list[list[int]], names: list[str], hw: tuple[int, int], points_per_side: int = 8,
                 global_pass: bool = True, workdir: str | Path | None = None, out: str | Path | None = None,
                 ordered_by: str | None = None, **fit) -> None:
        self.chunks, self.names, self.hw, self.ordered_by = chunks, names, tuple(hw), ordered_by
        self.owner = owners(chunks)
        self.pix = grid_pixels(*self.hw, points_per_side)
        self.geometry: list[ChunkGeometry | None] = [None] * len(chunks)
        self.K: dict[int, Tensor] = {}
        self.spill, self._lock_fd = _spill_dir(out, workdir)
        self.spilled: dict[int, Path] = {}
        self.global_pass, self.fit = global_pass, fit

    def owned(self, k: int) -> list[int]:
        """Positions (within chunk ``k``) of the photos chunk ``k`` owns: their Gaussians and cameras are its."""
        return [i for i, gv in enumerate(self.chunks[k]) if self.owner[gv] == k]

    def owned_rows(self, k: int) -> Tensor:
        """``[n]`` indices of the owned photos' Gaussians among chunk ``k``'s pixel-aligned ones (N = V*H*W)."""
        hw = self.hw[0] * self.hw[1]
        own = self.owned(k)
        return torch.cat([torch.arange(i * hw, (i + 1) * hw) for i in own]) if own else torch.zeros(0, dtype=torch.long)

    def add(self, k: int, gaussians: Gaussians, w2c: Tensor, K: Tensor, extra: dict[str, Tensor] | None = None) -> None:
        """Chunk ``k``'s reconstruction: one-scene ``gaussians`` (N = V*H*W), cameras ``w2c [V, 4, 4]``,
        ``K [V, 3, 3]``; ``extra``: per-Gaussian PLY columns ``{name: [1, N]}`` (provenance), written with them."""
        views = self.chunks[k]
        v, (h, w) = len(views), self.hw
        if w2c.shape != (v, 4, 4) or gaussians.means.shape[:2] != (1, v * h * w):
            raise ValueError(f"ChunkedScene.add: chunk {k} has {v} views of {h}x{w}; expected w2c [{v}, 4, 4] and "
                             f"{v * h * w} pixel-aligned Gaussians, got {tuple(w2c.shape)} and "
                             f"{tuple(gaussians.means.shape)} (voxel merging must be off)")
        g = gaussians.detach().to("cpu")
        means = g.means[0].reshape(v, h * w, 3)
        self.geometry[k] = ChunkGeometry(list(views), w2c.detach().cpu().double(), means[:, self.pix].double())
        own = self.owned(k)
        for i in own:
            self.K[views[i]] = K[i].detach().cpu().double()
        if own:
            sel = self.owned_rows(k)
            part = Gaussians(*(None if t is None else t[:, sel].clone() for t in
                               (g.means, g.quats, g.scales, g.opacities, g.sh, g.valid)))
            path = self.spill / f"chunk_{k:05d}.pt"
            cols = {name: t.detach().cpu()[:, sel].clone() for name, t in (extra or {}).items()}
            fields = {f.name: getattr(part, f.name) for f in dataclasses.fields(part)}  # tensors: read as data
            buf = io.BytesIO()  # torch.save to a path fails ENOSPC as a RuntimeError naming neither file nor size
            torch.save({"gaussians": fields, "views": [views[i] for i in own], "extra": cols,
                        "w2c": w2c[own].detach().cpu().double()}, buf)
            atomic_write_bytes(path, buf.getbuffer())  # a full disk: OSError naming the file and the bytes
            self.spilled[k] = path

    def finish(self, folder: str | Path, width: int | None = None, height: int | None = None,
               also: dict[Path, Path] | None = None) -> dict:
        """Align, merge and write ``folder/{scene.ply, cameras.json, chunks.json}``; returns the report.

        Nothing is left in ``folder`` when it fails: the files are written in full and fsynced in
        :func:`work_dir` (the scene's filesystem), then renamed into place. ``also``: ``{source: destination}``
        files or folders (the exporter's :func:`views_dir` renders) published after them, while the run still holds
        its lock, so that no other run takes them for a killed run's.
        """
        folder = Path(folder)
        stage = work_dir(folder)  # the spill folder itself when ``out`` is ``folder``
        try:
            missing = [k for k, g in enumerate(self.geometry) if g is None]
            if missing:
                raise ValueError(f"ChunkedScene.finish: chunks {missing} were never added")
            S, edges, rep = align_chunks(self.geometry, self.names, self.global_pass, **self.fit)
            stage.mkdir(parents=True, exist_ok=True)
            with PlyStream(folder / "scene.ply", scratch=stage) as ply:
                w2c = self._merge(ply, S)
                report = self._report(S, edges, rep, ply)
                save_cameras(stage / "cameras.json", w2c, torch.stack([self.K[v] for v in range(len(self.names))]),
                             int(width or self.hw[1]), int(height or self.hw[0]), self.names)
                atomic_write_bytes(stage / "chunks.json", json.dumps(report, indent=1).encode())
            for name in ("cameras.json", "chunks.json"):
                publish(stage / name, folder / name)
            for src, dst in (also or {}).items():
                if Path(src).exists():
                    publish(Path(src), Path(dst))
            self.w2c = w2c
            return report
        finally:
            self.close()
            shutil.rmtree(stage, ignore_errors=True)

    def _merge(self, ply: PlyStream, S: Tensor) -> Tensor:
        """Stream every spill file through its chunk's Sim(3) ``S[k]`` into ``ply``, deleting each once written;
        returns the world-frame ``w2c [n, 4, 4]`` of all photos."""
        w2c = torch.zeros(len(self.names), 4, 4, dtype=torch.float64)
        for k, path in sorted(self.spilled.items()):
            piece = torch.load(path, weights_only=True)
            ply.write(sim3_gaussians(Gaussians(**piece["gaussians"]), S[k]), piece["extra"] or None)
            for v, cam in zip(piece["views"], piece["w2c"]):
                w2c[v] = w2c_to_world(cam, S[k])
            del piece
            path.unlink()  # its rows are in the PLY body: the spill and the body never both hold the whole scene
        return w2c

    def close(self) -> None:
        """Remove the spill files, then release the spill folder's lock."""
        shutil.rmtree(self.spill, ignore_errors=True)
        if self._lock_fd is not None and _HELD.get(str(self.spill)) == self._lock_fd:
            os.close(_HELD.pop(str(self.spill)))
        self._lock_fd = None

    def _report(self, S: Tensor, edges, rep: dict, ply: PlyStream) -> dict:
        s = sim3_parts(S)[0]
        chunks = [{"index": k, "photos": [self.names[v] for v in views],
                   "owned": sum(self.owner[v] == k for v in views), "scale_to_world": float(s[k])}
                  for k, views in enumerate(self.chunks)]
        # a pair's fit is measured in chunk a's frame: scaled by chunk a's scale to chunk 0's units, as labelled
        pairs = [{"chunks": [e.a, e.b], "shared_photos": len(e.shared), "points": int(e.fit.inliers.numel()),
                  "inliers": e.fit.num_inliers, "rms_residual": e.fit.rms * float(s[e.a]),
                  "median_residual": e.fit.median * float(s[e.a]),
                  "inlier_threshold": e.fit.threshold * float(s[e.a]),
                  "pose_graph_rms": _finite(e.graph_rms * float(s[e.a]))} for e in edges]
        return {"num_photos": len(self.names), "ordered_by": self.ordered_by, "num_chunks": len(self.chunks),
                "chunks": chunks, "pairs": pairs,
                "pose_graph": {k: _finite(v) for k, v in rep.items()},
                "gaussians": ply.count, "dropped": ply.dropped,
                "units": "residuals in world units of chunk 0's frame"}


def _spill_dir(out: str | Path | None, workdir: str | Path | None) -> tuple[Path, int | None]:
    """A new, empty spill folder and the descriptor holding its lock: :func:`work_dir` of ``out`` (locked), else a
    temporary one in ``workdir`` (unique: no lock).

    Raises:
        ValueError: another process holds ``out``'s spill folder: a run of the same scene is still writing it.
    """
    if out is None:
        return Path(tempfile.mkdtemp(prefix="anycity_city_", dir=workdir)), None
    spill = work_dir(out)
    busy = ValueError(f"{out}: another anycity predict is writing this scene (its spill folder {spill} is in use); "
                      "wait for it to end, or pass another --export.out_dir")
    if spill.exists():  # a killed run's: its chunks are not this run's, and the disk space is wanted back
        held = _HELD.pop(str(spill), None)  # this process's own, never closed: as good as killed
        if held is not None:
            os.close(held)
        try:
            stale = _lock(spill)
        except BlockingIOError:
            raise busy from None
        warnings.warn(f"{spill}: removing the spill folder an interrupted run left", stacklevel=3)
        shutil.rmtree(spill)
        if stale is not None:
            os.close(stale)
    try:
        spill.mkdir(parents=True)
        fd = _lock(spill)
    except (FileExistsError, BlockingIOError):  # a run of the scene that started at the same moment
        raise busy from None
    if fd is not None:
        _HELD[str(spill)] = fd
    return spill, fd


def _lock(folder: Path) -> int | None:
    """An exclusive ``flock`` on ``folder``: the descriptor holding it, or None where the OS or the filesystem has
    none (the folder is then not guarded).

    Raises:
        BlockingIOError: another process holds it.
    """
    if not HAS_FLOCK:
        return None
    fd = os.open(folder, os.O_RDONLY)
    taken = try_flock(fd)
    if not taken:
        os.close(fd)
        if taken is False:
            raise BlockingIOError(f"{folder}: locked by another process")
        return None
    return fd


def _finite(v):
    """``v`` for JSON: a non-finite float as None (other values as they are)."""
    return None if isinstance(v, float) and not math.isfinite(v) else v
