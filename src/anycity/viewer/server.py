"""``anycity view PATH``: a viser server with the splats, the predicted cameras (frustums with the input
images), a provenance colouring control and a button that saves a render of the current view with our
renderer. Listens on 127.0.0.1 unless told otherwise."""

from __future__ import annotations

import argparse
import errno
import ipaddress
import math
import socket
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from anycity.atomic import atomic_path
from anycity.export.cli import refuse_unknown_flags
from anycity.viewer.scene import ViewScene, load_view_scene, ramp, splat_arrays

COLOURINGS = ("colour", "obs_views (blue 0 -> red 4+ views)", "completion (blue kept -> red completed)")


def _rotmat_to_wxyz(R: np.ndarray) -> np.ndarray:
    from anycity.geometry import rotmat_to_quat

    return rotmat_to_quat(torch.as_tensor(R, dtype=torch.float64)).numpy()


def camera_w2c(wxyz, position, fov_y: float, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A viser camera (OpenCV camera-to-world ``wxyz``, ``position``; vertical ``fov_y`` radians) ->
    ``(w2c [1, 1, 4, 4], K [1, 1, 3, 3])`` for a ``width x height`` render."""
    from anycity.geometry import quat_to_rotmat

    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz), dtype=torch.float64))
    c2w[:3, 3] = torch.as_tensor(np.asarray(position), dtype=torch.float64)
    f = 0.5 * height / math.tan(fov_y / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float64)
    return torch.linalg.inv(c2w)[None, None].float(), K[None, None].float()


def render_view(scene: ViewScene, w2c: torch.Tensor, K: torch.Tensor, width: int, height: int) -> np.ndarray:
    """Our renderer at one camera -> ``[H, W, 3]`` uint8."""
    from anycity.render import render

    out = render(scene.gaussians, w2c, K, width, height, backend="auto")
    return (out.rgb[0, 0].clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def scene_identity(path: str | Path) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of the scene folder at ``path`` (a predict folder, or the folder of a ``scene.ply``);
    None when it is gone. A re-predict moves the folder aside and writes a new one, so the identity taken when the
    viewer loads the scene tells the loaded folder from the one now at its path."""
    path = Path(path)
    try:
        st = (path if path.is_dir() else path.parent).stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


MAX_RENDER_WIDTH = 4096
"""Save render's widest image, px: the browser's aspect is clamped to [0.1, 10] and the width to this."""
ASPECT_RANGE = (0.1, 10.0)


def check_camera(wxyz, position, fov_y: float, aspect: float, height: int) -> None:
    """One-line ``ValueError`` naming the value for a camera :func:`save_render` cannot render: ``fov_y`` (radians)
    outside (0, pi), ``aspect`` not finite and > 0, ``height`` (px) not an integer >= 1, ``position [3]`` not
    finite, ``wxyz [4]`` not finite or zero. A browser may send any of these (a 0 px tall panel, a NaN)."""
    if isinstance(height, bool) or not isinstance(height, (int, np.integer)) or height < 1:
        raise ValueError(f"image height {height!r} is not a whole number of pixels >= 1")
    if not 0 < _number(fov_y) < math.pi:
        raise ValueError(f"field of view {fov_y!r} is not in (0, pi) radians")
    if not 0 < _number(aspect) < math.inf:
        raise ValueError(f"aspect (width / height) {aspect!r} is not a finite number > 0")
    for name, v, n in (("position", position, 3), ("rotation (wxyz)", wxyz, 4)):
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (n,) or not np.isfinite(a).all() or not a.any():
            what = f"{n} finite numbers" + (", not all 0" if n == 4 else "")
            raise ValueError(f"camera {name} {a.tolist()} is not {what}")


def _number(x) -> float:
    """``x`` as a float, NaN when it is not a real number (so every range check fails on it)."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def render_width(height: int, aspect: float) -> int:
    """The width (px) of a ``height`` px render at ``aspect`` (width / height): ``aspect`` clamped to
    :data:`ASPECT_RANGE`, the width to [1, :data:`MAX_RENDER_WIDTH`], so no browser asks for a 48000 px image."""
    aspect = min(max(aspect, ASPECT_RANGE[0]), ASPECT_RANGE[1])
    return min(MAX_RENDER_WIDTH, max(1, round(height * aspect)))


def save_render(scene: ViewScene, wxyz, position, fov_y: float, aspect: float, height: int = 480,
                loaded: tuple[int, int] | None = None) -> Path:
    """Our render of the viewer's current camera (as :func:`camera_w2c` takes it) at ``height`` px, ``aspect``
    (width / height) clamped by :func:`render_width` (at most 4096 px wide), written to
    ``<scene folder>/view_renders/render_<time>[_N].png``; returns the file. The name is reserved atomically, so
    clicks at once (viser runs callbacks in threads) each get their own file, never over an earlier one.
    A camera :func:`check_camera` refuses is a one-line ``ValueError``.
    ``loaded``: the :func:`scene_identity` taken when ``scene`` was loaded; a scene folder that has changed since
    (re-predicted, or moved aside while a re-predict runs) gets nothing, and ``FileNotFoundError`` says so."""
    if loaded is not None and scene_identity(scene.folder) != loaded:
        raise FileNotFoundError(f"{scene.folder}: the scene was replaced on disk (re-predicted?) since this viewer "
                                f"loaded it; no render saved; restart anycity view {scene.folder} to load the new one")
    check_camera(wxyz, position, fov_y, aspect, height)
    w = render_width(height, aspect)
    w2c, K = camera_w2c(wxyz, position, fov_y, w, height)
    out = scene.folder / "view_renders"
    out.mkdir(exist_ok=True)
    img = Image.fromarray(render_view(scene, w2c, K, w, height))
    f = _reserve_name(out, f"render_{time.strftime('%Y%m%d_%H%M%S')}")
    try:
        with atomic_path(f) as tmp:
            img.save(tmp)
    except BaseException:
        f.unlink(missing_ok=True)
        raise
    return f


def _reserve_name(folder: Path, stem: str) -> Path:
    """Create the first of ``folder/<stem>.png``, ``<stem>_1.png``, ... that does not exist (exclusively: of two
    threads or processes, one gets each name), empty; returns it."""
    n = 0
    while True:
        f = folder / (f"{stem}.png" if n == 0 else f"{stem}_{n}.png")
        try:
            with open(f, "xb"):
                return f
        except FileExistsError:
            n += 1


def frustum_shape(K: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """``(fov_y, aspect)`` of a ``width x height`` camera ``K [3, 3]`` as viser's frustums take them: vertical field
    of view (radians) and the image plane's width over height, ``(W / fx) / (H / fy)`` (not W / H when fx != fy)."""
    fx, fy = float(K[0, 0]), float(K[1, 1])
    return 2 * math.atan(0.5 * height / fy), (width / fx) / (height / fy)


def initial_view(c2w: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(up, position, look_at)``, each ``[3]``: the viewer's up axis, :func:`anycity.viewer.video.scene_up` (the
    ground's normal for a flat scene, so orbiting turns about the vertical; the cameras' mean "up" otherwise), and a
    first camera behind the mean input camera (``c2w [V, 4, 4]``), looking along its mean direction at the splats'
    median (``centres [N, 3]``). A direction within 18° of vertical (a nadir flight) is tilted to 30° off it, so the
    orbit controls have a horizontal to turn about."""
    from anycity.viewer.video import scene_up

    eyes, image_up = c2w[:, :3, 3], -c2w[:, :3, 1].mean(0)
    up = scene_up(torch.as_tensor(centres), torch.as_tensor(eyes), torch.as_tensor(image_up)).numpy()
    fwd = c2w[:, :3, 2].mean(0)
    fwd = fwd / (np.linalg.norm(fwd) or 1.0)
    along = image_up - (image_up @ up) * up  # the images' "up", on the ground
    if abs(fwd @ up) > 0.95 and np.linalg.norm(along) > 1e-6:
        fwd = -math.cos(math.pi / 6) * up + math.sin(math.pi / 6) * along / np.linalg.norm(along)
    extent = float(np.linalg.norm(eyes - eyes.mean(0), axis=-1).mean()) or 1.0
    centre = np.median(centres, 0)
    depth = float(np.dot(centre - eyes.mean(0), fwd))
    return up, centre - fwd * 1.6 * max(depth, extent), centre


def _viser():
    """The viser module, or one line naming the extra that installs it (not a ModuleNotFoundError traceback)."""
    try:
        import viser
    except ModuleNotFoundError as e:
        raise ValueError(f"anycity view needs the viewer extra (no module {e.name!r}): pip install -e '.[viewer]'") \
            from None
    return viser


def _bind_all(infos: list, port: int) -> None:
    """Listen on ``port`` at every address of ``infos`` (``socket.getaddrinfo`` rows) at once, as asyncio's server
    does (SO_REUSEADDR, IPv6 sockets v6-only), then close them; the first failure's ``OSError`` propagates."""
    socks = []
    try:
        for family, kind, proto, _, addr in infos:
            try:
                s = socket.socket(family, kind, proto)
            except OSError:  # a family this kernel lacks (IPv6 off): asyncio skips it too
                continue
            socks.append(s)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            s.bind((addr[0], port, *addr[2:]))
            s.listen()
    finally:
        for s in socks:
            s.close()


def listen_port(host: str, port: int) -> int:
    """The first of ``port``, ``port + 1``, ... 65535 that ``host`` can listen on (``port=0``: 0, for viser to pick
    one, once ``host`` is checked). One line naming ``--host`` for a name that does not resolve or an address this
    machine does not have, and naming ``--port`` when every port up to 65535 is taken: viser's server thread would
    die (or try 1000 ports) and ``anycity view`` would wait for it forever."""
    fix = "pass 127.0.0.1 (this machine only), 0.0.0.0 (every interface) or another address this machine has"
    try:
        infos = list(dict.fromkeys(socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM,
                                                      flags=socket.AI_PASSIVE)))
    except (OSError, UnicodeError) as e:  # socket.gaierror: no such name
        raise ValueError(f"--host {host}: cannot resolve it ({getattr(e, 'strerror', None) or e}); {fix}") from None
    for p in range(port, 65536) if port else (0,):
        try:
            _bind_all(infos, p)
            return p
        except OSError as e:
            if e.errno in (errno.EADDRINUSE, errno.EACCES):  # taken, or privileged: the next one (as viser does)
                continue
            if e.errno == errno.EADDRNOTAVAIL:
                raise ValueError(f"--host {host}: not an address of this machine; {fix}") from None
            raise ValueError(f"--host {host} --port {p}: cannot listen there ({e.strerror or e}); {fix}") from None
    ports = "it is" if port == 65535 else f"every port from {port} to 65535 is"
    raise ValueError(f"--port {port}: {ports} taken on {host}; pass --port 0 (any free one) or a lower port")


def build_server(path: str | Path, host: str = "127.0.0.1", port: int = 8080, cameras: bool = True):
    """Start the viewer on ``scene`` at ``path``; returns ``(server, scene)``. ``port=0`` picks a free port, a
    taken one moves up (:func:`listen_port`); ``cameras=False`` hides the camera frustums."""
    viser = _viser()
    port = listen_port(host, port)
    loaded = scene_identity(path)  # before loading: a scene replaced meanwhile reads as changed, never the reverse
    scene = load_view_scene(path)
    server = viser.ViserServer(host=host, port=port, verbose=False)
    server.scene.set_up_direction("-y")  # no cameras: the first camera's "up" (OpenCV: y points down)
    centres, cov, rgb, opac = splat_arrays(scene.gaussians)
    splats = {"h": server.scene.add_gaussian_splats("/splats", centres, cov, rgb, opac)}

    if scene.w2c is not None:
        c2w = torch.linalg.inv(scene.w2c.double()).numpy()
        fov = frustum_shape(scene.K[0].numpy(), scene.width, scene.height)[0]
        up, position, look_at = initial_view(c2w, centres)
        server.scene.set_up_direction(tuple(float(x) for x in up))
        server.initial_camera.position = tuple(position)
        server.initial_camera.look_at = tuple(look_at)
        server.initial_camera.up = tuple(float(x) for x in up)
        server.initial_camera.fov = fov
        extent = float(np.linalg.norm(c2w[:, :3, 3] - c2w[:, :3, 3].mean(0), axis=-1).mean()) or 1.0
        for v in range(len(c2w) if cameras else 0):
            fov_v, aspect = frustum_shape(scene.K[v].numpy(), scene.width, scene.height)
            server.scene.add_camera_frustum(
                f"/cameras/{v:03d}", fov=fov_v, aspect=aspect, scale=0.15 * extent,
                thickness=1.5, thickness_units="screen",
                image=scene.thumbs[v] if scene.thumbs else None, wxyz=_rotmat_to_wxyz(c2w[v, :3, :3]),
                position=c2w[v, :3, 3], color=(255, 160, 0))

    colouring = server.gui.add_dropdown("Colour by", colourings(scene.extras), initial_value="colour")
    info = server.gui.add_markdown(_share_text(scene))

    @colouring.on_update
    def _(_event) -> None:
        key = colouring.value.split()[0]
        col = rgb if key == "colour" else ramp(scene.extras[key] / (4.0 if key == "obs_views" else 1.0))
        splats["h"].remove()
        splats["h"] = server.scene.add_gaussian_splats("/splats", centres, cov, col.astype(np.float32), opac)

    button = server.gui.add_button("Save render")

    @button.on_click
    def _(event) -> None:
        info.content = _share_text(scene) + "\n\n" + save_click(scene, event.client.camera, loaded)

    return server, scene


def save_click(scene: ViewScene, cam, loaded: tuple[int, int] | None) -> str:
    """What the "Save render" button does for a client's camera ``cam`` (viser's ``CameraHandle``): the panel's line,
    "saved `FILE`" or "no render saved: WHY". A callback's exception would be a traceback on the server's terminal
    and nothing in the browser, so a refused camera or an unusable folder is that line instead."""
    try:
        try:
            aspect = cam.aspect
        except ZeroDivisionError:  # viser's width / height of a 0 px tall browser view
            raise ValueError(f"the browser's view is {cam.image_width} x 0 px") from None
        f = save_render(scene, cam.wxyz, cam.position, cam.fov, aspect, loaded=loaded)
    except (OSError, ValueError) as e:
        return f"no render saved: {e}"
    return f"saved `{f}`"


def _share_text(scene: ViewScene) -> str:
    n = scene.gaussians.num_gaussians
    lines = [f"**{n:,} Gaussians**"]
    if "obs_views" in scene.extras:
        lines.append(f"seen by >= 2 input views: {(scene.extras['obs_views'] >= 2).mean():.0%}")
    comp = scene.extras.get("completion")
    if comp is not None and not _known(comp):
        lines.append("completion n/a (voxel-merged)")
    elif comp is not None:
        unknown = np.isnan(comp)
        lines.append(f"completed by Stage II (> 0.25): {(comp[~unknown] > 0.25).sum() / len(comp):.0%}"
                     + (f", n/a for {unknown.mean():.0%} (grey)" if unknown.any() else ""))
    return "  \n".join(lines)


def colourings(extras: dict[str, np.ndarray]) -> tuple[str, ...]:
    """The "Colour by" choices for a scene's provenance columns: those present and not all NaN."""
    return tuple(c for c in COLOURINGS if c == "colour" or _known(extras.get(c.split()[0])))


def _known(column: np.ndarray | None) -> bool:
    """A provenance column to colour by: present, numeric and not all NaN (a voxel-merged prediction's completion)."""
    return (column is not None and column.dtype.kind in "iuf" and len(column) > 0
            and not np.isnan(column).all())


def _port(text: str) -> int:
    """argparse type: a TCP port (a port out of range used to fail in viser's server thread and hang the command).
    Not a number: argparse's "invalid int value" (it would name this function: "invalid _port value")."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port (0 to 65535; 0 picks a free one)")
    return port


def view_url(host: str, port: int) -> tuple[str, bool]:
    """``(url, every_interface)``: the address to open for a server listening on ``host``:``port``. An IPv6
    literal is bracketed (``http://[::1]:8080``); a wildcard host (``''``, ``0.0.0.0``, ``::``) serves every
    interface (``every_interface`` True) and gives this machine's loopback (127.0.0.1, or ``[::1]`` for ``::``)."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:  # a name (localhost, a host name), or '' (every interface)
        return (f"http://{host}:{port}", False) if host else (f"http://127.0.0.1:{port}", True)
    every = ip.is_unspecified
    if every:
        ip = ipaddress.ip_address("::1" if ip.version == 6 else "127.0.0.1")
    text = str(ip).replace("%", "%25")  # a scope id (fe80::1%eth0) is %25 in a URL (RFC 6874)
    return f"http://{f'[{text}]' if ip.version == 6 else text}:{port}", every


def view_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="anycity view", description="Open a predicted scene in the browser (viser).",
                                allow_abbrev=False)
    p.add_argument("path", help="scene.ply or a scene folder predict wrote (<--export.out_dir>/<scene>/)")
    p.add_argument("--host", default="127.0.0.1",
                   help="interface to listen on (default: %(default)s; 0.0.0.0 serves the network)")
    p.add_argument("--port", type=_port, default=8080,
                   help="port (default: %(default)s; 0: any free one; a busy one moves up)")
    p.add_argument("--no_cameras", "--no-cameras", action="store_true", help="hide the camera frustums")
    a = p.parse_args(refuse_unknown_flags(p, argv))
    server, scene = build_server(a.path, a.host, a.port, cameras=not a.no_cameras)
    url, every = view_url(a.host, server.get_port())
    print(f"anycity view: {scene.gaussians.num_gaussians:,} Gaussians at {url} (Ctrl-C to stop)", flush=True)
    if every:
        note = f"--host {a.host!r} serves on all interfaces; from another machine, open this one's address"
        print(f"anycity view: {note} at port {server.get_port()}", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        server.stop()
    return 0
