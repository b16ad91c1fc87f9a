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

from anycity.atomic import atomic_path, check_writable_folder
from anycity.export.cli import refuse_unknown_flags
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


def scene_up(means: Tensor, eyes: Tensor, camera_up: Tensor, flat: float = 0.25) -> Tensor:
    """World "up" ``[3]`` for an aerial scene: the normal of the Gaussians' principal plane (``means [N, 3]``), turned
    towards the cameras (``eyes [V, 3]``), when the scene is flat (its least spread below ``flat`` of the next);
    otherwise ``camera_up [3]``. The cameras' own mean "up" (-y) lies on the ground for a nadir flight."""
    pts = means.double()[:: max(1, len(means) // 100_000)]
    d = pts - pts.median(0).values
    evals, evecs = torch.linalg.eigh(d.T @ d / max(len(d), 1))
    if len(d) < 3 or evals[0] > flat * evals[1]:
        return camera_up / camera_up.norm()
    up = evecs[:, 0]
    return up if float((eyes.double().mean(0) - pts.median(0).values) @ up) >= 0 else -up


def orbit_path(w2c: Tensor, K: Tensor, centre: Tensor, frames: int, up: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``frames`` cameras on a circle around ``centre`` at the cameras' mean distance from the ``up`` axis through it
    and their mean height, looking at it; the circle lies in the plane orthogonal to ``up`` (default: the mean camera
    "up", -y; :func:`scene_up` gives a better one) and starts on the side of the mean camera (of the first camera
    when they surround the centre)."""
    c2w = torch.linalg.inv(w2c.double())
    eyes = c2w[:, :3, 3]
    up = -c2w[:, :3, 1].mean(0) if up is None else up.double()
    up = up / up.norm()
    rel = eyes - centre.double()  # [V, 3]
    heights = rel @ up
    radial = rel - heights[:, None] * up
    # Per camera, not of the mean camera: an orbit or a grid flight around the site has its mean camera above the
    # centre, whose radius would be ~0.
    r = max(float(radial.norm(dim=-1).mean()), 1e-6)
    height = heights.mean() * up
    start = radial.mean(0) if radial.mean(0).norm() > 0.25 * r else radial[0]
    a = start / start.norm() if start.norm() > 1e-9 else torch.linalg.svd(up[None])[2][1]
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


def _imageio_ffmpeg():
    """The imageio_ffmpeg module, or one line naming the extra that installs it."""
    try:
        import imageio_ffmpeg
    except ModuleNotFoundError as e:
        raise ValueError(f"anycity render-video needs the viewer extra (no module {e.name!r}): "
                         "pip install -e '.[viewer]'") from None
    return imageio_ffmpeg


VIDEO_SUFFIXES = (".mp4", ".m4v", ".mkv", ".mov")  # containers the bundled ffmpeg writes H.264 into


def check_video_out(out: str | Path) -> None:
    """One line naming ``--out`` when it cannot become a video: an existing folder, or a name whose suffix is not
    one of :data:`VIDEO_SUFFIXES` (ffmpeg picks the container by it). Checked before the scene is loaded: ffmpeg
    would otherwise fail only after every frame was rendered."""
    out = Path(out)
    if out.is_dir():
        raise IsADirectoryError(f"--out {out} is a folder; pass a video file name, e.g. --out "
                                f"{out / 'flythrough.mp4'}")
    if out.suffix.lower() not in VIDEO_SUFFIXES:
        got = f"suffix {out.suffix!r} is not a video container" if out.suffix else "no suffix"
        raise ValueError(f"--out {out}: {got}; end the name in {', '.join(VIDEO_SUFFIXES)} "
                         f"(e.g. --out {out.with_suffix('.mp4')})")


def _check_frames(imageio_ffmpeg, tmp: Path, frames: int, out: Path) -> None:
    """Raise one line naming ``--out`` unless ffmpeg reads ``frames`` frames back from ``tmp``. imageio-ffmpeg
    ignores ffmpeg's exit status, so a video ffmpeg could not finish (a full disk or quota at the muxer's last
    write) would otherwise be published as whole, over an earlier one under --overwrite."""
    try:
        got = imageio_ffmpeg.count_frames_and_secs(str(tmp))[0]
    except (RuntimeError, OSError):  # ffmpeg cannot read it (no moov atom): a cut file
        got = 0
    if got != frames:
        raise _ffmpeg_failed(out, f"the encoded video holds {got} of {frames} frames")


def _ffmpeg_failed(out: Path, what: str) -> ValueError:
    return ValueError(f"--out {out}: ffmpeg failed writing the video ({what}; a full disk or quota?); {out} is "
                      "unchanged: free space or pass --out on another disk, and rerun")


def render_video(path: str | Path, out: str | Path, per_segment: int = 12, orbit: int = 0, width: int | None = None,
                 fps: int = 24, progress: bool = True) -> int:
    """Write the fly-through mp4 of the scene at ``path``; returns the number of frames."""
    imageio_ffmpeg = _imageio_ffmpeg()
    check_video_out(out)
    scene = load_view_scene(path, thumbs=False)
    if scene.w2c is None:
        raise ValueError(f"{path}: no cameras.json beside the scene; render-video follows the predicted cameras, "
                         "pass the predict scene folder")
    w2c, K = interpolate_path(scene.w2c, scene.K, per_segment)
    if orbit > 0:
        means = scene.gaussians.means[0]
        c2w = torch.linalg.inv(scene.w2c.double())
        up = scene_up(means, c2w[:, :3, 3], -c2w[:, :3, 1].mean(0))
        ow, oK = orbit_path(scene.w2c, scene.K, means.median(0).values, orbit, up)
        w2c, K = torch.cat([w2c, ow]), torch.cat([K, oK])
    asked = width
    width = width or scene.width
    width -= width % 2  # yuv420p needs even sizes
    height = max(2, round(width * scene.height / scene.width / 2) * 2)
    if progress:
        why = ("the input width; --width sets another" if asked is None else
               "--width rounded down to an even width, as H.264 needs" if asked != width else "--width")
        print(f"render-video: {len(w2c)} frames of {width}x{height} ({why})")
    n = 0
    # renamed into place when complete: a run that fails or is killed leaves no short mp4 that looks whole, and an
    # --overwrite run that fails keeps the old one
    with atomic_path(out) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (width, height), fps=fps, quality=8, macro_block_size=2)
        writer.send(None)
        try:
            for frame in render_frames(scene, w2c, K, width, height, progress):
                try:
                    writer.send(np.ascontiguousarray(frame))
                except OSError:  # ffmpeg exited (a broken pipe); imageio's message holds its whole command line
                    raise _ffmpeg_failed(Path(out), f"it stopped after {n} frames") from None
                n += 1
        finally:
            writer.close()
        _check_frames(imageio_ffmpeg, tmp, n, Path(out))
    return n


def _int_at_least(low: int):
    def parse(text: str) -> int:
        value = int(text)
        if value < low:
            raise argparse.ArgumentTypeError(f"{value} is below {low}")
        return value
    parse.__name__ = "int"  # argparse names the type in its "invalid int value" message
    return parse


def render_video_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="anycity render-video",
                                description="Render an mp4 fly-through along the predicted cameras.",
                                allow_abbrev=False)
    p.add_argument("path", help="predict scene folder (scene.ply + cameras.json)")
    p.add_argument("--out", default=None,
                   help=f"video file, {'/'.join(VIDEO_SUFFIXES)} (default: <path>/flythrough.mp4)")
    p.add_argument("--per_segment", "--per-segment", type=_int_at_least(1), default=12,
                   help="frames between consecutive cameras (default: %(default)s)")
    p.add_argument("--orbit", type=_int_at_least(0), default=0,
                   help="frames of an orbit around the scene centre (default: %(default)s: none)")
    p.add_argument("--width", type=_int_at_least(2), default=None, help="frame width (default: the input width)")
    p.add_argument("--fps", type=_int_at_least(1), default=24, help="frames per second (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    a = p.parse_args(refuse_unknown_flags(p, argv))
    src = Path(a.path)
    out = Path(a.out) if a.out else (src if src.is_dir() else src.parent) / "flythrough.mp4"
    check_video_out(out)
    if out.exists() and not a.overwrite:
        raise FileExistsError(f"anycity render-video: {out} exists; pass --overwrite to replace it, or --out NEW.mp4")
    check_writable_folder(out.parent, "--out")  # ffmpeg would fail with a broken pipe after the first frame
    n = render_video(src, out, a.per_segment, a.orbit, a.width, a.fps)
    print(f"wrote {out} ({n} frames)")
    return 0
