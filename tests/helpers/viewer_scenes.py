"""A tiny predict-like output folder for the viewer and video tests."""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image

from anycity.export import save_cameras, save_ply
from anycity.structures import Gaussians


def tiny_predict_folder(root, n: int = 3000, with_prov: bool = True, names: list[str] | None = None):
    """A predict-like folder: a coloured cube of Gaussians seen by 3 cameras 4 units away, with input images
    (``inputs/NNN.png``; ``names``: the photo names ``cameras.json`` gives, as a photo-folder predict writes)."""
    gen = torch.Generator().manual_seed(0)
    means = torch.rand(1, n, 3, generator=gen) * 2 - 1
    g = Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4).clone(),
                  scales=torch.full((1, n, 3), 0.06), opacities=torch.full((1, n), 0.9),
                  sh=((means.clamp(-1, 1) * 0.5 + 0.5 - 0.5) / 0.28209479177387814)[:, :, None, :])
    v = 3
    w2c = torch.eye(4).repeat(v, 1, 1)
    for i, x in enumerate((-1.0, 0.0, 1.0)):
        w2c[i, :3, 3] = torch.tensor([x, 0.0, 4.0])
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]).repeat(v, 1, 1)
    prov = {"obs_views": torch.randint(0, 4, (1, n), generator=gen).float(),
            "completion": torch.rand(1, n, generator=gen)} if with_prov else None
    save_ply(g, root / "scene.ply", extra=prov)
    save_cameras(root / "cameras.json", w2c, K, 48, 32, names)
    (root / "inputs").mkdir()
    for i in range(v):
        Image.fromarray(np.full((32, 48, 3), 60 * i, np.uint8)).save(root / "inputs" / f"{i:03d}.png")
    return root
