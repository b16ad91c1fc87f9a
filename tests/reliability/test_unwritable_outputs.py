"""An output that cannot be written, or a port that does not exist, stops in one line before any work. They used to
end in a traceback after the network had run (predict), a broken pipe from ffmpeg (render-video) or a hang (view)."""

import os
import re
from pathlib import Path

import pytest
from helpers.viewer_scenes import tiny_predict_folder

from anycity.atomic import check_writable_folder
from anycity.cli import main


def test_a_folder_under_a_file_or_without_write_permission_is_refused(tmp_path, monkeypatch):
    f = tmp_path / "a.yaml"
    f.write_text("x")
    check_writable_folder(tmp_path / "new" / "deeper", "--out")  # missing folders are created by the writer
    with pytest.raises(NotADirectoryError, match=r"--out .*a\.yaml/sub: .*a\.yaml is a file, not a folder"):
        check_writable_folder(f / "sub", "--out")
    real = os.access  # the tests may run as root, who may write anywhere
    monkeypatch.setattr(os, "access", lambda p, mode: real(p, mode) and Path(p) != tmp_path)
    with pytest.raises(PermissionError, match=f"may not write in {tmp_path};"):
        check_writable_folder(tmp_path / "new", "--out")


def test_a_folder_whose_search_bit_is_off_is_refused(tmp_path, monkeypatch):
    """Creating a folder inside ``existing`` needs write and search (x) permission: a folder with the write bit but
    not the search bit is refused too."""
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: real(p, mode) and not (Path(p) == tmp_path and mode & os.X_OK))
    with pytest.raises(PermissionError, match=f"may not write in {tmp_path};"):
        check_writable_folder(tmp_path / "new", "--out")


def test_a_folder_under_a_broken_link_is_refused_naming_the_link(tmp_path):
    """A dangling symlink on the way used to pass the check, and creating the folder then failed with a bare
    FileExistsError; it is refused in one line that names the link."""
    link = tmp_path / "dangling"
    link.symlink_to(tmp_path / "nowhere")
    for out in (link / "sub", link):
        one_line = f"^--out {re.escape(str(out))}: {re.escape(str(link))} is a broken link .*nowhere.*; "
        with pytest.raises(NotADirectoryError, match=one_line) as e:
            check_writable_folder(out, "--out")
        assert "\n" not in str(e.value)
    assert not (tmp_path / "nowhere").exists()


def test_export_render_video_and_view_refuse_in_one_line(tmp_path, capsys, monkeypatch):
    scene = tiny_predict_folder(tmp_path / "scene")
    f = tmp_path / "file.txt"
    f.write_text("x")
    for argv in (["export", "--from", str(scene), "--format", "splat", "--out", str(f / "x")],
                 ["render-video", str(scene), "--out", str(f / "a.mp4")]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "is a file, not a folder" in err[0], (argv, err)
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: real(p, mode) and Path(p) != ro)
    assert main(["render-video", str(scene), "--out", str(ro / "a.mp4")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"may not write in {ro}" in err[0] and not list(ro.iterdir())
    with pytest.raises(SystemExit) as e:
        main(["view", str(scene), "--port", "99999"])
    assert e.value.code == 2 and "99999 is not a port (0 to 65535" in capsys.readouterr().err
