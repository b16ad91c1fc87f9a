"""Image previews (context | target | render(s) | depth) written to the log directory and the logger."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from PIL import Image
from torch import Tensor

from anycity.atomic import free_name


def depth_to_rgb(depth: Tensor, mask: Tensor | None = None) -> Tensor:
    """``[..., 1, H, W]`` depth -> ``[..., 3, H, W]`` inverse-depth colour map in [0, 1] (near = bright)."""
    valid = depth > 0 if mask is None else (mask.bool() & (depth > 0))
    inv = torch.where(valid, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))
    flat = inv.flatten(-3)
    lo = torch.where(valid.flatten(-3), flat, torch.full_like(flat, float("inf"))).amin(-1)
    hi = flat.amax(-1)
    x = ((inv - lo[..., None, None, None]) / (hi - lo).clamp_min(1e-6)[..., None, None, None]).clamp(0, 1) * valid
    # a compact "magma-like" ramp without matplotlib: dark blue -> red -> yellow
    return torch.cat([x.sqrt(), x.square(), 0.4 * (1 - x) * valid], dim=-3)


def region_colours(observed: Tensor, weak: Tensor) -> Tensor:
    """Region masks ``[..., 1, H, W]`` -> ``[..., 3, H, W]``: observation-supported green, weak red, neither (sky)
    black."""
    o, w = observed.float(), weak.float()
    return torch.cat([w, 0.8 * o, torch.zeros_like(o)], dim=-3)


def preview_grid(columns: list[Tensor]) -> np.ndarray:
    """Columns of ``[R, 3, H, W]`` images (same R, H, W) -> an ``[R*H, C*W, 3]`` uint8 image."""
    rows = torch.cat([c.float().clamp(0, 1) for c in columns], dim=-1)  # [R, 3, H, C*W]
    img = torch.cat(list(rows), dim=-2)  # [3, R*H, C*W]
    return (img.permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)


class ImagePreviews(Callback):
    """Write a preview grid for the first validation/test batch.

    The LightningModule returns ``{"preview": {"context", "target", "render", ...}}`` (each ``[R, 3, H, W]``)
    from ``validation_step``/``test_step`` for batch 0. The grid is saved as PNG under
    ``<log_dir>/previews/`` and sent to the logger when it can take images (TensorBoard, W&B). Under
    ``fast_dev_run`` nothing is written (Lightning's stand-in logger has no log_dir: the grid would land in the
    run folder, which a fast_dev_run leaves alone). The validation-run count is saved with the checkpoint, so a
    resumed run keeps the ``every_n_val`` cadence.

    Args:
        every_n_val: write on every n-th validation run.
        max_rows: at most this many rows (views).
    """

    def __init__(self, every_n_val: int = 1, max_rows: int = 4) -> None:
        self.every_n_val = max(1, every_n_val)
        self.max_rows = max_rows
        self._count = 0
        self.last_path: Path | None = None

    def _write(self, trainer: pl.Trainer, outputs: Any, tag: str) -> None:
        if not isinstance(outputs, dict) or "preview" not in outputs or not trainer.is_global_zero:
            return
        if getattr(trainer, "fast_dev_run", False):
            return
        cols = [v[: self.max_rows] for v in outputs["preview"].values()]
        rows = min(c.shape[0] for c in cols)
        grid = preview_grid([c[:rows] for c in cols])
        # not trainer.log_dir: that is a broadcast, and under DDP only rank 0 (maybe alone) gets here
        root = Path(getattr(trainer.logger, "log_dir", None) or trainer.default_root_dir)
        path = root / "previews" / f"{tag}_step{trainer.global_step:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists():  # an earlier run's preview at the same step (a rerun of test, a fresh fit): kept aside
            path.rename(free_name(path))
        Image.fromarray(grid).save(path)
        self.last_path = path
        for logger in trainer.loggers:
            exp = getattr(logger, "experiment", None)
            if hasattr(logger, "log_image"):
                logger.log_image(key=f"{tag}/preview", images=[grid], step=trainer.global_step)
            elif exp is not None and hasattr(exp, "add_image"):
                exp.add_image(f"{tag}/preview", grid, trainer.global_step, dataformats="HWC")

    def state_dict(self) -> dict[str, Any]:
        return {"count": self._count}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._count = int(state_dict.get("count", 0))

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if batch_idx == 0 and not trainer.sanity_checking:
            self._count += 1
            if (self._count - 1) % self.every_n_val == 0:
                self._write(trainer, outputs, "val")

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        if batch_idx == 0:
            self._write(trainer, outputs, "test")
