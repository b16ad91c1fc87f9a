"""A chunked predict's stand-in network output: each chunk's views at depth 5 on ``anycity.city.oracle.orbit_scene``'s
true cameras (the export tests of whole cities)."""

from __future__ import annotations

import torch

from anycity.city.oracle import orbit_scene
from anycity.geometry.projection import unproject_depth
from anycity.structures import Gaussians


def oracle_chunk_prediction(batch: dict, h: int, w: int) -> dict:
    """The prediction dict for one 6-view chunk of a 12-view orbit: Gaussians, true w2c, K and the batch's images."""
    gt, _ = orbit_scene(12)
    views = batch["chunk"]["views"]
    Ks = torch.tensor([[2.0, 0, 1], [0, 2, 1], [0, 0, 1]]).expand(1, 6, 3, 3)
    means = unproject_depth(torch.full((1, 6, 1, h, w), 5.0), Ks, gt[views][None].float())
    m = 6 * h * w
    g = Gaussians(means.reshape(1, m, 3), torch.tensor([1.0, 0, 0, 0]).expand(1, m, 4),
                  torch.full((1, m, 3), 0.01), torch.full((1, m), 0.5), torch.zeros(1, m, 1, 3))
    return {"gaussians": g, "w2c": gt[views].float()[None], "K": Ks, "images": batch["images"]}
