"""ChunkedScene end to end on oracle chunks: which rows, cameras and transforms each photo's output comes from."""

import json

import pytest
import torch

from anycity.city import (
    ChunkedScene,
    PlyStream,
    align_chunks,
    apply_sim3,
    owners,
    plan_chunks,
    robust_sim3,
    w2c_to_world,
)
from anycity.city.align import ChunkGeometry, sim3_parts
from anycity.city.oracle import camera_errors, oracle_chunks, orbit_scene, random_sim3
from anycity.export import load_ply
from anycity.geometry.projection import unproject_depth
from anycity.structures import Gaussians


def _tagged_gaussians(means: torch.Tensor, views: list[int], hw: int) -> Gaussians:
    """Gaussians at ``means [1, N, 3]`` whose opacity ``(photo + 1) / 20`` tags the photo of each pixel."""
    m = means.shape[1]
    op = ((torch.tensor(views, dtype=torch.float32) + 1) / 20).repeat_interleave(hw)[None]
    return Gaussians(means.float(), torch.tensor([1.0, 0, 0, 0]).expand(1, m, 4), torch.full((1, m, 3), 0.01), op,
                     torch.zeros(1, m, 1, 3))


def test_each_photo_comes_from_its_owning_chunk_moved_by_that_chunks_transform(tmp_path):
    """12 photos in chunks of 6 sharing 3, each chunk in its own random Sim(3) frame, portrait 6x4 views, a focal
    per photo: the merged scene is the true one in chunk 0's frame, with every photo's h*w Gaussians once, its own
    K and the views' width and height."""
    h, w, n = 6, 4, 12
    gt, _ = orbit_scene(n)
    plan = plan_chunks(n, 6, 3)
    K = torch.tensor([[4.0, 0, 2], [0, 4, 3], [0, 0, 1]], dtype=torch.float64).repeat(n, 1, 1)
    K[:, 0, 0] += torch.arange(n) * 0.25
    K[:, 1, 1] += torch.arange(n) * 0.25
    rng = torch.Generator().manual_seed(0)
    depth = 5 + torch.rand(n, 1, h, w, generator=rng, dtype=torch.float64)
    world = unproject_depth(depth[None], K[None], gt[None]).reshape(-1, 3)
    scene = ChunkedScene(plan, [f"p{i}.jpg" for i in range(n)], (h, w), points_per_side=3, workdir=tmp_path)
    G = []
    for k, views in enumerate(plan):
        G.append(random_sim3(rng))
        cams = w2c_to_world(gt[views], G[k])
        means = unproject_depth(depth[views][None] * sim3_parts(G[k])[0], K[views][None], cams[None])
        scene.add(k, _tagged_gaussians(means.reshape(1, -1, 3), views, h * w), cams.float(), K[views].float())
    rep = scene.finish(tmp_path / "out")
    ply = load_ply(tmp_path / "out" / "scene.ply")
    tag = (ply.opacities[0] * 20 - 1).round().long()
    assert torch.bincount(tag, minlength=n).tolist() == [h * w] * n
    expected = apply_sim3(G[0], world)[torch.argsort(tag, stable=True).argsort()]  # photo order -> PLY order
    assert float((ply.means[0].double() - expected).abs().max()) < 1e-5 * float(expected.abs().max())
    cams = json.loads((tmp_path / "out" / "cameras.json").read_text())["views"]
    assert [(c["width"], c["height"]) for c in cams] == [(w, h)] * n
    torch.testing.assert_close(torch.tensor([c["K"] for c in cams], dtype=torch.float64), K, atol=1e-5, rtol=0)
    assert [c["owned"] for c in rep["chunks"]] == [5, 3, 4]


def test_finish_without_every_chunk_names_the_missing_ones_and_writes_nothing(tmp_path):
    w2c, _ = orbit_scene(12)
    plan = plan_chunks(12, 6, 3)
    scene = ChunkedScene(plan, [f"p{i}" for i in range(12)], (2, 2), workdir=tmp_path)
    for k in (0, 2):
        means = torch.randn(1, 24, 3)
        scene.add(k, _tagged_gaussians(means, plan[k], 4), w2c[plan[k]].float(), torch.eye(3).expand(6, 3, 3))
    with pytest.raises(ValueError, match=r"chunks \[1\] were never added"):
        scene.finish(tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_ply_stream_counts_the_dropped_rows_of_every_piece(tmp_path):
    def gaussians(m, zero):
        g = Gaussians(torch.randn(1, m, 3), torch.tensor([1.0, 0, 0, 0]).expand(1, m, 4).clone(),
                      torch.full((1, m, 3), 0.1), torch.full((1, m), 0.5), torch.zeros(1, m, 1, 3))
        g.scales[0, :zero] = 0  # a zero scale is dropped
        return g

    with PlyStream(tmp_path / "s.ply") as s:
        for zero in (1, 2, 0):
            s.write(gaussians(5, zero))
    assert (s.count, s.dropped) == (12, 3)


def test_non_finite_points_in_a_shared_view_are_left_out_of_its_fit():
    w2c, pts = orbit_scene(20, points_per_view=32)
    plan = plan_chunks(20, 8, 3)
    chunks, _ = oracle_chunks(w2c, pts, plan, seed=1)
    p = chunks[1].points.clone()
    p[0, 0], p[1, 3, 2] = float("nan"), float("inf")  # views 5 and 6: shared with chunk 0
    chunks[1] = ChunkGeometry(chunks[1].views, chunks[1].w2c, p)
    S, edges, _ = align_chunks(chunks)
    assert len(edges) == 3 and all(torch.isfinite(e.src).all() for e in edges)
    own = owners(plan)
    merged = torch.stack([w2c_to_world(chunks[k].w2c[chunks[k].views.index(v)], S[k]) for v, k in sorted(own.items())])
    assert camera_errors(merged, w2c)["pos_rel_max"] < 1e-4


def test_robust_sim3_never_returns_fewer_inliers_than_asked():
    """The refits can shrink the inlier set below min_inliers after the loop's check: the final check catches it."""
    for seed in range(400):
        g = torch.Generator().manual_seed(seed)
        src = torch.randn(9, 3, generator=g, dtype=torch.float64)
        T = random_sim3(g)
        dst = src @ T[:3, :3].T + T[:3, 3]
        dst = dst + torch.randn(9, 3, generator=g, dtype=torch.float64) * 0.08 * T[:3, :3].det() ** (1 / 3)
        try:
            fit = robust_sim3(src, dst, min_inliers=6, trials=64)
        except ValueError:
            continue
        assert fit.num_inliers >= 6, seed
