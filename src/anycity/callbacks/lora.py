"""Inject LoRA adapters (peft) into linear layers chosen by glob pattern, in ``setup`` of every stage.

LoRA changes the state-dict keys, so it must be injected before any checkpoint is loaded: Lightning calls
callback ``setup`` before restoring ``--ckpt_path`` for fit, validate, test and predict alike.
"""

from __future__ import annotations

import re
from fnmatch import fnmatchcase

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Callback
from torch import nn


def inject_lora(module: nn.Module, patterns: list[str], rank: int = 8, alpha: float = 16.0,
                dropout: float = 0.0) -> list[str]:
    """Wrap every ``nn.Linear`` whose dotted name (relative to ``module``) matches a glob in ``patterns``.

    Already-injected layers are left alone (idempotent). Base weights of wrapped layers are frozen; the
    ``lora_A``/``lora_B`` weights are trainable (``lora_B`` starts at zero, so outputs are unchanged).

    Returns:
        The names of the wrapped layers.
    Raises:
        ValueError: a pattern matching no linear layer, or rank < 1.
    """
    from peft import LoraConfig, inject_adapter_in_model

    if rank < 1:
        raise ValueError(f"lora: rank must be >= 1, got {rank}")
    linears = [n for n, m in module.named_modules() if isinstance(m, nn.Linear) and "lora_" not in n]
    already = {n.rsplit(".base_layer", 1)[0] for n in linears if n.endswith(".base_layer")}
    candidates = [n for n in linears if not n.endswith(".base_layer")] + sorted(already)
    for pat in patterns:
        if not any(fnmatchcase(n, pat) for n in candidates):
            raise ValueError(f"lora: pattern {pat!r} matches no nn.Linear under the model; fix the pattern "
                             f"(e.g. 'video_prior.*.to_q'), first linear names: {candidates[:5]}")
    targets = [n for n in candidates if any(fnmatchcase(n, p) for p in patterns) and n not in already]
    if targets:
        # peft marks only adapters trainable across the whole model: remember and restore everyone else's flag
        trainable = {n: p.requires_grad for n, p in module.named_parameters()}
        regex = "|".join(re.escape(n) for n in targets)
        cfg = LoraConfig(r=rank, lora_alpha=alpha, lora_dropout=dropout, target_modules=f"^({regex})$")
        inject_adapter_in_model(cfg, module)
        for n, p in module.named_parameters():
            if n in trainable:
                p.requires_grad_(trainable[n])
    for n in sorted(already | set(targets)):
        layer = module.get_submodule(n)
        for pn, p in layer.named_parameters():
            p.requires_grad_("lora_" in pn)
    return targets


class LoRAInjection(Callback):
    """LoRA adapters on ``pl_module.<attribute>``'s linear layers, injected in ``setup`` for every stage.

    Args:
        patterns: glob patterns over linear-layer names relative to ``attribute`` (e.g.
            ``["video_prior.backbone.*.attn1.to_q"]``). Empty list = no-op.
        rank, alpha, dropout: LoRA hyper-parameters.
        attribute: the submodule of the LightningModule to inject into (default ``"net"``).
    """

    def __init__(self, patterns: list[str] | None = None, rank: int = 8, alpha: float = 16.0,
                 dropout: float = 0.0, attribute: str = "net") -> None:
        self.patterns = list(patterns or [])
        self.rank, self.alpha, self.dropout, self.attribute = rank, alpha, dropout, attribute
        self.injected: list[str] = []

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if not self.patterns:
            return
        target = pl_module.get_submodule(self.attribute) if self.attribute else pl_module
        self.injected += inject_lora(target, self.patterns, self.rank, self.alpha, self.dropout)
