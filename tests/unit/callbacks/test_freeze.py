"""Freeze-by-glob on small modules (LoRA lives in the network: models/video_prior.py, NetConfig.wan_lora_rank)."""

import pytest
from torch import nn

from anycity.callbacks import FreezeModules, freeze_by_patterns


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
