"""The ``anycity`` command: LightningCLI subcommands ``fit|validate|test|predict`` plus ``anycity data ...``.

Heavy imports (torch, Lightning, the network) happen only when a training subcommand runs, so
``anycity data synth`` starts quickly and does not need the network.
"""

from __future__ import annotations

import sys


def _cli_class():
    from lightning.pytorch.cli import LightningCLI

    from anycity.callbacks import FreezeModules, ImagePreviews, LoRAInjection, LossProgressBar, PredictionExport

    class AnyCityCLI(LightningCLI):
        """LightningCLI with the always-present ("forced") callbacks as top-level config groups:
        ``freeze``, ``lora``, ``previews``, ``progress``, ``export``. They merge key by key across ``--config``
        files, unlike the ``trainer.callbacks`` list."""

        def add_arguments_to_parser(self, parser) -> None:
            parser.add_lightning_class_args(FreezeModules, "freeze")
            parser.add_lightning_class_args(LoRAInjection, "lora")
            parser.add_lightning_class_args(ImagePreviews, "previews")
            parser.add_lightning_class_args(LossProgressBar, "progress")
            parser.add_lightning_class_args(PredictionExport, "export")

        def _run_subcommand(self, subcommand: str) -> None:
            from anycity.lit.keep import keep_previous_run  # earlier runs' logs/checkpoints/exports are kept

            out = next((c.out_dir for c in self.trainer.callbacks if isinstance(c, PredictionExport)), None)
            keep_previous_run(self.trainer, subcommand, self.config[subcommand].get("ckpt_path"), out)
            super()._run_subcommand(subcommand)

        def before_predict(self) -> None:
            # A data module without a predict set reconstructs its test scenes.
            from lightning.pytorch import LightningDataModule

            dm = self.datamodule
            if dm is not None and type(dm).predict_dataloader is LightningDataModule.predict_dataloader:
                dm.predict_dataloader = dm.test_dataloader

    return AnyCityCLI


def build_cli(args: list[str] | None = None, run: bool = True):
    """Build (and by default run) the training CLI in-process; ``args`` as on the command line after
    ``anycity``, e.g. ``["fit", "--config", "configs/quickstart.yaml"]``. Returns the LightningCLI object."""
    from anycity.lit import AnyCityModule
    from anycity.lit.datamodule import AerialDataModule

    return _cli_class()(
        AnyCityModule,
        AerialDataModule,
        subclass_mode_model=True,
        auto_configure_optimizers=False,  # the modules build their own AdamW param groups + schedule
        save_config_kwargs={"overwrite": True},
        # atomic checkpoint writes, weights_only reads (issue 16)
        trainer_defaults={"plugins": {"class_path": "anycity.lit.checkpoint_io.SafeCheckpointIO"}},
        args=args,
        run=run,
    )


def main(argv: list[str] | None = None) -> int:
    """Console entry point (``anycity``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] == "data":
        from anycity.data.cli import data_main

        return int(data_main(args[1:]) or 0)
    build_cli(None if argv is None else args)  # None: LightningCLI reads sys.argv itself
    return 0


if __name__ == "__main__":
    sys.exit(main())
