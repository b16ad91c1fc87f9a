"""Whole cities: many photos reconstructed in overlapping chunks, aligned by Sim(3) and merged into one scene.

Pure torch (no Lightning): :mod:`~anycity.city.plan` orders photos and cuts chunks, :mod:`~anycity.city.align`
fits pairwise robust Sim(3)s on shared views, :mod:`~anycity.city.posegraph` a checked global pose graph over them,
:mod:`~anycity.city.merge` moves Gaussians and streams one PLY, :class:`~anycity.city.scene.ChunkedScene` drives
them chunk by chunk with bounded memory.
``anycity predict`` uses it through :class:`anycity.callbacks.PredictionExport` when a photo folder holds more
photos than ``predict_chunk_size``.
"""

from anycity.city.align import ChunkGeometry, apply_sim3, robust_sim3, sim3_inverse, sim3_parts, w2c_to_world
from anycity.city.merge import PlyStream, sim3_gaussians
from anycity.city.plan import order_from_descriptors, order_photos, owners, plan_chunks
from anycity.city.posegraph import align_chunks, pose_graph
from anycity.city.scene import ChunkedScene

__all__ = ["ChunkGeometry", "align_chunks", "apply_sim3", "pose_graph", "robust_sim3", "sim3_inverse", "sim3_parts",
           "w2c_to_world", "PlyStream", "sim3_gaussians", "order_from_descriptors", "order_photos", "owners",
           "plan_chunks", "ChunkedScene"]
