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


def test_a_bad_reference_or_too_few_common_photos_is_one_line(tmp_path, capsys):
    """A missing or directory --cameras, a --colmap folder without a model and fewer than 3 common photo names used
    to end in tracebacks."""
    import json

    mod = load_script("city_cameras")
    eye = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    (tmp_path / "cameras.json").write_text(json.dumps({"views": [{"name": "a.jpg", "w2c": eye}]}))
    for ref, says in ((["--cameras", str(tmp_path / "no.json")], "no.json: no such file"),
                      (["--cameras", str(tmp_path)], f"--cameras {tmp_path}: no such file"),
                      (["--colmap", str(tmp_path)], "no COLMAP model"),
                      (["--cameras", str(tmp_path / "cameras.json")], "only 1 photo names in common")):
        with pytest.raises(SystemExit) as stop:
            mod.main([str(tmp_path), *ref])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and says in err and "Traceback" not in err, (ref, err)
        assert len([ln for ln in err.splitlines() if "error:" in ln]) == 1
