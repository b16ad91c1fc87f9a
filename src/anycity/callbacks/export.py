"""Write ``predict`` results: one folder per scene with ``scene.ply``, ``cameras.json`` and context re-renders."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities.exceptions import SIGTERMException

from anycity.atomic import staged_folder
from anycity.export import save_cameras, save_ply
from anycity.export.ply import PLY_MAX_SH_DEGREE
from anycity.export.provenance import provenance, summary
from anycity.export.smoothing import VARIANCE_PX, smooth_3d
from anycity.export.views import save_view_pngs
from anycity.structures import Gaussians


class PredictionExport(BasePredictionWriter):
    """Export every predicted scene under ``out_dir/<scene>/``.

    A shard set's split holds several samples of one scene (other context views): its later samples go to
    ``<scene>-2/``, ``<scene>-3/`` ... in the order predicted, and under DDP the folders of rank ``r > 0`` end in
    ``-rank<r>``, so no sample overwrites another.

    Files: ``scene.ply`` (standard 3DGS PLY plus the provenance columns ``obs_views`` and ``completion`` when
    the prediction carries ``scaffold`` and ``depth``; see :mod:`anycity.export.provenance`), ``cameras.json``
    (predicted OpenCV w2c + K; ``metres_per_unit`` null: the network's frame has no known metric scale),
    ``renders/NNN.png`` (the Gaussians re-rendered at the predicted context cameras) and
    ``inputs/NNN.png`` (the context images, for side-by-side comparison).

    A photo folder reconstructed in chunks (batches carrying ``"chunk"``, see
    :class:`anycity.lit.datamodule.AerialDataModule` ``predict_chunk_size``) is merged into one scene by
    :class:`anycity.city.ChunkedScene`: ``scene.ply`` and ``cameras.json`` for all photos plus ``chunks.json``
    (per-chunk photos, pairwise alignment residuals and inlier counts). Renders and inputs are then written per
    photo from the chunk that owns it (renders of that chunk's Gaussians), and the provenance columns count the views
    of the Gaussian's own chunk. Chunk predictions are consumed here
    (emptied in place), so ``trainer.predict`` does not keep every chunk's Gaussians in memory: they spill into the
    hidden folder ``.<scene>.anycity_city_work/`` beside the scene's (:func:`anycity.city.scene.work_dir`), removed
    when the scene is written or the run stops; one that a killed run left is removed by the next run of the scene,
    and a run of the same scene still writing it is refused (its folder is locked).
    The chunks' renders and inputs are written to the hidden ``.<scene>.anycity_city_views/`` beside it and moved
    into the scene folder when the scene is written, so a city that does not finish (a chunk fails, SIGTERM,
    ``--trainer.limit_predict_batches`` below the chunk count) leaves nothing in its scene folder; a run that ends
    with a city unfinished says so in a warning. A voxel merge (``net.voxel_size``) with several chunks is refused in
    :meth:`on_predict_start`, before the network runs: the chunks are aligned and merged on pixel-aligned Gaussians.

    ``trainer.log_dir`` (the default ``out_dir``'s parent) is a collective under DDP: it is read once, in
    :meth:`setup`, which every rank runs, never per sample (ranks export different numbers of samples). A run that
    received SIGTERM stops after the batch being written (Lightning's predict loop does not check).

    Args:
        out_dir: output folder; None = ``<log_dir>/predictions``.
        save_renders: also write the PNG renders and inputs.
        smooth_3d: Mip-Splatting 3-D filter variance in px² of the input cameras, baked into the PLY's scales and
            opacities so that other viewers (and zoomed-in views) show no holes; 0 writes the raw Gaussians (a
            negative value is refused).
    """

    def __init__(self, out_dir: str | None = None, save_renders: bool = True,
                 smooth_3d: float = VARIANCE_PX) -> None:
        super().__init__(write_interval="batch")
        if not smooth_3d >= 0:  # NaN too: a negative variance turned the filter off without a word
            raise ValueError(f"--export.smooth_3d: expected a variance in px² >= 0 (0 turns the filter off), got "
                             f"{smooth_3d}")
        self.out_dir = out_dir
        self.save_renders = save_renders
        self.smooth_3d = smooth_3d
        self.written: list[Path] = []
        self._folders: set[str] = set()  # written in this run by this rank
        self._city = None
        self._city_scene: tuple[str, Path, Path, int] | None = None  # (scene, folder, views folder, chunks)
        self._bar = None
        self._root: Path | None = None
        self._told_sh = False
        self.city_report: dict | None = None
        self.unfinished: str | None = None  # the city scene a stopped run left unwritten

    def root(self, trainer: pl.Trainer) -> Path:
        """The folder the scenes are exported to: ``out_dir``, else ``<log_dir>/predictions`` (resolved once per
        run in :meth:`setup`: ``trainer.log_dir`` broadcasts from rank 0 under DDP, so only a hook every rank runs
        may read it)."""
        if self._root is not None:
            return self._root
        return Path(self.out_dir) if self.out_dir else Path(trainer.log_dir or trainer.default_root_dir) / "predictions"

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        super().setup(trainer, pl_module, stage)
        self._root = None
        self._root = self.root(trainer)  # every rank, once: the per-sample writes then run no collective

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._root = None

    def _sample_folder(self, trainer: pl.Trainer, scene: str) -> Path:
        """``<scene>``, or ``<scene>-N`` for the scene's N-th sample in this run (``-rank<r>`` first on rank r > 0)."""
        base = str(scene).replace("/", "_") + (f"-rank{trainer.global_rank}" if trainer.global_rank else "")
        name, n = base, 1
        while name in self._folders:
            n += 1
            name = f"{base}-{n}"
        self._folders.add(name)
        return self.root(trainer) / name

    def on_predict_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._folders = set()
        self.unfinished = None
        if self._root is None:  # a Trainer that skipped setup (none does): still once, on every rank
            self._root = self.root(trainer)
        _refuse_voxel_merged_chunks(trainer, pl_module)

    def on_predict_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                             batch_idx: int, dataloader_idx: int = 0) -> None:
        """Write the batch, then stop the run if it received SIGTERM (a cluster's preemption or ``kill``), unless
        that was the last batch: Lightning checks in its training and evaluation loops, not in predict's."""
        super().on_predict_batch_end(trainer, pl_module, outputs, batch, batch_idx, dataloader_idx)
        last = getattr(trainer.predict_loop.batch_progress, "is_last_batch", False)
        if getattr(trainer, "received_sigterm", False) and not last:
            raise SIGTERMException

    def on_predict_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int,
                               dataloader_idx: int = 0) -> None:
        """A chunked prediction's bar shows from the start of its first chunk (the network and the camera fit of one
        chunk take seconds to minutes on a CPU)."""
        if isinstance(batch, dict) and batch.get("chunk") is not None and batch["chunk"]["index"] == 0:
            self._start_bar(batch)

    def _warn_sh_cut(self, g: Gaussians | None) -> None:
        """Once a run: say that ``scene.ply`` holds SH up to degree 3 when the network predicts more (``vggt-1b``:
        degree 4, AnySplat's), so viewers show other view-dependent colour than predict's own ``renders/``."""
        if self._told_sh or g is None or g.sh_degree <= PLY_MAX_SH_DEGREE:
            return
        self._told_sh = True
        warnings.warn(f"anycity predict: the network predicts SH degree {g.sh_degree}; scene.ply keeps degrees 0 to "
                      f"{PLY_MAX_SH_DEGREE}, the 3DGS PLY's limit (45 f_rest), so viewers show slightly other "
                      "view-dependent colour than renders/, which use every degree", stacklevel=2)

    def _start_bar(self, batch: dict) -> None:
        from tqdm.auto import tqdm

        if self._bar is not None:
            self._bar.close()
        self._bar = tqdm(total=batch["chunk"]["count"], desc=f"city: chunks of {batch['scene'][0]}", unit="chunk")

    def write_on_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, prediction: dict[str, Any],
                           batch_indices: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0) -> None:
        self._warn_sh_cut(prediction.get("gaussians"))
        if isinstance(batch, dict) and batch.get("chunk") is not None:
            self._write_chunk(trainer, prediction, batch)
            prediction.clear()
            return
        g, w2c, K = prediction["gaussians"], prediction["w2c"], prediction["K"]
        images, renders = prediction["images"], prediction["renders"]
        h, w = images.shape[-2:]
        scenes = prediction.get("scene") or [f"scene_{batch_idx:04d}_{i}" for i in range(w2c.shape[0])]
        g, prov = self._exported(prediction)
        from anycity.city.scene import remove_leftovers

        for i, name in enumerate(scenes):
            folder = self._sample_folder(trainer, name)
            remove_leftovers(folder)  # a killed chunked run's spill and renders, unless a live run holds them
            names = batch.get("names") if isinstance(batch, dict) else None  # a photo folder's file names
            # staged: a failure or a kill part-way leaves no scene folder (a scene.ply without its cameras.json)
            with staged_folder(folder) as stage:
                save_ply(g, stage / "scene.ply", index=i, extra=prov)
                save_cameras(stage / "cameras.json", w2c[i], K[i], int(w), int(h), names[i] if names else None)
                if self.save_renders:
                    for kind, imgs in (("renders", renders.rgb[i]), ("inputs", images[i])):
                        save_view_pngs(stage, kind, imgs, range(len(imgs)))
            _warn_non_square_pixels(folder.name, K[i])
            if prov is not None:
                _print_shares(folder.name, _shares(prov, g.valid, slice(i, i + 1), slice(None))[0])
            self.written.append(folder)

    def _exported(self, prediction: dict[str, Any]):
        """``(gaussians, provenance or None)`` as written: provenance of the predicted Gaussians (when the
        prediction carries ``scaffold`` and ``depth``), then the 3-D smoothing filter baked in."""
        g, w2c, K = prediction["gaussians"], prediction["w2c"], prediction["K"]
        prov = None
        if prediction.get("scaffold") is not None and prediction.get("depth") is not None:
            prov = provenance(g, prediction["scaffold"], prediction["depth"], w2c, K)
        if self.smooth_3d > 0:
            h, w = prediction["images"].shape[-2:]
            g = smooth_3d(g, w2c, K, int(w), int(h), self.smooth_3d)
        return g, prov

    def _write_chunk(self, trainer: pl.Trainer, prediction: dict[str, Any], batch: dict) -> None:
        from anycity.city import ChunkedScene

        info = batch["chunk"]
        k, views = info["index"], info["views"]
        folder = self.root(trainer) / f"{batch['scene'][0]}".replace("/", "_")
        if k == 0:
            self._drop_city(bar=False)  # a city that never reached its last chunk: its files go (the bar is this one's)
            self._city = ChunkedScene(info["plan"], info["names"], info["hw"], out=folder,
                                      ordered_by=info.get("ordered_by"))
            self._city_scene = (batch["scene"][0], folder, _views_dir(folder, fresh=True), info["count"])
            self._share_sums, self._share_count = None, 0
            if self._bar is None or self._bar.n:  # not started by on_predict_batch_start
                self._start_bar(batch)
        city = self._city
        if city is None:
            raise RuntimeError("PredictionExport: a chunked prediction did not start at chunk 0")
        # Provenance counts this chunk's views; the filter is Sim(3)-covariant, so baking it in the chunk's own
        # frame is the same as after alignment.
        g, prov = self._exported(prediction)
        city.add(k, g, prediction["w2c"][0], prediction["K"][0], prov)
        if prov is not None:  # shares over the Gaussians this chunk writes (those of the photos it owns)
            share, n = _shares(prov, g.valid, slice(0, 1), city.owned_rows(k))
            sums = {key: v * n for key, v in share.items()}
            self._share_sums = sums if self._share_sums is None else {
                key: self._share_sums[key] + v for key, v in sums.items()}
            self._share_count += n
        views_dir = self._city_scene[2]
        if self.save_renders:  # into the hidden views folder: the scene folder gets them when the scene is written
            own = city.owned(k)
            for kind, imgs in (("renders", prediction["renders"].rgb[0]), ("inputs", prediction["images"][0])):
                save_view_pngs(views_dir, kind, imgs[own], [views[i] for i in own])
        self._bar.update(1)
        if k == info["count"] - 1:
            self._bar.close()
            self._bar = None
            self._city = None
            try:  # the renders go in while the run still holds its lock: no other run takes them for a killed one's
                self.city_report = city.finish(folder, also={views_dir / kind: folder / kind
                                                             for kind in ("renders", "inputs")})
                _warn_non_square_pixels(folder.name, torch.stack([city.K[v] for v in sorted(city.K)]))
            finally:
                self._city_scene = None
                shutil.rmtree(views_dir, ignore_errors=True)
            rep = self.city_report
            if self._share_sums is not None:
                n = max(self._share_count, 1)
                _print_shares(batch["scene"][0], {key: v / n for key, v in self._share_sums.items()},
                              " of their chunk")
            worst = max((p["rms_residual"] for p in rep["pairs"]), default=0.0)
            order = f" (ordered by {rep['ordered_by']})" if rep.get("ordered_by") else ""
            print(f"anycity predict: {rep['num_photos']} photos{order} in {rep['num_chunks']} chunks -> "
                  f"{folder}/scene.ply "
                  f"({rep['gaussians']} Gaussians); worst pairwise rms residual {worst:.4g}, pose graph rms "
                  f"{rep['pose_graph'].get('final_rms', 0.0):.4g} (details: chunks.json)")
            self.written.append(folder)

    def on_predict_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """A city whose last chunk was never predicted (``--trainer.limit_predict_batches`` below its chunk count)
        is dropped with a warning: the run otherwise ends as if it had written it."""
        done = self._city_scene
        if self._drop_city() and done is not None:
            scene, folder, _, count = done
            warnings.warn(f"anycity predict: the run ended before the last of the {count} chunks of {scene}, so "
                          f"nothing was written for it ({folder} has no scene); predict all its chunks (raise or "
                          "drop --trainer.limit_predict_batches)", stacklevel=2)

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException) -> None:
        self._drop_city()  # Lightning calls this, not on_predict_end, when a chunk fails (e.g. an undecodable photo)

    def _drop_city(self, bar: bool = True) -> bool:
        """An unfinished whole-city scene: remove its spill files (gigabytes for a city) and its staged renders and
        inputs, write nothing; ``bar``: close its progress bar too. Returns whether there was one (its name is then
        in :attr:`unfinished`)."""
        dropped = self._city is not None
        if self._city is not None:
            self._city.close()
            self._city = None
        if self._city_scene is not None:  # set while self._city is
            self.unfinished = self._city_scene[0]
            shutil.rmtree(self._city_scene[2], ignore_errors=True)
            self._city_scene = None
        if bar and self._bar is not None:
            self._bar.close()
            self._bar = None
        return dropped


NON_SQUARE_TOL = 0.05  # fx / fy further from 1 than this is named in a warning


def _warn_non_square_pixels(scene: str, K: torch.Tensor) -> None:
    """Warn when the predicted intrinsics ``K [V, 3, 3]`` give pixels further from square than
    :data:`NON_SQUARE_TOL` (fx / fy): photos have square pixels, so the network's two fields of view disagree with
    the image's shape (e.g. a model trained on square images only, run on 16:9 photos), and every export carries it."""
    ratio = (K[..., 0, 0] / K[..., 1, 1]).double()
    worst = float(ratio[(ratio - 1).abs().argmax()])
    if abs(worst - 1) > NON_SQUARE_TOL:
        warnings.warn(f"anycity predict: {scene}: the predicted cameras have non-square pixels (fx / fy up to "
                      f"{worst:.2f}; photos have 1.00), so its cameras.json and every export carry that; the model "
                      "was probably trained on images of another aspect ratio (the quickstart's are square): train "
                      "on this aspect, or pass --data.predict_resize crop with a square --data.image_size",
                      stacklevel=2)


def _refuse_voxel_merged_chunks(trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
    """Refuse ``net.voxel_size`` for a photo folder predicted in several chunks, before the network runs: the chunks
    are aligned and merged on pixel-aligned Gaussians (:meth:`anycity.city.ChunkedScene.add`), which used to refuse
    only after chunk 0's network pass and camera refinement. The plan is the predict dataset's ``chunks``
    (:class:`anycity.lit.datamodule.AerialDataModule`'s photo chunks; duck-typed: callbacks do not import lit)."""
    from anycity.data.photos import MAX_VIEWS

    voxel = getattr(getattr(getattr(pl_module, "net", None), "cfg", None), "voxel_size", None)
    loaders = getattr(trainer, "predict_dataloaders", None)
    if voxel is None or loaders is None:
        return
    for loader in loaders if isinstance(loaders, (list, tuple)) else [loaders]:
        plan = getattr(getattr(loader, "dataset", None), "chunks", None)
        if isinstance(plan, list) and len(plan) > 1:
            n = len({v for views in plan for v in views})
            refine = getattr(pl_module, "hparams", {}).get("camera_refine_steps", 0)  # it needs unmerged ones too
            one_pass = (f" or raise --data.predict_chunk_size to {n} (one pass"
                        f"{', with --model.camera_refine_steps 0' if refine else ''})") if n <= MAX_VIEWS else ""
            raise ValueError(f"--model.net.voxel_size {voxel}: the {n} photos of --data.predict_images are "
                             f"predicted in {len(plan)} chunks, which are aligned and merged on pixel-aligned "
                             f"Gaussians, and voxel merging is single-pass only; drop --model.net.voxel_size"
                             f"{one_pass}")


def _views_dir(folder: Path, fresh: bool = False) -> Path:
    """Where a chunked scene's renders and inputs wait until the scene is written: the hidden
    ``.<scene>.anycity_city_views/`` beside the scene folder (on its filesystem, so that they move in by a rename).
    ``fresh``: emptied first (a killed run's, with a warning)."""
    from anycity.city.scene import drop_views, views_dir

    if fresh:
        drop_views(folder, strict=True)
    return views_dir(folder)


def _shares(prov: dict, valid, scene: slice, rows) -> tuple[dict[str, float], int]:
    """:func:`anycity.export.provenance.summary` of scene ``scene`` restricted to Gaussians ``rows``, and how many
    (valid) Gaussians it covers."""
    keep = None if valid is None else valid[scene][:, rows]
    share = summary({k: v[scene][:, rows] for k, v in prov.items()}, keep)
    n = int(keep.sum()) if keep is not None else int(prov["obs_views"][scene][:, rows].numel())
    return share, n


def _print_shares(name: str, share: dict[str, float], views: str = "") -> None:
    """One line of :func:`anycity.export.provenance.summary` shares; a voxel-merged prediction (completion NaN:
    the scaffold's rows do not pair with the final ones) says "completion n/a" instead of a share."""
    few = f"{share['unsupported']:.0%} seen by < 2 views{views}"
    unknown = share.get("unknown", 0.0)
    if unknown >= 1 - 1e-9:
        print(f"{name}: completion n/a (voxel-merged), {1 - share['unsupported']:.0%} of Gaussians seen by >= 2 "
              f"views{views}, {few}")
        return
    tail = f", completion n/a (voxel-merged) for {unknown:.0%}" if unknown > 0 else ""
    print(f"{name}: {share['supported']:.0%} of Gaussians observation-supported (>= 2 views{views}, kept), "
          f"{share['completed']:.0%} completed by Stage II, {few}{tail}")
