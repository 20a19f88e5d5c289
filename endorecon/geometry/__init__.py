"""The geometry core: camera model, poses, warping, similarity alignment.

Conventions, stated once for the whole project:

* **Poses** are ``cam_from_world`` 4x4 matrices, x_cam = R x_world + t (as
  COLMAP).  Transforms are named by their frames (``b_from_a``).
* **Depth** is z-depth along the optical axis (not ray length), in the
  sequence's units (mm for the phantom; arbitrary for SfM).
* **Pixels** are (u, v) = (column, row) with **(0, 0) at the centre of the
  top-left pixel** (kornia/OpenCV).  COLMAP and Open3D use the corner
  convention; convert with :func:`to_corner_convention` and
  :func:`from_corner_convention` at those boundaries only.
* **Shapes**: images (B,C,H,W), depth/std (B,1,H,W), masks bool (B,1,H,W),
  intrinsics (B,3,3), poses (B,4,4), point sets (B,N,3).
"""

from endorecon.geometry.camera import (
    crop_intrinsics,
    from_corner_convention,
    mask_bbox_crop,
    pixel_grid,
    project,
    scale_intrinsics,
    to_corner_convention,
    unproject,
)
from endorecon.geometry.pose import (
    camera_centers,
    invert_pose,
    matrix_to_quaternion,
    pose_from_rt,
    quaternion_to_matrix,
    relative_pose,
    rotation_angle_deg,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
)
from endorecon.geometry.sim3 import apply_sim3, umeyama
from endorecon.geometry.warp import flow_from_depth, sample_bilinear, warp_depth

__all__ = [
    "apply_sim3",
    "camera_centers",
    "crop_intrinsics",
    "flow_from_depth",
    "from_corner_convention",
    "invert_pose",
    "mask_bbox_crop",
    "matrix_to_quaternion",
    "pixel_grid",
    "pose_from_rt",
    "project",
    "quaternion_to_matrix",
    "relative_pose",
    "rotation_angle_deg",
    "sample_bilinear",
    "scale_intrinsics",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_log",
    "to_corner_convention",
    "transform_points",
    "umeyama",
    "unproject",
]
