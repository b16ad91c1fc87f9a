"""``anycity render-video``: an mp4 fly-through along the predicted cameras (interpolated poses: slerp rotation,
linear centre and intrinsics), optionally followed by an orbit around the scene centre. Encoded with
imageio-ffmpeg (H.264, yuv420p)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from anycity.viewer.scene import ViewScene, load_view_scene


def _slerp(q0: Tensor, q1: Tensor, t: float) -> Tensor:
    if (q0 * q1).sum() < 0:
        q1 = -q1
    d = float((q0 * q1).sum().clamp(-1, 1))
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
    else:
        th = math.acos(d)
        q = (math.sin((1 - t) * th) * q0 + math.sin(t * th) * q1) / math.sin(th)
    return q / q.norm()


def interpolate_path(w2c: Tensor, K: Tensor, per_segment: int) -> tuple[Tensor, Tensor]:
    """``w2c [V, 4, 4]``, ``K [V, 3, 3]`` -> ``per_segment`` poses between each consecutive pair plus the last:
    ``[(V-1) * per_segment + 1, 4, 4]`` and matching ``K``."""
    from anycity.geometry import quat_to_rotmat, rotmat_to_quat

    c2w = torch.linalg.inv(w2c.double())
    q = rotmat_to_quat(c2w[:, :3, :3])
    poses, Ks = [], []
    for i in range(len(c2w) - 1):
        for s in range(per_segment):
            t = s / per_segment
            T = torch.eye(4, dtype=torch.float64)
            T[:3, :3] = quat_to_rotmat(_slerp(q[i], q[i + 1], t))
            T[:3, 3] = (1 - t) * c2w[i, :3, 3] + t * c2w[i + 1, :3, 3]
            poses.append(T)
            Ks.append((1 - t) * K[i].double() + t * K[i + 1].double())
    poses.append(c2w[-1])
    Ks.append(K[-1].double())
    return torch.linalg.inv(torch.stack(poses)), torch.stack(Ks)


def orbit_path(w2c: Tensor, K: Tensor, centre: Tensor, frames: int) -> tuple[Tensor, Tensor]:
    """``frames`` cameras on a circle around ``centre`` at the mean camera distance and height, looking at it;
    the circle lies in the plane orthogonal to the mean camera "up" (-y)."""
    c2w = torch.linalg.inv(w2c.double())
    eyes = c2w[:, :3, 3]
    up = -c2w[:, :3, 1].mean(0)
    up = up / up.norm()
    rel = eyes.mean(0) - centre.double()
    height = (rel @ up) * up
    radial = rel - height
    r = max(float(radial.norm()), 1e-6)
    a = radial / r if radial.norm() > 1e-9 else torch.linalg.svd(up[None])[2][1]
    b = torch.linalg.cross(up, a)
    out = []
    for i in range(frames):
        th = 2 * math.pi * i / frames
        eye = centre.double() + height + r * (math.cos(th) * a + math.sin(th) * b)
        z = centre.double() - eye
        z = z / z.norm()
        x = torch.linalg.cross(z, up)  # OpenCV: x right, y down (= -up), z forward
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        T = torch.eye(4, dtype=torch.float64)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
        out.append(torch.linalg.inv(T))
    return torch.stack(out), K[:1].double().expand(frames, 3, 3)


def render_frames(scene: ViewScene, w2c: Tensor, K: Tensor, width: int, height: int, progress: bool = True):
    """Yield ``[H, W, 3]`` uint8 frames of ``scene`` at each camera (``K`` for the input size, rescaled)."""
    from tqdm import tqdm

    from anycity.render import render

    sx, sy = width / scene.width, height / scene.height
    S = torch.tensor([[sx, 0, 0], [0, sy, 0], [0, 0, 1]], dtype=torch.float64)
    for i in tqdm(range(len(w2c)), desc="render-video", unit="frame", disable=not progress):
        out = render(scene.gaussians, w2c[i][None, None].float(), (S @ K[i])[None, None].float(), width, height)
        yield (out.rgb[0, 0].clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def render_video(path: str | Path, out: str | Path, per_segment: int = 12, orbit: int = 0, width: int | None = None,
                 fps: int = 24, progress: bool = True) -> int:
    """Write the fly-through mp4 of the scene at ``path``; returns the number of frames."""
    import imageio_ffmpeg

    scene = load_view_scene(path)
    if scene.w2c is None:
        raise ValueError(f"{path}: no cameras.json beside the scene; render-video follows the predicted cameras, "
                         "pass the predict scene folder")
    w2c, K = interpolate_path(scene.w2c, scene.K, per_segment)
    if orbit > 0:
        centre = scene.gaussians.means[0].median(0).values
        ow, oK = orbit_path(scene.w2c, scene.K, centre, orbit)
        w2c, K = torch.cat([w2c, ow]), torch.cat([K, oK])
    width = width or scene.width
    width -= width % 2  # yuv420p needs even sizes
    height = round(width * scene.height / scene.width / 2) * 2
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(str(out), (width, height), fps=fps, quality=8, macro_block_size=2)
    writer.send(None)
    n = 0
    for frame in render_frames(scene, w2c, K, width, height, progress):
        writer.send(np.ascontiguousarray(frame))
        n += 1
    writer.close()
    return n


def render_video_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="anycity render-video",
                                description="Render an mp4 fly-through along the predicted cameras.")
    p.add_argument("path", help="predict scene folder (scene.ply + cameras.json)")
    p.add_argument("--out", default=None, help="mp4 path (default: <path>/flythrough.mp4)")
    p.add_argument("--per-segment", type=int, default=12,
                   help="frames between consecutive cameras (default: %(default)s)")
    p.add_argument("--orbit", type=int, default=0,
                   help="frames of an orbit around the scene centre (default: %(default)s: none)")
    p.add_argument("--width", type=int, default=None, help="frame width (default: the input width)")
    p.add_argument("--fps", type=int, default=24, help="frames per second (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    a = p.parse_args(argv)
    src = Path(a.path)
    out = Path(a.out) if a.out else (src if src.is_dir() else src.parent) / "flythrough.mp4"
    if out.exists() and not a.overwrite:
        raise FileExistsError(f"anycity render-video: {out} exists; pass --overwrite to replace it, or --out NEW.mp4")
    n = render_video(src, out, a.per_segment, a.orbit, a.width, a.fps)
    print(f"wrote {out} ({n} frames)")
    return 0
