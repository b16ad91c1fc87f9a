"""scripts/city_cameras.py: a folder without cameras.json, or no reference, is one line (it was a traceback)."""

import pytest
from helpers.scripts import load_script


def test_a_folder_without_cameras_json_or_no_reference_is_named_in_one_line(tmp_path, capsys):
    mod = load_script("city_cameras")
    with pytest.raises(SystemExit) as stop:
        mod.main([str(tmp_path), "--cameras", str(tmp_path / "gt.json")])
    assert stop.value.code == 2 and f"{tmp_path}: no cameras.json; pass the scene folder" in capsys.readouterr().err
    (tmp_path / "cameras.json").write_text("{}")
    with pytest.raises(SystemExit):
        mod.main([str(tmp_path)])
    assert "pass the reference cameras" in capsys.readouterr().err
