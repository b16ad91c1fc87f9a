"""``anycity export`` never writes over the scene it reads, whatever ``--overwrite`` says."""

from __future__ import annotations

import pytest
import torch

from anycity.export import save_cameras, save_ply
from anycity.export.cli import export
from anycity.structures import Gaussians


def _scene_dir(tmp_path):
    gen = torch.Generator().manual_seed(0)
    n = 20
    g = Gaussians(means=torch.randn(1, n, 3, generator=gen), quats=torch.randn(1, n, 4, generator=gen),
                  scales=torch.rand(1, n, 3, generator=gen) * 0.1 + 0.01,
                  opacities=torch.rand(1, n, generator=gen) * 0.9 + 0.05, sh=torch.randn(1, n, 4, 3, generator=gen))
    d = tmp_path / "pred" / "sceneA"
    save_ply(g, d / "scene.ply")
    K = torch.tensor([[40.0, 0, 24.5], [0, 41.0, 16.0], [0, 0, 1]]).repeat(2, 1, 1).double()
    save_cameras(d / "cameras.json", torch.eye(4).repeat(2, 1, 1).double(), K, 48, 32)
    return d


@pytest.mark.parametrize("fmt", ["ply", "splat", "nerfstudio"])
def test_an_out_folder_that_is_the_scene_is_refused_even_with_overwrite(fmt, tmp_path):
    """``--from SCENE --out SCENE --overwrite`` replaced the predicted scene.ply with the export's (SH padded, the
    provenance columns gone)."""
    d = _scene_dir(tmp_path)
    before = {f.name: f.read_bytes() for f in d.iterdir()}
    for src in (d, d / "scene.ply"):
        with pytest.raises(ValueError, match=r"^--out .*sceneA is the scene folder --from reads; .*pass another --out"):
            export(src, fmt, d / "." if src == d else d, overwrite=True)
    assert {f.name: f.read_bytes() for f in d.iterdir()} == before


def test_an_out_folder_holding_the_input_ply_is_refused(tmp_path):
    """A bare .ply given as --from inside the folder the export writes its images/ (or scene.ply) into."""
    d = _scene_dir(tmp_path)
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    ply = out / "images" / "mine.ply"
    ply.write_bytes((d / "scene.ply").read_bytes())
    with pytest.raises(ValueError, match=r"would write over \(or into\) its input .*mine.ply; pass another --out"):
        export(ply, "ply", out, overwrite=True)
    # the default folder (<from>/export_<format>) and any folder beside the scene are fine
    assert export(d, "ply", d / "export_ply").is_file()
    assert export(d, "splat", tmp_path / "elsewhere").is_file()
