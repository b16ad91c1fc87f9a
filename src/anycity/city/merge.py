"""Moving chunk Gaussians into the world frame and writing them as one PLY, a piece at a time."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from anycity.atomic import atomic_open
from anycity.city.align import sim3_parts
from anycity.export.ply import gaussians_to_ply_records
from anycity.geometry.rotations import quat_multiply, rotmat_to_quat
from anycity.render.sh import sh_rotation
from anycity.structures import Gaussians


def sim3_gaussians(g: Gaussians, S: Tensor) -> Gaussians:
    """Gaussians (any batch) moved by one Sim(3) ``S [4, 4]``: centres ``s R p + t``, rotations ``R q``, scales
    ``s x``, and every SH band rotated with the scene (``render.sh.sh_rotation``), so each Gaussian's view-dependent
    colour turns with it."""
    S = S.to(g.means)
    s, R, t = sim3_parts(S.double())
    s, R, t = s.to(g.means), R.to(g.means), t.to(g.means)
    means = g.means @ (s * R).T + t
    quats = quat_multiply(rotmat_to_quat(R).expand_as(g.quats), g.quats)
    sh = g.sh
    if g.sh_degree >= 1:
        sh = torch.einsum("ij,...jc->...ic", sh_rotation(R, g.sh_degree).to(sh), sh)
    return Gaussians(means, quats, g.scales * s, g.opacities, sh, g.valid)


class PlyStream:
    """Write a standard 3DGS PLY (the layout of :func:`anycity.export.save_ply`) piece by piece, so the whole scene
    never sits in memory: rows go to a hidden body file in ``scratch`` (default: ``path``'s folder; it must be on
    ``path``'s filesystem); :meth:`close` streams the header with the final count and the body through
    :func:`anycity.atomic.atomic_open` (temp file in ``scratch``, fsync, rename to ``path``). Used as a context
    manager it closes on success and aborts on an exception, so ``path`` is the old file or the whole new one."""

    def __init__(self, path: str | Path, max_degree: int = 3, scratch: str | Path | None = None) -> None:
        self.path = Path(path)
        self.scratch = Path(scratch) if scratch is not None else self.path.parent
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.scratch.mkdir(parents=True, exist_ok=True)
        self.body_path = self.scratch / f".{self.path.name}.body.tmp"
        self.body = open(self.body_path, "wb")  # noqa: SIM115 - closed in close()/abort()
        self.max_degree = max_degree
        self.columns: list[str] | None = None
        self.count = 0
        self.dropped = 0

    def __enter__(self) -> PlyStream:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def write(self, g: Gaussians, extra: dict[str, Tensor] | None = None) -> None:
        """Append every scene of ``g`` (invalid / non-finite rows dropped, as in ``save_ply``); ``extra``: more
        columns ``{name: [B, N]}``, as in :func:`anycity.export.ply.gaussians_to_ply_records` (every piece the same
        names)."""
        for i in range(g.batch_size):
            rec, dropped = gaussians_to_ply_records(g, i, self.max_degree, extra)  # one array, written as it is
            cols = list(rec.dtype.names)
            if self.columns is None:
                self.columns = cols
            elif cols != self.columns:
                raise ValueError(f"PlyStream: piece has columns {cols[:6]}..., expected {self.columns[:6]}...")
            self.body.write(rec.reshape(-1).view(np.uint8))  # the array's bytes, no copy
            self.count += len(rec)
            self.dropped += dropped

    def close(self) -> Path:
        """Write ``path`` (header + body) crash-safely and remove the body file; returns ``path``."""
        self.body.close()
        if self.columns is None:
            self.abort()
            raise ValueError(f"PlyStream: nothing was written to {self.path}")
        header = ["ply", "format binary_little_endian 1.0", f"element vertex {self.count}"]
        header += [f"property float {k}" for k in self.columns] + ["end_header"]
        head = ("\n".join(header) + "\n").encode("ascii")
        size = len(head) + self.body_path.stat().st_size
        try:
            with atomic_open(self.path, self.scratch, size) as out, open(self.body_path, "rb") as body:
                out.write(head)
                shutil.copyfileobj(body, out, 1 << 22)
        finally:
            self.body_path.unlink(missing_ok=True)
        return self.path

    def abort(self) -> None:
        """Drop what was written; ``path`` is left as it was."""
        if not self.body.closed:
            self.body.close()
        self.body_path.unlink(missing_ok=True)
