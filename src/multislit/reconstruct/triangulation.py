"""Image points on identified slits -> 3D points (paper section 5.5, eq. 5-6, and our model).

:func:`triangulate_matrix` is the paper's conversion: for each image point (u, v) on slit X_p,
solve F = Q V (eq. 5-6) for V = (X, Y, Z), all points at once.

:func:`triangulate` is the general form used with our calibration: undistort through the
camera's lines of sight and intersect each with the plane of its slit. For a
:class:`~multislit.geometry.PinholeCamera` this runs as one compiled loop over the points (the
same undistortion and intersection, point by point).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MultislitError
from multislit.geometry import Camera, PinholeCamera, as_points, intersect_rays_planes
from multislit.geometry.camera import line_of_sight

F64 = NDArray[np.float64]


def check_min_angle(min_angle_deg: object) -> float:
    """``min_angle_deg`` as a float if it is a number of degrees in [0, 90); else a
    :class:`~multislit.errors.MultislitError` naming it."""
    if isinstance(min_angle_deg, bool) or not isinstance(
        min_angle_deg, int | float | np.integer | np.floating
    ):
        raise MultislitError(
            f"min_angle_deg must be a number of degrees, got {type(min_angle_deg).__name__} "
            f"{min_angle_deg!r}"
        )
    x = float(min_angle_deg)
    if not 0.0 <= x < 90.0:  # NaN fails too
        raise MultislitError(f"min_angle_deg must be 0 to less than 90 degrees, got {x}")
    return x


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
        ``slit`` has a value >= K or < -1, the shapes do not match, or ``min_angle_deg`` is
        not a number of degrees in [0, 90).
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
    min_cos = math.sin(math.radians(check_min_angle(min_angle_deg)))
    if type(camera) is PinholeCamera:
        pts = np.empty((len(p), 3))
        valid = np.empty(len(p), bool)
        _pinhole_points(
            np.array([camera.fx, camera.fy, camera.cx, camera.cy]),
            np.asarray(camera.dist_array, np.float64),
            np.ascontiguousarray(camera.R, np.float64),
            np.ascontiguousarray(camera.centre, np.float64),
            np.ascontiguousarray(pl),
            np.ascontiguousarray(p),
            s,
            min_cos,
            pts,
            valid,
        )
        return pts, valid
    known = s >= 0
    o, d = camera.rays(p)
    per = np.full((len(p), 4), np.nan)
    per[known] = pl[s[known]]
    with np.errstate(invalid="ignore"):
        pts, _ = intersect_rays_planes(o, d, per, min_cos=min_cos)
    valid = np.all(np.isfinite(pts), axis=1)
    pts[~valid] = np.nan
    return pts, valid


@njit(cache=True)
def _pinhole_points(intr, dist, R, centre, planes, uv, slit, min_cos, pts, valid):
    """:meth:`PinholeCamera.rays` and :func:`intersect_rays_planes` point by point: ``intr``
    (fx, fy, cx, cy), ``dist`` (4 or 5 coefficients), ``R`` (3, 3) world -> camera,
    ``centre`` (3,) mm, ``planes`` (K, 4), ``uv`` (N, 2) px, ``slit`` (N,) (-1: none); writes
    ``pts`` (N, 3) mm (NaN where not valid) and ``valid`` (N,)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2 = dist[0], dist[1], dist[2], dist[3]
    k3 = dist[4] if dist.size > 4 else 0.0
    distorted = k1 != 0 or k2 != 0 or p1 != 0 or p2 != 0 or k3 != 0
    for i in range(uv.shape[0]):
        pts[i, 0] = pts[i, 1] = pts[i, 2] = np.nan
        valid[i] = False
        s = slit[i]
        if s < 0:
            continue
        d0, d1, d2 = line_of_sight(
            uv[i, 0], uv[i, 1], fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, R
        )
        n0, n1, n2, n3 = planes[s, 0], planes[s, 1], planes[s, 2], planes[s, 3]
        denom = n0 * d0 + n1 * d1 + n2 * d2
        num = -((n0 * centre[0] + n1 * centre[1] + n2 * centre[2]) + n3)
        dn = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if denom == 0 or abs(denom) <= min_cos * dn:
            continue
        t = num / denom
        if not t >= 0:  # behind the camera, or NaN (a slit without a plane)
            continue
        X = centre[0] + t * d0
        Y = centre[1] + t * d1
        Z = centre[2] + t * d2
        if math.isfinite(X) and math.isfinite(Y) and math.isfinite(Z):
            pts[i, 0], pts[i, 1], pts[i, 2] = X, Y, Z
            valid[i] = True


def compile_kernels() -> None:
    """Compile the triangulation's Numba kernels now: :func:`triangulate` with a pinhole
    camera (with and without lens distortion), a point in front of the camera and one left
    out, and the camera's undistortion (:meth:`PinholeCamera.rays`,
    :meth:`PinholeCamera.normalized`).

    Numba compiles it on first use and caches the machine code on disk beside the package;
    :func:`multislit.compile_kernels` calls this with the other stages' warm-ups.
    """
    planes = np.array([[1.0, 0.0, 0.0, -10.0]])
    uv = np.array([[700.0, 500.0], [600.0, 500.0]])
    slit = np.array([0, -1])
    for dist in ((0.0, 0.0, 0.0, 0.0), (-0.1, 0.01, 0.0, 0.0, 0.001)):
        camera = PinholeCamera(1000.0, 1000.0, 640.0, 512.0, tvec=(0.0, 0.0, 500.0), dist=dist)
        triangulate(camera, planes, uv, slit)
        camera.rays(uv)
        camera.normalized(uv)
