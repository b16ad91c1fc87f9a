"""Standard 3DGS PLY (graphdeco ``save_ply`` layout): x y z, nx ny nz, f_dc, f_rest (channel-major), opacity
(logit), scale (log std), rot (wxyz). Readable by the common viewers (SuperSplat, antimatter15, SIBR, viser)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from torch import Tensor

from anycity.atomic import atomic_write_bytes
from anycity.structures import Gaussians


def gaussians_to_ply_arrays(g: Gaussians, index: int = 0, max_degree: int = 3,
                            extra: dict[str, Tensor] | None = None,
                            pad_degree: int | None = None) -> tuple[dict[str, np.ndarray], int]:
    """Columns of scene ``index`` of ``g`` as float32 arrays; returns ``(columns, dropped)``.

    ``extra``: more per-Gaussian columns ``{name: [B, N]}`` (e.g. provenance) appended after the standard ones;
    readers that find columns by name in the header ignore them (SuperSplat, gsplat, graphdeco's Python loader);
    fixed-record readers such as SIBR's gaussianViewer do not. ``pad_degree`` zero-pads the SH up to that degree,
    for readers that expect one (SIBR and graphdeco's loader: 3, 45 ``f_rest``).

    Invalid, non-finite and zero-norm-rotation Gaussians are dropped (their count is returned). SH above
    ``max_degree`` (at most 3, the format's limit) are cut per band, then written channel-major.
    """
    if not 0 <= max_degree <= 3 or not 0 <= (pad_degree or 0) <= 3:
        raise ValueError(f"max_degree, pad_degree: the PLY format holds SH degree 0..3, got {max_degree}, {pad_degree}")
    means, quats = g.means[index].float(), g.quats[index].float()
    scales, opac, sh = g.scales[index].float(), g.opacities[index].float(), g.sh[index].float()
    deg = min(g.sh_degree, max_degree)
    sh = sh[:, : (deg + 1) ** 2]  # bands are stored in order, so cutting keeps the lower degrees intact
    if pad_degree is not None and pad_degree > deg:
        sh = torch.cat([sh, sh.new_zeros(sh.shape[0], (pad_degree + 1) ** 2 - sh.shape[1], 3)], 1)
    keep = torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
    if g.valid is not None:
        keep &= g.valid[index]
    for t in (means, quats, scales, opac[:, None], sh.flatten(1)):
        keep &= torch.isfinite(t).all(-1)
    keep &= quats.norm(dim=-1) > 0
    keep &= scales.min(-1).values > 0
    dropped = int((~keep).sum())
    means, quats, scales, opac, sh = means[keep], quats[keep], scales[keep], opac[keep], sh[keep]
    quats = quats / quats.norm(dim=-1, keepdim=True)
    p = opac.clamp(1e-6, 1 - 1e-6)
    cols: dict[str, Tensor] = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    for c in "xyz":
        cols[f"n{c}"] = torch.zeros_like(means[:, 0])
    for i in range(3):
        cols[f"f_dc_{i}"] = sh[:, 0, i]
    rest = sh[:, 1:, :].transpose(1, 2).reshape(sh.shape[0], 3 * (sh.shape[1] - 1))  # [N, 3*(K-1)] channel-major
    for i in range(rest.shape[1]):
        cols[f"f_rest_{i}"] = rest[:, i]
    cols["opacity"] = torch.log(p / (1 - p))
    for i in range(3):
        cols[f"scale_{i}"] = scales[:, i].log()
    for i in range(4):
        cols[f"rot_{i}"] = quats[:, i]
    for name, t in (extra or {}).items():
        cols[name] = t[index].to(keep.device).float()[keep]
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in cols.items()}, dropped


def save_ply(g: Gaussians, path: str | Path, index: int = 0, max_degree: int = 3,
             extra: dict[str, Tensor] | None = None, pad_degree: int | None = None) -> int:
    """Write scene ``index`` of ``g`` to ``path`` as a binary little-endian 3DGS PLY; returns rows dropped.
    ``extra`` and ``pad_degree`` as in :func:`gaussians_to_ply_arrays`."""
    cols, dropped = gaussians_to_ply_arrays(g, index, max_degree, extra, pad_degree)
    n = len(cols["x"])
    data = np.empty(n, dtype=[(k, "f4") for k in cols])
    for k, v in cols.items():
        data[k] = v
    write_vertices(path, data)
    return dropped


def write_vertices(path: str | Path, data: np.ndarray) -> None:
    """A binary little-endian PLY of one ``vertex`` element (a structured array, one field per property) at
    ``path``, written whole then renamed: a killed export leaves no file that looks complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<").write(buf)
    with buf.getbuffer() as view:  # released even on an error (see lit/checkpoint_io.py)
        atomic_write_bytes(path, view)


def load_ply(path: str | Path) -> Gaussians:
    """Read a PLY written by :func:`save_ply` (or graphdeco) back into a one-scene ``Gaussians``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"load_ply: {path} does not exist; pass the scene.ply written by `anycity predict`")
    try:
        g = _read_ply(path)
        bad = not all(bool(torch.isfinite(t).all()) for t in (g.means, g.quats, g.scales, g.opacities, g.sh))
    except Exception as e:  # noqa: BLE001 - a damaged file of any kind: one line naming it (issue 16)
        raise ValueError(f"load_ply: {path} is not a readable 3DGS PLY ({type(e).__name__}: "
                         f"{' '.join(str(e).split())[:160]}); re-export it with `anycity predict`") from None
    if bad:
        raise ValueError(f"load_ply: {path} holds NaN/inf Gaussian parameters; re-export it with `anycity predict`")
    return g


def _read_ply(path: Path) -> Gaussians:
    v = PlyData.read(str(path))["vertex"]
    names = v.data.dtype.names

    def col(*keys: str) -> Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[k], dtype=np.float32) for k in keys], -1))

    n_rest = sum(1 for k in names if k.startswith("f_rest_"))
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]
    rest = col(*[f"f_rest_{i}" for i in range(n_rest)]).reshape(-1, 3, n_rest // 3).transpose(1, 2) if n_rest \
        else dc[:, :0]
    return Gaussians(
        means=col("x", "y", "z")[None], quats=col("rot_0", "rot_1", "rot_2", "rot_3")[None],
        scales=col("scale_0", "scale_1", "scale_2").exp()[None],
        opacities=torch.sigmoid(col("opacity")[:, 0])[None], sh=torch.cat([dc, rest], 1)[None],
    )


STANDARD = ("x", "y", "z", "nx", "ny", "nz", "opacity")


def load_ply_extras(path: str | Path) -> dict[str, np.ndarray]:
    """The non-standard per-Gaussian columns of a PLY (e.g. ``obs_views``, ``completion``), ``{name: [N]}``."""
    v = PlyData.read(str(path))["vertex"]
    skip = ("f_dc_", "f_rest_", "scale_", "rot_")
    return {k: np.asarray(v[k]) for k in v.data.dtype.names if k not in STANDARD and not k.startswith(skip)}
