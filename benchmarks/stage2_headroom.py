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
3. With ``--fit-steps N`` (> 0): a ceiling for any Stage II that keeps the cameras, as the paper's does. After the
   context-only camera refinement, the scaffold's Gaussians (every attribute, or the geometry only: centres,
   rotations, scales) are fitted by Adam to the context images alone (test-time optimisation, no target image),
   and then to the context images plus the test sample's dense views (other real views of the same place, near the
   targets, never a target). The second reads images the protocol does not give: it stands in for a prior that
   knows the scene. Observed / weak PSNR at the targets, pooled. Use a test datamodule with ``num_dense`` 8, all
   of the 8 non-held-out views the context is drawn from (``--dense 8``, the default).
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


def accumulate(sq: dict, n: dict, name: str, rgb: torch.Tensor, images: torch.Tensor, parts: dict,
               count: bool) -> None:
    """Add the squared error of render ``rgb`` against ``images`` over each region of ``parts`` to ``sq[name, part]``
    (for pooled PSNR); with ``count``, add the regions' pixel counts to ``n[part]`` (once per batch)."""
    err = ((rgb - images) ** 2).mean(2, keepdim=True)
    for part, mask in parts.items():
        sq[name, part] = sq.get((name, part), 0.0) + err[mask].sum().item()
        n[part] = n.get(part, 0) + (mask.sum().item() if count else 0)


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
            accumulate(sq, n, name, r.rgb, tgt.images, parts, count=name == "scaffold")
    total = n["observed"] + n["weak"]
    names = ["scaffold", "refined", "GT cameras", "GT cameras + depth"]
    print("feed-forward PSNR (dB) per region; the GT columns read ground-truth context cameras/depth (ceilings)")
    print("| region | share | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for part in n:
        psnr = [-10 * math.log10(sq[name, part] / max(n[part], 1)) for name in names]
        print(f"| {part} | {n[part] / total:.3f} | " + " | ".join(f"{p:.2f}" for p in psnr) + " |")


GEOMETRY = ("means", "quats", "scales")
ALL_ATTRIBUTES = ("means", "quats", "scales", "opacities", "sh")


def fit_gaussians(module, g, views: list[tuple], context_images: torch.Tensor, steps: int,
                  free: tuple[str, ...] = ALL_ATTRIBUTES, lr_scale: float = 1.0):
    """``g`` with the attributes named in ``free`` fitted by Adam (``steps``) so that its renders reproduce
    ``views``: a list of ``(w2c [B, V, 4, 4], K [B, V, 3, 3], images [B, V, 3, H, W])``, MSE averaged over the
    lists. Centres move as offsets, scales and opacities through log and logit, so the fit starts exactly at ``g``.
    Learning rates are 3DGS's times ``lr_scale``, the centres' relative to the scene's median distance from the
    first camera."""
    from anycity.geometry import camera_centers
    from anycity.structures import Gaussians

    with torch.enable_grad():
        base = [t.detach().float() for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
        extent = (base[0] - camera_centers(views[0][0].float())[:, :1]).norm(dim=-1)  # [B, N]
        params = {"means": torch.zeros_like(base[0]), "quats": base[1].clone(),
                  "scales": base[2].clamp_min(1e-8).log(), "opacities": base[3].clamp(1e-4, 1 - 1e-4).logit(),
                  "sh": base[4].clone()}
        lrs = {"means": 1.6e-4 * extent.median().item(), "quats": 1e-3, "scales": 5e-3, "opacities": 5e-2, "sh": 2.5e-3}
        for name in free:
            params[name].requires_grad_(True)
        opt = torch.optim.Adam([{"params": [params[k]], "lr": lr_scale * lrs[k]} for k in free])

        def current():
            return Gaussians(base[0] + params["means"], params["quats"], params["scales"].exp(),
                             params["opacities"].sigmoid(), params["sh"], g.valid)

        for _ in range(steps):
            cur = current()
            loss = sum(((module.render(cur, w2c, K, tuple(img.shape[-2:]), context_images).rgb - img) ** 2).mean()
                       for w2c, K, img in views) / len(views)
            opt.zero_grad()
            loss.backward()
            opt.step()
        cur = current()
        return Gaussians(*[t.detach() for t in (cur.means, cur.quats, cur.scales, cur.opacities, cur.sh)], g.valid)


def perfect_knowledge(module, dm, steps: int) -> None:
    """Section 3 of the module docstring: the camrefine scaffold, then its Gaussians fitted to the context images
    alone, and to the context plus the dense views (a ceiling: it reads images the protocol does not give); every
    attribute free at 3DGS's learning rates, or the geometry only (centres, rotations, scales) at 4x those: the
    settings that scored best of those tried (every attribute at 4x overfits the fitted views in 100 steps)."""
    from anycity.lit import protocols as P

    dm.setup("test")
    sq, n = {}, {}
    fits = {"scaffold, camrefine": None,
            "all attributes, fitted to the context": ("context", ALL_ATTRIBUTES, 1.0),
            "all attributes, fitted to the context + dense views (ceiling)": ("dense", ALL_ATTRIBUTES, 1.0),
            "geometry only, fitted to the context": ("context", GEOMETRY, 4.0),
            "geometry only, fitted to the context + dense views (ceiling)": ("dense", GEOMETRY, 4.0)}
    for batch in dm.test_dataloader():
        ctx, tgt, dense = batch.context, batch.target, batch.dense
        obs, weak = module.region_masks(ctx, tgt)
        parts = {"observed": obs, "weak": weak}
        out = module.net(ctx.images, refine=False)
        scene = P.Scene(out["scaffold_gaussians"], *module.variant_cameras(out, "scaffold"))
        r, _, scene = P.camrefine(module, scene, ctx, P.TargetCameras.of(tgt), module.hparams.camera_refine_steps)
        w2c_d, _ = P.place(module, scene, ctx, P.TargetCameras.of(dense))
        views = {"context": [(scene.w2c, scene.K, ctx.images)]}
        views["dense"] = views["context"] + [(w2c_d, dense.K, dense.images)]
        for name, how in fits.items():
            if how is not None:  # (the first row is the camrefine render itself)
                g = fit_gaussians(module, scene.gaussians, views[how[0]], ctx.images, steps, free=how[1],
                                  lr_scale=how[2])
                r, _ = P.feedforward(module, P.Scene(g, scene.w2c, scene.K), ctx, P.TargetCameras.of(tgt))
            accumulate(sq, n, name, r.rgb, tgt.images, parts, count=how is None)
    print(f"\nafter camrefine, the scaffold's Gaussians fitted by {steps} Adam steps (pooled PSNR at the targets, dB;"
          " the ceiling rows read the dense views' images, which the protocol does not give)")
    print("| Gaussians | observed | weak |\n|---|---|---|")
    for name in fits:
        o, w = (-10 * math.log10(sq[name, part] / max(n[part], 1)) for part in ("observed", "weak"))
        print(f"| {name} | {o:.2f} | {w:.2f} |")


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


def load_module(ckpt: str):
    """The LightningModule (Stage I or Stage II class, from the checkpoint's hyperparameters) in eval mode."""
    import importlib

    from anycity.lit.checkpoint_io import safe_torch_load

    path = safe_torch_load(ckpt)["hyper_parameters"].get("_class_path", "anycity.lit.RefinementModule")
    mod, _, name = path.rpartition(".")
    return getattr(importlib.import_module(mod), name).load_from_checkpoint(ckpt, map_location="cpu").eval()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ckpt", nargs="?", default="runs/quickstart/stage2/checkpoints/last.ckpt")
    p.add_argument("--data", default="data/quickstart")
    p.add_argument("--teacher-batches", type=int, default=30)
    p.add_argument("--fit-steps", type=int, default=0, help="section 3 (the perfect-knowledge ceiling); 0 = off")
    p.add_argument("--dense", type=int, default=8, help="dense views per test sample for section 3 (<= 8 keeps the "
                   "context views of sections 1-2)")
    args = p.parse_args()
    for what, path in (("shards", Path(args.data) / "index.json"), ("checkpoint", Path(args.ckpt))):
        if not path.is_file():
            print(f"benchmarks/stage2_headroom.py: skipped, no {what} at {path} (make quickstart first, or pass it)")
            return
    from anycity.lit.datamodule import AerialDataModule

    module = load_module(args.ckpt)
    settings = dict(root=args.data, image_size=(48, 48), patch_size=8, num_context=4, num_targets=2, batch_size=1,
                    num_workers=0)
    dm = AerialDataModule(num_dense=6, **settings)
    headroom(module, dm)
    teacher_vs_student(module, dm, args.teacher_batches)
    if args.fit_steps > 0:
        perfect_knowledge(module, AerialDataModule(num_dense=args.dense, eval_dense=True, **settings), args.fit_steps)


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
