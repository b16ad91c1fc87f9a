"""``PredictionExport`` (callbacks/export.py): the provenance line a voxel-merged prediction prints, and the
``--export.smooth_3d`` values it refuses."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch

from anycity.callbacks.export import PredictionExport
from anycity.export import load_ply_extras
from anycity.structures import Gaussians

V, H, W = 2, 16, 16


def _prediction(valid: bool) -> dict:
    """A 2-view prediction of 50 Gaussians in front of both cameras; ``valid``: the Gaussians carry the mask a voxel
    merge (and only it) sets, as do their scaffold's."""
    n = 50
    means = torch.rand(1, n, 3, generator=torch.Generator().manual_seed(0)) * 0.4 + torch.tensor([-0.2, -0.2, 3.0])

    def gaussians() -> Gaussians:  # the scaffold's the same: nothing completed
        return Gaussians(means.clone(),
                         torch.tensor([1.0, 0, 0, 0]).repeat(1, n, 1), torch.full((1, n, 3), 0.05),
                         torch.full((1, n), 0.8), torch.zeros(1, n, 1, 3),
                         torch.ones(1, n, dtype=torch.bool) if valid else None)

    w2c = torch.eye(4).repeat(1, V, 1, 1)
    K = torch.tensor([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]).repeat(1, V, 1, 1)
    return {"gaussians": gaussians(), "scaffold": gaussians(), "depth": torch.full((1, V, 1, H, W), 3.5), "w2c": w2c,
            "K": K, "images": torch.rand(1, V, 3, H, W), "renders": SimpleNamespace(rgb=torch.rand(1, V, 3, H, W)),
            "scene": ["s"]}


def _export(tmp_path, prediction: dict) -> None:
    cb = PredictionExport(out_dir=str(tmp_path), save_renders=False)
    cb._root = tmp_path
    cb.write_on_batch_end(SimpleNamespace(global_rank=0), None, prediction, None, {"scene": ["s"]}, 0)


def test_a_voxel_merged_prediction_prints_completion_n_a(tmp_path, capsys):
    """With a test-time voxel merge the completion is unknown (NaN): predict printed "100 % observation-supported,
    0 % completed" (NaN counted as kept, or voxels paired by their order at the same count)."""
    _export(tmp_path, _prediction(valid=True))
    out = capsys.readouterr().out
    assert "s: completion n/a (voxel-merged), 100% of Gaussians seen by >= 2 views, 0% seen by < 2 views" in out
    assert "observation-supported" not in out and "completed by Stage II" not in out
    assert torch.from_numpy(load_ply_extras(tmp_path / "s" / "scene.ply")["completion"]).isnan().all()


def test_a_pixel_aligned_prediction_prints_its_shares(tmp_path, capsys):
    _export(tmp_path, _prediction(valid=False))
    assert ("s: 100% of Gaussians observation-supported (>= 2 views, kept), 0% completed by Stage II, 0% seen by "
            "< 2 views\n") in capsys.readouterr().out


def test_cameras_json_has_no_metres_per_unit(tmp_path):
    """The network's frame has no known metric scale (docs/viewer.md, scale.json): null, not the sample's scale."""
    _export(tmp_path, _prediction(valid=False))
    assert json.loads((tmp_path / "s" / "cameras.json").read_text())["metres_per_unit"] is None


@pytest.mark.parametrize("value", [-0.2, float("nan")])
def test_a_negative_smooth_3d_is_refused(value):
    """-0.2 turned the filter off without a word (``if self.smooth_3d > 0``)."""
    with pytest.raises(ValueError, match=r"--export.smooth_3d: expected a variance in px² >= 0 \(0 turns the filter "
                                         r"off\), got (-0.2|nan)"):
        PredictionExport(smooth_3d=value)
    assert PredictionExport(smooth_3d=0.0).smooth_3d == 0.0


def test_a_degree_4_network_is_told_once_that_the_ply_keeps_degree_3(tmp_path):
    """vggt-1b predicts SH degree 4 (AnySplat's); the 3DGS PLY holds up to degree 3 and the cut was silent, so
    viewers showed other colours than predict's renders/ with no word why."""
    import dataclasses
    import warnings

    from anycity.export import load_ply

    pred = _prediction(valid=False)
    for key in ("gaussians", "scaffold"):
        g = pred[key]
        pred[key] = dataclasses.replace(g, sh=torch.zeros(1, g.num_gaussians, 25, 3))
    cb = PredictionExport(out_dir=str(tmp_path), save_renders=False)
    cb._root = tmp_path
    with pytest.warns(UserWarning, match="SH degree 4; scene.ply keeps degrees 0 to 3"):
        cb.write_on_batch_end(SimpleNamespace(global_rank=0), None, pred, None, {"scene": ["s"]}, 0)
    assert load_ply(tmp_path / "s" / "scene.ply").sh_degree == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once a run
        cb._warn_sh_cut(pred["gaussians"])


def test_a_network_within_the_ply_degrees_is_not_warned(tmp_path):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _export(tmp_path, _prediction(valid=False))


def test_a_scene_that_fails_part_way_leaves_no_scene_folder(tmp_path, monkeypatch):
    """Each scene folder is staged and renamed when complete: a failure (or a kill) after ``scene.ply`` left it
    without ``cameras.json``, and ``anycity view`` showed it without a word."""
    import anycity.callbacks.export as export

    def no_cameras(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(export, "save_cameras", no_cameras)
    with pytest.raises(OSError, match="disk full"):
        _export(tmp_path, _prediction(valid=False))
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    monkeypatch.undo()
    _export(tmp_path, _prediction(valid=False))  # the next run writes the whole folder
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["cameras.json", "scene.ply"]


def test_predicted_cameras_with_non_square_pixels_are_named_in_a_warning(tmp_path):
    # a model trained on square images predicts equal fields of view: on 2:1 photos fx/fy = 2, and every export
    # (COLMAP, nerfstudio) carried it without a word
    p = _prediction(valid=False)
    p["K"][..., 0, 0] = 40.0
    with pytest.warns(UserWarning, match=r"^anycity predict: s: the predicted cameras have non-square pixels \(fx / "
                                         r"fy up to 2.00; photos have 1.00\)"):
        _export(tmp_path / "wide", p)
    p = _prediction(valid=False)
    p["K"][..., 0, 0] = 20.8  # within 5 %: rounding, not a wrong camera (the test above checks no warning at 1.0)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _export(tmp_path / "near", p)
