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
