"""Freeze-by-glob and LoRA injection on small modules."""

import pytest
import torch
from torch import nn

from anycity.callbacks import FreezeModules, LoRAInjection, freeze_by_patterns, inject_lora


class Tiny(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = nn.ModuleDict({"aggregator": nn.Sequential(nn.Linear(4, 4), nn.LayerNorm(4)),
                                  "head": nn.Linear(4, 2)})

    def forward(self, x):
        return self.net["head"](self.net["aggregator"](x))


def test_freeze_by_patterns_and_unfreeze_exceptions():
    m = Tiny()
    frozen = freeze_by_patterns(m, ["net.aggregator.*"], unfreeze=["net.aggregator.1.*"])
    assert frozen == ["net.aggregator.0.weight", "net.aggregator.0.bias"]
    flags = {n: p.requires_grad for n, p in m.named_parameters()}
    assert not flags["net.aggregator.0.weight"] and flags["net.aggregator.1.weight"] and flags["net.head.weight"]


def test_freeze_pattern_matching_nothing_is_an_error():
    with pytest.raises(ValueError, match="net.agregator"):
        freeze_by_patterns(Tiny(), ["net.agregator.*"])


def test_freeze_callback_runs_in_setup():
    m = Tiny()
    FreezeModules(["net.head.*"]).setup(None, m, "fit")
    assert not m.net["head"].weight.requires_grad
    FreezeModules([]).setup(None, Tiny(), "fit")  # empty = no-op


def test_inject_lora_keeps_output_and_other_flags_and_is_idempotent():
    m = Tiny()
    x = torch.randn(3, 4)
    before = m(x)
    m.net["aggregator"][1].weight.requires_grad_(False)
    names = inject_lora(m.net, ["head"], rank=2)
    assert names == ["head"]
    torch.testing.assert_close(m(x), before)  # lora_B starts at zero
    flags = {n: p.requires_grad for n, p in m.named_parameters()}
    assert flags["net.aggregator.0.weight"] and not flags["net.aggregator.1.weight"]  # untouched by peft
    assert not flags["net.head.base_layer.weight"]
    assert flags["net.head.lora_A.default.weight"] and flags["net.head.lora_B.default.weight"]
    assert inject_lora(m.net, ["head"], rank=2) == []  # second injection: nothing new


def test_lora_callback_injects_for_every_stage_so_checkpoints_load():
    trained = Tiny()
    LoRAInjection(["head"], rank=2).setup(None, trained, "fit")
    state = trained.state_dict()
    fresh = Tiny()
    LoRAInjection(["head"], rank=2).setup(None, fresh, "test")
    fresh.load_state_dict(state)  # strict: keys match because the test stage injected too
    with pytest.raises(ValueError, match="nothing_here"):
        LoRAInjection(["nothing_here"]).setup(None, Tiny(), "fit")
