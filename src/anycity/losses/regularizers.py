"""Stage II regulariser ``L_reg``: residual magnitude, gate statistics, Gaussian attribute stability."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from anycity.structures import Gaussians


def _gate_terms(gates: Sequence[Tensor] | Tensor | None, ref: Tensor) -> tuple[Tensor, Tensor]:
    if gates is None:
        return ref.new_zeros(()), ref.new_zeros(())
    gs = [gates] if isinstance(gates, Tensor) else list(gates)
    if not gs:
        return ref.new_zeros(()), ref.new_zeros(())
    g = torch.cat([x.float().reshape(-1) for x in gs]).clamp(1e-6, 1 - 1e-6)
    entropy = -(g * g.log() + (1 - g) * (1 - g).log()).mean()
    return g.mean(), entropy


def regularizer_loss(
    delta: Sequence[Tensor] | Tensor | None = None,
    gates: Sequence[Tensor] | Tensor | None = None,
    final: Gaussians | None = None,
    scaffold: Gaussians | None = None,
    gate_mode: str = "entropy",
    weights: dict[str, float] | None = None,
) -> dict[str, Tensor]:
    """Regularisers of the completion branch.

    Args:
        delta: the residual(s) ``Delta Z`` added to the geometry tokens (any shapes); term = mean |Delta Z|.
        gates: gate activations ``g`` in (0, 1) (any shapes); term = binary entropy (``gate_mode="entropy"``,
            pushes gates to decide) or the mean (``"mean"``, keeps the prior switched off unless useful).
        final, scaffold: Gaussians decoded with and without the residual (same N); stability = mean L1 over
            means, log-scales, opacities and colours, scaffold detached.
        weights: per-term weights ``{"residual", "gate", "stability"}``, default 1 each.
    Returns:
        ``{"reg_residual", "reg_gate", "reg_stability", "total"}``.
    """
    if gate_mode not in ("entropy", "mean"):
        raise ValueError(f"regularizer_loss: gate_mode must be 'entropy' or 'mean', got {gate_mode!r}")
    wts = {"residual": 1.0, "gate": 1.0, "stability": 1.0, **(weights or {})}
    ref = torch.zeros(())
    for x in (delta, gates, final.means if final is not None else None):
        if isinstance(x, Tensor):
            ref = x
            break
        if isinstance(x, Sequence) and len(x) > 0:
            ref = x[0]
            break
    ref = ref.float().new_zeros(())
    ds = [] if delta is None else ([delta] if isinstance(delta, Tensor) else list(delta))
    residual = torch.stack([d.float().abs().mean() for d in ds]).mean() if ds else ref
    g_mean, g_ent = _gate_terms(gates, ref)
    gate = g_ent if gate_mode == "entropy" else g_mean
    stability = ref
    if final is not None and scaffold is not None:
        s = scaffold.detach()
        stability = ((final.means - s.means).abs().mean()
                     + (final.scales.clamp_min(1e-8).log() - s.scales.clamp_min(1e-8).log()).abs().mean()
                     + (final.opacities - s.opacities).abs().mean()
                     + (final.sh - s.sh).abs().mean())
    total = wts["residual"] * residual + wts["gate"] * gate + wts["stability"] * stability
    return {"reg_residual": residual, "reg_gate": gate, "reg_stability": stability, "total": total}
