"""The 3DGS PLY writer fills one structured array and streams it: byte for byte what plyfile writes, at about one
copy of the file in memory (it held four: torch columns, float32 copies, the structured array, plyfile's buffer)."""

from __future__ import annotations

import io
import tracemalloc

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from anycity.export import load_ply, load_ply_extras, save_ply
from anycity.export.formats import save_points_ply
from anycity.structures import Gaussians


def _scene(n: int, degree: int, seed: int = 0) -> tuple[Gaussians, dict[str, torch.Tensor]]:
    gen = torch.Generator().manual_seed(seed)
    g = Gaussians(means=torch.randn(1, n, 3, generator=gen), quats=torch.randn(1, n, 4, generator=gen),
                  scales=torch.rand(1, n, 3, generator=gen) + 0.01, opacities=torch.rand(1, n, generator=gen),
                  sh=torch.randn(1, n, (degree + 1) ** 2, 3, generator=gen),
                  valid=torch.rand(1, n, generator=gen) > 0.1)
    return g, {"obs_views": torch.rand(1, n, generator=gen), "completion": torch.rand(1, n, generator=gen)}


def _plyfile_bytes(g: Gaussians, extra: dict | None, max_degree: int, pad_degree: int | None) -> bytes:
    """graphdeco's ``save_ply`` record, built column by column and written by plyfile (the writer it replaced)."""
    keep = g.valid[0].clone()
    k = (min(g.sh_degree, max_degree) + 1) ** 2
    sh = g.sh[0, :, :k]
    for t in (g.means[0], g.quats[0], g.scales[0], g.opacities[0][:, None], sh.flatten(1)):
        keep &= torch.isfinite(t).all(-1)
    keep &= (g.quats[0].norm(dim=-1) > 0) & (g.scales[0].min(-1).values > 0)
    sh = sh[keep]
    if pad_degree is not None and (pad_degree + 1) ** 2 > k:
        sh = torch.cat([sh, sh.new_zeros(len(sh), (pad_degree + 1) ** 2 - k, 3)], 1)
    q = g.quats[0][keep] / g.quats[0][keep].norm(dim=-1, keepdim=True)
    p = g.opacities[0][keep].clamp(1e-6, 1 - 1e-6)
    rest = sh[:, 1:].transpose(1, 2).reshape(len(sh), 3 * (sh.shape[1] - 1))
    cols = {**{c: g.means[0][keep][:, i] for i, c in enumerate("xyz")},
            **{f"n{c}": torch.zeros(len(sh)) for c in "xyz"}, **{f"f_dc_{i}": sh[:, 0, i] for i in range(3)},
            **{f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])}, "opacity": torch.log(p / (1 - p)),
            **{f"scale_{i}": g.scales[0][keep][:, i].log() for i in range(3)},
            **{f"rot_{i}": q[:, i] for i in range(4)}, **{k: v[0][keep] for k, v in (extra or {}).items()}}
    data = np.empty(int(keep.sum()), dtype=[(k, "<f4") for k in cols])
    for name, v in cols.items():
        data[name] = v.numpy()
    buf = io.BytesIO()
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<").write(buf)
    return buf.getvalue()


@pytest.mark.parametrize(("degree", "extra", "max_degree", "pad_degree"),
                         [(3, True, 3, None), (1, False, 3, 3), (2, True, 1, None), (0, False, 3, None)])
def test_the_file_is_byte_for_byte_plyfiles(tmp_path, degree, extra, max_degree, pad_degree, monkeypatch):
    import anycity.export.ply as ply

    monkeypatch.setattr(ply, "ROWS", 64, raising=False)  # several row blocks, the last one short
    monkeypatch.setattr(ply, "WRITE_STEP", 1000)  # several write slices, not a multiple of the record length
    g, prov = _scene(300, degree)
    g.means[0, 0, 1] = float("nan")
    g.quats[0, 1] = 0
    g.scales[0, 2, 2] = 0
    g.sh[0, 3, -1, 0] = float("inf")
    path = tmp_path / "s.ply"
    with pytest.warns(UserWarning, match="dropped"):  # the bad rows, beside the padding
        dropped = save_ply(g, path, extra=prov if extra else None, max_degree=max_degree, pad_degree=pad_degree)
    expected = _plyfile_bytes(g, prov if extra else None, max_degree, pad_degree)
    assert path.read_bytes() == expected
    assert dropped == 300 - PlyData.read(str(path))["vertex"].count
    back = load_ply(path)  # and our reader (plyfile underneath) reads it
    assert back.num_gaussians == 300 - dropped and back.sh_degree == max(min(degree, max_degree), pad_degree or 0)
    assert set(load_ply_extras(path)) == ({"obs_views", "completion"} if extra else set())


def test_opacity_one_or_zero_is_written_as_a_finite_logit(tmp_path):
    g = Gaussians(means=torch.zeros(1, 2, 3), quats=torch.tensor([[[1.0, 0, 0, 0]] * 2]),
                  scales=torch.full((1, 2, 3), 0.1), opacities=torch.tensor([[1.0, 0.0]]), sh=torch.zeros(1, 2, 1, 3))
    save_ply(g, tmp_path / "s.ply")
    raw = np.asarray(PlyData.read(str(tmp_path / "s.ply"))["vertex"]["opacity"])
    assert np.isfinite(raw).all() and np.abs(raw).max() < 14  # logit(1 - 1e-6) = 13.8, not +-inf
    assert raw[0] > 13 and raw[1] < -13


def test_an_empty_scene_and_a_coloured_point_cloud_are_plyfiles_too(tmp_path):
    g, _ = _scene(5, 1)
    g.opacities.fill_(float("nan"))
    with pytest.warns(UserWarning, match="dropped 4 of 4"):  # the fifth is padding (valid=False)
        assert save_ply(g, tmp_path / "e.ply") == 5
    assert (tmp_path / "e.ply").read_bytes() == _plyfile_bytes(g, None, 3, None)
    g, _ = _scene(40, 1, seed=1)
    save_points_ply(tmp_path / "p.ply", g)
    v = PlyData.read(str(tmp_path / "p.ply"))["vertex"]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(v.data, "vertex")], text=False, byte_order="<").write(buf)
    assert (tmp_path / "p.ply").read_bytes() == buf.getvalue()
    assert v.data.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue")
    assert v.count == int(g.valid.sum())


def test_the_writer_holds_about_one_copy_of_the_file(tmp_path):
    """numpy reports its buffers to tracemalloc (torch does not): the float32 column copies, the structured array
    and plyfile's BytesIO made ~3x the file; one structured array streamed to disk is ~1x."""
    g, prov = _scene(20_000, 3)
    g.valid = None
    tracemalloc.start()
    try:
        save_ply(g, tmp_path / "s.ply", extra=prov)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    size = (tmp_path / "s.ply").stat().st_size
    assert peak < 1.3 * size, (peak, size)


def test_dropped_rows_are_named_in_one_warning(tmp_path):
    # save_ply dropped rows it cannot store (a PLY holds log-scales) and reported it only in its return value
    g, _ = _scene(20, 1)
    g.valid = None
    g.quats[0, :3] = 0
    g.scales[0, 3:5, 1] = 0
    with pytest.warns(UserWarning, match=r"save_ply: .*s\.ply: dropped 5 of 20 Gaussians with a NaN/inf field, a "
                                         r"zero-norm rotation or a scale <= 0 .*; 15 written"):
        assert save_ply(g, tmp_path / "s.ply") == 5
    assert load_ply(tmp_path / "s.ply").num_gaussians == 15


def test_padding_rows_are_dropped_without_a_warning(tmp_path, recwarn):
    g, _ = _scene(20, 1)  # ~10 % valid=False: a voxel merge's padding, not the user's data
    assert save_ply(g, tmp_path / "s.ply") == int((~g.valid).sum()) > 0
    assert not [w for w in recwarn if "save_ply" in str(w.message)]
