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


def test_freezing_random_scaffold_weights_in_a_fit_is_refused():
    """The frozen-transformer ablations without model.pretrained froze a random aggregator and trained on."""
    from anycity.lit import ScaffoldModule

    m = ScaffoldModule(preset="tiny")  # no pretrained: random init
    with pytest.raises(ValueError, match=r"freeze.patterns: \d+ scaffold weights \(e.g. net.aggregator.*random init.*"
                                         r"--model.init_args.pretrained .*--freeze.allow_random_init true"):
        FreezeModules(["net.aggregator.*"]).setup(None, m, "fit")
    FreezeModules(["net.aggregator.*"], allow_random_init=True).setup(None, m, "fit")  # on purpose
    FreezeModules(["net.aggregator.*"]).setup(None, m, "test")  # evaluation takes its weights from a checkpoint


def test_freezing_scaffold_weights_a_module_loads_is_allowed():
    for hp in ({"pretrained": "vggt.pt"}, {"init_from": "stage1.ckpt"}):
        m = Tiny()
        m.hparams = hp
        FreezeModules(["net.aggregator.*"]).setup(None, m, "fit")
        assert not m.net["aggregator"][0].weight.requires_grad
    with pytest.raises(ValueError, match="freeze.patterns: 4 scaffold weights"):
        FreezeModules(["net.aggregator.*"]).setup(None, Tiny(), "fit")
    FreezeModules(["net.head.*"]).setup(None, Tiny(), "fit")  # not the scaffold (the prior, say): no weights needed


def test_an_unfreeze_pattern_that_exempts_nothing_is_an_error():
    """unfreeze only exempts parameters from freeze.patterns (it sets nothing trainable); one matching none of them,
    or given without patterns (which returned before reading it), silently did nothing."""
    with pytest.raises(ValueError, match=r"freeze.unfreeze: pattern 'net.head.\*' matches none of the parameters "):
        freeze_by_patterns(Tiny(), ["net.aggregator.*"], unfreeze=["net.head.*"])  # a parameter, not a frozen one
    with pytest.raises(ValueError, match=r"freeze.unfreeze: \['net.head.\*'\] given without freeze.patterns"):
        FreezeModules([], unfreeze=["net.head.*"]).setup(None, Tiny(), "fit")
    m = Tiny()
    with pytest.raises(ValueError, match="net.agregator"):  # a typo: as for a freeze pattern
        freeze_by_patterns(m, ["net.aggregator.*"], unfreeze=["net.agregator.1.*"])
    assert all(p.requires_grad for p in m.parameters())  # refused before anything was frozen
