"""Pretrain the pair-correlation pose prior that ``net.pose_prior`` (beyond the paper) loads in Stage II.

    python scripts/pose_prior.py --data data/quickstart --out runs/pose_prior.pt    # about 18 min on 2 CPU cores

It trains :class:`anycity.lit.pose_prior.PosePriorModule` (a Lightning ``Trainer``: any accelerator, DDP with
``--devices``) on the context views of the training split and their ground-truth poses, prints the mean relative
rotation error on the validation split every ``--val-every`` steps and on the test split once at the end (no
checkpoint is chosen by it), and writes ``OUT``: ``{"state_dict", "channels", "grid", "image_size", "num_context",
"data", "steps", "rre_val", "rre_test"}`` (``rre_val`` null with ``--val-batches 0``; the weights are written before
the test, so a failed test keeps them). Missing splits, an ``--out`` that cannot be written and a disk without room
for it stop it before training; a disk full when it is written says, in one line, that the weights were not saved
(exit 1). A SIGTERM stops it with exit 143 and one line: during training nothing is saved; during the test ``OUT``
keeps the weights (``rre_test`` null). Then, in Stage II:

    anycity fit -c configs/quickstart.yaml -c configs/quickstart_stage2.yaml --model.init_args.init_from STAGE1 \\
        --model.init_args.net.refine_cameras true --model.init_args.net.camera_video true \\
        --model.init_args.net.pose_prior runs/pose_prior.pt --model.init_args.camera_weight 5 ...

(``scripts/stage2_tables.py --rows prior_cameras --pose_prior runs/pose_prior.pt`` runs that row.)
"""

from __future__ import annotations

import argparse
import errno
import io
import shutil
import sys
from pathlib import Path


def _before_training(args: argparse.Namespace, out: Path) -> str | None:
    """What would stop the run only after training: a split it reads missing, an --out it cannot write."""
    from anycity.atomic import check_writable_folder
    from anycity.data.writer import read_index

    has = {k: len(v) for k, v in read_index(args.data).get("splits", {}).items() if v}
    for split, fix in (("train", ""), ("val", ", or pass --val-batches 0"), ("test", "")):
        if split not in has and (split != "val" or args.val_batches > 0):
            return (f"--data {args.data}: index.json lists no {split} shards (it has "
                    f"{', '.join(f'{k}: {n}' for k, n in has.items()) or 'none'}; the 8:1:1 scene split puts a set of "
                    f"few scenes in train alone): pass a shard set with more scenes{fix}")
    try:
        check_writable_folder(out.parent, "--out")
    except OSError as e:
        return str(e)
    return None


def _serialise(payload: dict) -> memoryview:
    import torch

    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getbuffer()


def _save(out: Path, payload: dict) -> str | None:
    """Write ``payload`` to ``out`` crash-safely; the disk-full line (naming the file and the bytes) or None."""
    from anycity.atomic import atomic_write_bytes

    try:
        atomic_write_bytes(out, _serialise(payload))  # torch.save to a path fails ENOSPC as a bare RuntimeError
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        return e.strerror or str(e)
    return None


def _room_for(out: Path, payload: dict) -> str | None:
    """Why ``out`` (``payload``'s size: the untrained weights' shapes are the trained ones') cannot be written now."""
    folder = next(p for p in (out.absolute().parent, *out.absolute().parents) if p.exists())
    need, free = len(_serialise(payload)), shutil.disk_usage(folder).free
    if free < need:
        return (f"--out {out}: {need} bytes needed for the weights but {free} free on its disk; free space or pass "
                "another path")
    return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--data", default="data/quickstart", help="shard directory (its index.json names the splits)")
    p.add_argument("--out", default="runs/pose_prior.pt")
    p.add_argument("--steps", type=int, default=12000,
                   help="12000: 2.7 deg on the quickstart's test cities, 6000: 4.05 (docs/stage2.md)")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--image-size", type=int, nargs=2, default=(48, 48), metavar=("H", "W"))
    p.add_argument("--patch-size", type=int, default=8, help="the network's (views are cropped to a multiple)")
    p.add_argument("--num-context", type=int, default=4)
    p.add_argument("--val-every", type=int, default=1000)
    p.add_argument("--val-batches", type=int, default=24, help="validation samples per check")
    p.add_argument("--workers", type=int, default=0)
    p.add_argument("--accelerator", default="auto")
    p.add_argument("--devices", default="1")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if not (Path(args.data) / "index.json").is_file():
        print(f"error: --data {args.data}: no index.json; make the shards first (make quickstart, or anycity data "
              "synth|convert)", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.exists():
        print(f"error: --out {out} exists; delete it or pass another path", file=sys.stderr)
        return 2
    problem = _before_training(args, out)  # found now, not after the last step
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2

    import lightning.pytorch as pl

    from anycity.cli import quiet_third_party_noise
    from anycity.lit.datamodule import AerialDataModule
    from anycity.lit.pose_prior import PosePriorModule

    quiet_third_party_noise()
    pl.seed_everything(args.seed)
    # the views as Stage II sees them: the same size, crop and scale normalisation (context depth), so the
    # translations come in the same units
    dm = AerialDataModule(root=args.data, image_size=tuple(args.image_size), patch_size=args.patch_size,
                          num_context=args.num_context, num_targets=1, num_dense=0, batch_size=args.batch,
                          eval_batch_size=1, num_workers=args.workers, epoch_samples=args.steps * args.batch,
                          with_normals=False, seed=args.seed)
    module = PosePriorModule()
    problem = _room_for(out, {"state_dict": module.net.state_dict()})  # not found only after the last step
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2

    class Report(pl.Callback):
        def on_validation_end(self, trainer, pl_module):
            if trainer.is_global_zero and not trainer.sanity_checking:
                print(f"step {trainer.global_step}: validation cities, mean relative rotation error "
                      f"{trainer.callback_metrics['val/rre']:.2f} deg", flush=True)

    trainer = pl.Trainer(max_steps=args.steps, accelerator=args.accelerator, devices=args.devices, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        num_sanity_val_steps=0, val_check_interval=min(args.val_every, args.steps),
                        limit_val_batches=args.val_batches,
                        check_val_every_n_epoch=None, callbacks=[Report()])
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    try:
        trainer.fit(module, datamodule=dm)
    except SIGTERMException:  # a SystemExit with no code: `pose_prior.py && stage2_tables.py` would carry on
        return _stopped(trainer, f"stopped by SIGTERM at step {trainer.global_step}; nothing saved ({out} not "
                                 "written): rerun the same command")
    rre_val = trainer.callback_metrics.get("val/rre")  # none with --val-batches 0
    saved = {"state_dict": module.net.state_dict(), "channels": module.hparams.channels, "grid": module.hparams.grid,
             "image_size": list(args.image_size), "num_context": args.num_context, "data": str(args.data),
             "steps": args.steps, "rre_val": None if rre_val is None else float(rre_val), "rre_test": None}
    if trainer.is_global_zero:  # the weights are kept even if the test below fails
        full = _save(out, saved)
        if full:
            print(f"error: {full}; the {trainer.global_step} trained steps' weights were NOT saved (nothing else "
                  "holds them)", file=sys.stderr)
            return 1
    try:
        rre_test = float(trainer.test(module, datamodule=dm, verbose=False)[0]["test/rre"])
    except SIGTERMException:
        return _stopped(trainer, f"stopped by SIGTERM during the test; {out} holds the trained weights with rre_test "
                                 "null")
    print(f"test cities, mean relative rotation error {rre_test:.2f} deg (read once, after training)")
    if trainer.is_global_zero:
        full = _save(out, {**saved, "rre_test": rre_test})
        if full:
            print(f"error: {full}; {out} keeps the trained weights, with rre_test null", file=sys.stderr)
            return 1
        print(f"wrote {out}")
    return 0


def _stopped(trainer, line: str) -> int:
    """Exit code 143 (128 + SIGTERM, what a shell reports for a process the signal ended), and rank 0's ``line``."""
    if trainer.is_global_zero:
        print(f"pose_prior: {line}", file=sys.stderr, flush=True)
    return 143


if __name__ == "__main__":
    sys.exit(main())
