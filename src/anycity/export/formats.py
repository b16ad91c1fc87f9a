"""Exports for other tools: antimatter15 ``.splat``, a COLMAP text model and a nerfstudio ``transforms.json``.

All of them stay in the predicted world frame (OpenCV axes, the network's normalised units); ``scale.json`` beside
them copies ``metres_per_unit`` from ``cameras.json`` (null as ``predict`` writes it: the network's frame has no known
metric scale; a number when the user set one there). Every file is written through :mod:`anycity.atomic`: a killed
export leaves no partial file under a final name.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from torch import Tensor

from anycity.atomic import atomic_write_bytes
from anycity.export.ply import keep_mask, write_vertices
from anycity.geometry import rotmat_to_quat
from anycity.structures import Gaussians

SH_C0 = 0.28209479177387814
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # c2w_gl = c2w_cv @ GL_TO_CV (its own inverse)


def _dc_rgb(g: Gaussians, index: int) -> np.ndarray:
    """Base colour ``[N, 3]`` in [0, 1] from the SH DC band."""
    return (0.5 + SH_C0 * g.sh[index, :, 0, :].float()).clamp(0, 1).cpu().numpy()


def _keep(g: Gaussians, index: int) -> np.ndarray:
    """``[N]`` bool: the rows the PLY writer keeps (:func:`anycity.export.ply.keep_mask`: valid, finite SH
    included, positive scales), so every format holds the same Gaussians."""
    return keep_mask(g, index).cpu().numpy()


def splat_bytes(g: Gaussians, index: int = 0) -> bytes:
    """Scene ``index`` as antimatter15 ``.splat`` records (32 B each, sorted by descending size x opacity):
    float32 xyz, float32 linear scales, uint8 RGBA, uint8 quaternion wxyz as ``q * 128 + 128``."""
    keep = _keep(g, index)
    means = g.means[index].float().cpu().numpy()[keep]
    scales = g.scales[index].float().cpu().numpy()[keep]
    opac = g.opacities[index].float().cpu().numpy()[keep]
    q = g.quats[index].float().cpu().numpy()[keep]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    rgba = np.concatenate([_dc_rgb(g, index)[keep], opac[:, None]], -1)
    order = np.argsort(-(scales.prod(-1) * opac), kind="stable")
    rec = np.zeros(len(order), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
    rec["pos"], rec["scale"] = means[order], scales[order]
    rec["rgba"] = np.clip(np.round(rgba[order] * 255), 0, 255)
    rec["rot"] = np.clip(np.round(q[order] * 128 + 128), 0, 255)
    return rec.tobytes()


def save_splat(g: Gaussians, path: str | Path, index: int = 0) -> int:
    """Write :func:`splat_bytes` to ``path``; returns the number of splats written."""
    data = splat_bytes(g, index)
    atomic_write_bytes(path, data)
    return len(data) // 32


def save_colmap(path: str | Path, w2c: Tensor, K: Tensor, width: int, height: int, names: list[str],
                g: Gaussians | None = None, index: int = 0, max_points: int | None = None) -> Path:
    """COLMAP text model in ``path`` (``cameras.txt``, ``images.txt``, ``points3D.txt``).

    ``w2c [V, 4, 4]``, ``K [V, 3, 3]`` pixels for ``width x height`` images; one PINHOLE camera per view. The
    point cloud is the Gaussian centres of scene ``index`` with their DC colours (no 2-D tracks), at most
    ``max_points`` of the most opaque ones.
    """
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    w2c, K = w2c.detach().double().cpu(), K.detach().double().cpu()
    cams = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[] (written by anycity export)"]
    imgs = ["# Image list: IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME / POINTS2D[] (empty)"]
    quats = rotmat_to_quat(w2c[:, :3, :3])
    for v in range(w2c.shape[0]):
        k = K[v]
        cams.append(f"{v + 1} PINHOLE {width} {height} {k[0, 0]:.17g} {k[1, 1]:.17g} {k[0, 2]:.17g} {k[1, 2]:.17g}")
        q, t = quats[v], w2c[v, :3, 3]
        q = q if q[0] >= 0 else -q
        imgs.append(f"{v + 1} " + " ".join(f"{x:.17g}" for x in [*q.tolist(), *t.tolist()]) + f" {v + 1} {names[v]}")
        imgs.append("")
    _write_lines(path / "cameras.txt", cams)
    _write_lines(path / "images.txt", imgs)
    pts = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] (Gaussian centres, no tracks)"]
    if g is not None:
        xyz, rgb = _coloured_points(g, index, max_points)
        pts += [f"{i + 1} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {c[0]} {c[1]} {c[2]} 0"
                for i, (p, c) in enumerate(zip(xyz, rgb, strict=True))]
    _write_lines(path / "points3D.txt", pts)
    return path


def _coloured_points(g: Gaussians, index: int, max_points: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Centres ``[P, 3]`` (float64) and DC colours ``[P, 3]`` (uint8) of scene ``index``'s valid Gaussians, at most
    ``max_points`` of the most opaque ones, in their stored order."""
    keep = np.nonzero(_keep(g, index))[0]
    if max_points is not None and len(keep) > max_points:
        op = g.opacities[index].float().cpu().numpy()[keep]
        keep = np.sort(keep[np.argsort(-op, kind="stable")[:max_points]])
    xyz = g.means[index].double().cpu().numpy()[keep]
    return xyz, np.round(_dc_rgb(g, index)[keep] * 255).astype(np.uint8)


def save_points_ply(path: str | Path, g: Gaussians, index: int = 0, max_points: int | None = None) -> Path:
    """The Gaussian centres of scene ``index`` as a coloured point cloud (``x y z`` float, zero ``nx ny nz`` float,
    ``red green blue`` uchar: graphdeco's ``storePly`` layout, which its ``fetchPly`` requires, and nerfstudio's
    ``ply_file_path`` reads); returns ``path``. Points as in :func:`save_colmap`."""
    xyz, rgb = _coloured_points(g, index, max_points)
    data = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                                     ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, c in enumerate("xyz"):
        data[c] = xyz[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        data[c] = rgb[:, i]
    write_vertices(path, data)
    return Path(path)


def _write_lines(path: Path, lines: list[str]) -> None:
    """``lines`` as a text file, one a line; a photo name that is not UTF-8 (a latin-1 ``caf\\xe9.jpg``, which
    Python holds as surrogate escapes) is written as the bytes of the file's own name."""
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8", "surrogateescape"))


def transforms_dict(w2c: Tensor, K: Tensor, width: int, height: int, names: list[str],
                    ply_file_path: str | None = None) -> dict:
    """nerfstudio ``transforms.json`` content: per-frame intrinsics, OpenGL camera-to-world ``transform_matrix``."""
    c2w = np.linalg.inv(w2c.detach().double().cpu().numpy()) @ GL_TO_CV
    K = K.detach().double().cpu().numpy()
    frames = [{"file_path": n, "transform_matrix": c.tolist(), "fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]),
               "cx": float(k[0, 2]), "cy": float(k[1, 2]), "w": int(width), "h": int(height)}
              for n, c, k in zip(names, c2w, K, strict=True)]
    out: dict = {"camera_model": "OPENCV", "frames": frames}
    if ply_file_path:
        out["ply_file_path"] = ply_file_path  # nerfstudio's key for an initial point cloud
    return out


def save_transforms(path: str | Path, w2c: Tensor, K: Tensor, width: int, height: int, names: list[str],
                    ply_file_path: str | None = None) -> Path:
    """Write :func:`transforms_dict` as ``path`` (a ``.json`` file or a folder that gets ``transforms.json``)."""
    path = Path(path)
    if path.suffix != ".json":
        path = path / "transforms.json"
    content = transforms_dict(w2c, K, width, height, names, ply_file_path)
    atomic_write_bytes(path, json.dumps(content, indent=1).encode())
    return path


def save_scale(path: str | Path, metres_per_unit: float | None, fmt: str) -> None:
    """``scale.json`` beside an export: the frame and its scale (metres per unit, null when unknown)."""
    atomic_write_bytes(path, json.dumps({
        "frame": "anycity predicted world frame, OpenCV camera convention (see cameras.json)",
        "units": "metres" if metres_per_unit == 1.0 else "predicted (normalised)",
        "metres_per_unit": metres_per_unit, "format": fmt}, indent=1).encode())
