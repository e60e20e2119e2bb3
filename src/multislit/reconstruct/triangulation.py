"""Image points on identified slits -> 3D points (paper section 5.5, eq. 5-6, and our model).

:func:`triangulate_matrix` is the paper's conversion: for each image point (u, v) on slit X_p,
solve F = Q V (eq. 5-6) for V = (X, Y, Z), all points at once.

:func:`triangulate` is the general form used with our calibration: undistort through the
camera's lines of sight and intersect each with the plane of its slit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MultislitError
from multislit.geometry import Camera, as_points, intersect_rays_planes

F64 = NDArray[np.float64]


def triangulate_matrix(
    C: ArrayLike, P: ArrayLike, uv: ArrayLike, xp: ArrayLike, min_sin: float = 1e-6
) -> tuple[F64, NDArray[np.bool_]]:
    """3D points from the paper's camera matrix C and projector matrix P (eq. 5-6).

    Parameters
    ----------
    C : (3, 4) float64, camera matrix of eq. (1)
    P : (2, 4) float64, projector matrix of eq. (3)
    uv : (N, 2) float64, px, image points on slits
    xp : (N,) float64, slit coordinate X_p of each point (NaN: unknown slit)
    min_sin : float
        Points whose system Q is nearly singular (|det Q| below ``min_sin`` times the product
        of its row norms, i.e. the line of sight nearly parallel to the slit plane) are rejected.

    Returns
    -------
    points : (N, 3) float64, mm, world frame (NaN where not valid)
    valid : (N,) bool
    """
    C = np.asarray(C, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    if C.shape != (3, 4) or not np.all(np.isfinite(C)):
        raise MultislitError(f"C must be a finite (3, 4) camera matrix, got shape {C.shape}")
    if P.shape != (2, 4) or not np.all(np.isfinite(P)):
        raise MultislitError(f"P must be a finite (2, 4) projector matrix, got shape {P.shape}")
    p = as_points(uv, 2, "uv")
    x = np.asarray(xp, dtype=np.float64).reshape(-1)
    if len(x) != len(p):
        raise MultislitError(f"uv has {len(p)} points but xp has {len(x)} values")
    u, v = p[:, 0:1], p[:, 1:2]
    xq = x[:, None]
    Q = np.stack(
        [
            C[0, :3] - u * C[2, :3],
            C[1, :3] - v * C[2, :3],
            P[0, :3] - xq * P[1, :3],
        ],
        axis=1,
    )  # (N, 3, 3)
    F = np.stack(
        [
            C[2, 3] * p[:, 0] - C[0, 3],
            C[2, 3] * p[:, 1] - C[1, 3],
            P[1, 3] * x - P[0, 3],
        ],
        axis=1,
    )  # (N, 3)
    with np.errstate(invalid="ignore", over="ignore"):
        det = np.linalg.det(Q)
        scale = np.prod(np.linalg.norm(Q, axis=2), axis=1)
        valid = np.isfinite(det) & np.isfinite(F).all(axis=1) & (np.abs(det) > min_sin * scale)
    Qs = np.where(valid[:, None, None], Q, np.eye(3))
    Fs = np.where(valid[:, None], F, 0.0)
    V = np.linalg.solve(Qs, Fs[:, :, None])[:, :, 0]
    V[~valid] = np.nan
    return V, valid


def triangulate(
    camera: Camera,
    planes: ArrayLike,
    uv: ArrayLike,
    slit: ArrayLike,
    min_angle_deg: float = 2.0,
) -> tuple[F64, NDArray[np.bool_]]:
    """3D points: each pixel's line of sight intersected with the plane of its slit.

    Parameters
    ----------
    camera : any camera with ``rays`` (PinholeCamera: distortion is removed there)
    planes : (K, 4) float64, unit normals, n.X + d = 0 (mm), one per slit; NaN rows are slits
        without a calibrated plane
    uv : (N, 2) float64, px
    slit : (N,) int, slit number 0..K-1 of each point; -1 marks an unidentified point
    min_angle_deg : float, deg
        Lines of sight meeting the plane at a smaller angle are rejected.

    Returns
    -------
    points : (N, 3) float64, mm, world frame (NaN where not valid)
    valid : (N,) bool; False for unidentified points, slits without a plane, grazing rays and
        intersections behind the camera

    Raises
    ------
    MultislitError
        ``slit`` has a value >= K or < -1, or the shapes do not match.
    """
    pl = as_points(planes, 4, "planes")
    p = as_points(uv, 2, "uv")
    s = np.asarray(slit).reshape(-1)
    if len(s) != len(p):
        raise MultislitError(f"uv has {len(p)} points but slit has {len(s)} values")
    if s.size and not np.issubdtype(s.dtype, np.integer):
        raise MultislitError(f"slit must be integer slit numbers, got dtype {s.dtype}")
    s = s.astype(np.intp)
    bad = (s < -1) | (s >= len(pl))
    if np.any(bad):
        raise MultislitError(
            f"slit has values outside 0..{len(pl) - 1} (e.g. {int(s[bad][0])}; -1 = "
            "unidentified); the planes and the slit numbers do not belong together"
        )
    known = s >= 0
    o, d = camera.rays(p)
    per = np.full((len(p), 4), np.nan)
    per[known] = pl[s[known]]
    min_cos = math.sin(math.radians(min_angle_deg))
    with np.errstate(invalid="ignore"):
        pts, _ = intersect_rays_planes(o, d, per, min_cos=min_cos)
    valid = np.all(np.isfinite(pts), axis=1)
    pts[~valid] = np.nan
    return pts, valid
