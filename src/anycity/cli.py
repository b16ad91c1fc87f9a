"""The ``anycity`` command: one front door for every subcommand.

``anycity data synth|convert``, ``export``, ``view`` and ``render-video`` run without importing Lightning (they
start in about a second; ``anycity --help`` does not import torch either); ``fit|validate|test|predict`` are the
LightningCLI subcommands. Errors a user caused (``ValueError``/``FileNotFoundError``, also when raised inside a
DataLoader worker, and unknown config keys), and a full disk or quota (``ENOSPC``/``EDQUOT``, exit code 1), print as
one line; ``--debug`` or ``ANYCITY_DEBUG=1`` shows the traceback. A training command stopped by SIGTERM exits with
143 and one line: where it stopped and how to go on.
"""

from __future__ import annotations

import logging
import pickle
import sys
import warnings
from pathlib import Path

from anycity.cli_sources import (  # noqa: F401  (re-exported: anycity.cli's public checks)
    LIGHTNING,
    _init_params,
    _model_class,
    _option_values,
    check_config_placement,
    check_input_files,
    check_model_class,
    dropped_model_keys,
    replaced_net_keys,
)

# Test-time settings: taken from the config files and the command line even when --ckpt_path holds other values
# (LightningCLI otherwise re-applies every hyperparameter stored in the checkpoint over them).
TEST_TIME_KEYS = ("eval_align", "eval_pose_align_steps", "eval_pose_align_lr", "eval_joint", "camera_refine_steps",
                  "camera_refine_lr", "render_backend")
# model.net keys the weights do not depend on (machine-local paths, the inference-time voxel merge): a value given in
# the config files or on the command line wins over the checkpoint's. Any other net key comes from the checkpoint,
# with a warning when the config asked for another value.
NET_TEST_TIME_KEYS = ("voxel_size", "wan_dir", "wan_empty_prompt")
# model.net paths whose presence the weights depend on (pose_prior adds completion.camera_pose.* and pose_prior.*):
# the config's path wins only where the checkpoint has one too (a moved file); None on either side keeps the stored.
NET_MOVED_PATH_KEYS = ("pose_prior",)


def _same_value(a, b) -> bool:
    """A config value equals a stored one, YAML lists and stored/dataclass tuples alike."""
    norm = lambda v: tuple(v) if isinstance(v, list) else v  # noqa: E731
    return norm(a) == norm(b)


def merge_ckpt_net(asked: dict | None, stored: dict | None, preset: str) -> tuple[dict, list[str]]:
    """The ``model.net`` overrides to build a checkpoint's network with: the checkpoint's (``stored``), and the
    :data:`NET_TEST_TIME_KEYS` the config ``asked`` for (a null ``wan_dir``/``wan_empty_prompt`` keeps the stored
    path), and :data:`NET_MOVED_PATH_KEYS` where both name a file.
    Also ``"key is used, not asked"`` for each other key asked for that the checkpoint's network does not have."""
    from anycity.models.presets import preset_config

    asked, merged = dict(asked or {}), dict(stored or {})
    # a config's null path is "not set here" (stage2.yaml ships wan_dir: null), not "drop the stored one";
    # voxel_size null is "no voxel merge", a choice
    merged.update({k: v for k, v in asked.items() if k in NET_TEST_TIME_KEYS
                   and (v is not None or k == "voxel_size" or merged.get(k) is None)})
    merged.update({k: asked[k] for k in NET_MOVED_PATH_KEYS if asked.get(k) is not None and merged.get(k) is not None})
    try:
        used = preset_config(preset, **merged)
    except ValueError:
        return merged, []  # the network's own construction reports it
    ignored = [f"{k} is {getattr(used, k)!r}, not {v!r}" for k, v in asked.items()
               if k not in NET_TEST_TIME_KEYS and hasattr(used, k) and not _same_value(v, getattr(used, k))]
    return merged, ignored


def resumed_settings_ignored(asked: dict, stored: dict) -> list[str]:
    """``"key is stored, not asked"`` for each ``model.init_args`` key whose value the config asks differently
    from the resumed checkpoint's: Lightning rebuilds the module from the checkpoint's hyperparameters, so a resumed
    fit keeps its own (a new ``lr`` or ``init_from`` is silently not used). Not compared: ``net``
    (:func:`merge_ckpt_net` says what it keeps), :data:`TEST_TIME_KEYS`, and ``pretrained`` (the checkpoint's
    weights replace that file's, and the run keeps its own on record)."""
    return [f"{k} is {stored[k]!r}, not {v!r}" for k, v in asked.items()
            if k not in ("net", "pretrained", *TEST_TIME_KEYS) and k in stored and not _same_value(v, stored[k])]


def _warn_resumed_settings(ckpt: str, asked: dict, stored: dict) -> None:
    ignored = resumed_settings_ignored(asked, stored)
    if ignored:
        from lightning.pytorch.utilities import rank_zero_warn

        rank_zero_warn(f"--ckpt_path {ckpt}: a resumed fit continues with the model settings it was started with, "
                       f"so model.init_args {'; '.join(ignored)}; to change them, start a new run (another "
                       "--trainer.default_root_dir, or RUN_DIR for the SLURM jobs) instead of resuming this one")


def _as_dict(value):
    """A parsed config value as plain data (jsonargparse Namespaces as dicts)."""
    return value.as_dict() if hasattr(value, "as_dict") else value


def configured_trainer(trainer: dict):
    """What Lightning's checkpoint look-up reads of the Trainer the parsed ``trainer`` section configures: its
    ``default_root_dir``, loggers and checkpoint callbacks, built without the Trainer or the model (and nothing
    written). Lightning's default logger is a ``lightning_logs/version_N`` one, as this CSVLogger."""
    import os
    from types import SimpleNamespace

    from lightning.pytorch.callbacks import Checkpoint, ModelCheckpoint
    from lightning.pytorch.cli import instantiate_class
    from lightning.pytorch.loggers import CSVLogger

    trainer = _as_dict(trainer) or {}
    root = trainer.get("default_root_dir") or os.getcwd()
    logger = trainer.get("logger")
    specs = [] if logger is False else logger if isinstance(logger, list) else [logger]
    loggers = [instantiate_class((), s) if isinstance(s, dict) else s if s not in (None, True)
               else CSVLogger(save_dir=root) for s in specs]
    callbacks = []
    for spec in trainer.get("callbacks") or []:
        if isinstance(spec, dict):
            module, _, name = spec["class_path"].rpartition(".")
            if not issubclass(getattr(__import__(module, fromlist=[name]), name), Checkpoint):
                continue
            spec = instantiate_class((), spec)
        if isinstance(spec, Checkpoint):
            callbacks.append(spec)
    if not any(isinstance(c, ModelCheckpoint) for c in callbacks) and trainer.get("enable_checkpointing") is not False:
        callbacks.append(ModelCheckpoint())  # what the Trainer adds
    return SimpleNamespace(default_root_dir=str(root), loggers=loggers, callbacks=callbacks,
                           checkpoint_callbacks=callbacks)


def check_accelerator(trainer: dict | None) -> None:
    """Refuse ``trainer.accelerator: gpu``/``cuda`` (the paper configs') on a machine without CUDA, and ``mps``, in
    one line, before the Trainer is built: Lightning's own "No supported gpu backend found!" comes as a 40-line
    traceback, and on a Mac Lightning takes ``gpu`` for Apple's MPS, which has no float64 (the DPT heads' pixel grid
    and the renderer's camera checks use it), so the first step failed with a traceback."""
    accelerator = str((_as_dict(trainer) or {}).get("accelerator") or "").lower()
    if accelerator in ("gpu", "cuda", "mps"):
        import torch

        cuda = torch.cuda.is_available()
        if accelerator == "mps" or not cuda:
            what = "anycity runs on CUDA GPUs and the CPU only" if cuda else "this machine has no CUDA GPU"
            fix = "gpu" if cuda else ("cpu --trainer.precision 32-true, or use configs/quickstart.yaml, which runs on "
                                      "CPU")
            raise ValueError(f"trainer.accelerator {accelerator}: {what} (torch {torch.__version__}; Apple MPS is not "
                             f"supported: it has no float64, which anycity needs); pass --trainer.accelerator {fix}")


def check_nodes(trainer: dict | None) -> None:
    """Refuse ``trainer.num_nodes`` > 1 outside a multi-node job (no SLURM, torchrun or LSF environment, no
    ``NODE_RANK``/``MASTER_ADDR`` of a hand-started or Kubeflow one): the run would wait for nodes that never come,
    silently, until the process group's timeout (30 min). A multi-node run's ``config.yaml``, reused for a ``test``
    on one machine as the docs show, keeps its ``num_nodes``."""
    import os

    nodes = (_as_dict(trainer) or {}).get("num_nodes") or 1
    if not isinstance(nodes, int) or nodes <= 1 or {"NODE_RANK", "MASTER_ADDR"} & set(os.environ):
        return
    from lightning.fabric.plugins.environments import LSFEnvironment, SLURMEnvironment, TorchElasticEnvironment

    if any(env.detect() for env in (SLURMEnvironment, TorchElasticEnvironment, LSFEnvironment)):
        return  # (Kubeflow's PyTorchJob sets MASTER_ADDR)
    raise ValueError(f"trainer.num_nodes {nodes}: this machine is not in a multi-node job (no SLURM, torchrun or LSF "
                     "environment, no NODE_RANK/MASTER_ADDR), so the run would wait for the other nodes "
                     "until its timeout; pass --trainer.num_nodes 1 (and --trainer.devices N for this machine's GPUs)")


def check_run_folder(trainer: dict | None) -> None:
    """Refuse a ``trainer.default_root_dir`` that a CSV or TensorBoard logger's ``save_dir`` contradicts: Lightning
    writes the checkpoints and logs under the logger's folder, so a config (an ablation on the quickstart) or a
    ``--trainer.default_root_dir`` alone would write into, and move aside, another run's files."""
    import os

    trainer = _as_dict(trainer) or {}
    root, logger = trainer.get("default_root_dir"), trainer.get("logger")
    first = logger[0] if isinstance(logger, list) and logger else logger
    if root is None or not isinstance(first, dict):
        return
    save = (first.get("init_args") or {}).get("save_dir")
    if first.get("class_path", "").rsplit(".", 1)[-1] not in ("CSVLogger", "TensorBoardLogger") or save is None:
        return
    if os.path.abspath(str(save)) != os.path.abspath(str(root)):
        raise ValueError(f"trainer.default_root_dir {root} and trainer.logger's save_dir {save} disagree: the "
                         f"checkpoints and logs would go to {save}; give both the same folder, e.g. "
                         f"--trainer.default_root_dir {root} --trainer.logger.init_args.save_dir {root}")


def hpc_resume_path(trainer: dict | None, ckpt_path: str | None) -> str | None:
    """The checkpoint Lightning reads when ``hpc`` is named, or resumes a ``fit`` from when none is: with
    ``--ckpt_path hpc``, or under SLURM (a requeued job's plain ``srun anycity fit``) with no ``--ckpt_path``, the
    newest ``hpc_ckpt_N.ckpt`` (the largest N) in the parsed ``trainer`` section's ``default_root_dir`` (the working
    folder when unset), found by Lightning's own look-up; None where there is none, or another ``ckpt_path`` is
    given."""
    import os
    from types import SimpleNamespace

    from lightning.fabric.plugins.environments import SLURMEnvironment
    from lightning.pytorch.trainer.connectors.checkpoint_connector import _CheckpointConnector

    if not (ckpt_path == "hpc" or (ckpt_path is None and SLURMEnvironment.detect())):
        return None
    root = (_as_dict(trainer) or {}).get("default_root_dir") or os.getcwd()
    return _CheckpointConnector(SimpleNamespace(default_root_dir=str(root)))._hpc_resume_path


def require_weights(subcommand: str, config) -> None:
    """Refuse ``validate|test|predict`` with neither ``--ckpt_path`` nor ``model.pretrained``: it would score or
    export a randomly initialised network. ``model.init_from`` does not count: ``fit`` alone reads it, and it holds
    the Stage I scaffold only (the completion branch would be random)."""
    if config.get("ckpt_path") or config.get("model.init_args.pretrained"):
        return
    from anycity.lit.keep import _checkpoint_dirs

    where = (_checkpoint_dirs(configured_trainer(config.get("trainer"))) or [Path("runs/RUN/checkpoints")])[0]
    stage1 = " (model.init_from is read by fit only)" if config.get("model.init_args.init_from") else ""
    raise ValueError(f"anycity {subcommand}: no --ckpt_path, so the network's weights would be random{stage1}; pass "
                     f"the trained checkpoint, e.g. --ckpt_path {where / 'last.ckpt'}")


def check_checkpoint(path: str) -> None:
    """Refuse, in one line and before anything runs, a ``--ckpt_path`` file that is not a Lightning checkpoint (a
    plain ``state_dict`` such as VGGT's ``model.pt``), or whose stored hyperparameters this version has no option
    for (written by another version). Read memory-mapped: the weights are not loaded."""
    import importlib

    from anycity.safe_load import safe_torch_load

    ckpt = safe_torch_load(path, mmap=True, what="--ckpt_path")
    if not isinstance(ckpt, dict) or "pytorch-lightning_version" not in ckpt:
        raise ValueError(f"--ckpt_path {path}: not a Lightning checkpoint (a plain weights file?); pass it as "
                         "model.init_args.pretrained")
    stored = ckpt.get("hyper_parameters") or {}
    if not isinstance(stored, dict) or not isinstance(stored.get("_class_path", ""), str):
        raise ValueError(f"--ckpt_path {path}: its stored hyper_parameters are not an anycity model's (a checkpoint "
                         "of another project, or damaged); pass a checkpoint that an anycity fit wrote")
    stored = dict(stored)
    unknown = []
    if stored.get("_class_path"):  # written by LightningCLI: the class it names takes the stored keys
        module, _, name = stored["_class_path"].rpartition(".")
        try:
            cls = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError):
            return  # Lightning's own read names the class
        known = _init_params(cls)
        unknown = [k for k in stored if not k.startswith("_") and k not in known]
    net = _as_dict(stored.get("net"))
    if isinstance(net, dict):
        unknown += [f"net.{k}" for k in net if k not in _section_candidates("model.net.x")]
    if unknown:
        raise ValueError(f"--ckpt_path {path}: its stored model.{unknown[0]} is not an option of this anycity (written "
                         "by another version); use the anycity version that wrote it")


class Stopped(SystemExit):
    """A training command stopped by SIGTERM: exit code 143 (128 + 15, what a shell reports for a process the signal
    ended) and, on rank 0, one line saying where it stopped and how to go on (:func:`main` prints it)."""

    def __init__(self, message: str | None, code: int = 143) -> None:
        super().__init__(code)
        self.message = message


def _resume_verb(subcommand: str) -> str:
    return "resume from" if subcommand == "fit" else f"{subcommand} with"


def _cli_class():
    from lightning.pytorch.cli import LightningCLI

    import anycity.callbacks
    from anycity.callbacks import LossProgressBar, PredictionExport

    class AnyCityCLI(LightningCLI):
        """LightningCLI with the always-present ("forced") callbacks as top-level config groups:
        ``freeze``, ``previews``, ``progress``, ``export``, ``nonfinite``. They merge key by key across ``--config``
        files, unlike the ``trainer.callbacks`` list. The ``progress`` bar stays out when the trainer's bars are off
        or another progress bar is listed. ``predict`` keeps no predictions in memory (the export wrote them;
        ``--return_predictions true`` keeps them). ``--ckpt_path`` reads with the checkpoint allow-list of
        :mod:`anycity.safe_load`; ``--ckpt_path last`` is the file it names from the start (no last checkpoint:
        refused), and so are ``--ckpt_path hpc`` and the ``hpc_ckpt_N.ckpt`` a ``fit`` resumes from under SLURM with
        no ``--ckpt_path`` (a requeued job; :func:`hpc_resume_path`), so that the run is kept and built as a resumed
        one. Refused before
        anything is built or written: ``validate|test|predict`` with no weights (no
        ``--ckpt_path``, no ``model.pretrained``), and a ``trainer.default_root_dir`` that the logger's
        ``save_dir`` contradicts (:func:`check_run_folder`)."""

        def add_arguments_to_parser(self, parser) -> None:
            for section, name in CALLBACK_SECTIONS.items():
                parser.add_lightning_class_args(getattr(anycity.callbacks, name), section)

        def _prepare_subcommand_parser(self, klass, subcommand: str, **kwargs):
            parser = super()._prepare_subcommand_parser(klass, subcommand, **kwargs)
            if subcommand == "predict":  # the export writes every prediction; Lightning would also keep them all in
                parser.set_defaults(return_predictions=False)  # RAM (~350 MB a sample at paper size) until the end
            return parser

        def instantiate_trainer(self, **kwargs):
            """The trainer, with the ``progress`` bar unless the config turns bars off
            (``trainer.enable_progress_bar: false``) or lists another progress bar (Lightning refuses both),
            :class:`~anycity.callbacks.last_checkpoint.FinalLastCheckpoint` last (a finished fit's ``last.ckpt`` is
            its final step, whatever checkpoint callbacks the config lists), then
            :class:`~anycity.callbacks.requeue.RequeueAtSafePoint` after the checkpoint callbacks (a SLURM
            time-limit checkpoint is saved between steps), and ``SafeCheckpointIO`` also when the config lists
            other ``trainer.plugins`` (:func:`with_safe_checkpoint_io`)."""
            from lightning.pytorch.callbacks import ProgressBar

            from anycity.callbacks.last_checkpoint import FinalLastCheckpoint
            from anycity.callbacks.requeue import RequeueAtSafePoint

            extra = [self._get(self.config_init, c) for c in self._parser(self.subcommand).callback_keys]
            config = {**self._get(self.config_init, "trainer", default={}), **kwargs}
            config["plugins"] = with_safe_checkpoint_io(config.get("plugins"))
            listed = config.get("callbacks") or []
            listed = listed if isinstance(listed, list) else [listed]
            if config.get("enable_progress_bar") is False or any(isinstance(c, ProgressBar) for c in listed):
                extra = [c for c in extra if not isinstance(c, LossProgressBar)]
            # last: after NonFiniteGuard's on_train_end, which refuses a run whose steps were all skipped
            trainer = self._instantiate_trainer(config, [*extra, FinalLastCheckpoint()])
            trainer.callbacks.append(RequeueAtSafePoint())  # the Trainer has moved the checkpoint callbacks last
            return trainer

        @staticmethod
        def _find_last(subcommand: str, trainer) -> str:
            """The checkpoint ``--ckpt_path last`` means, found as Lightning finds it (the newest ``last*.ckpt`` of
            the checkpoint callbacks' folders) for ``trainer`` (:func:`configured_trainer`: before the network is
            built, so that it is built from that file's settings as for a file named, and before a
            ``validate|test|predict`` run moves its log folder). None found: one line naming any
            ``<folder>.N/last*.ckpt`` that an earlier fresh fit moved aside (Lightning would only warn and go on from
            the config's weights)."""
            from lightning.pytorch.callbacks import ModelCheckpoint, OnExceptionCheckpoint

            from anycity.lit.keep import _checkpoint_dirs

            found = {getattr(c, "ckpt_path", None) for c in trainer.callbacks
                     if isinstance(c, OnExceptionCheckpoint)}
            for c in trainer.checkpoint_callbacks:
                if isinstance(c, ModelCheckpoint):
                    found |= c._find_last_checkpoints(trainer)
            found = [Path(f) for f in found if f and Path(f).is_file()]
            if found:
                return str(max(found, key=lambda f: f.stat().st_mtime))
            dirs = _checkpoint_dirs(trainer) or [Path(trainer.default_root_dir) / "checkpoints"]
            aside = sorted((f for d in dirs for f in d.parent.glob(f"{d.name}.*/last*.ckpt")),
                           key=lambda f: f.stat().st_mtime)
            where = ", ".join(str(d) for d in dirs)
            if aside:
                raise FileNotFoundError(
                    f"--ckpt_path last: no last*.ckpt in {where}; an earlier run's is {aside[-1]} (a fresh fit moves "
                    f"the checkpoints before it aside): pass --ckpt_path {aside[-1]} to {_resume_verb(subcommand)} it")
            raise FileNotFoundError(f"--ckpt_path last: no last*.ckpt in {where}, so there is nothing to "
                                    f"{_resume_verb(subcommand)}; pass a checkpoint file"
                                    + (", or leave --ckpt_path out to start afresh" if subcommand == "fit" else ""))

        def _stopped(self, subcommand: str) -> str | None:
            """The line for a run stopped by SIGTERM (rank 0's; None on the other ranks)."""
            t = self.trainer
            if t.global_rank != 0:
                return None
            if subcommand == "fit":
                ckpts = [f for c in t.checkpoint_callbacks if getattr(c, "dirpath", None)
                         for f in Path(c.dirpath).glob("*.ckpt") if f.is_file()]
                ckpts += [f for f in Path(t.default_root_dir).glob("hpc_ckpt_*.ckpt") if f.is_file()]  # SIGUSR1's
                newest = max(ckpts, key=lambda f: f.stat().st_mtime) if ckpts else None
                how = (f"resume with the same command and --ckpt_path {newest}" if newest else
                       "nothing to resume from: rerun the command to start again")
                return (f"stopped by SIGTERM at step {t.global_step}; the newest checkpoint is "
                        f"{newest or 'none'}; {how}")
            line = f"stopped by SIGTERM during {subcommand}"
            export = next((c for c in t.callbacks if isinstance(c, PredictionExport)), None)
            if subcommand == "predict" and export is not None:
                line += f" after {len(export.written)} exported scene(s)"
                if export.unfinished:
                    line += f"; the city {export.unfinished} was not finished, so nothing was written for it"
                return line + "; rerun the command to predict them all"
            return line + "; no results were reported; rerun the command"

        def _parse_ckpt_path(self) -> None:
            import argparse

            sub = self.config.get("subcommand")
            if sub and isinstance(self.config[sub].get("ckpt_path"), str):  # --ckpt_path=~/x: no shell expands it
                self.config[f"{sub}.ckpt_path"] = str(Path(self.config[sub].ckpt_path).expanduser())
            if sub and self.config[sub].get("ckpt_path") == "last":  # the file, before the network is built
                self.config[f"{sub}.ckpt_path"] = self._find_last(sub, configured_trainer(self.config[sub].trainer))
            ckpt = self.config[sub].get("ckpt_path") if sub else None
            hpc = hpc_resume_path(self.config[sub].get("trainer"), ckpt) if sub == "fit" or ckpt == "hpc" else None
            if hpc:  # named, so that a fit resumes as with --ckpt_path: its checkpoints/ kept, the network built from
                from lightning.pytorch.utilities import rank_zero_info  # the file's settings, pretrained unread

                rank_zero_info(f"anycity: {sub} from {hpc} (this run folder's newest SLURM time-limit checkpoint)")
                self.config[f"{sub}.ckpt_path"] = hpc
            if sub and self.config[sub].get("ckpt_path") and Path(self.config[sub].ckpt_path).is_file():
                check_checkpoint(self.config[sub].ckpt_path)
            init = self.config.get(f"{sub}.model.init_args") if sub else None
            keep = {k: init[k] for k in TEST_TIME_KEYS if init is not None and k in init}
            asked_net = (init.get("net") if init is not None else None) or {}
            asked_init = dict(_as_dict(init) or {}) if init is not None else {}
            asked_class = self.config.get(f"{sub}.model.class_path") if sub else None
            import torch

            from anycity.safe_load import _safe_globals

            try:  # Lightning reads the checkpoint's hyperparameters with a bare weights_only torch.load: the types
                with torch.serialization.safe_globals(_safe_globals()):  # every other read allows, it allows too
                    super()._parse_ckpt_path()
            except (pickle.UnpicklingError, RuntimeError, EOFError):
                from anycity.safe_load import safe_torch_load

                safe_torch_load(self.config[sub].get("ckpt_path"), what="--ckpt_path")  # the one-line reason
                raise
            except argparse.ArgumentError as e:  # a stored value check_checkpoint could not foresee
                raise ValueError(f"--ckpt_path {self.config[sub].get('ckpt_path')}: its stored hyperparameters are "
                                 f"not accepted by this anycity (written by another version?): {_one_line(e)}") from e
            for k, v in keep.items():
                self.config[f"{sub}.model.init_args.{k}"] = v
            now_class = self.config.get(f"{sub}.model.class_path") if sub else None
            if asked_class and now_class and now_class != asked_class and sub == "fit":
                # a Stage II job sent to a Stage I run folder resumed Stage I under Stage II's trainer settings (or,
                # Stage I done, ended at once with exit 0, and the jobs waiting on it started)
                have, want = now_class.rsplit(".", 1)[-1], asked_class.rsplit(".", 1)[-1]
                fix = ("to start Stage II from it, pass it as --model.init_args.init_from in another run folder"
                       if (have, want) == ("ScaffoldModule", "RefinementModule") else
                       "resume it with its own stage's config, or give this fit another run folder")
                raise ValueError(f"--ckpt_path {self.config[sub].get('ckpt_path')} holds a {have}, but the config "
                                 f"fits a {want}: a fit resumes its own stage; {fix}")
            if asked_class and now_class and now_class != asked_class:  # Lightning takes the checkpoint's class
                from lightning.pytorch.utilities import rank_zero_warn

                rank_zero_warn(f"--ckpt_path {self.config[sub].get('ckpt_path')} holds a {now_class.rsplit('.', 1)[-1]}"
                               f", so that is what runs, not the config's {asked_class.rsplit('.', 1)[-1]}; pass the "
                               "other stage's checkpoint (or config) if that is not what you meant")
            ckpt = self.config[sub].get("ckpt_path") if sub else None
            if init is None or not ckpt or not Path(ckpt).is_file():
                return
            now = self.config[f"{sub}.model.init_args"]
            net, ignored = merge_ckpt_net(asked_net, now.get("net"), now.get("preset", "tiny"))
            from anycity.lit.scaffold import STAGE2_NET_KEYS, ScaffoldModule

            if issubclass(_model_class(now_class) or type, ScaffoldModule):  # a Stage I network: no completion branch
                ignored += [f"{k} {asked_net[k]!r} is not used (a Stage I network has no completion branch)"
                            for k in STAGE2_NET_KEYS if k in net and asked_net.get(k) is not None]
                net = {k: v for k, v in net.items() if k not in STAGE2_NET_KEYS}
            self.config[f"{sub}.model.init_args.net"] = net
            if ignored:
                from lightning.pytorch.utilities import rank_zero_warn

                rank_zero_warn(f"--ckpt_path {ckpt}: its network is built as it was trained, so model.net "
                               f"{'; '.join(ignored)} (only {', '.join(NET_TEST_TIME_KEYS)} may differ from the "
                               f"checkpoint's, and {', '.join(NET_MOVED_PATH_KEYS)} only as a moved file)")
            if sub == "fit":
                _warn_resumed_settings(ckpt, asked_init, _as_dict(now))
            if sub != "fit":  # the checkpoint holds the weights: the pretrained file is neither read nor needed (a
                # resumed fit keeps it, so that the checkpoints it writes still say what the run started from)
                self.config[f"{sub}.model.init_args.pretrained"] = None

        def before_instantiate_classes(self) -> None:
            sub = self.subcommand
            config = self.config[sub] if sub else self.config
            check_accelerator(config.get("trainer"))
            check_nodes(config.get("trainer"))
            check_run_folder(config.get("trainer"))
            check_model_class(config.get("model.class_path"))
            if sub in ("validate", "test", "predict"):
                require_weights(sub, config)

        def instantiate_classes(self) -> None:
            import contextlib

            from anycity.lit.base import resuming

            sub = self.config.get("subcommand")
            ckpt = self.config[sub].get("ckpt_path") if sub == "fit" else None
            with resuming() if ckpt and Path(ckpt).is_file() else contextlib.nullcontext():
                super().instantiate_classes()

        def _run_subcommand(self, subcommand: str) -> None:
            from lightning.pytorch.utilities import rank_zero_info

            from anycity.lit.keep import RunLocks, separate_from_training

            check_split = getattr(self.datamodule, "check_split", None)
            if check_split is not None:  # a split with no shards: refused before any log file moves
                check_split(subcommand, self.trainer)
            moved_to = separate_from_training(self.trainer, subcommand) or \
                self._separate_without_logger(subcommand)  # the training's own files stay as they are
            if moved_to is not None:
                rank_zero_info(f"anycity: this {subcommand} run's config, logs and previews go to {moved_to}")
            # a second run in this folder would move this one's files aside and write beside them: refused, before
            # anything moves; rank 0 alone writes there
            locks = RunLocks(subcommand, enabled=self.trainer.global_rank == 0)
            try:
                locks.take(Path(self.trainer.log_dir or self.trainer.default_root_dir), "--trainer.default_root_dir")
                self._run_locked(subcommand, locks)
            finally:
                locks.release()

        def _run_locked(self, subcommand: str, locks) -> None:
            """:meth:`_run_subcommand` holding the run folder's lock: a ``predict`` also locks the export folder
            it moves aside, then earlier runs' files are kept and Lightning runs."""
            from anycity.lit.keep import keep_previous_run

            export_root = scene = None
            if subcommand == "predict":
                export = next((c for c in self.trainer.callbacks if isinstance(c, PredictionExport)), None)
                if export is not None:  # checked before the model runs: the export is written after it
                    from anycity.atomic import check_writable_folder

                    export_root = export.root(self.trainer)
                    check_writable_folder(export_root, "--export.out_dir" if export.out_dir else
                                          "the predictions folder")
                photos = getattr(getattr(self.datamodule, "hp", None), "predict_images", None)
                if photos:
                    from anycity.data.photos import scene_name

                    scene = scene_name(photos)
                    folder = (export_root / scene).resolve() if export_root is not None else None
                    if folder is not None and folder in (Path(photos).resolve(), *Path(photos).resolve().parents):
                        raise ValueError(f"--export.out_dir: the scene folder {folder} would hold the photos "
                                         f"{photos} (an earlier export there is moved aside); pass an "
                                         "--export.out_dir outside it")
                if export_root is not None:  # another predict into it would move it aside while this one writes
                    locks.take(export_root / scene if scene else export_root,
                               "--export.out_dir" if export.out_dir else "--trainer.default_root_dir", beside=True)
            keep_previous_run(self.trainer, subcommand, self.config[subcommand].get("ckpt_path"), export_root, scene)
            from lightning.pytorch.utilities.exceptions import SIGTERMException

            try:
                self._run_lightning(subcommand)
            except SIGTERMException as e:  # a SystemExit with no code: the shell would see success, and no word
                raise Stopped(self._stopped(subcommand)) from e

        def _separate_without_logger(self, subcommand: str) -> Path | None:
            """With no logger (``--trainer.logger false``), :func:`~anycity.lit.keep.separate_from_training` for a
            ``validate|test|predict`` run in a training run's folder (``default_root_dir``, by
            :func:`~anycity.lit.keep.is_training_folder`): its ``config.yaml``, previews and default ``predictions/``
            go to ``<default_root_dir>/<subcommand>/``, not over the training's ``config.yaml``. Returns that folder, or
            None. A ``--ckpt_path hpc`` was resolved in the training's folder already (``_parse_ckpt_path``)."""
            from anycity.lit.keep import is_training_folder

            t = self.trainer
            root = Path(t.default_root_dir)
            if subcommand == "fit" or t.loggers or not is_training_folder(root):
                return None
            t._default_root_dir = str(root / subcommand)  # where Lightning's log_dir and SaveConfigCallback write
            return root / subcommand

        def _run_lightning(self, subcommand: str) -> None:
            from lightning.pytorch.utilities import rank_zero_info

            if subcommand == "fit":
                super()._run_subcommand(subcommand)
                last = next((c.last_model_path for c in self.trainer.checkpoint_callbacks if c.last_model_path), None)
                if last:
                    rank_zero_info(f"anycity: last checkpoint {last} (--ckpt_path last resumes from it)")
                return
            with warnings.catch_warnings():  # no checkpoint is written, so which callback states come back is moot
                for note in ("The dirpath has changed from", "Be aware that when using `ckpt_path`, callbacks"):
                    warnings.filterwarnings("ignore", message=note)
                # shards stream as an IterableDataset, and PredictionExport does not read the batch indices
                warnings.filterwarnings("ignore", message="Couldn't infer the batch indices fetched from your")
                super()._run_subcommand(subcommand)

        def before_predict(self) -> None:
            # A data module without a predict set reconstructs its test scenes.
            from lightning.pytorch import LightningDataModule

            dm = self.datamodule
            if dm is not None and type(dm).predict_dataloader is LightningDataModule.predict_dataloader:
                dm.predict_dataloader = dm.test_dataloader

    return AnyCityCLI


def with_safe_checkpoint_io(plugins):
    """``trainer.plugins`` with :class:`~anycity.lit.checkpoint_io.SafeCheckpointIO` added unless one of them is a
    ``CheckpointIO``: naming any plugin (a cluster environment, a precision plugin) replaces the CLI's default
    value, which would silently drop the atomic checkpoint writes and the weights-only reads."""
    from lightning.fabric.plugins import CheckpointIO

    from anycity.lit.checkpoint_io import SafeCheckpointIO

    listed = [] if plugins is None else list(plugins) if isinstance(plugins, (list, tuple)) else [plugins]
    if any(isinstance(p, CheckpointIO) for p in listed):
        return plugins
    return [*listed, SafeCheckpointIO()]


def _not_an_advert(record: logging.LogRecord) -> bool:
    """False for Lightning's "💡 Tip: ... try installing litlogger / litmodels" lines (printed at every Trainer)."""
    return not record.getMessage().startswith("💡 Tip:")


def quiet_third_party_noise() -> None:
    """Silence warnings and notices about other libraries' code or products that no user setting can change."""
    # Lightning 2.6's pytree helper builds torch's deprecated LeafSpec: with torch >= 2.10 every fit and test printed it
    warnings.filterwarnings("ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated",
                            category=FutureWarning)
    # Lightning 2.6 advertises its cloud logger and model registry (up to two lines per Trainer) on its rank-zero logger
    lightning_info = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    if _not_an_advert not in lightning_info.filters:
        lightning_info.addFilter(_not_an_advert)


def build_cli(args: list[str] | None = None, run: bool = True, parser_kwargs: dict | None = None):
    """Build (and by default run) the training CLI in-process; ``args`` as on the command line after
    ``anycity``, e.g. ``["fit", "--config", "configs/quickstart.yaml"]``. Returns the LightningCLI object."""
    quiet_third_party_noise()
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
        parser_kwargs=parser_kwargs,
    )


HELP = """usage: anycity COMMAND [options]   (anycity COMMAND --help for a command's options)

Commands:
  data synth     render procedural aerial cities into webdataset shards
  data convert   convert a posed dataset (colmap, nerfstudio, llff, ...) into shards
  fit            train a model (LightningCLI; --config configs/quickstart.yaml)
  validate       evaluate a model on the validation split
  test           evaluate a model on the test split (held-out views)
  predict        reconstruct scenes from photos: scene.ply, cameras.json, renders
  export         write a predicted scene as .splat, COLMAP text, nerfstudio transforms.json or PLY
  view           open a predicted scene in the browser (viser: splats, cameras, provenance)
  render-video   render an mp4 fly-through along the predicted cameras

Options:
  --debug        show the full traceback of an error (or set ANYCITY_DEBUG=1)
  --version      print anycity's version
"""

# the top-level keys of a training command's config (`anycity fit --print_config`; tests/integration/test_front_door.py)
SECTIONS = ("seed_everything", "trainer", "model", "data", "freeze", "previews", "progress", "export", "nonfinite",
            "ckpt_path", "weights_only")
# the always-present callbacks' config sections and their classes in anycity.callbacks
CALLBACK_SECTIONS = {"freeze": "FreezeModules", "previews": "ImagePreviews", "progress": "LossProgressBar",
                     "export": "PredictionExport", "nonfinite": "NonFiniteGuard"}
_ALIASES = {"learning_rate": "lr", "learningrate": "lr", "max_step": "max_steps", "epochs": "max_epochs"}


def _one_line(e: BaseException) -> str:
    """The message our code wrote, without the DataLoader worker's "Caught ... Original Traceback" wrapper."""
    import re

    lines = [ln for ln in str(e).strip().splitlines() if ln.strip()]
    if not lines:
        return type(e).__name__
    if lines[0].startswith("Caught ") and "worker" in lines[0]:
        m = re.match(r"^\s*(?:\w+\.)*\w+(?:Error|Exception): (.*)$", lines[-1])
        return m.group(1) if m else lines[-1].strip()
    # jsonargparse's "Does not validate against any of the Union subtypes ... Errors: - <ours> - Expected a
    # <class 'NoneType'>": the first listed error that is not the None alternative is the one our code wrote.
    for i, ln in enumerate(lines):
        if ln.strip().startswith("- ") and "Expected a <class" not in ln:
            indent = len(ln) - len(ln.lstrip())
            rest = [r.strip() for r in lines[i + 1:i + 3] if len(r) - len(r.lstrip()) > indent
                    and not r.strip().startswith("- ")]  # the reason jsonargparse wraps onto the next lines
            return " ".join([ln.strip()[2:], *rest])
    return " ".join(ln.strip() for ln in lines) if len(lines) <= 3 else lines[0]


def _candidates(message: str) -> list[str]:
    """Option names the bad key could have meant: init parameters of the class the error names, else of every
    class the training CLI configures."""
    import importlib
    import re

    classes = []
    for path in re.findall(r"class_path '([\w.]+)'", message):
        mod, _, name = path.rpartition(".")
        try:
            classes.append(getattr(importlib.import_module(mod), name))
        except (ImportError, AttributeError):
            pass
    if not classes:
        from lightning.pytorch import Trainer

        from anycity.lit import AnyCityModule
        from anycity.lit.datamodule import AerialDataModule

        classes = [Trainer, AerialDataModule, AnyCityModule, *AnyCityModule.__subclasses__()]
    return sorted(set().union(*(_init_params(c) for c in classes)))


def _section_candidates(dotted: str) -> list[str] | None:
    """Valid keys beside ``dotted`` (``data.x``, ``trainer.x``, ``model[.init_args].net.x``), or None when the
    section is not one of those."""

    parts = dotted.lstrip("-").split(".")[:-1]
    if "net" in parts:
        import dataclasses

        from anycity.models.presets import preset_config

        return sorted(f.name for f in dataclasses.fields(preset_config("tiny")))
    if parts[:1] in (["data"], ["trainer"]):
        if parts[0] == "data":
            from anycity.lit.datamodule import AerialDataModule as cls
        else:
            from lightning.pytorch import Trainer as cls
        return sorted(_init_params(cls))
    if parts[:1] and parts[0] in CALLBACK_SECTIONS:
        import anycity.callbacks

        return sorted(_init_params(getattr(anycity.callbacks, CALLBACK_SECTIONS[parts[0]])))
    return None


def config_error(message: str, argv: list[str]) -> str:
    """One line for a jsonargparse error: the unknown option or config-file key and the nearest valid key."""
    import difflib
    import re

    refused = _refused_value(message, argv) or _missing_model(message, argv) or _net_value_error(message)
    if refused:
        return refused
    path = re.search(r"Expected a path but ([\w.]+) either not accessible or invalid", message)
    if path and 'Parser key "model"' in message:  # a class that is not an AnyCityModule (PosePriorModule)
        try:
            check_model_class(path.group(1))
        except ValueError as e:
            return str(e)
    # a command-line option's key; not one whose class_path was refused (that is a value, named below)
    nested = [] if "has no attribute" in message else re.findall(r"NestedArg\(key='(\w+)'", message)
    bad = re.findall(r"Option '([\w.]+)' is not accepted", message) + nested
    bad += re.findall(r"[Kk]ey '([\w.]+)' is not expected", message)
    # a key in a --config file ("nested key" in jsonargparse 4.39); in a callback section, the section named apart
    grouped = re.findall(r"Group '(\w+)' does not accept (?:option|nested key) '([\w.]+)'", message)
    bad += [f"{g}.{k}" for g, k in grouped] or re.findall(r"does not accept (?:option|nested key) '([\w.]+)'", message)
    bad += re.findall(r"[Uu]nrecognized arguments: --([\w.]+)", message)  # capitalised in older releases
    from_top = bool(bad)  # each of these names the key from the config's top (model.init_args.x)
    unexpected = re.search(r"Unexpected keys: \{'(\w+)'", message)  # a typed dict's key (model.net) in a file
    if unexpected:
        section = re.findall(r'Parser key "(\w+)"', message[:unexpected.start()])
        bad.append(".".join(section[-1:] + [unexpected.group(1)]))
    if not bad:
        # a class typo as --model's value: jsonargparse lists "Expected a path" before the class_path problem
        flat = " ".join(ln.strip() for ln in message.splitlines())
        problem = re.search(r"Problem with given class_path '[\w.]+': module '[\w.]+' has no attribute '\w+'", flat)
        return (_yaml_error(argv) if "Problems parsing config" in message else None) or \
            _class_path_hint(problem.group(0) if problem else _one_line(message).replace("\n", " "))
    section = bad[0].split(".")[0]
    model_key = _model_section_key(bad[0], message, argv)
    if model_key:
        return model_key
    if from_top and "." in bad[0] and section not in SECTIONS:  # a misspelt section (modle:) is the key to name
        near = difflib.get_close_matches(section, SECTIONS, n=1, cutoff=0.6)
        return f"unknown section {section} (in {bad[0]})" + (f"; did you mean {near[0]}?" if near else
                                                              f"; expected one of {', '.join(SECTIONS)}")
    key = bad[0].split(".")[-1]
    elsewhere = _other_module_option(key, message, argv)
    if elsewhere:
        return elsewhere
    given = next((a.split("=")[0] for a in argv if a.startswith("--") and
                  (a.split("=")[0].endswith("." + key) or a.split("=")[0] == f"--{bad[0]}")), None)
    where = given or bad[0]
    candidates = _section_candidates(where) if "." in where else None
    near = difflib.get_close_matches(key, candidates if candidates is not None else _candidates(message), n=1,
                                     cutoff=0.6)
    alias = difflib.get_close_matches(key.lower(), list(_ALIASES), n=1, cutoff=0.8)
    hint = near[0] if near else (f"{_ALIASES[alias[0]]} ({alias[0].replace('_', ' ')})" if alias else None)
    what = f"unknown option {given}" if given else f"unknown key {bad[0]} in a --config file"
    command = argv[0] if argv and argv[0] in LIGHTNING else "COMMAND"
    return what + (f"; did you mean {hint}?" if hint else f"; see anycity {command} --help")


def _model_section_key(bad: str, message: str, argv: list[str]) -> str | None:
    """One line for a misspelt ``init_args``/``class_path`` under ``model`` (``model: {init_arg: ...}``,
    ``--model.init_arg.lr``): jsonargparse names the key from ``model`` down, which read as an unknown top-level
    section (``init_arg``). None for other keys."""
    import difflib

    if 'Parser key "model"' not in message:
        return None
    head, _, rest = bad.partition(".")
    near = difflib.get_close_matches(head, ["init_args", "class_path"], n=1, cutoff=0.6)
    if not near or near[0] == head:
        return None
    given = next((a.split("=")[0] for a in argv if a.split("=")[0] == f"--model.{bad}"), None)
    if given:
        return f"unknown option {given}; did you mean --model.{near[0]}{'.' + rest if rest else ''}?"
    return f"unknown key model.{head} (in model.{bad}) in a --config file; did you mean model.{near[0]}?"


def _missing_model(message: str, argv: list[str]) -> str | None:
    """One line for "the following arguments are required: test.model" (a ``validate|test|predict`` given only a
    ``--ckpt_path``): which config or class to pass. None for other errors."""
    import re

    m = re.search(r"arguments are required: (\w+)\.model\b", message)
    if not m:
        return None
    ckpt = _option_values(argv, ("--ckpt_path",))
    named = Path(ckpt[-1][1]) if ckpt else None
    run = named.parent.parent / "config.yaml" if named and named.is_file() else None  # <run>/checkpoints/last.ckpt
    config = run if run is not None and run.is_file() else "<run folder>/config.yaml"
    return (f"anycity {m.group(1)}: no model given (no config named one); pass the run's config, -c {config}, or "
            "the stage's class, --model anycity.lit.ScaffoldModule (Stage I) or --model anycity.lit.RefinementModule "
            "(Stage II)")


def _net_value_error(message: str) -> str | None:
    """One line for a ``model.init_args.net`` value of the wrong type in a --config file (``inject_layers: 3``):
    jsonargparse's message names ``net`` only ("Parser key "net": Does not validate against any of the Union
    subtypes"). None for other errors, and where the key cannot be told."""
    import ast
    import dataclasses
    import re

    start = re.search(r'Parser key "net":', message)
    if not start or "Unexpected keys" in message:
        return None
    values = []
    for given in re.findall(r"Given value: (.*)$", message[start.end():], re.M):
        try:
            values.append(ast.literal_eval(given.strip()))
        except (ValueError, SyntaxError):
            values.append(given.strip())
    net = next((v for v in values if isinstance(v, dict)), None)
    bad = next((v for v in values if not isinstance(v, dict)), None)
    key = next((k for k, v in (net or {}).items() if not isinstance(v, dict) and str(v) == str(bad)), None)
    if key is None:
        return None
    from anycity.models.presets import NetConfig

    kind = next((str(f.type) for f in dataclasses.fields(NetConfig) if f.name == key), "another type")
    kind = kind.replace(" | None", " or null").replace("tuple[int, ...]", "a list of integers")
    return f"model.init_args.net.{key} {net[key]!r}: not accepted; expected {kind} (in a --config file)"


def _other_module_option(key: str, message: str, argv: list[str]) -> str | None:
    """One line for a model key that the class jsonargparse built does not take but the other stage's module does
    (``pres_weight``, Stage II's, in an ablation overlay given without its stage's config); None otherwise."""
    import importlib
    import re

    import yaml

    import anycity.lit

    named = []
    for path in re.findall(r"class_path '([\w.]+)'", message):
        module, _, name = path.rpartition(".")
        try:
            named.append(getattr(importlib.import_module(module), name))
        except (ImportError, AttributeError, ValueError):
            pass
    built = next((c for c in named if isinstance(c, type) and issubclass(c, anycity.lit.AnyCityModule)), None)
    if built is None or key in _init_params(built):
        return None
    other = next((name for name in _STAGE_MODULES if getattr(anycity.lit, name) is not built
                  and key in _init_params(getattr(anycity.lit, name))), None)
    if other is None:
        return None
    source = None
    for _, value in _option_values(argv, ("-c", "--config")):
        try:
            model = (yaml.safe_load(Path(value).read_text()) or {}).get("model") or {}
        except (OSError, yaml.YAMLError, AttributeError):
            continue
        if key in ((model.get("init_args") if isinstance(model, dict) else None) or {}):
            source = value
    stage, configs = _STAGE_MODULES[other]
    where = f"before -c {source}" if source else "before this option"
    return (f"{key} is an option of anycity.lit.{other} ({stage}), not of the model class this run builds "
            f"({built.__name__}); put {configs} {where}")


# each stage's module in anycity.lit and the configs that build it, named when a key of one is given to another
_STAGE_MODULES = {"ScaffoldModule": ("Stage I", "-c configs/stage1.yaml (or -c configs/quickstart.yaml)"),
                  "RefinementModule": ("Stage II", "-c configs/stage2.yaml (or -c configs/quickstart.yaml -c "
                                                   "configs/quickstart_stage2.yaml)")}

_UNKNOWN_KEY = ("is not accepted", "is not expected", "Unexpected keys", "does not accept", "No action for key",
                "nrecognized arguments")


def _refused_value(message: str, argv: list[str]) -> str | None:
    """One line for a value jsonargparse refused for a known command-line option (``--model.init_args.preset huge``;
    its message names the option only as ``NestedArg(key='preset', ...)``): the option, the value and what is
    accepted. None for other errors."""
    import re

    keys = re.findall(r"NestedArg\(key='([\w.]+)'", message)
    expected = [e for e in re.findall(r"Expected a (.+?)(?:\. Got value: .*)?$", message, re.M) if "NoneType" not in e]
    if not keys or not expected or any(m in message for m in _UNKNOWN_KEY):
        return None
    option = next((a.split("=")[0] for a in argv if a.startswith("--") and a.split("=")[0].endswith("." + keys[-1])),
                  f"--model.init_args.{keys[-1]}")
    given = _option_values(argv, (option,))
    literal = re.match(r"typing\.Literal\[(.*)\]$", expected[0])
    kind = re.match(r"<class '(?:\w+\.)*(\w+)'>$", expected[0])
    if literal:
        accepted = "one of " + ", ".join(v.strip().strip("'\"") for v in literal.group(1).split(","))
    elif kind:
        accepted = {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string",
                    "list": "a list, e.g. [a, b]", "dict": "a mapping, e.g. {key: value}"}.get(kind.group(1),
                                                                                            f"a {kind.group(1)}")
    else:
        accepted = expected[0]
    return f"{option} {given[-1][1] if given else ''}: not accepted; expected {accepted}".replace("  ", " ")


def _yaml_error(argv: list[str]) -> str | None:
    """The --config file that is not valid YAML, with the parser's line and column (jsonargparse names neither)."""
    import yaml

    for _, value in _option_values(argv, ("-c", "--config")):
        if Path(value).is_file():
            try:
                yaml.safe_load(Path(value).read_text())
            except yaml.YAMLError as e:
                mark = getattr(e, "problem_mark", None)
                where = f" line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
                problem = getattr(e, "problem", None) or str(e).splitlines()[0]
                return f"--config {value}:{where}: not valid YAML ({problem})"
    return None


def _class_path_hint(line: str) -> str:
    """Add the nearest class to jsonargparse's "Problem with given class_path 'a.b.C': module 'a.b' has no
    attribute 'C'"."""
    import difflib
    import importlib
    import re

    m = re.search(r"class_path '([\w.]+)'.*has no attribute '(\w+)'", line)
    if not m:
        return line
    try:
        module = importlib.import_module(m.group(1).rpartition(".")[0])
    except ImportError:
        return line
    classes = [n for n in dir(module) if not n.startswith("_") and isinstance(getattr(module, n), type)
               and n != "AnyCityModule"]  # a class, never a submodule (anycity.lit.scaffold); not the base class
    near = difflib.get_close_matches(m.group(2), classes, n=1)
    return line + (f"; did you mean {module.__name__}.{near[0]}?" if near else "")


def _dispatch(args: list[str], argv_given: bool) -> int:
    if not args or args[0] in ("-h", "--help", "help"):
        print(HELP, end="")
        return 0
    if args[0] in ("--version", "-V"):
        from anycity import __version__

        print(f"anycity {__version__}")
        return 0
    cmd, rest = args[0], args[1:]
    if cmd == "data":
        from anycity.data.cli import data_main

        return int(data_main(rest) or 0)
    if cmd == "export":
        from anycity.export.cli import export_main

        return int(export_main(rest) or 0)
    if cmd == "view":
        from anycity.viewer.server import view_main

        return int(view_main(rest) or 0)
    if cmd == "render-video":
        from anycity.viewer.video import render_video_main

        return int(render_video_main(rest) or 0)
    if cmd in LIGHTNING or cmd.startswith("-"):
        import argparse

        check_input_files(args)
        check_config_placement(args)
        replaced = replaced_net_keys(args) + dropped_model_keys(args)
        if replaced:
            from lightning.pytorch.utilities import rank_zero_warn

            for message in replaced:
                rank_zero_warn(message)
        saved = sys.argv[:]
        sys.argv[1:] = args  # LightningCLI reads sys.argv itself (and warns when given args that differ from it)
        try:
            build_cli(None, parser_kwargs={"exit_on_error": False})
        except argparse.ArgumentError as e:
            raise ValueError(config_error(str(e), args)) from e
        finally:
            sys.argv[:] = saved
        return 0
    raise ValueError(f"unknown command {cmd!r}; expected one of data, {', '.join(LIGHTNING)}, export, view, "
                     "render-video (anycity --help)")


def main(argv: list[str] | None = None) -> int:
    """Console entry point (``anycity``)."""
    import errno
    import os

    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args or os.environ.get("ANYCITY_DEBUG", "") not in ("", "0")
    args = [a for a in args if a != "--debug"]
    try:
        if debug:
            return _dispatch(args, argv is not None)
        try:
            return _dispatch(args, argv is not None)
        except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError,
                PermissionError) as e:
            print(f"anycity: error: {_one_line(e)}  (--debug for the traceback)", file=sys.stderr)
            return 2
        except OSError as e:  # a full disk or quota: anycity.atomic and the shard writer name the file and the bytes
            if e.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            what = e.strerror or str(e)
            print(f"anycity: error: {what}{f': {e.filename}' if e.filename else ''}  (--debug for the traceback)",
                  file=sys.stderr)
            return 1
    except Stopped as e:  # SIGTERM (a cluster's preemption, kill): exit 143, not the 0 of a finished run
        if e.message:
            print(f"anycity: {e.message}", file=sys.stderr)
        return e.code


if __name__ == "__main__":
    sys.exit(main())
