"""How much could Stage II gain on the quickstart's test cities, and what limits it? (docs/stage2.md, "Headroom")

    python benchmarks/stage2_headroom.py [CKPT] [--data data/quickstart] [--teacher-batches 30]

``CKPT`` is a Stage II checkpoint (default: the quickstart's, ``runs/quickstart/stage2/checkpoints/last.ckpt``) or
a Stage I one. Prints:

1. Per region (observed; weak, split into out of every context frame / seen by fewer than 2 context views / the
   rest: weak parallax or a depth edge), its share of target pixels and the feed-forward PSNR (pooled over the
   region's pixels, so it differs a little from the per-image mean ``anycity test`` logs) of:
   the scaffold; the refined model; the scaffold's Gaussians placed with the ground-truth context cameras instead
   of the predicted ones; and with ground-truth cameras and ground-truth depth. The last two read ground truth
   and are ceilings, not results: they show how much of the error lies in what Stage II cannot change (cameras).
2. The dense-to-sparse teacher (the scaffold on the dense views) against the student (the scaffold on the context
   views) at the dense cameras, on training batches: if the teacher is not better, ``L_d2s`` cannot help.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch


def region_parts(module, ctx, tgt) -> dict[str, torch.Tensor]:
    """Observed and weak target pixels, the weak ones split by why they are weak; bool ``[B, T, 1, H, W]``."""
    from anycity.geometry.projection import unproject_depth
    from anycity.geometry.visibility import visible_views
    from anycity.metrics.regions import DEFAULT_DEPTH_TOL

    obs, weak = module.region_masks(ctx, tgt)
    b, t, _, h, w = tgt.depth.shape
    pts = unproject_depth(tgt.depth.clamp_min(1e-6).float(), tgt.K.float(), tgt.w2c.float()).reshape(b, -1, 3)
    in_frame = visible_views(pts, ctx.depth, ctx.w2c, ctx.K, depth_tol=1e9).any(1).reshape(b, t, 1, h, w)
    seen = visible_views(pts, ctx.depth, ctx.w2c, ctx.K, depth_tol=DEFAULT_DEPTH_TOL).sum(1).reshape(b, t, 1, h, w)
    return {"observed": obs, "weak": weak, "weak: out of frame": weak & ~in_frame,
            "weak: < 2 views": weak & in_frame & (seen < 2), "weak: parallax/edge": weak & in_frame & (seen >= 2)}


def placed_with_gt(module, scaffold: dict, ctx, depth: torch.Tensor | None = None):
    """The scaffold's Gaussians (``scaffold``: a ``refine=False`` forward) re-placed with the ground-truth context
    cameras (in the predicted frame and units) and, when given, ground-truth ``depth [B, V, 1, H, W]``; returns the
    Gaussians and those cameras."""
    from anycity.models.gaussians import pixel_centres

    w2c, s = module.target_cameras(scaffold["w2c"], ctx, ctx)
    d, offset = scaffold["depth"], scaffold["offset"]
    if depth is not None:
        d, offset = depth * s[:, None, None, None, None], None
    means = pixel_centres(d, ctx.K, w2c, offset)
    return module.net._gaussians(scaffold["raw_gaussians"], means, d, ctx.K, ctx.images), w2c


def headroom(module, dm) -> None:
    from anycity.lit import protocols as P

    dm.setup("test")
    sq, n = {}, {}
    for batch in dm.test_dataloader():
        ctx, tgt = batch.context, batch.target
        parts = region_parts(module, ctx, tgt)
        out = module.net(ctx.images, refine=True)
        scaffold = module.net(ctx.images, refine=False)
        g_cam, w2c_gt = placed_with_gt(module, scaffold, ctx)
        g_geo, _ = placed_with_gt(module, scaffold, ctx, ctx.depth)
        variants = {"scaffold": (out["scaffold_gaussians"], *module.variant_cameras(out, "scaffold")),
                    "refined": (out["gaussians"], out["w2c"], out["K"]),
                    "GT cameras": (g_cam, w2c_gt, ctx.K), "GT cameras + depth": (g_geo, w2c_gt, ctx.K)}
        for name, (g, w2c, K) in variants.items():
            r, _ = P.feedforward(module, P.Scene(g, w2c, K), ctx, P.TargetCameras.of(tgt))
            err = ((r.rgb - tgt.images) ** 2).mean(2, keepdim=True)
            for part, mask in parts.items():
                sq[name, part] = sq.get((name, part), 0.0) + err[mask].sum().item()
                n[part] = n.get(part, 0) + (mask.sum().item() if name == "scaffold" else 0)
    total = n["observed"] + n["weak"]
    names = ["scaffold", "refined", "GT cameras", "GT cameras + depth"]
    print("feed-forward PSNR (dB) per region; the GT columns read ground-truth context cameras/depth (ceilings)")
    print("| region | share | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for part in n:
        psnr = [-10 * math.log10(sq[name, part] / max(n[part], 1)) for name in names]
        print(f"| {part} | {n[part] / total:.3f} | " + " | ".join(f"{p:.2f}" for p in psnr) + " |")


def teacher_vs_student(module, dm, batches: int) -> None:
    dm.setup("fit")
    psnr = {"teacher": [], "student": []}
    dl1 = {"teacher": [], "student": []}
    for _, batch in zip(range(batches), dm.train_dataloader()):
        ctx, dense = batch.context, batch.dense
        for who, inputs, frame in (("teacher", dense, dense), ("student", ctx, ctx)):
            out = module.net(inputs.images, refine=False)
            w2c, s = module.target_cameras(out["w2c"], frame, dense)
            r = module.render(out["scaffold_gaussians"], w2c, dense.K, dense.hw, ctx.images)
            psnr[who].append(-10 * math.log10(((r.rgb - dense.images) ** 2).mean().item()))
            valid = dense.depth > 0
            dl1[who].append((r.depth / s[:, None, None, None, None] - dense.depth).abs()[valid].mean().item())
    print(f"\nat the dense cameras, {batches} training batches (ground-truth RGB and depth):")
    for who in psnr:
        print(f"  {who}: PSNR {sum(psnr[who]) / batches:.2f} dB, depth L1 {sum(dl1[who]) / batches:.3f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ckpt", nargs="?", default="runs/quickstart/stage2/checkpoints/last.ckpt")
    p.add_argument("--data", default="data/quickstart")
    p.add_argument("--teacher-batches", type=int, default=30)
    args = p.parse_args()
    for what, path in (("shards", Path(args.data) / "index.json"), ("checkpoint", Path(args.ckpt))):
        if not path.is_file():
            print(f"benchmarks/stage2_headroom.py: skipped, no {what} at {path} (make quickstart first, or pass it)")
            return
    import importlib

    from anycity.lit.checkpoint_io import safe_torch_load
    from anycity.lit.datamodule import AerialDataModule

    path = safe_torch_load(args.ckpt)["hyper_parameters"].get("_class_path", "anycity.lit.RefinementModule")
    mod, _, name = path.rpartition(".")
    module = getattr(importlib.import_module(mod), name).load_from_checkpoint(args.ckpt, map_location="cpu").eval()
    dm = AerialDataModule(root=args.data, image_size=(48, 48), patch_size=8, num_context=4, num_targets=2,
                          num_dense=6, batch_size=1, num_workers=0)
    headroom(module, dm)
    teacher_vs_student(module, dm, args.teacher_batches)


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
