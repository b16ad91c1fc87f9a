"""The first-CUDA-machine check (``make gpu-check``): one table of what a cluster job needs to know.

    python scripts/gpu_check.py [--vggt /path/model.pt] [--wan-dir /path/Wan2.2-TI2V-5B-Diffusers] [--steps 20]

1. ``pytest tests/gpu`` (the CUDA renderer tests, and fit -> test -> predict through the CLI on CUDA);
2. gsplat vs the pure-PyTorch backend on one scene (max |difference|, forward+backward time of each);
3. ``steps`` optimiser steps of ``configs/stage1.yaml`` and of ``configs/stage2.yaml`` at the paper's size
   (vggt-1b, 4 context + 12 views at 448x448, bf16-mixed, one GPU), random init unless weights are given; Stage II
   without ``--wan-dir`` uses a randomly initialised Wan 2.2 TI2V-5B of the published shape;
4. inference on 32 views at 448x448.
It prints step time, peak memory and inference time as one table. On a machine without CUDA it refuses in one line.
``--smoke-cpu`` runs the same code at toy size on CPU (tiny preset, 64 px, 2 steps; no tests/gpu, no gsplat): the
test suite uses it to keep this script working without a GPU.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _peak_gb(dev: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated(dev) / 1e9 if dev.type == "cuda" else None


def _reset_peak(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(dev)


def check_gpu_tests() -> tuple[str, str]:
    proc = subprocess.run([sys.executable, "-m", "pytest", "tests/gpu", "-p", "no:warnings"], cwd=ROOT,
                          capture_output=True, text=True)
    last = (proc.stdout.strip().splitlines() or ["(no output)"])[-1]
    return ("pass" if proc.returncode == 0 else "FAIL"), last


def check_backends(dev: torch.device, n: int = 200_000, size: int = 448) -> str:
    """gsplat vs the torch backend on one n-Gaussian scene; without gsplat, the torch backend alone."""
    from anycity.render import render
    from anycity.render.api import _module_available
    from anycity.structures import Gaussians

    g = torch.Generator().manual_seed(0)
    means = torch.randn(1, n, 3, generator=g) * 0.5 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.nn.functional.normalize(torch.randn(1, n, 4, generator=g), dim=-1)
    scales = torch.rand(1, n, 3, generator=g) * 0.01 + 0.002
    opac = torch.rand(1, n, generator=g)
    sh = torch.rand(1, n, 1, 3, generator=g)
    w2c = torch.eye(4).expand(1, 4, 4, 4).clone()
    w2c[:, :, 0, 3] = torch.linspace(-0.2, 0.2, 4)
    f = size * 400 / 448
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]]).expand(1, 4, 3, 3)
    out, times = {}, {}
    backends = ("gsplat", "torch") if _module_available("gsplat") else ("torch",)
    for backend in backends:
        params = [t.to(dev).requires_grad_(True) for t in (means, quats, scales, opac, sh)]
        best = float("inf")
        for i in range(4):  # the first call loads kernels: min over the three after it
            for p in params:
                p.grad = None
            _sync(dev)
            t0 = time.perf_counter()
            r = render(Gaussians(*params), w2c.to(dev), K.to(dev), size, size, backend=backend)
            (r.rgb.mean() + r.depth.mean()).backward()
            _sync(dev)
            if i:
                best = min(best, time.perf_counter() - t0)
        times[backend] = best
        out[backend] = r.rgb.detach()
    if "gsplat" not in out:
        return f"gsplat NOT INSTALLED; torch backend fwd+bwd {times['torch']:.3f} s ({n} Gaussians, 4 x {size} px)"
    diff = (out["gsplat"] - out["torch"]).abs().max().item()
    return f"max abs rgb difference {diff:.2e}; fwd+bwd gsplat {times['gsplat']:.3f} s, torch {times['torch']:.3f} s"


class _StepStats:
    """Lightning callback: wall time of each training batch (synchronised) and the peak memory."""

    def __new__(cls, dev):
        from lightning.pytorch.callbacks import Callback

        class StepStats(Callback):
            def __init__(self):
                self.times: list[float] = []
                self._t = 0.0

            def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
                _sync(dev)
                self._t = time.perf_counter()

            def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
                _sync(dev)
                self.times.append(time.perf_counter() - self._t)

        return StepStats()


def _random_wan(dev: torch.device):
    """A random Wan 2.2 TI2V-5B (bf16) on ``dev``, for Stage II without weights (shape from benchmarks/memory.py)."""
    import diffusers
    from memory import WAN22_5B_TRANSFORMER, WAN22_VAE

    from anycity.models.video_prior import WanVideoPrior

    default = torch.get_default_dtype()
    try:  # built directly in bf16 on the GPU: a float32 detour would hold 20 GB for a moment
        torch.set_default_dtype(torch.bfloat16)
        with torch.device(dev):
            tr = diffusers.WanTransformer3DModel(**WAN22_5B_TRANSFORMER)
    finally:
        torch.set_default_dtype(default)
    with torch.device(dev):
        vae = diffusers.AutoencoderKLWan(**WAN22_VAE, latents_mean=[0.0] * 48, latents_std=[1.0] * 48)
    return lambda *a, **k: WanVideoPrior(vae, tr, block=k.get("block"), t_feat=k.get("t_feat", 0.0))


def train_steps(stage: str, args, data: Path, dev: torch.device, init_from: Path | None, ckpt_out: Path) -> dict:
    from anycity.cli import build_cli

    cfg = ROOT / "configs" / ("stage1.yaml" if stage == "stage1" else "stage2.yaml")
    a = ["-c", str(cfg), "--data.root", str(data), "--trainer.devices", "1", "--trainer.max_steps",
         str(args.steps), "--trainer.limit_val_batches", "0", "--trainer.num_sanity_val_steps", "0",
         "--trainer.logger", "false", "--trainer.enable_checkpointing", "false", "--trainer.callbacks", "[]",
         "--trainer.default_root_dir", str(ckpt_out.parent), "--data.num_workers", "2"]
    if stage == "stage1":
        a += ["--data.num_targets", "12"]  # 4 context + 12 rendered views
        if args.vggt:
            a += ["--model.init_args.pretrained", args.vggt]
    else:
        a += ["--model.init_args.init_from", str(init_from)]
        if args.wan_dir:
            a += ["--model.init_args.net.wan_dir", args.wan_dir]
    if args.smoke_cpu:
        a += ["--trainer.accelerator", "cpu", "--trainer.precision", "32-true", "--trainer.strategy", "auto",
              "--model.init_args.preset", "tiny", "--data.image_size", "[64, 64]", "--data.patch_size", "8",
              "--data.num_targets", "2", "--data.num_dense", "2", "--data.num_workers", "0",
              "--model.init_args.pretrained_patterns", "[]", "--model.init_args.render_backend", "torch"]
        if stage == "stage2":
            a += ["--model.init_args.net", '{"video_prior": "wan-tiny", "inject_layers": null, "wan_lora_rank": 2}']
    patch = nullcontext()
    if stage == "stage2" and not args.wan_dir and not args.smoke_cpu:
        patch = mock.patch("anycity.models.anycity.build_video_prior", _random_wan(dev))
    with patch, mock.patch.object(sys, "argv", sys.argv[:1]):  # LightningCLI warns when sys.argv has arguments too
        cli = build_cli(a, run=False)
    stats = _StepStats(dev)
    cli.trainer.callbacks.append(stats)
    _reset_peak(dev)
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    cli.trainer.save_checkpoint(ckpt_out, weights_only=True)  # Stage II reads only the weights (not 14 GB of AdamW)
    steady = stats.times[2:] or stats.times
    from anycity.render.api import resolve_backend

    backend = resolve_backend(cli.model.hparams.render_backend, dev)
    return {"step_s": sum(steady) / len(steady), "peak_gb": _peak_gb(dev), "model": cli.model,
            "detail": f"renderer {backend}; mean of steps {len(stats.times) - len(steady) + 1}-{len(stats.times)}"}


def inference(model, dev: torch.device, views: int, size: int) -> dict:
    net = model.net.to(dev).eval()
    x = torch.rand(1, views, 3, size, size, device=dev)
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if dev.type == "cuda" else nullcontext()
    with torch.no_grad(), amp:
        net(x, refine=True)  # warm-up
        _reset_peak(dev)
        _sync(dev)
        t0 = time.perf_counter()
        for _ in range(3):
            net(x, refine=True)
        _sync(dev)
    return {"s": (time.perf_counter() - t0) / 3, "peak_gb": _peak_gb(dev)}


def _guarded(rows: list, name: str, fn):
    """Run one check; a failure becomes a FAIL row (its traceback on stderr) so the other checks still run."""
    t0 = time.perf_counter()
    try:
        return fn()
    except Exception as e:  # noqa: BLE001 - the table must report every check, whatever broke
        import traceback

        traceback.print_exc()
        rows.append((name, "FAIL", f"{type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}",
                     f"{time.perf_counter() - t0:.1f} (until it failed)", ""))
        return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    ap.add_argument("--vggt", help="VGGT-1B model.pt for Stage I (default: random init)")
    ap.add_argument("--wan-dir", help="local Wan2.2-TI2V-5B-Diffusers folder (default: random Wan of that shape)")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--data", help="448 px shards (default: synthesised into a temporary folder)")
    ap.add_argument("--smoke-cpu", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if not torch.cuda.is_available() and not args.smoke_cpu:
        print(f"gpu-check: refused, no CUDA device here (torch {torch.__version__}); run it on a GPU machine")
        return 2
    dev = torch.device("cpu" if args.smoke_cpu else "cuda")
    if args.smoke_cpu:
        args.steps, size, views = 2, 64, 4
    else:
        size, views = 448, 32
    rows = []
    if not args.smoke_cpu:
        res = _guarded(rows, "tests/gpu", check_gpu_tests)
        if res:
            rows.append(("tests/gpu", *res, "", ""))
        res = _guarded(rows, "gsplat vs torch", lambda: check_backends(dev))
        if res:
            rows.append(("gsplat vs torch", res, "", "", ""))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = Path(args.data) if args.data else tmp / "synth"
        if not args.data:
            from anycity.data.cli import data_main

            data_main(["synth", "--out", str(data), "--scenes", "10", "--views", "24", "--size", f"{size}x{size}"])
        s1 = _guarded(rows, "stage1.yaml", lambda: train_steps("stage1", args, data, dev, None, tmp / "s1.ckpt"))
        if s1:
            rows.append(("stage1.yaml", f"{args.steps} steps", s1["detail"], f"{s1['step_s']:.3f}", s1["peak_gb"]))
            s1.pop("model")
        s2 = None
        if s1:
            s2 = _guarded(rows, "stage2.yaml",
                          lambda: train_steps("stage2", args, data, dev, tmp / "s1.ckpt", tmp / "s2.ckpt"))
        if s2:
            rows.append(("stage2.yaml", f"{args.steps} steps", s2["detail"], f"{s2['step_s']:.3f}", s2["peak_gb"]))
            inf = _guarded(rows, f"inference {views} views", lambda: inference(s2["model"], dev, views, size))
            if inf:
                rows.append((f"inference {views} views", f"{size}x{size}", "", f"{inf['s']:.3f}", inf["peak_gb"]))
    device_name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"
    print(f"\n| check | result | detail | time (s; step or inference) | peak memory (GB) |  [{device_name}, torch "
          f"{torch.__version__}]")
    print("|---|---|---|---|---|")
    for name, res, detail, t, mem in rows:
        print(f"| {name} | {res} | {detail} | {t} | {'' if mem is None or mem == '' else f'{mem:.1f}'} |")
    return 0 if all(r[1] != "FAIL" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
