"""Preview grids, depth colouring, PLY and cameras.json export."""

import json

import numpy as np
import torch

from anycity.callbacks import depth_to_rgb, preview_grid
from anycity.export import load_ply, save_cameras, save_ply
from anycity.structures import Gaussians


def test_preview_grid_layout():
    a = torch.zeros(2, 3, 4, 5)
    b = torch.ones(2, 3, 4, 5)
    grid = preview_grid([a, b])
    assert grid.shape == (8, 10, 3) and grid.dtype == np.uint8
    assert grid[:, :5].max() == 0 and grid[:, 5:].min() == 255


def test_depth_to_rgb_near_is_bright_and_invalid_black():
    d = torch.tensor([[1.0, 2.0], [4.0, 0.0]]).reshape(1, 1, 2, 2)
    rgb = depth_to_rgb(d)
    assert rgb.shape == (1, 3, 2, 2)
    assert rgb[0, 0, 0, 0] > rgb[0, 0, 0, 1] > rgb[0, 0, 1, 0]
    assert rgb[0, :, 1, 1].abs().sum() == 0


def test_ply_round_trip(tmp_path):
    g = torch.Generator().manual_seed(0)
    n = 7
    quats = torch.nn.functional.normalize(torch.randn(1, n, 4, generator=g), dim=-1)
    gs = Gaussians(means=torch.randn(1, n, 3, generator=g), quats=quats, scales=torch.rand(1, n, 3, generator=g) + 0.1,
                   opacities=torch.rand(1, n, generator=g) * 0.9 + 0.05, sh=torch.randn(1, n, 4, 3, generator=g))
    gs.valid = torch.ones(1, n, dtype=torch.bool)
    gs.valid[0, 3] = False
    assert save_ply(gs, tmp_path / "s.ply") == 1
    back = load_ply(tmp_path / "s.ply")
    keep = gs.valid[0]
    torch.testing.assert_close(back.means[0], gs.means[0, keep])
    torch.testing.assert_close(back.scales[0], gs.scales[0, keep], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(back.opacities[0], gs.opacities[0, keep], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(back.sh[0], gs.sh[0, keep])  # channel-major f_rest survives the round trip
    torch.testing.assert_close(back.quats[0], quats[0, keep])


def test_cameras_json(tmp_path):
    w2c = torch.eye(4).repeat(2, 1, 1)
    K = torch.eye(3).repeat(2, 1, 1)
    save_cameras(tmp_path / "cameras.json", w2c, K, 64, 48)
    data = json.loads((tmp_path / "cameras.json").read_text())
    assert data["convention"] == "opencv_w2c" and len(data["views"]) == 2
    assert data["views"][1]["width"] == 64 and data["views"][0]["w2c"][3] == [0, 0, 0, 1]


def test_previews_go_to_the_logger_image_api_and_skip_the_log_dir_broadcast(tmp_path):
    from types import SimpleNamespace

    from anycity.callbacks import ImagePreviews

    calls = []

    class TB:  # TensorBoard-like: experiment.add_image
        log_dir = str(tmp_path / "tb")
        experiment = SimpleNamespace(add_image=lambda tag, img, step, dataformats: calls.append(("tb", tag, img.shape)))

    class WB:  # W&B-like: log_image
        experiment = None

        def log_image(self, key, images, step):
            calls.append(("wb", key, images[0].shape))

    class Trainer:
        is_global_zero, global_step, sanity_checking, default_root_dir = True, 7, False, str(tmp_path)
        logger, loggers = TB(), [TB(), WB()]

        @property
        def log_dir(self):  # a collective under DDP: the callback must not touch it
            raise AssertionError("trainer.log_dir broadcasts; only rank 0 gets here")

    out = {"preview": {"context": torch.rand(2, 3, 8, 8), "target": torch.rand(2, 3, 8, 8)}}
    ImagePreviews().on_validation_batch_end(Trainer(), None, out, None, 0)
    assert ("tb", "val/preview", (16, 16, 3)) in calls  # 2 rows x 2 columns of 8 px
    assert any(c[0] == "wb" and c[1] == "val/preview" for c in calls)
    first = tmp_path / "tb" / "previews" / "val_step000007.png"
    assert first.is_file()
    before = first.read_bytes()
    out = {"preview": {"context": torch.zeros(2, 3, 8, 8), "target": torch.ones(2, 3, 8, 8)}}
    ImagePreviews().on_validation_batch_end(Trainer(), None, out, None, 0)  # a later run at the same step
    assert (tmp_path / "tb" / "previews" / "val_step000007.1.png").read_bytes() == before  # kept, not overwritten
    assert first.read_bytes() != before


def test_samples_of_one_scene_do_not_overwrite_each_other(tmp_path):
    """A split holds several samples of a scene: each gets its own folder, per rank under DDP."""
    from types import SimpleNamespace

    from anycity.callbacks import PredictionExport
    from anycity.structures import Gaussians, RenderOutput

    n, v, h, w = 6, 2, 8, 8
    g = Gaussians(torch.rand(1, n, 3) + torch.tensor([0, 0, 3.0]), torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4),
                  torch.full((1, n, 3), 0.05), torch.full((1, n), 0.5), torch.zeros(1, n, 1, 3))
    imgs = torch.rand(1, v, 3, h, w)
    K = torch.tensor([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]]).expand(1, v, 3, 3)

    def predict(cb, trainer, scene, k):
        pred = {"gaussians": g, "w2c": torch.eye(4).expand(1, v, 4, 4), "K": K, "images": imgs, "scene": [scene],
                "renders": RenderOutput(rgb=imgs, depth=torch.ones(1, v, 1, h, w), alpha=torch.ones(1, v, 1, h, w))}
        cb.write_on_batch_end(trainer, None, pred, None, None, k)

    out = tmp_path / "out"
    cb = PredictionExport(out_dir=str(out), save_renders=False)
    for rank in (0, 1):
        trainer = SimpleNamespace(log_dir=None, default_root_dir=str(tmp_path), global_rank=rank)
        cb.on_predict_start(trainer, None)
        for k, scene in enumerate(["a", "b", "a", "a"]):
            predict(cb, trainer, scene, k)
    assert sorted(p.name for p in out.iterdir()) == ["a", "a-2", "a-3", "a-rank1", "a-rank1-2", "a-rank1-3", "b",
                                                     "b-rank1"]
    assert all((p / "scene.ply").is_file() and (p / "cameras.json").is_file() for p in out.iterdir())


def test_each_sample_of_a_batch_writes_its_own_gaussians(tmp_path):
    """A predict batch of 2 scenes: scene b's folder holds sample 1's Gaussians, not sample 0's."""
    from types import SimpleNamespace

    from anycity.callbacks import PredictionExport

    n, v, h, w = 5, 2, 8, 8
    means = torch.stack([torch.rand(n, 3) + torch.tensor([0, 0, 3.0]), torch.rand(n, 3) + torch.tensor([0, 0, 6.0])])
    g = Gaussians(means, torch.tensor([1.0, 0, 0, 0]).expand(2, n, 4), torch.full((2, n, 3), 0.05),
                  torch.full((2, n), 0.5), torch.zeros(2, n, 1, 3))
    K = torch.tensor([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]]).expand(2, v, 3, 3)
    pred = {"gaussians": g, "w2c": torch.eye(4).expand(2, v, 4, 4), "K": K, "images": torch.rand(2, v, 3, h, w),
            "scene": ["a", "b"], "renders": None}
    out = tmp_path / "out"
    cb = PredictionExport(out_dir=str(out), save_renders=False, smooth_3d=0)
    trainer = SimpleNamespace(log_dir=None, default_root_dir=str(tmp_path), global_rank=0)
    cb.on_predict_start(trainer, None)
    cb.write_on_batch_end(trainer, None, pred, None, {"scene": ["a", "b"]}, 0)
    for scene, (lo, hi) in (("a", (3, 4)), ("b", (6, 7))):
        z = load_ply(out / scene / "scene.ply").means[..., 2]
        assert z.numel() == n and bool(((z >= lo) & (z <= hi)).all()), (scene, z)
