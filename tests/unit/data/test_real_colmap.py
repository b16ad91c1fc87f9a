"""The shared real aerial COLMAP scenes convert, load into batches, and their 3D points reproject onto the
recorded 2D observations after conversion, resizing and normalisation (< 1 px mean error)."""

import numpy as np
import pytest
import torch
import webdataset as wds

from anycity.data.parsers import convert
from anycity.data.parsers.colmap import read_model
from anycity.data.pipeline import SampleBuilder
from anycity.geometry import project_points, transform_points

from .conftest import REAL

SCENE = REAL / "brighton_beach"
pytestmark = pytest.mark.skipif(not (SCENE / "sparse").exists(),
                                reason=f"shared real data not found at {SCENE} (expected <repo>/../shared)")


@pytest.mark.parametrize("size,mode", [((224, 320), "crop"), ((252, 448), "keep")])
def test_real_scene_reprojects(tmp_path, size, mode):
    out = tmp_path / "real"
    convert("colmap", SCENE, out, split="test")
    sample = next(iter(wds.WebDataset(str(out / "test-000000.tar"), shardshuffle=False)))
    builder = SampleBuilder(num_context=4, num_targets=2, num_dense=4, image_size=size, resize_mode=mode,
                            train=False)
    item = builder(sample)[0]
    model = read_model(SCENE)
    by_name = {im["name"]: im for im in model.images.values()}
    names = sorted(by_name)
    errs = []
    for g in ("context", "target"):
        grp = item[g]
        H, W = grp["images"].shape[-2:]
        for v in range(grp["images"].shape[0]):
            im = by_name[names[int(grp["index"][v])]]
            cam = model.cameras[im["camera_id"]]
            w0, h0 = cam[1], cam[2]
            keep = im["point3D_ids"] >= 0
            xyz = torch.tensor(np.stack([model.points[int(i)] for i in im["point3D_ids"][keep]]))
            obs = im["xys"][keep]
            # the resize applied to the image, computed independently of the K bookkeeping
            if mode == "crop":
                s = max(H / h0, W / w0)
                nw, nh = max(W, round(w0 * s)), max(H, round(h0 * s))
            else:
                nw, nh = W, H
            x0, y0 = (nw - W) // 2, (nh - H) // 2
            exp = np.stack([obs[:, 0] * nw / w0 - x0, obs[:, 1] * nh / h0 - y0], 1)
            pts = transform_points(item["world_from_source"].double(), xyz)
            uv, z = project_points(pts, grp["w2c"][v].double(), grp["K"][v].double())
            inside = (exp[:, 0] > 0) & (exp[:, 0] < W) & (exp[:, 1] > 0) & (exp[:, 1] < H)
            assert (z > 0).all()
            errs.append(np.linalg.norm(uv.numpy()[inside] - exp[inside], axis=1))
    err = np.concatenate(errs)
    print(f"mean reprojection error {err.mean():.3f} px over {len(err)} observations")
    assert len(err) > 1000 and err.mean() < 1.0, err.mean()
    assert torch.allclose(item["context"]["w2c"][0], torch.eye(4), atol=1e-5)
    assert "depth" not in item["context"]  # SfM scenes carry no depth
