"""Camera and rotation geometry (OpenCV cameras, world-to-camera extrinsics, pixel intrinsics, wxyz)."""

from anycity.geometry.alignment import sim3_matrix, umeyama
from anycity.geometry.cameras import (
    c2w_to_w2c,
    camera_centers,
    camera_problem,
    crop_intrinsics,
    focal_to_fov,
    fov_to_focal,
    invert_rigid,
    make_intrinsics,
    rescale_intrinsics,
    to_homogeneous,
    w2c_to_c2w,
)
from anycity.geometry.normals import depth_to_normals
from anycity.geometry.projection import (
    pixel_grid,
    pixel_rays,
    project_points,
    transform_points,
    unproject_depth,
    unproject_depth_to_camera,
)
from anycity.geometry.rotations import quat_multiply, quat_to_rotmat, rotmat_to_quat, wxyz_to_xyzw, xyzw_to_wxyz
from anycity.geometry.visibility import count_visible, visible_views

__all__ = [
    "c2w_to_w2c", "camera_centers", "camera_problem", "crop_intrinsics", "focal_to_fov", "fov_to_focal", "invert_rigid",
    "make_intrinsics", "rescale_intrinsics", "to_homogeneous", "w2c_to_c2w", "depth_to_normals", "pixel_grid",
    "pixel_rays", "project_points", "transform_points", "unproject_depth", "unproject_depth_to_camera",
    "quat_multiply", "quat_to_rotmat", "rotmat_to_quat", "wxyz_to_xyzw", "xyzw_to_wxyz", "sim3_matrix", "umeyama",
    "count_visible", "visible_views",
]
