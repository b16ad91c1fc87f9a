"""``anycity render-video``'s camera paths: the interpolated flight, the orbit's radius, height, start and up,
the frames' intrinsics, and its argument checks."""

import math
from types import SimpleNamespace

import pytest
import torch
from helpers.viewer_scenes import tiny_predict_folder

from anycity.viewer.scene import load_view_scene
from anycity.viewer.video import interpolate_path, orbit_path, render_frames, render_video_main, scene_up


def _look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)):
    """OpenCV w2c of a camera at ``eye`` looking at ``target`` with world ``up`` (z)."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = (target - eye) / (target - eye).norm()
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return torch.linalg.inv(c2w)


def _orbit_eyes(w2c):
    return torch.linalg.inv(w2c)[:, :3, 3]


K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])


def test_an_orbit_flight_gives_an_orbit_at_its_radius_and_height():
    # 24 cameras circling the site: their mean position is above the centre, and the orbit must not collapse there.
    w2c = torch.stack([_look_at((10 * math.cos(t), 10 * math.sin(t), 6.0))
                       for t in torch.linspace(0, 2 * math.pi, 25)[:-1].tolist()])
    ow, oK = orbit_path(w2c, K.expand(24, 3, 3), torch.zeros(3), 8)
    eyes = _orbit_eyes(ow)
    assert torch.allclose(eyes[:, :2].norm(dim=-1), torch.full((8,), 10.0, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(eyes[:, 2], torch.full((8,), 6.0, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(eyes[0], torch.tensor([10.0, 0, 6], dtype=torch.float64), atol=1e-6)  # the first camera
    optical = torch.linalg.inv(ow)[:, :3, 2]
    toward = -eyes / eyes.norm(dim=-1, keepdim=True)
    assert torch.allclose(optical, toward, atol=1e-6)  # each frame looks at the centre
    assert (-torch.linalg.inv(ow)[:, 2, 1] > 0.1).all()  # the image's up (-y) points up: no frame upside down
    assert oK.shape == (8, 3, 3) and torch.equal(oK[3], K.double())


def test_cameras_on_one_side_start_the_orbit_on_their_side():
    w2c = torch.stack([_look_at((8.0, y, 5.0)) for y in (-1.0, 0.0, 1.0)])
    eyes = _orbit_eyes(orbit_path(w2c, K.expand(3, 3, 3), torch.zeros(3), 4, torch.tensor([0.0, 0, 1]))[0])
    assert torch.allclose(eyes[:, 2], torch.full((4,), 5.0, dtype=torch.float64), atol=1e-6)
    r = torch.tensor([65.0, 64.0, 65.0]).sqrt().mean().item()
    assert torch.allclose(eyes[:, :2].norm(dim=-1), torch.full((4,), r, dtype=torch.float64), atol=1e-6)
    assert eyes[0, 0] > 8.0 and abs(eyes[0, 1]) < 1e-6


def test_a_nadir_grid_orbits_above_the_ground():
    """Straight-down cameras: their own "up" (-y) lies on the ground, so the orbit's axis comes from the scene: the
    normal of the Gaussians' ground plane, turned towards the cameras."""
    w2c = torch.stack([_look_at((x, y, 20.0), (x, y, 0.0), up=(0.0, 1.0, 0.0))
                       for x in (-6.0, 0.0, 6.0) for y in (-6.0, 0.0, 6.0)])
    g = torch.Generator().manual_seed(0)
    means = torch.cat([torch.rand(2000, 2, generator=g) * 20 - 10, torch.rand(2000, 1, generator=g)], -1)
    c2w = torch.linalg.inv(w2c)
    camera_up = -c2w[:, :3, 1].mean(0)
    assert abs(float(camera_up[2])) < 1e-6  # the cameras' mean "up" is horizontal here
    up = scene_up(means, c2w[:, :3, 3], camera_up)
    assert torch.allclose(up, torch.tensor([0.0, 0, 1], dtype=torch.float64), atol=0.05)
    centre = means.median(0).values
    eyes = _orbit_eyes(orbit_path(w2c, K.expand(9, 3, 3), centre, 6, up)[0])
    assert (eyes[:, 2] > 15).all()  # at the flight's height, not through the ground
    # a tall, narrow scene is not flat: the cameras' own "up" is kept
    tower = torch.cat([torch.rand(2000, 2, generator=g), torch.rand(2000, 1, generator=g) * 30], -1)
    assert torch.allclose(scene_up(tower, c2w[:, :3, 3], camera_up), camera_up / camera_up.norm())


def test_the_ground_normal_is_turned_towards_the_cameras():
    g = torch.Generator().manual_seed(0)
    ground = torch.cat([torch.rand(2000, 2, generator=g) * 20 - 10, torch.rand(2000, 1, generator=g)], -1)
    side = torch.tensor([1.0, 0, 0])
    assert scene_up(ground, torch.tensor([[0.0, 0, 20]]), side)[2] > 0.95
    assert scene_up(ground, torch.tensor([[0.0, 0, -20]]), side)[2] < -0.95  # a flight below the scene: down


def _yaw(deg):
    """w2c [4, 4] of a camera at the origin turned ``deg`` degrees about z."""
    a = math.radians(deg)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return w2c


def test_the_flight_turns_the_short_way():
    """Yaw +170 -> -170 is a 20 degree turn through 180, not 340 through 0."""
    w2c, _ = interpolate_path(torch.stack([_yaw(170), _yaw(-170)]), K.expand(2, 3, 3), 2)
    mid = torch.linalg.inv(w2c[1])
    assert abs(abs(math.degrees(math.atan2(mid[1, 0], mid[0, 0]))) - 180) < 1e-6


def test_the_flight_moves_the_centre_and_intrinsics_linearly_and_ends_at_the_last_camera():
    w2c = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    w2c[1, 0, 3] = -1.0  # centre x = 1
    Ks = torch.stack([K, 2 * K])
    Ks[1, 2, 2] = 1
    path, pK = interpolate_path(w2c, Ks, 4)
    xs = torch.linalg.inv(path)[:, 0, 3]
    torch.testing.assert_close(xs, torch.tensor([0, 0.25, 0.5, 0.75, 1], dtype=torch.float64))
    torch.testing.assert_close(pK[:, 0, 0], torch.tensor([50.0, 62.5, 75, 87.5, 100], dtype=torch.float64))


def test_frames_wider_than_the_inputs_scale_the_intrinsics(tmp_path, monkeypatch):
    """--width 96 for 48x32 inputs: K's focal lengths and principal point double with the frame."""
    import anycity.render

    scene = load_view_scene(tiny_predict_folder(tmp_path, n=20), thumbs=False)
    seen = []

    def render(g, w2c, K, width, height, **kwargs):
        seen.append(K)
        return SimpleNamespace(rgb=torch.zeros(1, 1, 3, height, width))

    monkeypatch.setattr(anycity.render, "render", render)
    frames = list(render_frames(scene, scene.w2c[:1], scene.K[:1], 96, 64, progress=False))
    assert frames[0].shape == (64, 96, 3)
    torch.testing.assert_close(seen[0][0, 0], torch.tensor([[80.0, 0, 48], [0, 80, 32], [0, 0, 1]]))


@pytest.mark.parametrize("args, name", [(["--per-segment", "0"], "--per_segment/--per-segment"),
                                        (["--fps", "0"], "--fps"), (["--orbit", "-1"], "--orbit"),
                                        (["--width", "1"], "--width")])
def test_nonsense_arguments_stop_with_the_option_named(tmp_path, capsys, args, name):
    with pytest.raises(SystemExit):
        render_video_main([str(tmp_path), *args])
    assert f"argument {name}: " in capsys.readouterr().err


@pytest.fixture
def _no_scene_load(monkeypatch):
    """render-video must refuse a bad --out before loading (and rendering) the scene."""
    from anycity.viewer import video

    def load(*args, **kwargs):
        raise AssertionError("the scene was loaded before --out was checked")

    monkeypatch.setattr(video, "load_view_scene", load)


@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
@pytest.mark.parametrize("name", ["vids", "clip.mp4"])
def test_an_out_that_is_a_folder_is_refused_up_front(tmp_path, capsys, _no_scene_load, name, overwrite):
    """It failed only after every frame was rendered, naming a hidden temp file (or said "exists, pass
    --overwrite")."""
    from anycity.cli import main

    pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / name
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    assert main(["render-video", str(tmp_path), "--out", str(out), *overwrite]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--out {out} is a folder" in err and len(err.splitlines()) == 1 and ".anycity-tmp" not in err
    assert (out / "keep.txt").read_text() == "user data"
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


@pytest.mark.parametrize("name", ["flythrough", "fly.gif", "fly.webm", "fly.mp4.part"])
def test_an_out_with_no_video_suffix_is_refused_up_front(tmp_path, capsys, _no_scene_load, name):
    from anycity.cli import main

    pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / name
    assert main(["render-video", str(tmp_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--out {out}: " in err and ".mp4, .m4v, .mkv, .mov" in err and len(err.splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["fly.mp4", "fly.MKV", "fly.mov", "fly.m4v"])
def test_video_suffixes_ffmpeg_writes_h264_into_pass(tmp_path, name):
    from anycity.viewer.video import check_video_out

    check_video_out(tmp_path / name)
