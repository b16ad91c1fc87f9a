"""The CLI end to end on CUDA: Stage I fit -> Stage II fit -> test (every protocol) -> predict (shards and a chunked
photo folder), tiny preset, bf16-mixed and 32-true (AdamW foreach and fused). What ``test_cli_tiny.py`` checks on
CPU, on the GPU path.

Skipped without CUDA; ``make gpu-check`` runs it. The renderer is "auto": gsplat when it is installed, else the
PyTorch backend (with its warning).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

if not torch.cuda.is_available():
    pytest.skip("needs CUDA", allow_module_level=True)

from anycity.cli import build_cli  # noqa: E402


@pytest.fixture(autouse=True)
def _argv(monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])  # LightningCLI warns when sys.argv also carries arguments


def _args(root, run_dir, stage2_from=None, steps=4, precision="bf16-mixed"):
    a = ["-c", "configs/quickstart.yaml"]
    if stage2_from:
        # every Stage II option
        a += ["-c", "configs/quickstart_stage2.yaml", "--model.init_args.init_from", str(stage2_from),
              "--model.init_args.net", '{"camera_trunk_depth": 2, "video_prior": "wan-tiny", "wan_lora_rank": 2, '
              '"refine_cameras": true, "camera_video": true, "pose_prior": "random", "pose_prior_mix": true}',
              "--model.init_args.camera_weight", "5"]
    return a + [
        "--data.root", str(root), "--data.image_size", "[32, 32]", "--data.num_context", "2",
        "--data.num_targets", "1", "--data.num_dense", "2",
        "--trainer.accelerator", "gpu", "--trainer.precision", precision,
        "--trainer.max_steps", str(steps), "--trainer.val_check_interval", str(steps),
        "--trainer.limit_val_batches", "1",
        "--trainer.default_root_dir", str(run_dir), "--trainer.logger.init_args.save_dir", str(run_dir),
        "--model.init_args.warmup_steps", "1", "--model.init_args.camera_refine_steps", "2",
        "--model.init_args.eval_pose_align_steps", "2",
    ]


@pytest.mark.parametrize("precision", ["bf16-mixed", "32-true"])
def test_fit_test_predict_on_cuda(tiny_shards, tmp_path, precision):
    s1 = tmp_path / "s1"
    cli = build_cli(["fit", *_args(tiny_shards, s1, precision=precision)])
    # (Lightning moves the module back to the CPU when fit ends: ask the strategy where it ran)
    assert cli.trainer.global_step == 4 and cli.trainer.strategy.root_device.type == "cuda"
    assert {bool(g["fused"]) for g in cli.trainer.optimizers[0].param_groups} == {precision == "32-true"}
    ckpt1 = s1 / "checkpoints" / "last.ckpt"
    state1 = torch.load(ckpt1, map_location="cpu", weights_only=True)["state_dict"]
    assert all(torch.isfinite(v).all() for v in state1.values() if v.is_floating_point())

    s2 = tmp_path / "s2"
    cli = build_cli(["fit", *_args(tiny_shards, s2, stage2_from=ckpt1, precision=precision)])
    assert cli.trainer.global_step == 4 and cli.trainer.strategy.root_device.type == "cuda"
    ckpt2 = s2 / "checkpoints" / "last.ckpt"
    state2 = torch.load(ckpt2, map_location="cpu", weights_only=True)["state_dict"]
    assert any("lora_A" in k for k in state2) and any(k.startswith("net.pose_prior.") for k in state2)
    for k in (k for k in state1 if k.startswith("net.aggregator.")):  # the scaffold stays frozen on the GPU too
        torch.testing.assert_close(state2[k], state1[k], msg=k)

    t = tmp_path / "test"
    cli = build_cli(["test", *_args(tiny_shards, t, stage2_from=ckpt1, precision=precision), "--ckpt_path", str(ckpt2),
                     "--model.init_args.eval_joint", "true"])
    metrics = cli.trainer.callback_metrics
    for key in ("test/psnr_scaffold", "test/psnr_refined", "test/psnr_refined_camrefine",
                "test/psnr_refined_targetalign", "test/psnr_refined_joint", "test/rre_refined_camrefine",
                "test/rre_scaffold"):
        assert torch.isfinite(metrics[key]), key

    p = tmp_path / "pred"
    build_cli(["predict", *_args(tiny_shards, p, stage2_from=ckpt1, precision=precision), "--ckpt_path", str(ckpt2),
               "--export.out_dir", str(p / "out")])
    scene = sorted((p / "out").iterdir())[0]
    assert (scene / "scene.ply").stat().st_size > 1000
    assert len(json.loads((scene / "cameras.json").read_text())["views"]) == 2

    photos = tmp_path / "my_photos"  # more photos than one chunk: chunks aligned and merged on the GPU path
    photos.mkdir()
    for i in range(7):
        pixels = np.random.default_rng(i).integers(0, 255, (40, 56, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(photos / f"{i:02d}.jpg")
    build_cli(["predict", *_args(tiny_shards, p, stage2_from=ckpt1), "--ckpt_path", str(ckpt2),
               "--data.predict_images", str(photos), "--data.predict_chunk_size", "4",
               "--data.predict_chunk_overlap", "2", "--export.out_dir", str(p / "mine")])
    out = p / "mine" / "my_photos"
    assert len(json.loads((out / "cameras.json").read_text())["views"]) == 7
    assert (out / "scene.ply").stat().st_size > 1000 and (out / "chunks.json").is_file()
