"""Freeze parameters by glob pattern before optimisers are built (covers the "frozen transformer" ablations)."""

from __future__ import annotations

from fnmatch import fnmatchcase

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Callback
from torch import nn

from anycity.models.anycity import SCAFFOLD_PREFIXES


def require_matches(module: nn.Module, patterns: list[str], what: str) -> None:
    """Raise one line for the first glob of ``patterns`` that matches no name of ``module.named_parameters()``
    (``what`` starts the message, e.g. ``"freeze: pattern"``): a typo would otherwise silently do nothing."""
    names = [n for n, _ in module.named_parameters()]
    for pat in patterns:
        if not any(fnmatchcase(n, pat) for n in names):
            sample = ", ".join(sorted({n.split(".")[0] + "." + n.split(".")[1] if "." in n else n for n in names})[:8])
            raise ValueError(f"{what} {pat!r} matches no parameter; names look like {sample}, ...; "
                             "fix the pattern (globs match full dotted names)")


def freeze_by_patterns(module: nn.Module, patterns: list[str], unfreeze: list[str] | None = None) -> list[str]:
    """Set ``requires_grad=False`` on every parameter whose name matches one of ``patterns`` and none of
    ``unfreeze``.

    Args:
        module: the model (names as in ``module.named_parameters()``).
        patterns: glob patterns, e.g. ``"net.aggregator.*"``.
        unfreeze: exceptions inside the group ``patterns`` match (e.g. LoRA ``"*lora_*"``): those parameters are
            left as they are, not frozen. Nothing is set trainable, so a parameter frozen elsewhere (e.g. Stage
            II's scaffold) stays frozen.
    Returns:
        The names frozen.
    Raises:
        ValueError: a pattern that matches no parameter (a typo would silently train everything), or an
            ``unfreeze`` pattern that matches none of the parameters ``patterns`` match (it would do nothing).
    """
    unfreeze = unfreeze or []
    require_matches(module, [*patterns, *unfreeze], "freeze: pattern")
    grouped = {n for n, _ in module.named_parameters() if any(fnmatchcase(n, pat) for pat in patterns)}
    for u in unfreeze:
        if not any(fnmatchcase(n, u) for n in grouped):
            raise ValueError(f"freeze.unfreeze: pattern {u!r} matches none of the parameters freeze.patterns "
                             f"{patterns} freeze, so it would change nothing (it only exempts parameters from those "
                             "patterns); fix it, add the pattern it belongs under to freeze.patterns, or drop it")
    frozen = []
    for n, p in module.named_parameters():
        if n in grouped and not any(fnmatchcase(n, u) for u in unfreeze):
            p.requires_grad_(False)
            frozen.append(n)
    return frozen


class FreezeModules(Callback):
    """Freeze parameters of the LightningModule whose names match glob patterns, in ``setup``.

    ``setup`` runs before ``configure_optimizers`` and before DDP wraps the model, so frozen parameters get
    neither optimiser state nor gradient buckets. The module is frozen for the whole run (no unfreezing
    schedule), so a plain callback is used rather than ``BaseFinetuning``, whose param-group restore on resume
    would fight the LR schedule.

    Args:
        patterns: glob patterns over ``pl_module.named_parameters()`` names, e.g. ``["net.aggregator.*"]``.
            Empty list = no-op. A pattern that matches nothing raises ``ValueError``.
        unfreeze: patterns not frozen inside the set ``patterns`` match (e.g. ``["*lora_*"]``); one that matches
            none of that set, or any given without ``patterns``, raises ``ValueError``.
        allow_random_init: freeze scaffold weights (``net.aggregator|camera_head|depth_head|gaussian_head.*``) in a
            fit whose module loads none (neither ``model.pretrained`` nor ``model.init_from``): they stay at their
            random init. Refused unless true (e.g. the frozen ablations at quickstart scale, trained from scratch).
    """

    def __init__(self, patterns: list[str] | None = None, unfreeze: list[str] | None = None,
                 allow_random_init: bool = False) -> None:
        self.patterns = list(patterns or [])
        self.unfreeze = list(unfreeze or [])
        self.allow_random_init = allow_random_init
        self.frozen: list[str] = []

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if not self.patterns:
            if self.unfreeze:
                raise ValueError(f"freeze.unfreeze: {self.unfreeze} given without freeze.patterns, so it would change "
                                 "nothing (it only exempts parameters from those patterns, and unfreezes nothing "
                                 "frozen elsewhere); set freeze.patterns or drop freeze.unfreeze")
            return
        self.frozen = freeze_by_patterns(pl_module, self.patterns, self.unfreeze)
        if stage == "fit" and not self.allow_random_init:
            require_loaded_weights(pl_module, self.frozen)


def require_loaded_weights(module: nn.Module, frozen: list[str]) -> None:
    """Raise one line when ``frozen`` (parameter names) holds scaffold weights and ``module`` loads none: its
    ``hparams`` have neither ``pretrained`` nor ``init_from``, so they would stay random for the whole fit."""
    hp = getattr(module, "hparams", None) or {}
    if hp.get("pretrained") or hp.get("init_from"):
        return
    scaffold = [n for n in frozen if n.startswith(tuple(f"net.{p}" for p in SCAFFOLD_PREFIXES))]
    if scaffold:
        raise ValueError(f"freeze.patterns: {len(scaffold)} scaffold weights (e.g. {scaffold[0]}) would stay frozen at "
                         "their random init (no model.pretrained, no model.init_from); pass the weights, e.g. "
                         "--model.init_args.pretrained /path/to/vggt/model.pt, or --freeze.allow_random_init true to "
                         "freeze random weights on purpose")
