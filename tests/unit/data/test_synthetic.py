import json
import math
import sys
import tarfile

import numpy as np
import pytest
import torch
import webdataset as wds

from anycity.data.city import make_city
from anycity.data.cli import data_main
from anycity.data.raycast import SceneTensors, fov_intrinsics, look_at, render
from anycity.data.synthetic import parse_size, render_scene, render_view, synth, trajectory
from anycity.geometry import project_points, unproject_depth


def _view(sc, eye, target, h=48, w=64):
    K = torch.tensor(fov_intrinsics(w, h, 60.0), dtype=torch.float32)
    w2c = torch.tensor(look_at(eye, target), dtype=torch.float32)
    return render(sc, w2c, K, h, w), w2c, K


def test_depth_is_exact_and_multiview_consistent():
    sc = SceneTensors(make_city(np.random.default_rng(0)))
    a, w2c_a, K = _view(sc, [150, -120, 160], [0, 0, 0])
    b, w2c_b, _ = _view(sc, [158, -112, 165], [2, 0, 0])  # a nearby view: few occlusions
    assert a["mask"].float().mean() > 0.9
    pts = unproject_depth(a["depth"][None, None], K, w2c_a)[0].reshape(-1, 3)
    pts = pts[a["mask"].reshape(-1)]
    uv, z = project_points(pts, w2c_b, K)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 64) & (uv[:, 1] >= 0) & (uv[:, 1] < 48) & (z > 0)
    g = uv[inside] / torch.tensor([64.0, 48.0]) * 2 - 1  # bilinear lookup (align_corners=False: centres at +0.5)
    zb = torch.nn.functional.grid_sample(b["depth"][None, None], g[None, None], align_corners=False)[0, 0, 0]
    rel = (zb - z[inside]).abs() / z[inside]
    # visible points agree (occlusion edges, and interpolation across them, differ at this tiny size)
    assert rel.median() < 1e-3 and (rel < 0.01).float().mean() > 0.75
    uv_a, z_a = project_points(pts, w2c_a, K)  # the same camera reproduces its own depth exactly
    assert torch.allclose(z_a, a["depth"][a["mask"]], rtol=1e-4)
    # camera-frame normals are unit length and face the camera
    n = a["normal"][a["mask"]]
    rays = unproject_depth(torch.ones(1, 1, 48, 64), K, torch.eye(4))[0][a["mask"]]
    assert torch.allclose(n.norm(dim=-1), torch.ones(len(n)), atol=1e-3)
    assert ((n * rays).sum(-1) < 0).float().mean() > 0.99


def test_ground_hit_exact():
    sc = SceneTensors(make_city(np.random.default_rng(1), n_blocks=4))
    out, w2c, K = _view(sc, [3000, 0, 10], [3000, 0, 0])  # nadir over the countryside: ground at 10 m
    assert torch.allclose(out["depth"][out["mask"]], torch.tensor(10.0), rtol=1e-4)
    assert torch.allclose(out["normal"][24, 32], torch.tensor([0.0, 0.0, -1.0]), atol=1e-3)
    sky, _, _ = _view(sc, [0, -500, 50], [0, 1000, 300])
    assert not sky["mask"][0].any() and (sky["depth"][0] == 0).all()


def test_boxes_behind_a_street_level_camera_are_not_hit():
    """A camera standing beside a building, looking along its wall: the boxes behind it (and the one it stands
    next to, half behind) must not be hit at a negative ray distance; every depth is >= 0 and every hit > 0."""
    city = make_city(np.random.default_rng(0))
    sc = SceneTensors(city)
    i = int(np.argmax(city.box_hi[:, 2] - city.box_lo[:, 2]))  # the tallest building
    lo, hi = city.box_lo[i], city.box_hi[i]
    eye = [float(hi[0]) + 3.0, float(lo[1] + hi[1]) / 2, 2.0]
    out, _, _ = _view(sc, eye, [eye[0], eye[1] + 50, 2.0])
    assert out["mask"].any()
    assert (out["depth"] >= 0).all() and (out["depth"][out["mask"]] > 0).all()


@pytest.mark.parametrize("kind", ["orbit", "nadir", "mixed"])
def test_trajectories(kind):
    city = make_city(np.random.default_rng(2))
    w2c, used = trajectory(kind, 12, city, np.random.default_rng(5))
    fwd = w2c[:, 2, :3]  # camera z axis in world coordinates
    pitch = np.degrees(np.arcsin(-fwd[:, 2]))
    if used == "orbit":
        assert ((pitch > 25) & (pitch < 65)).all()
    elif used == "nadir":
        assert (pitch > 85).all()
    centres = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
    assert (centres[:, 2] > city.max_height).all()


def _rows(n):
    rows = max(1, round(math.sqrt(n)))
    return rows, math.ceil(n / rows)


def test_nadir_views_keep_the_flight_heading_up_when_tilted():
    """The top of a nadir image points along the flight line, also for the views whose tilt jitter takes them past
    look_at's vertical threshold (|f_z| < 0.999; about 1 in 100 views rolled up to 140 deg before)."""
    city = make_city(np.random.default_rng(2))
    _, cols = _rows(48)
    worst = 0.0
    for s in range(40):
        w2c, used = trajectory("nadir", 48, city, np.random.default_rng([0, s]))
        assert used == "nadir"
        for k in range(48):
            fwd = 1.0 if (k // cols) % 2 == 0 else -1.0
            up = -w2c[k, 1, :2] / np.linalg.norm(w2c[k, 1, :2])  # image up (minus the camera's y axis), xy
            worst = max(worst, math.degrees(math.acos(np.clip(up[0] * fwd, -1, 1))))
    assert worst < 10


def test_oblique_lawnmower_camera_steps_forward_at_every_view():
    """The pitch jitter moves the look-at point, not the camera (a camera drawn per view went backwards in a few
    percent of the steps); the pitch stays 45 +- 4 deg."""
    city = make_city(np.random.default_rng(2))
    _, cols = _rows(48)
    backwards, pitch = [], []
    for s in range(20):
        w2c, used = trajectory("oblique", 48, city, np.random.default_rng([0, s]))
        assert used == "oblique"
        c = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
        fwd = np.where((np.arange(47) // cols) % 2 == 0, 1.0, -1.0)
        same_line = (np.arange(1, 48) % cols) != 0
        backwards += [(s, k) for k in np.flatnonzero(same_line & ((c[1:, 0] - c[:-1, 0]) * fwd <= 0))]
        pitch.append(np.degrees(np.arcsin(-w2c[:, 2, 2])))
    assert backwards == []
    assert ((np.concatenate(pitch) > 40.99) & (np.concatenate(pitch) < 49.01)).all()


def test_scene_deterministic_and_learnable():
    a = render_scene(7, 1, 3, (24, 32), "orbit")
    b = render_scene(7, 1, 3, (24, 32), "orbit")
    c = render_scene(7, 2, 3, (24, 32), "orbit")
    assert all(np.array_equal(x.image, y.image) for x, y in zip(a.views, b.views))
    assert not np.array_equal(a.views[0].image, c.views[0].image)
    assert a.views[0].image.std() > 20  # structured, not flat


def test_supersample_box_filters_colour_and_keeps_centre_depth():
    sc = SceneTensors(make_city(np.random.default_rng(3)))
    K = torch.tensor(fov_intrinsics(32, 24, 60.0), dtype=torch.float32)
    w2c = torch.tensor(look_at([140, -110, 150], [0, 0, 0]), dtype=torch.float32)
    ss = render_view(sc, w2c, K, 24, 32, supersample=2)
    fine = render(sc, w2c, K * torch.tensor([[2.0], [2.0], [1.0]]), 48, 64)["rgb"]
    centre = render(sc, w2c, K, 24, 32, aa=False)
    # colour: the mean of each pixel's 2x2 sub-pixel rays; depth, normals, mask: the pixel-centre ray
    assert torch.allclose(ss["rgb"], fine.view(24, 2, 32, 2, 3).mean(dim=(1, 3)), atol=1e-6)
    assert torch.equal(ss["depth"], centre["depth"]) and torch.equal(ss["mask"], centre["mask"])
    one = render_view(sc, w2c, K, 24, 32)
    # box filtering removes sub-pixel texture energy: the image is smoother than one ray per pixel
    grad = lambda im: (im[1:] - im[:-1]).abs().mean() + (im[:, 1:] - im[:, :-1]).abs().mean()  # noqa: E731
    assert grad(ss["rgb"]) < grad(one["rgb"])
    with pytest.raises(ValueError, match="supersample"):
        synth("/nonexistent", scenes=1, supersample=0)


def test_hfov_sets_the_intrinsics():
    rec = render_scene(7, 1, 2, (24, 32), "orbit", hfov=40.0)
    fx = rec.views[0].K[0, 0]
    assert fx == pytest.approx(16 / math.tan(math.radians(20)))
    assert rec.extra["hfov_deg"] == 40.0
    assert fov_intrinsics(64, 48, 60.0)[:2, 2].tolist() == [32.0, 24.0]  # the image centre, pixel edges at integers
    with pytest.raises(ValueError, match="hfov"):
        synth("/nonexistent", scenes=1, hfov=200)


def test_parse_size():
    assert parse_size("64x96") == (64, 96)
    assert parse_size("128") == (128, 128)
    with pytest.raises(ValueError, match="HxW"):
        parse_size("64x")


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "s"
    assert data_main(["synth", "--out", str(out), "--scenes", "1", "--views", "3", "--size", "24x32", "--preview",
                      "--workers", "1", "--trajectory", "nadir"]) == 0
    assert (out / "preview.png").stat().st_size > 1000
    index = json.loads((out / "index.json").read_text())
    assert index["scenes"][0]["num_views"] == 3
    sample = next(iter(wds.WebDataset(str(out / index["shards"][0]["path"]), shardshuffle=False)))
    meta = json.loads(sample["cameras.json"])
    assert meta["units"] == "metres" and len(meta["views"]) == 3 and "000.depth.npy" in sample
    # normals only on request; the sky mask is depth > 0, so it is not stored
    assert "000.normal.npy" not in sample and "000.mask.png" not in sample and meta["views"][0]["normal"] is None
    K = np.array(meta["views"][0]["K"])
    assert math.isclose(K[0, 2], 16) and math.isclose(K[1, 2], 12)
    out2 = tmp_path / "n"
    assert data_main(["synth", "--out", str(out2), "--scenes", "1", "--views", "6", "--size", "24x32", "--workers",
                      "1", "--normals", "--window", "4", "--stride", "2"]) == 0
    index = json.loads((out2 / "index.json").read_text())
    assert [s["first"] for s in index["samples"]] == [0, 2]
    sample = next(iter(wds.WebDataset(str(out2 / index["shards"][0]["path"]), shardshuffle=False)))
    assert sample["__key__"].endswith("_w0000") and "003.normal.npy" in sample and "004.jpg" not in sample


def test_a_set_a_sample_cannot_be_built_from_is_refused(tmp_path):
    """One view per city (or per converted sample) gives shards that fit fails on later; refused at the start."""
    import pytest

    from anycity.data.parsers import convert
    from anycity.data.synthetic import synth

    with pytest.raises(ValueError, match="views >= 2, got scenes=2, views=1"):
        synth(tmp_path / "a", scenes=2, views=1, size="16x16")
    with pytest.raises(ValueError, match="max_views: expected >= 2 views per sample, got 1"):
        convert("colmap", tmp_path, tmp_path / "b", max_views=1)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_bad_window_and_depth_dtype_are_refused_before_a_scene_is_rendered(tmp_path, monkeypatch):
    import anycity.data.synthetic as synthetic

    def no_render(*a, **k):
        raise AssertionError("rendered a scene before refusing the settings")

    monkeypatch.setattr(synthetic, "render_scene", no_render)
    with pytest.raises(ValueError, match=r"window: expected .*stride=30"):
        synth(tmp_path / "a", scenes=3, views=48, size="16x16", workers=1, window=24, stride=30)
    with pytest.raises(ValueError, match=r"depth_dtype: expected one of \('float16', 'float32'\)"):
        synth(tmp_path / "b", scenes=1, views=2, size="16x16", workers=1, depth_dtype="uint8")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_negative_seed_is_refused_naming_it_before_the_out_folder_is_made(tmp_path, capsys):
    """numpy's "expected non-negative integer" named neither --seed nor the fix, after --out was created."""
    with pytest.raises(ValueError, match=r"^seed: expected an integer >= 0, got -1; pass --seed 0 or more$"):
        synth(tmp_path / "a", scenes=1, views=2, size="16x16", workers=1, seed=-1)
    from anycity.cli import main

    assert main(["data", "synth", "--out", str(tmp_path / "b"), "--scenes", "1", "--views", "2", "--size", "16x16",
                 "--workers", "1", "--seed", "-3"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "seed: expected an integer >= 0, got -3; pass --seed 0 or more" in err[0], err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_preview_in_a_folder_whose_name_is_not_utf8(tmp_path, child, latin1_path):
    """``--out`` with a latin-1 name (``caf\\xe9``): OpenCV 5's imwrite crashed the process (SIGSEGV) on the
    surrogate-escaped path of preview.png, after the shards were written."""
    import os

    out = latin1_path(tmp_path, b"caf\xe9")
    os.rmdir(out)
    child("import sys; from anycity.data.cli import data_main\n"
          "sys.exit(data_main(['synth', '--out', sys.argv[1], '--scenes', '1', '--views', '2', '--size', '16x16', "
          "'--workers', '1', '--trajectory', 'orbit', '--preview']))", out)
    names = sorted(os.listdir(os.fsencode(out)))
    assert names == [b"index.json", b"preview.png", b"train-000000.tar"], names
    with open(os.path.join(os.fsencode(out), b"preview.png"), "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_two_identical_runs_write_identical_bytes(tmp_path):
    import time

    for name in ("a", "b"):
        synth(tmp_path / name, scenes=1, views=2, size="16x16", workers=1, trajectory="orbit")
        time.sleep(1.1 if name == "a" else 0)  # tar members used to carry the time of the run
    files = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "b").iterdir()) and "index.json" in files
    assert all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)


def test_synth_to_folder_reads_the_shards_the_index_lists(tmp_path):
    """Another ``*.tar`` in the folder (an earlier set's shard, a backup) is not mixed into the photo folder."""
    import shutil

    from helpers.scripts import load_script

    synth(tmp_path / "a", scenes=1, views=3, size="16x16", workers=1, trajectory="orbit", seed=1)
    synth(tmp_path / "b", scenes=1, views=5, size="16x16", workers=1, trajectory="orbit", seed=2)
    shutil.copy(tmp_path / "b" / "train-000000.tar", tmp_path / "a" / "old-000000.tar")
    assert load_script("synth_to_folder").main([str(tmp_path / "a"), str(tmp_path / "photos")]) == 0
    views = json.loads((tmp_path / "photos" / "cameras_gt.json").read_text())["views"]
    meta = json.loads(next(iter(wds.WebDataset(str(tmp_path / "a" / "train-000000.tar"),
                                               shardshuffle=False)))["cameras.json"])
    assert [v["w2c"] for v in views] == [v["w2c"] for v in meta["views"]]
    assert sorted(p.name for p in (tmp_path / "photos" / "photos").iterdir()) == [f"view_{i:04d}.jpg" for i in range(3)]


def test_split_assignment_is_pinned():
    """A scene's split depends on --scenes (a held-out set needs another --seed, see `anycity data synth --help`);
    the assignment itself stays as it was, so existing sets and the quickstart's held-out cities keep their splits."""
    from anycity.data.writer import split_scenes

    s = split_scenes(80, 0)  # the quickstart's set
    assert [i for i, x in enumerate(s) if x == "val"] == [5, 9, 19, 36, 50, 53, 64, 66]
    assert [i for i, x in enumerate(s) if x == "test"] == [8, 11, 13, 16, 20, 52, 65, 74]
    assert split_scenes(1, 0) == ["train"] and split_scenes(80, 0)[0] == "train"


def test_synth_to_folder_writes_one_named_scene_and_refuses_old_photos(tmp_path, capsys):
    """A set of several scenes used to give the first scene's views (the others' dropped: they share the indices)
    and a rerun mixed in an earlier run's photos."""
    from helpers.scripts import load_script

    synth(tmp_path / "a", scenes=2, views=3, size="16x16", workers=1, trajectory="orbit", seed=1)
    run = load_script("synth_to_folder").main
    index = json.loads((tmp_path / "a" / "index.json").read_text())
    keys = [sc["key"] for sc in index["scenes"]]
    with pytest.raises(SystemExit) as e:
        run([str(tmp_path / "a"), str(tmp_path / "p")])
    assert e.value.code == 2 and f"pass --scene KEY, one of {', '.join(keys)}" in capsys.readouterr().err
    assert run([str(tmp_path / "a"), str(tmp_path / "p"), "--scene", keys[1]]) == 0
    views = json.loads((tmp_path / "p" / "cameras_gt.json").read_text())["views"]
    sample = next(s for s in index["samples"] if s["scene"] == keys[1])
    with tarfile.open(tmp_path / "a" / sample["shard"]) as tar:
        meta = json.loads(tar.extractfile(f"{sample['key']}.cameras.json").read())
    assert [v["w2c"] for v in views] == [v["w2c"] for v in meta["views"]]
    with pytest.raises(SystemExit):
        run([str(tmp_path / "a"), str(tmp_path / "p"), "--scene", keys[0]])
    assert f"{tmp_path / 'p' / 'photos'} is not empty" in capsys.readouterr().err


def test_a_failure_in_the_main_process_cancels_the_queued_scenes(tmp_path, monkeypatch):
    """``--workers N``: a failed write (a full disk) used to wait until every queued scene had been rendered, only
    to throw them away (minutes at the default 64 scenes of 48 views of 256 px)."""
    import errno
    from concurrent.futures import ProcessPoolExecutor

    import anycity.data.synthetic as synthetic
    from anycity.data.writer import ShardSetWriter

    futures, shutdowns = [], []

    class Recording(ProcessPoolExecutor):
        def submit(self, *a, **k):
            futures.append(super().submit(*a, **k))
            return futures[-1]

        def shutdown(self, wait=True, *, cancel_futures=False):
            shutdowns.append((cancel_futures, sum(not f.done() for f in futures)))
            super().shutdown(wait, cancel_futures=cancel_futures)

    def full(self, rec, split="train"):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(synthetic, "ProcessPoolExecutor", Recording)
    monkeypatch.setattr(ShardSetWriter, "write", full)
    with pytest.raises(OSError, match="No space left"):
        synth(tmp_path / "s", scenes=40, views=8, size="96x96", workers=2, window=None)
    assert len(futures) == 40
    # no bound on how many finished first (that depends on the machine's load): the shutdown cancels the queue, and
    # every scene still pending then but the two running and the three in the pool's call queue is not rendered
    assert [c for c, _ in shutdowns] == [True], shutdowns
    pending = shutdowns[0][1]
    assert sum(f.cancelled() for f in futures) >= pending - 5, ([f._state for f in futures], pending)
    assert not list((tmp_path / "s").iterdir())  # no shard, no lock


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the process tree from /proc")
@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_render_workers_exit_when_the_main_process_is_killed(tmp_path, sig):
    """``kill -9`` (or an OOM kill, or a plain ``kill``) of ``anycity data synth --workers 2`` reaches only its own
    pid: its render workers kept rendering with no parent, 30 s later still."""
    import os
    import signal
    import subprocess
    import time
    from pathlib import Path

    out = tmp_path / "s"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    main = subprocess.Popen([sys.executable, "-c", "import sys; from anycity.data.synthetic import synth; "
                             "synth(sys.argv[1], scenes=400, views=4, size='32x32', workers=2, window=None)", str(out)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def alive(pid):
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    workers = []
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob("*.tar*")):  # a scene was written: the workers are rendering
            assert main.poll() is None and time.monotonic() < deadline, "synth ended or wrote nothing in 120 s"
            time.sleep(0.2)
        workers = [int(k) for k in Path(f"/proc/{main.pid}/task/{main.pid}/children").read_text().split()
                   if b"multiprocessing" in Path(f"/proc/{k}/cmdline").read_bytes()]
        assert len(workers) >= 2  # the render workers (and the resource tracker, if one runs)
        main.send_signal(getattr(signal, sig))
        main.wait()
        deadline = time.monotonic() + 10
        while any(alive(k) for k in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [k for k in workers if alive(k)], f"render workers still running 10 s after {sig} of their parent"
    finally:
        main.kill()
        main.wait()
        for k in workers:
            if alive(k):
                os.kill(k, signal.SIGKILL)


def test_seed_and_scene_index_do_not_alias():
    """Scene 1 of seed 0 and scene 0 of seed 1 are different scenes (a seed + index rng made them the same)."""
    a = render_scene(0, 1, 2, (16, 16), "orbit")
    b = render_scene(1, 0, 2, (16, 16), "orbit")
    assert not np.allclose(a.views[0].w2c, b.views[0].w2c)


class _MidRng:
    """Every draw at its distribution's centre: a trajectory without jitter."""

    def uniform(self, lo, hi, size=None):
        return (lo + hi) / 2 if size is None else np.full(size, (lo + hi) / 2)

    def normal(self, loc, scale, size=None):
        return loc if size is None else np.full(size, float(loc))


def test_an_orbit_spreads_its_views_evenly_around_the_whole_circle():
    """n views 360/n deg apart: the last view is one step before the first, not on top of it."""
    n = 8
    w2c, _ = trajectory("orbit", n, make_city(np.random.default_rng(2)), _MidRng())
    centres = -np.einsum("nji,nj->ni", w2c[:, :3, :3], w2c[:, :3, 3])
    az = np.arctan2(centres[:, 1], centres[:, 0])  # the jitter-free orbit centres on the origin
    steps = np.degrees(np.angle(np.exp(1j * (np.roll(az, -1) - az))))
    np.testing.assert_allclose(steps, 360 / n, atol=1e-6)


def test_depth_beyond_float16_range_is_invalid(monkeypatch):
    """A camera 2 m over the ground, away from the city, whose centre row (odd height: the optical axis) dips 1e-5
    below the horizon: its ground hits at z-depth 2e5 m, beyond float16 range, get depth 0 and mask False."""
    import anycity.data.synthetic as synthetic

    eye = np.array([0.0, 1e4, 2.0])
    w2c = look_at(eye, eye + np.array([0.0, 1.0, -1e-5]))
    monkeypatch.setattr(synthetic, "trajectory", lambda kind, n, city, rng: (np.stack([w2c] * n), "orbit"))
    v = render_scene(0, 0, 1, (9, 9), "orbit").views[0]
    assert not v.mask[4].any() and (v.depth[4] == 0).all()
    assert v.mask[5:].all() and 0 < v.depth[5:].max() <= 6e4  # the nearer ground, one pixel lower, stays valid
