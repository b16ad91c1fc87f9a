"""Standard 3DGS PLY (graphdeco ``save_ply`` layout): x y z, nx ny nz, f_dc, f_rest (channel-major), opacity
(logit), scale (log std), rot (wxyz). Readable by the common viewers (SuperSplat, antimatter15, viser); graphdeco's
own loader and SIBR take only SH degree 3 (45 ``f_rest``) and no extra columns: ``pad_degree=3`` and no ``extra``
(``anycity export --format ply`` writes that)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData
from torch import Tensor

from anycity.atomic import atomic_open
from anycity.structures import Gaussians

PLY_MAX_SH_DEGREE = 3  # the 3DGS PLY's convention: 45 f_rest at most (SIBR, graphdeco and the web viewers)
MAX_READ_SH_DEGREE = 4  # the most a Gaussians holds (structures.sh_degree_from_k)
ROWS = 1 << 16  # Gaussians per step of the PLY writer: temporaries of a few MB, not copies of the scene


def keep_mask(g: Gaussians, index: int = 0, max_degree: int = 3) -> Tensor:
    """``[N]`` bool: the rows of scene ``index`` every export writes: valid, every field finite (SH up to
    ``max_degree``, the bands written), a non-zero rotation and positive scales."""
    k = (min(g.sh_degree, max_degree) + 1) ** 2
    n = g.num_gaussians
    keep = torch.ones(n, dtype=torch.bool, device=g.means.device)
    if g.valid is not None:
        keep &= g.valid[index]
    for s in range(0, n, ROWS):
        rows = slice(s, s + ROWS)
        quats, scales = g.quats[index, rows], g.scales[index, rows]
        for t in (g.means[index, rows], quats, scales, g.opacities[index, rows, None],
                  g.sh[index, rows, :k].flatten(1)):
            keep[rows] &= torch.isfinite(t).all(-1)
        keep[rows] &= (quats.float().norm(dim=-1) > 0) & (scales.float().min(-1).values > 0)
    return keep


def ply_columns(g: Gaussians, max_degree: int = 3, extra: dict[str, Tensor] | None = None,
                pad_degree: int | None = None) -> list[str]:
    """The property names :func:`gaussians_to_ply_records` writes, in order."""
    k = (max(min(g.sh_degree, max_degree), pad_degree or 0) + 1) ** 2
    return ["x", "y", "z", "nx", "ny", "nz", *(f"f_dc_{i}" for i in range(3)),
            *(f"f_rest_{i}" for i in range(3 * (k - 1))), "opacity", *(f"scale_{i}" for i in range(3)),
            *(f"rot_{i}" for i in range(4)), *(extra or {})]


def gaussians_to_ply_records(g: Gaussians, index: int = 0, max_degree: int = 3,
                             extra: dict[str, Tensor] | None = None,
                             pad_degree: int | None = None) -> tuple[np.ndarray, int]:
    """Scene ``index`` of ``g`` as one structured array ``[M]`` (one little-endian float32 field per PLY property,
    :func:`ply_columns`), filled :data:`ROWS` Gaussians at a time (no whole-scene copies besides it); returns
    ``(records, dropped)``.

    ``extra``: more per-Gaussian columns ``{name: [B, N]}`` (e.g. provenance) appended after the standard ones;
    readers that find columns by name in the header ignore them (SuperSplat, gsplat, graphdeco's Python loader);
    fixed-record readers such as SIBR's gaussianViewer do not. ``pad_degree`` zero-pads the SH up to that degree,
    for readers that expect one (SIBR and graphdeco's loader: 3, 45 ``f_rest``).

    Rows outside :func:`keep_mask` (invalid, non-finite, zero-norm rotation, non-positive scale) are dropped (their
    count is returned). SH above ``max_degree`` (at most 3, the format's limit) are cut per band, then written
    channel-major.
    """
    if not 0 <= max_degree <= 3 or not 0 <= (pad_degree or 0) <= 3:
        raise ValueError(f"max_degree, pad_degree: the PLY format holds SH degree 0..3, got {max_degree}, {pad_degree}")
    keep = keep_mask(g, index, max_degree)
    dropped = int((~keep).sum())
    names = ply_columns(g, max_degree, extra, pad_degree)
    rec = np.empty(g.num_gaussians - dropped, dtype=[(k, "<f4") for k in names])
    table = rec.view("<f4").reshape(len(rec), len(names))  # the same memory, one float32 row per Gaussian
    done = 0
    for s in range(0, g.num_gaussians, ROWS):
        rows = slice(s, s + ROWS)
        block = _ply_rows(g, index, rows, keep[rows] if dropped else None, max_degree, pad_degree, extra)
        table[done:done + len(block)] = block.detach().cpu().numpy()
        done += len(block)
    return rec, dropped


def _ply_rows(g: Gaussians, index: int, rows: slice, keep: Tensor | None, max_degree: int, pad_degree: int | None,
              extra: dict[str, Tensor] | None) -> Tensor:
    """``[n, P]`` float32: the PLY properties of Gaussians ``rows`` of scene ``index`` (those ``keep`` marks)."""
    def take(t: Tensor) -> Tensor:
        return (t[keep] if keep is not None else t).float()

    k = (min(g.sh_degree, max_degree) + 1) ** 2
    sh = take(g.sh[index, rows, :k])  # bands are stored in order, so cutting keeps the lower degrees intact
    n = sh.shape[0]
    rest = sh[:, 1:, :].transpose(1, 2)  # [n, 3, k-1]: channel-major
    if pad_degree is not None and (pad_degree + 1) ** 2 > k:
        rest = torch.cat([rest, rest.new_zeros(n, 3, (pad_degree + 1) ** 2 - k)], -1)
    p = take(g.opacities[index, rows]).clamp(1e-6, 1 - 1e-6)
    quats = take(g.quats[index, rows])
    cols = [take(g.means[index, rows]), sh.new_zeros(n, 3), sh[:, 0, :], rest.reshape(n, 3 * rest.shape[-1]),
            torch.log(p / (1 - p))[:, None], take(g.scales[index, rows]).log(),
            quats / quats.norm(dim=-1, keepdim=True)]
    cols += [take(t[index, rows].to(sh.device))[:, None] for t in (extra or {}).values()]
    return torch.cat(cols, -1)


def gaussians_to_ply_arrays(g: Gaussians, index: int = 0, max_degree: int = 3,
                            extra: dict[str, Tensor] | None = None,
                            pad_degree: int | None = None) -> tuple[dict[str, np.ndarray], int]:
    """:func:`gaussians_to_ply_records` as ``({name: float32 [M]}, dropped)`` (views of one structured array)."""
    rec, dropped = gaussians_to_ply_records(g, index, max_degree, extra, pad_degree)
    return {k: rec[k] for k in rec.dtype.names}, dropped


def save_ply(g: Gaussians, path: str | Path, index: int = 0, max_degree: int = 3,
             extra: dict[str, Tensor] | None = None, pad_degree: int | None = None) -> int:
    """Write scene ``index`` of ``g`` to ``path`` as a binary little-endian 3DGS PLY; returns rows dropped.
    ``extra`` and ``pad_degree`` as in :func:`gaussians_to_ply_records`. Dropped rows other than ``valid=False``
    ones (non-finite, zero-norm rotation, non-positive scale: the format stores log-scales) are named in one
    warning."""
    rec, dropped = gaussians_to_ply_records(g, index, max_degree, extra, pad_degree)
    write_vertices(path, rec)
    invalid = 0 if g.valid is None else int((~g.valid[index]).sum())
    if dropped > invalid:  # padding (valid=False) is not the user's data
        warnings.warn(f"save_ply: {path}: dropped {dropped - invalid} of {g.num_gaussians - invalid} Gaussians with "
                      "a NaN/inf field, a zero-norm rotation or a scale <= 0 (a PLY stores log-scales); "
                      f"{len(rec)} written", stacklevel=2)
    return dropped


PLY_TYPES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint", "f4": "float",
             "f8": "double"}  # plyfile's names, so the header is the one it writes
WRITE_STEP = 1 << 26  # bytes per write call


def vertex_header(data: np.ndarray) -> bytes:
    """The binary little-endian PLY header of one ``vertex`` element holding the structured array ``data``."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {len(data)}"]
    for name in data.dtype.names:
        kind = data.dtype.fields[name][0]
        if kind.str[1:] not in PLY_TYPES or kind.shape:
            raise ValueError(f"write_vertices: field {name!r} is {kind}, not a scalar PLY type "
                             f"({', '.join(PLY_TYPES)})")
        lines.append(f"property {PLY_TYPES[kind.str[1:]]} {name}")
    return ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")


def write_vertices(path: str | Path, data: np.ndarray) -> None:
    """A binary little-endian PLY of one ``vertex`` element (a structured array, one field per property) at
    ``path``, byte for byte what plyfile writes: the header, then the array's bytes streamed in slices through
    :func:`anycity.atomic.atomic_open` (temp file, rename), so a killed export leaves no file that looks complete
    and no second copy of the scene is held in memory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    packed = np.dtype([(k, data.dtype.fields[k][0].newbyteorder("<")) for k in data.dtype.names])
    data = np.ascontiguousarray(data.astype(packed, copy=False))  # what plyfile writes; no copy for ours
    head = vertex_header(data)
    body = data.reshape(-1).view(np.uint8)
    with atomic_open(path, size=len(head) + body.nbytes) as f:
        f.write(head)
        for s in range(0, body.nbytes, WRITE_STEP):
            f.write(memoryview(body[s:s + WRITE_STEP]))


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
    coeffs = n_rest // 3 + 1  # SH coefficients per channel: (degree + 1)^2
    if n_rest % 3 or round(coeffs ** 0.5) ** 2 != coeffs:
        raise ValueError(f"{n_rest} f_rest_* properties: no SH degree has that many (3 * ((degree + 1)^2 - 1): 0, 9, "
                         "24, 45, ...)")  # load_ply names the file
    if coeffs > (MAX_READ_SH_DEGREE + 1) ** 2:  # Gaussians holds degree 4 at most (vggt-1b's)
        raise ValueError(f"{n_rest} f_rest_* properties: SH degree {round(coeffs ** 0.5) - 1}; anycity reads degree "
                         f"0 to {MAX_READ_SH_DEGREE} (a 3DGS PLY holds up to {PLY_MAX_SH_DEGREE})")
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
    """The non-standard per-Gaussian columns of a PLY (e.g. ``obs_views``, ``completion``), ``{name: [N]}``, each a
    numeric scalar property; a list property (another tool's, not ours) is left out with one warning naming it."""
    v = PlyData.read(str(path))["vertex"]
    skip = ("f_dc_", "f_rest_", "scale_", "rot_")
    extra = [k for k in v.data.dtype.names if k not in STANDARD and not k.startswith(skip)]
    lists = [k for k in extra if v.data.dtype[k].kind not in "iuf"]  # plyfile reads a list property as objects
    if lists:
        warnings.warn(f"{path}: ignoring the list propert{'ies' if len(lists) > 1 else 'y'} {', '.join(lists)} (per-"
                      "Gaussian columns are one number each, as `anycity predict` writes them)", stacklevel=2)
    return {k: np.asarray(v[k]) for k in extra if k not in lists}
