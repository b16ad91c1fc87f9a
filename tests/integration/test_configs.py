"""Every shipped config parses with --print_config (overlays on top of the config they extend)."""

from pathlib import Path

import pytest

from anycity.cli import build_cli

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
COMPLETE = {"quickstart.yaml", "stage1.yaml", "stage2.yaml"}
BASE = {"quickstart_stage2.yaml": "quickstart.yaml", "ablations/wo_lora.yaml": "stage2.yaml",
        "ablations/wo_pres.yaml": "stage2.yaml", "debug/fast_dev_run.yaml": "quickstart.yaml",
        "debug/overfit.yaml": "quickstart.yaml"}  # every other overlay extends stage1.yaml


def _chain(rel: str) -> list[str]:
    if rel in COMPLETE:
        return [rel]
    return [*_chain(BASE.get(rel, "stage1.yaml")), rel]


ALL = sorted(str(p.relative_to(CONFIGS)) for p in CONFIGS.rglob("*.yaml"))


@pytest.mark.parametrize("rel", ALL)
def test_config_prints(rel, capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])
    args = []
    for c in _chain(rel):
        args += ["-c", str(CONFIGS / c)]
    with pytest.raises(SystemExit) as exc:
        build_cli([*args, "--print_config"], run=False)
    assert exc.value.code in (0, None)
    out = capsys.readouterr().out
    assert "model:" in out and "trainer:" in out and "freeze:" in out and "lora:" not in out
