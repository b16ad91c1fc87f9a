"""scripts/quickstart.py refuses shards made with other settings instead of silently training on them."""

import json

from helpers.scripts import load_script


def _quickstart():
    return load_script("quickstart")


def test_foreign_shards_stop_with_the_fix(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["quickstart.py"])
    data = tmp_path / "qs"
    data.mkdir()
    (data / "index.json").write_text("{}")  # shards of unknown origin
    assert _quickstart().main(["--data", str(data), "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert str(data) in err and "delete" in err and "--data NEW_DIR" in err
    # other synth settings are refused too; nothing was trained or written
    (data / "quickstart_data.json").write_text(json.dumps(["--scenes", "3"]))
    assert _quickstart().main(["--data", str(data), "--out", str(tmp_path / "runs")]) == 2
    assert not (tmp_path / "runs").exists()


def test_printed_tables_are_well_formed_markdown(capsys):
    """Every row of each table has the header's cells and width (the baseline rows used to miss a cell)."""
    from collections import defaultdict

    _quickstart().print_tables(defaultdict(lambda: 19.876))
    lines = capsys.readouterr().out.splitlines()
    tables, current = [], []
    for line in [*lines, ""]:
        if line.startswith("|"):
            current.append(line)
        elif current:
            tables, current = [*tables, current], []
    assert [len(t) for t in tables] == [6, 5]
    for t in tables:
        assert len({len(r) for r in t}) == 1 and len({r.count("|") for r in t}) == 1, "\n".join(t)
