"""multislit.geometry."""

from multislit.geometry.camera import (
    Camera,
    MatrixCamera,
    PinholeCamera,
    as_points,
    camera_from_dict,
    fit_plane,
    intersect_rays_planes,
    look_at,
    normalize_planes,
    rotation_from_rvec,
    rvec_from_rotation,
)

__all__ = [
    "as_points",
    "rotation_from_rvec",
    "rvec_from_rotation",
    "look_at",
    "Camera",
    "PinholeCamera",
    "MatrixCamera",
    "camera_from_dict",
    "normalize_planes",
    "fit_plane",
    "intersect_rays_planes",
]
