"""Export of reconstructions: standard 3DGS PLY, cameras.json."""

from anycity.export.cameras import cameras_to_dict, save_cameras
from anycity.export.ply import gaussians_to_ply_arrays, load_ply, load_ply_extras, save_ply
from anycity.export.views import save_view_pngs, view_png

__all__ = ["cameras_to_dict", "save_cameras", "gaussians_to_ply_arrays", "load_ply", "load_ply_extras", "save_ply",
           "save_view_pngs", "view_png"]
