import math

import pytest
import torch

from anycity.city import (
    ChunkedScene,
    ChunkGeometry,
    PlyStream,
    align_chunks,
    apply_sim3,
    order_from_descriptors,
    owners,
    plan_chunks,
    robust_sim3,
    sim3_gaussians,
    sim3_inverse,
    w2c_to_world,
)
from anycity.city.oracle import camera_errors, oracle_chunks, orbit_scene, random_sim3
from anycity.export import load_ply
from anycity.structures import Gaussians


def _merged_cameras(chunks, S, plan):
    own = owners(plan)
    n = max(own) + 1
    w2c = torch.zeros(n, 4, 4, dtype=torch.float64)
    for v, k in own.items():
        w2c[v] = w2c_to_world(chunks[k].w2c[chunks[k].views.index(v)], S[k])
    return w2c


def test_plan_chunks_overlap_and_cover():
    plan = plan_chunks(20, 8, 3)
    assert all(len(c) == 8 for c in plan) and plan[0][0] == 0 and plan[-1][-1] == 19
    assert all(len(set(a) & set(b)) >= 3 for a, b in zip(plan, plan[1:]))
    assert plan_chunks(5, 8, 3) == [list(range(5))]
    own = owners(plan)
    assert sorted(own) == list(range(20))
    assert own[5] == 0 and own[7] == 1  # 7 is chunk 0's last view but sits inside chunk 1
    with pytest.raises(ValueError, match="overlap"):
        plan_chunks(20, 8, 8)
    # consecutive chunks align on >= 2 shared photos: said before the network runs, not after every chunk
    with pytest.raises(ValueError, match="20 photos in chunks of 8 need an overlap of at least 2 .*got 1"):
        plan_chunks(20, 8, 1)
    assert plan_chunks(8, 8, 0) == [list(range(8))]  # one chunk: nothing to align



def test_a_view_equally_central_in_two_chunks_is_owned_by_the_earlier():
    """owners' documented tie rule: view 3 sits 1 view from an end in both chunks; taking it from the later chunk
    would make ownership depend on the chunk loop's tie handling."""
    own = owners([[0, 1, 2, 3, 4], [2, 3, 4, 5, 6]])
    assert own[3] == 0
    assert own[2] == 0 and own[4] == 1  # 2 is central in chunk 0, 4 in chunk 1


def test_order_from_descriptors_recovers_a_shuffled_sequence():
    t = torch.linspace(0, 3, 30)
    desc = torch.stack([t.cos(), t.sin(), 0.2 * t], -1)  # a smooth curve: neighbours are similar
    perm = torch.randperm(30, generator=torch.Generator().manual_seed(0))
    order = order_from_descriptors(desc[perm])
    seq = perm[order].tolist()
    assert seq == list(range(30)) or seq == list(range(29, -1, -1))


def test_robust_sim3_rejects_outliers_and_degenerate_sets():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(200, 3, generator=g, dtype=torch.float64)
    T = random_sim3(g)
    dst = src @ T[:3, :3].T + T[:3, 3]
    dst[:40] += torch.randn(40, 3, generator=g, dtype=torch.float64) * 50  # 20 % gross outliers
    fit = robust_sim3(src, dst)
    assert fit.num_inliers == 160 and not fit.inliers[:40].any()
    assert torch.allclose(fit.T, T, atol=1e-8)
    line = torch.linspace(0, 1, 10, dtype=torch.float64)[:, None] * torch.tensor([[1.0, 2, 3]], dtype=torch.float64)
    with pytest.raises(ValueError, match="degenerate"):
        robust_sim3(line, line * 2)


def test_oracle_chunks_merge_to_ground_truth_up_to_one_sim3():
    w2c, pts = orbit_scene(40, points_per_view=32)
    plan = plan_chunks(40, 10, 3)
    chunks, _ = oracle_chunks(w2c, pts, plan, seed=3)
    S, edges, rep = align_chunks(chunks)
    assert len(edges) == len(plan) - 1 and all(e.fit.num_inliers == e.fit.inliers.numel() for e in edges)
    err = camera_errors(_merged_cameras(chunks, S, plan), w2c)
    assert err["w2c_max_abs"] < 1e-4 and err["pos_rel_max"] < 1e-4, err
    assert rep["final_rms"] < 1e-6


def test_pose_graph_spreads_error_over_extra_edges():
    # overlap > size/2: every view is in up to 3 chunks, so the graph has more edges than a chain
    w2c, pts = orbit_scene(36, points_per_view=32, seed=1)
    plan = plan_chunks(36, 8, 5)
    chunks, _ = oracle_chunks(w2c, pts, plan, seed=4, rot_deg=0.5, centre_noise=0.005, depth_noise=0.01)
    S_chain, edges, _ = align_chunks(chunks, global_pass=False)
    S_graph, _, rep = align_chunks(chunks)
    assert len(edges) > len(plan) - 1
    e_chain = camera_errors(_merged_cameras(chunks, S_chain, plan), w2c)
    e_graph = camera_errors(_merged_cameras(chunks, S_graph, plan), w2c)
    assert rep["final_rms"] < rep["initial_rms"]
    assert e_graph["pos_rel_mean"] < e_chain["pos_rel_mean"], (e_chain, e_graph)


@pytest.mark.parametrize("noise", [0.001, 0.01])
def test_noise_degrades_gracefully(noise):
    w2c, pts = orbit_scene(40, points_per_view=32)
    plan = plan_chunks(40, 10, 3)
    chunks, _ = oracle_chunks(w2c, pts, plan, seed=5, rot_deg=30 * noise, centre_noise=noise, depth_noise=noise)
    S, _, _ = align_chunks(chunks)
    err = camera_errors(_merged_cameras(chunks, S, plan), w2c)
    # error of the same order as the noise, not piled up along the 5 chunks
    assert err["pos_rel_mean"] < 5 * noise and err["rot_deg_mean"] < 30 * 5 * noise, err


def test_alignment_failure_names_the_chunks():
    w2c, pts = orbit_scene(20, points_per_view=8)
    plan = [list(range(0, 10)), list(range(9, 20))]  # one shared view
    chunks, _ = oracle_chunks(w2c, pts, plan)
    with pytest.raises(ValueError, match=r"chunks 0 and 1 \(shared photos: p9\).*predict_chunk_overlap"):
        align_chunks(chunks, names=[f"p{i}" for i in range(20)])


def _gaussians(n, deg=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(torch.randn(1, n, 3, generator=g), torch.nn.functional.normalize(torch.randn(1, n, 4, generator=g),
                     dim=-1), torch.rand(1, n, 3, generator=g) + 0.1, torch.rand(1, n, generator=g),
                     torch.randn(1, n, (deg + 1) ** 2, 3, generator=g))


@pytest.mark.parametrize("deg", [1, 2, 3, 4])
def test_sim3_gaussians_rotates_view_dependent_colour(deg):
    from anycity.render.sh import sh_basis

    g = _gaussians(5, deg)
    T = random_sim3(torch.Generator().manual_seed(1))
    moved = sim3_gaussians(g, T)
    R = T[:3, :3] / torch.linalg.det(T[:3, :3]) ** (1 / 3)
    d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    before = (sh_basis(d, deg)[:, None] @ g.sh[0])[:, 0]
    after = (sh_basis(d @ R.float().T, deg)[:, None] @ moved.sh[0])[:, 0]
    assert torch.allclose(before, after, atol=1e-4)
    torch.testing.assert_close(moved.sh[..., 0, :], g.sh[..., 0, :])  # the base colour does not turn
    back = sim3_gaussians(moved, sim3_inverse(T))
    assert torch.allclose(back.means, g.means, atol=1e-4) and torch.allclose(back.scales, g.scales, atol=1e-5)



def _wxyz_to_matrix(q):
    """The standard unit-quaternion (w, x, y, z) rotation matrix, written out (Hamilton convention)."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).unflatten(-1, (3, 3))


def test_sim3_gaussians_moves_each_covariance():
    """A Sim(3) (s, R, t) maps a Gaussian N(mu, Sigma) to N(s R mu + t, s^2 R Sigma R^T): unscaled sizes or a rotation
    composed on the wrong side would warp every merged chunk's splats."""
    g = torch.Generator().manual_seed(7)
    n = 16
    gs = Gaussians(torch.randn(1, n, 3, generator=g, dtype=torch.float64),
                   torch.nn.functional.normalize(torch.randn(1, n, 4, generator=g, dtype=torch.float64), dim=-1),
                   torch.rand(1, n, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.3, 0.05],
                                                                                       dtype=torch.float64) + 0.01,
                   torch.rand(1, n, generator=g, dtype=torch.float64),
                   torch.zeros(1, n, 1, 3, dtype=torch.float64))
    s, t = 2.5, torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64), dim=0)
    a = math.radians(70)
    kx = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64) + math.sin(a) * kx + (1 - math.cos(a)) * kx @ kx  # Rodrigues
    S = torch.eye(4, dtype=torch.float64)
    S[:3, :3], S[:3, 3] = s * R, t
    out = sim3_gaussians(gs, S)

    def cov(q, sc):
        Rq = _wxyz_to_matrix(q[0])
        return Rq @ torch.diag_embed(sc[0] ** 2) @ Rq.transpose(-1, -2)

    torch.testing.assert_close(out.means[0], gs.means[0] @ (s * R).T + t, atol=1e-10, rtol=0)
    torch.testing.assert_close(cov(out.quats, out.scales), s ** 2 * R @ cov(gs.quats, gs.scales) @ R.T,
                               atol=1e-10, rtol=0)


def test_chunked_scene_writes_one_ply_and_cameras(tmp_path):
    h = w = 4
    w2c, _ = orbit_scene(12)
    plan = plan_chunks(12, 6, 3)
    rng = torch.Generator().manual_seed(0)
    scene = ChunkedScene(plan, [f"im{i}.png" for i in range(12)], (h, w), points_per_side=3, workdir=tmp_path)
    K = torch.tensor([[4.0, 0, 2], [0, 4, 2], [0, 0, 1]]).expand(6, 3, 3)
    from anycity.geometry.projection import unproject_depth

    for k, views in enumerate(plan):
        G = random_sim3(rng)
        cams = w2c_to_world(w2c[views], G).float()
        depth = 5 + torch.rand(1, 6, 1, h, w, generator=rng)  # depth of the view in its own camera
        means = unproject_depth(depth, K[None], cams[None]).reshape(1, -1, 3)
        g = _gaussians(6 * h * w, seed=k)
        g.means = means
        scene.add(k, g, cams, K)
    # one Gaussian per pixel of every photo: overlapping views are not doubled
    rep = scene.finish(tmp_path / "out")
    loaded = load_ply(tmp_path / "out" / "scene.ply")
    assert loaded.num_gaussians == 12 * h * w == rep["gaussians"]
    assert (tmp_path / "out" / "cameras.json").is_file() and (tmp_path / "out" / "chunks.json").is_file()
    assert not list(tmp_path.glob("anycity_city_*")), "spill folder removed"
    assert rep["num_chunks"] == len(plan) and all(p["inliers"] > 0 for p in rep["pairs"])


def _noisy_chunks_report(tmp_path, chunk_scale: dict[int, float]) -> dict:
    """``ChunkedScene`` over 12 orbit photos in 3 chunks, each in its own random Sim(3) frame (chunk k's scaled by
    ``chunk_scale[k]`` more) with 2 % depth noise; returns its chunks.json report."""
    from anycity.city.align import sim3_parts
    from anycity.geometry.projection import unproject_depth

    h = w = 4
    w2c, _ = orbit_scene(12)
    plan = plan_chunks(12, 6, 3)
    K = torch.tensor([[4.0, 0, 2], [0, 4, 2], [0, 0, 1]], dtype=torch.float64).expand(6, 3, 3)
    rng = torch.Generator().manual_seed(0)
    depth_world = 5 + torch.rand(12, 1, h, w, generator=rng, dtype=torch.float64)  # one scene for every chunk
    scene = ChunkedScene(plan, [f"im{i}.png" for i in range(12)], (h, w), points_per_side=3, workdir=tmp_path)
    for k, views in enumerate(plan):
        G = torch.diag(torch.tensor([chunk_scale.get(k, 1.0)] * 3 + [1.0], dtype=torch.float64)) @ random_sim3(rng)
        cams = w2c_to_world(w2c[views], G)
        noise = 1 + 0.02 * torch.randn(len(views), 1, h, w, generator=rng, dtype=torch.float64)
        depth = depth_world[views] * sim3_parts(G)[0] * noise
        g = _gaussians(6 * h * w, seed=k)
        g.means = unproject_depth(depth[None], K[None], cams[None]).reshape(1, -1, 3).float()
        scene.add(k, g, cams.float(), K.float())
    return scene.finish(tmp_path / f"out{len(list(tmp_path.iterdir()))}")


def test_pair_residuals_are_in_chunk_0s_units_whatever_scale_each_chunk_has(tmp_path):
    """A pair's fit is measured in its first chunk's frame; chunks.json says chunk 0's units, so it rescales."""
    plain, scaled = _noisy_chunks_report(tmp_path, {}), _noisy_chunks_report(tmp_path, {1: 10.0})
    assert [p["chunks"] for p in plain["pairs"]] == [[0, 1], [1, 2]]
    for a, b in zip(plain["pairs"], scaled["pairs"], strict=True):
        assert a["rms_residual"] > 0
        for key in ("rms_residual", "median_residual", "inlier_threshold", "pose_graph_rms"):
            assert b[key] == pytest.approx(a[key], rel=1e-3), (key, a, b)
    # a chain: the pose graph keeps the pairwise fits, and its rms is theirs pooled, in the same units
    for rep in (plain, scaled):
        pairs = rep["pairs"]
        assert all(p["pose_graph_rms"] == pytest.approx(p["rms_residual"], rel=1e-6) for p in pairs)
        pooled = math.sqrt(sum(p["rms_residual"] ** 2 for p in pairs) / len(pairs))
        assert rep["pose_graph"]["final_rms"] == pytest.approx(pooled, rel=1e-6)
        assert rep["pose_graph"]["dropped_pairs"] == []


def test_a_loop_chunk_too_small_to_align_is_refused_before_the_network_runs():
    with pytest.raises(ValueError, match=r"predict_loop: the loop-closure chunk shares 1 photo\(s\) .*raise "
                                         "predict_chunk_size to 4"):
        plan_chunks(10, 3, 2, loop=True)
    assert plan_chunks(10, 4, 2, loop=True)[-1] == [8, 9, 0, 1]


def test_cameras_on_a_straight_strip_are_scored_without_a_free_roll():
    from anycity.city.oracle import random_rotation
    from anycity.geometry.alignment import sim3_matrix

    g = torch.Generator().manual_seed(0)
    xs = torch.linspace(-20, 20, 8, dtype=torch.float64)
    gt = torch.stack([torch.linalg.inv(_c2w_looking_down_forward(float(x))) for x in xs])
    T = sim3_matrix(torch.tensor(2.5, dtype=torch.float64), random_rotation(g), torch.tensor([3.0, -1, 7]))
    err = camera_errors(w2c_to_world(gt, T), gt)  # perfect cameras in another frame
    assert err["rot_deg_max"] < 1e-6 and err["pos_rel_max"] < 1e-9, err


def _c2w_looking_down_forward(x: float) -> torch.Tensor:
    """A camera at (x, 0, 50) pitched 30 degrees forward of nadir along +x (OpenCV axes)."""
    a = math.radians(30)
    z = torch.tensor([math.sin(a), 0.0, -math.cos(a)], dtype=torch.float64)  # looking down, ahead
    y = torch.tensor([math.cos(a), 0.0, math.sin(a)], dtype=torch.float64)
    y = -y  # image "down" points back along the strip
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = torch.linalg.cross(y, z), y, z
    c2w[:3, 3] = torch.tensor([x, 0.0, 50.0], dtype=torch.float64)
    return c2w


def test_chunked_scene_failure_leaves_no_ply(tmp_path):
    w2c, _ = orbit_scene(8)
    plan = [list(range(0, 5)), list(range(4, 8))]  # one shared view: alignment must fail
    scene = ChunkedScene(plan, [f"im{i}.png" for i in range(8)], (2, 2), workdir=tmp_path)
    K = torch.eye(3).expand(5, 3, 3)
    for k, views in enumerate(plan):
        scene.add(k, _gaussians(len(views) * 4), w2c[views].float(), K[: len(views)])
    with pytest.raises(ValueError, match="chunks 0 and 1"):
        scene.finish(tmp_path / "out")
    assert not list((tmp_path / "out").glob("*")) if (tmp_path / "out").exists() else True


def test_ply_stream_matches_save_ply(tmp_path):
    from anycity.export import save_ply

    g = _gaussians(10)
    save_ply(g, tmp_path / "a.ply")
    s = PlyStream(tmp_path / "b.ply")
    s.write(Gaussians(g.means[:, :4], g.quats[:, :4], g.scales[:, :4], g.opacities[:, :4], g.sh[:, :4]))
    s.write(Gaussians(g.means[:, 4:], g.quats[:, 4:], g.scales[:, 4:], g.opacities[:, 4:], g.sh[:, 4:]))
    s.close()
    assert (tmp_path / "a.ply").read_bytes()[-400:] == (tmp_path / "b.ply").read_bytes()[-400:]
    a, b = load_ply(tmp_path / "a.ply"), load_ply(tmp_path / "b.ply")
    assert torch.equal(a.means, b.means) and torch.equal(a.sh, b.sh)
    assert not list(tmp_path.glob("*.tmp"))


def test_a_piece_whose_every_gaussian_is_dropped_adds_no_rows(tmp_path):
    g, bad = _gaussians(6), _gaussians(3, seed=1)
    bad.scales.zero_()  # every row invalid: dropped, as save_ply drops them
    with PlyStream(tmp_path / "s.ply") as s:
        s.write(g)
        s.write(bad)
    assert (s.count, s.dropped) == (6, 3)
    assert torch.equal(load_ply(tmp_path / "s.ply").means, g.means)


def test_token_descriptors_are_per_photo():
    from anycity.city.plan import token_descriptors
    from anycity.models import build_network

    torch.manual_seed(0)
    net = build_network("tiny").eval()
    imgs = torch.rand(5, 3, 28, 28)
    imgs[3] = imgs[1]
    d = token_descriptors(net, lambda idx: imgs[idx], 5, batch=2)
    assert d.shape[0] == 5 and torch.allclose(d[1], d[3], atol=1e-5) and not torch.allclose(d[0], d[1])


def test_loop_closure_chunk_adds_a_cycle_and_owns_nothing():
    plan = plan_chunks(40, 10, 3, loop=True)
    assert plan[-1] == list(range(35, 40)) + list(range(5))
    assert all(k != len(plan) - 1 for k in owners(plan).values())
    w2c, pts = orbit_scene(120, points_per_view=64, arc=1.0)
    errs = []
    for loop in (False, True):
        p = plan_chunks(120, 16, 4, loop=loop)
        chunks, _ = oracle_chunks(w2c, pts, p, seed=0, rot_deg=0.3, centre_noise=0.01, depth_noise=0.01)
        S, edges, rep = align_chunks(chunks)
        errs.append(camera_errors(_merged_cameras(chunks, S, p), w2c))
    assert rep["dropped_pairs"] == []  # a consistent loop is used
    assert errs[1]["pos_rel_max"] < errs[0]["pos_rel_max"] and errs[1]["rot_deg_mean"] < errs[0]["rot_deg_mean"]


def test_a_loop_over_two_chunks_gets_its_loop_chunk():
    """28 photos in chunks of 16/4 are 2 chunks: predict_loop was ignored there, silently."""
    plan = plan_chunks(28, 16, 4, loop=True)
    assert plan == [list(range(16)), list(range(12, 28)), list(range(20, 28)) + list(range(8))]
    assert sorted(owners(plan)) == list(range(28)) and all(k < 2 for k in owners(plan).values())
    w2c, pts = orbit_scene(28, points_per_view=32, arc=1.0)
    chunks, _ = oracle_chunks(w2c, pts, plan, seed=0, depth_noise=0.003)
    S, edges, rep = align_chunks(chunks)
    assert {(e.a, e.b) for e in edges} == {(0, 1), (0, 2), (1, 2)} and rep["dropped_pairs"] == []
    assert camera_errors(_merged_cameras(chunks, S, plan), w2c)["pos_rel_max"] < 0.01
    assert plan_chunks(16, 16, 4, loop=True) == [list(range(16))]  # one pass sees both ends already


def test_each_spill_file_is_deleted_once_its_rows_are_in_the_ply(tmp_path, monkeypatch):
    """They stayed until the scene was written: the disk held the spill, the PLY body and the PLY (3x the scene)."""
    from anycity.geometry.projection import unproject_depth

    h = w = 4
    w2c, _ = orbit_scene(12)
    plan = plan_chunks(12, 6, 3)
    scene = ChunkedScene(plan, [f"im{i}.png" for i in range(12)], (h, w), points_per_side=3, out=tmp_path / "out")
    K = torch.tensor([[4.0, 0, 2], [0, 4, 2], [0, 0, 1]]).expand(6, 3, 3)
    depth = 5 + torch.rand(1, 12, 1, h, w, generator=torch.Generator().manual_seed(0))  # one scene for all chunks
    for k, views in enumerate(plan):
        g = _gaussians(6 * h * w, seed=k)
        g.means = unproject_depth(depth[:, views], K[None], w2c[None, views].float()).reshape(1, -1, 3)
        scene.add(k, g, w2c[views].float(), K)
    spilled = []
    write, close = PlyStream.write, PlyStream.close

    def spy_write(self, *args):
        spilled.append(sorted(p.name for p in scene.spill.glob("chunk_*.pt")))
        return write(self, *args)

    def spy_close(self):
        spilled.append(sorted(p.name for p in scene.spill.glob("chunk_*.pt")))
        return close(self)

    monkeypatch.setattr(PlyStream, "write", spy_write)
    monkeypatch.setattr(PlyStream, "close", spy_close)
    scene.finish(tmp_path / "out")
    names = [f"chunk_{k:05d}.pt" for k in range(3)]
    assert spilled == [names, names[1:], names[2:], []]


def _with_sky(chunks, rows: int = 1, seed: int = 7):
    """The chunks with the first ``rows`` grid rows of every view pushed 5 to 50 times as far along their rays, by
    other factors in each chunk: sky or horizon pixels of oblique photos, which each chunk's pass puts at its own
    depth."""
    from anycity.geometry.cameras import camera_centers

    g, out = torch.Generator().manual_seed(seed), []
    for c in chunks:
        k, cc, p = 8 * rows, camera_centers(c.w2c), c.points.clone()
        f = torch.empty(p.shape[0], k, dtype=torch.float64).uniform_(5, 50, generator=g)
        p[:, :k] = cc[:, None] + (p[:, :k] - cc[:, None]) * f[..., None]
        out.append(ChunkGeometry(c.views, c.w2c, p))
    return out


def _first_cameras(chunks, S, n):
    """World cameras ``[n, 4, 4]`` from the first chunk holding each photo (a loop chunk holds none first)."""
    own = {}
    for k, c in enumerate(chunks):
        for i, v in enumerate(c.views):
            own.setdefault(v, w2c_to_world(c.w2c[i], S[k]))
    return torch.stack([own[v] for v in range(n)])


def test_far_points_that_disagree_between_chunks_do_not_loosen_the_fit():
    """One grid row of sky points per view dragged the points' mean away: the inlier threshold (5 % of the median
    distance to it) grew ~17x, the sky points became inliers and the cameras came out 5x worse."""
    n = 60
    w2c, pts = orbit_scene(n)
    chunks, _ = oracle_chunks(w2c, pts, plan_chunks(n, 16, 4), rot_deg=0.3, centre_noise=0.01, depth_noise=0.01)
    S, edges, _ = align_chunks(chunks)
    S_sky, edges_sky, _ = align_chunks(_with_sky(chunks))
    clean, sky = camera_errors(_first_cameras(chunks, S, n), w2c), camera_errors(_first_cameras(chunks, S_sky, n), w2c)
    assert sky["rot_deg_mean"] < 1.5 * clean["rot_deg_mean"] and sky["pos_rel_max"] < 1.5 * clean["pos_rel_max"], (
        clean, sky)
    assert all(b.fit.threshold < 1.5 * a.fit.threshold for a, b in zip(edges, edges_sky))


def test_sky_points_do_not_hide_a_broken_loop_chunk():
    """A loop chunk whose halves are a random Sim(3) apart was kept with one row of sky points (the inflated
    threshold blinded the pose graph's check): 31 degrees mean rotation error, only a loop-correction warning."""
    n = 120
    w2c, pts = orbit_scene(n, arc=1.0)
    chunks, _ = oracle_chunks(w2c, pts, plan_chunks(n, 16, 4, loop=True), rot_deg=0.09, centre_noise=0.003,
                              depth_noise=0.003)
    L, h, E = chunks[-1], 8, random_sim3(torch.Generator().manual_seed(9))
    w, p = L.w2c.clone(), L.points.clone()
    w[h:], p[h:] = w2c_to_world(w[h:], E), apply_sim3(E, p[h:])
    chunks[-1] = ChunkGeometry(L.views, w, p)
    with pytest.warns(UserWarning, match="the loop-closure chunk 10 .* disagrees with the chain"):
        S, _, rep = align_chunks(_with_sky(chunks))
    assert rep["dropped_pairs"] == [[0, 10]]
    err = camera_errors(_first_cameras(chunks, S, n), w2c)
    assert err["rot_deg_mean"] < 0.5 and err["pos_rel_max"] < 0.02, err


def test_chunks_of_two_are_refused_naming_the_chunk_size():
    """Chunks of 2 were accepted, but no overlap worked for more than 2 photos, and the two overlap errors
    contradicted each other (overlap 1: "need at least 2"; overlap 2: "expected 0..1")."""
    for overlap in (0, 1, 2, 4):
        with pytest.raises(ValueError, match=r"^predict_chunk_size: 5 photos in chunks of 2 cannot be aligned .*"
                                             r"raise predict_chunk_size to 3 or more$"):
            plan_chunks(5, 2, overlap)
    assert plan_chunks(2, 2, 0) == [[0, 1]]  # one pass of 2 still works
    assert plan_chunks(5, 3, 2) == [[0, 1, 2], [1, 2, 3], [2, 3, 4]]
    with pytest.raises(ValueError, match=r"^predict_chunk_overlap: expected 2\.\.2 \(below the chunk size 3\), got 3$"):
        plan_chunks(5, 3, 3)


def test_the_overlap_of_a_folder_that_fits_one_pass_is_not_checked():
    """A folder that fits one pass was refused over the overlap it never uses (chunk size 3, default overlap 4)."""
    assert plan_chunks(3, 3, 4) == [[0, 1, 2]]
    assert plan_chunks(10, 16, 16) == [list(range(10))]
    with pytest.raises(ValueError, match=r"^predict_chunk_overlap: expected >= 0 .*got -1$"):
        plan_chunks(3, 3, -1)


def _timed_jpegs(folder, times):
    import numpy as np
    from PIL import Image

    for i, t in enumerate(times):
        exif = Image.Exif()
        if t:
            exif[306] = t  # DateTime
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / f"DJI_{i:04d}.jpg", exif=exif)
    return sorted(folder.iterdir())


def test_order_by_time_names_the_photos_that_share_a_capture_time(tmp_path):
    """It said "two photos has no (distinct) EXIF capture time": in a folder of 2,000 photos, which two?"""
    from anycity.city import order_photos

    files = _timed_jpegs(tmp_path, ["2024:05:01 10:00:00", "2024:05:01 10:00:02", "2024:05:01 10:00:04",
                                    "2024:05:01 10:00:02", "2024:05:01 10:00:04"])
    assert order_photos(files, "auto") == ([0, 1, 2, 3, 4], "name")
    with pytest.raises(ValueError, match=r"^predict_order 'time': DJI_0001\.jpg and DJI_0003\.jpg share the capture "
                                         r"time 2024:05:01 10:00:02; use predict_order 'name' or 'auto'$"):
        order_photos(files, "time")


def test_order_by_time_names_a_photo_without_a_capture_time(tmp_path):
    from anycity.city import order_photos

    files = _timed_jpegs(tmp_path, ["2024:05:01 10:00:00", None, "2024:05:01 10:00:04"])
    with pytest.raises(ValueError, match=r"^predict_order 'time': DJI_0001\.jpg has no EXIF capture time; use "):
        order_photos(files, "time")
