"""Would content-based context cameras lift the scaffold? A lead for issue 12 (docs/stage2.md, "A lead").

    python benchmarks/pose_correlation.py [CKPT] [--data data/quickstart] [--steps 6000] [--batch 8]

The tiny scaffold's camera head predicts nearly one mean relative pose per view position (docs/stage2.md). This
trains a small pose regressor with an explicit correlation between view pairs, a cue that depends on the images'
content and not on the view order:

1. ``PairFlowPose`` (``anycity.models.pose_prior``; ``net.pose_prior`` loads it in Stage II): a 4-layer CNN gives
   each context view a 12 x 12 grid of unit features; for each view i > 0 the soft-argmax of the feature
   correlation with view 0 (both ways) gives a flow field, and an MLP shared by all views
   maps it to view i's rotation (6-D) and translation relative to view 0, in the normalised frame. It reads the
   context images only. It trains on the training cities' context views and their ground-truth poses (as the
   network's camera loss does), L1 on the rotation matrix and the translation. Each ``--eval-every`` steps it prints
   its mean relative rotation error over all context view pairs of the test cities, and that of a constant pose
   per view position (the training mean), the best an order-only cue gives.
2. It then scores ``CKPT``'s scaffold (a Stage I or Stage II checkpoint) on the test cities twice: placed with its
   own predicted cameras, and with the regressor's (the scaffold's depth, offsets and intrinsics unchanged): pooled
   observed / weak PSNR at the targets, feed-forward and after the context-only camera refinement (the quickstart's
   protocols; neither reads a target image).

Here the regressor is not part of the network: this measures what its cameras are worth on their own. The Stage II
option that reads it is ``net.pose_prior`` (pretrained by ``scripts/pose_prior.py``; docs/stage2.md).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from anycity.models.pose_prior import PairFlowPose


def as_w2c(R: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:
    """Rotations ``[B, V, 3, 3]`` (and translations ``[B, V, 3]``) -> ``w2c [B, V, 4, 4]`` for
    :func:`anycity.metrics.pose.relative_pose_errors`."""
    w2c = torch.eye(4, dtype=R.dtype, device=R.device).repeat(*R.shape[:2], 1, 1)
    w2c[..., :3, :3] = R
    if t is not None:
        w2c[..., :3, 3] = t
    return w2c


def train_regressor(dm, test: list, steps: int, eval_every: int, lr: float = 1e-3) -> PairFlowPose:
    from anycity.lit.pose_prior import PosePriorModule
    from anycity.metrics.pose import relative_pose_errors

    trainee = PosePriorModule()  # its loss (scripts/pose_prior.py trains the same recipe with a Lightning Trainer)
    net = trainee.net
    opt = torch.optim.AdamW(net.parameters(), lr, weight_decay=1e-4)
    steps = max(steps, 4)  # OneCycleLR divides by its warm-up length, which must be >= 1 step
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, lr, total_steps=steps, pct_start=max(0.05, 2 / steps))
    mean_R, n, t0 = None, 0, time.time()

    def evaluate() -> tuple[float, float]:
        """Mean relative rotation error (all context view pairs, as ``anycity test``'s ``rre``) of the regressor
        and of the training mean per position, projected onto rotations."""
        net.eval()
        u, _, vh = torch.linalg.svd(mean_R / n)
        with torch.no_grad():
            e = torch.cat([relative_pose_errors(net(b.context.images), b.context.w2c)[0].flatten()
                           for b in test])
            e0 = torch.cat([relative_pose_errors(as_w2c((u @ vh).expand(len(b.context.w2c), -1, -1, -1)),
                                                 b.context.w2c)[0].flatten() for b in test])
        net.train()
        return e.mean().item(), e0.mean().item()

    for step, batch in enumerate(dm.train_dataloader()):
        if step >= steps:
            break
        R_gt = batch.context.w2c[..., :3, :3]
        mean_R = R_gt.sum(0) if mean_R is None else mean_R + R_gt.sum(0)
        n += R_gt.shape[0]
        loss = trainee.loss(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if (step + 1) % eval_every == 0 or step + 1 == steps:
            e, e0 = evaluate()
            print(f"step {step + 1}: loss {loss.item():.4f}; test cities, mean relative rotation error: regressor "
                  f"{e:.2f} deg, a constant pose per view position {e0:.2f} deg ({time.time() - t0:.0f} s)", flush=True)
    return net.eval()


def score(module, dm, regressor: PairFlowPose) -> dict[tuple[str, str], float]:
    """Pooled PSNR ``{(row, region): dB}`` of the scaffold placed with its own cameras and with the regressor's."""
    import stage2_headroom as headroom  # this script's folder is sys.path[0]

    from anycity.lit import protocols as P
    from anycity.models.gaussians import pixel_centres

    sq, n = {}, {}
    for batch in dm.test_dataloader():
        ctx, tgt = batch.context, batch.target
        obs, weak = module.region_masks(ctx, tgt)
        parts = {"observed": obs, "weak": weak}
        out = module.net(ctx.images, refine=False)
        w2c = out["w2c"].clone()
        w2c[..., :3, :4] = regressor(ctx.images)[..., :3, :4]
        means = pixel_centres(out["depth"], out["K"], w2c, out["offset"])
        rows = {"own cameras": P.Scene(out["scaffold_gaussians"], out["w2c"], out["K"]),
                "regressor's cameras": P.Scene(module.net._gaussians(out["raw_gaussians"], means, out["depth"],
                                                                     out["K"], ctx.images), w2c, out["K"])}
        for name, scene in rows.items():
            r, _ = P.feedforward(module, scene, ctx, P.TargetCameras.of(tgt))
            headroom.accumulate(sq, n, f"{name}, feed-forward", r.rgb, tgt.images, parts, count=name == "own cameras")
            r, _, _ = P.camrefine(module, scene, ctx, P.TargetCameras.of(tgt), module.hparams.camera_refine_steps)
            headroom.accumulate(sq, n, f"{name}, camrefine", r.rgb, tgt.images, parts, count=False)
    return {k: -10 * math.log10(v / max(n[k[1]], 1)) for k, v in sq.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ckpt", nargs="?", default="runs/quickstart/stage1/checkpoints/last.ckpt")
    p.add_argument("--data", default="data/quickstart")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    for what, path in (("shards", Path(args.data) / "index.json"), ("checkpoint", Path(args.ckpt))):
        if not path.is_file():
            print(f"benchmarks/pose_correlation.py: skipped, no {what} at {path} (make quickstart first, or pass it)")
            return
    from stage2_headroom import load_module

    from anycity.lit.datamodule import AerialDataModule

    torch.manual_seed(args.seed)
    module = load_module(args.ckpt)
    settings = dict(root=args.data, image_size=(48, 48), patch_size=8, num_context=4, num_targets=2, num_dense=0,
                    num_workers=0, seed=args.seed)
    train_dm = AerialDataModule(batch_size=args.batch, epoch_samples=10 ** 7, with_normals=False, **settings)
    test_dm = AerialDataModule(batch_size=1, **settings)
    regressor = train_regressor(train_dm, list(test_dm.test_dataloader()), args.steps, args.eval_every)
    with torch.no_grad():
        psnr = score(module, test_dm, regressor)
    print("\nthe scaffold's Gaussians on the test cities, pooled PSNR at the targets (dB), observed / weak; no target "
          "image read")
    print("| context cameras | feed-forward | camrefine |\n|---|---|---|")
    for name in ("own cameras", "regressor's cameras"):
        cells = [f"{psnr[f'{name}, {proto}', 'observed']:.2f} / {psnr[f'{name}, {proto}', 'weak']:.2f}"
                 for proto in ("feed-forward", "camrefine")]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
