"""Camera calibration from 3D markers and their images (paper section 5, eq. 1-2).

:func:`calibrate_dlt` is the paper's eq. (1)-(2): a 3x4 matrix C by linear least squares
(Hartley-normalised DLT) from >= 6 non-coplanar markers. :func:`decompose_camera` splits C into
K [R | t]; :func:`refine_camera` adds lens distortion (k1, k2, p1, p2) and minimises the
reprojection error from the DLT start. :func:`refine_camera_with_lines` also makes image curves
that are straight lines in space (stripes on flat faces) straight.

Units: mm in the world (target) frame, px in the image; pixel (0, 0) is the centre of the
top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from multislit.errors import CalibrationError
from multislit.geometry import (
    MatrixCamera,
    PinholeCamera,
    as_points,
    rotation_from_rvec,
    rvec_from_rotation,
)
from multislit.geometry.camera import F64, _distort, _undistort

#: Least number of markers for the DLT.
MIN_DLT_POINTS = 6


def check_finite(a: F64, name: str) -> None:
    """Raise :class:`CalibrationError` naming ``name`` and the rows of ``a`` that are not finite."""
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.all(np.isfinite(a.reshape(len(a), -1)), axis=1))
        raise CalibrationError(
            f"{name} contains NaN or infinite values (rows {bad[:10].tolist()}"
            f"{' ...' if len(bad) > 10 else ''}); remove those points"
        )


def hartley_normalisation(points: F64, name: str) -> F64:
    """Hartley's similarity: centroid to 0, mean distance to sqrt(dim). Returns (dim+1, dim+1)."""
    dim = points.shape[1]
    c = points.mean(axis=0)
    mean_dist = np.linalg.norm(points - c, axis=1).mean()
    if not mean_dist > 0:
        raise CalibrationError(
            f"all points of {name} coincide; the calibration needs distinct points"
        )
    s = math.sqrt(dim) / mean_dist
    T = np.eye(dim + 1)
    T[:dim, :dim] *= s
    T[:dim, dim] = -s * c
    return T


def homogeneous(p: F64) -> F64:
    """Points (N, d) with a column of ones appended: (N, d + 1)."""
    return np.concatenate([p, np.ones((len(p), 1))], axis=1)


# --------------------------------------------------------------------------- DLT
def calibrate_dlt(
    world: ArrayLike,
    image: ArrayLike,
    image_size: tuple[int, int] = (1280, 1024),
    coplanar_tol: float = 1e-3,
) -> tuple[MatrixCamera, F64]:
    """Camera matrix C of eq. (1) by the linear DLT of eq. (2), Hartley-normalised.

    Parameters
    ----------
    world : (N, 3) float64, mm, target frame; N >= 6, not all on one plane
    image : (N, 2) float64, px, the measured images of ``world``
    image_size : (W, H) int, px, stored in the returned camera
    coplanar_tol : float
        The world points count as coplanar when the third singular value of the centred points
        is below ``coplanar_tol`` times the first.

    Returns
    -------
    camera : MatrixCamera, C scaled so that ||C[2, :3]|| = 1 and points in front have
        positive homogeneous scale H_c
    residuals : (N,) float64, px, reprojection distance of each point

    Raises
    ------
    CalibrationError
        Fewer than 6 points, non-finite input, coplanar points, degenerate solution.
    """
    X = as_points(world, 3, "world")
    x = as_points(image, 2, "image")
    if len(X) != len(x):
        raise CalibrationError(
            f"world has {len(X)} points but image has {len(x)}; they must be corresponding pairs"
        )
    if len(X) < MIN_DLT_POINTS:
        raise CalibrationError(
            f"the DLT needs >= {MIN_DLT_POINTS} marker points, {len(X)} given; "
            "detect more markers (on at least two non-parallel faces)"
        )
    check_finite(X, "world")
    check_finite(x, "image")
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if s[2] < coplanar_tol * s[0]:
        raise CalibrationError(
            f"the {len(X)} world points are coplanar: the DLT needs markers on at least two "
            f"non-parallel faces (singular values of the centred points {s[0]:.3g}, {s[1]:.3g}, "
            f"{s[2]:.3g})"
        )
    U = hartley_normalisation(X, "world")
    T = hartley_normalisation(x, "image")
    Xn = homogeneous(X) @ U.T
    xn = homogeneous(x) @ T.T
    n = len(X)
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -xn[:, 0:1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -xn[:, 1:2] * Xn
    _, sv, vt = np.linalg.svd(A, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise CalibrationError(
            "the DLT solution is not unique (the points do not constrain all 11 parameters); "
            "use markers spread over the image and over at least two non-parallel faces"
        )
    Cn = vt[-1].reshape(3, 4)
    C = np.linalg.inv(T) @ Cn @ U
    M = C[:, :3]
    cond = np.linalg.cond(Cn[:, :3])
    if not np.isfinite(cond) or cond > 1e10:
        raise CalibrationError(
            f"the DLT solution is degenerate (condition number {cond:.3g} of its 3x3 block); "
            "check the marker coordinates and their pairing with the image points"
        )
    C = C / np.linalg.norm(M[2])
    if np.median(homogeneous(X) @ C[2]) < 0:
        C = -C
    cam = MatrixCamera(C, image_size)
    res = np.linalg.norm(cam.project(X) - x, axis=1)
    return cam, res


def decompose_camera(
    camera: MatrixCamera | ArrayLike, image_size: tuple[int, int] | None = None
) -> PinholeCamera:
    """Split a 3x4 matrix C = s K [R | t] into a distortion-free :class:`PinholeCamera`.

    Parameters
    ----------
    camera : MatrixCamera or (3, 4) float64
    image_size : (W, H) px; default the MatrixCamera's (or (1280, 1024) for a bare matrix)

    Returns
    -------
    PinholeCamera
        K with positive fx, fy (the skew of K is dropped: the model has square axes);
        R a proper rotation; points in front of the camera have positive depth.

    Notes
    -----
    C and -C are the same projective camera; the sign is chosen so that det(C[:, :3]) > 0,
    which puts the points in front of the camera for a right-handed target frame.
    """
    if isinstance(camera, MatrixCamera):
        C = camera.C.copy()
        size = camera.image_size if image_size is None else image_size
    else:
        C = np.asarray(camera, dtype=float)
        if C.shape != (3, 4) or not np.all(np.isfinite(C)):
            raise CalibrationError(f"camera must be a finite (3, 4) matrix, got shape {C.shape}")
        size = (1280, 1024) if image_size is None else image_size
    M = C[:, :3]
    if np.linalg.det(M) < 0:
        # C and -C are the same projective camera; det(K R) > 0 needs det(M) > 0
        C = -C
        M = -M
    K, R = scipy.linalg.rq(M)
    D = np.diag(np.sign(np.diag(K)))
    K = K @ D
    R = D @ R
    scale = K[2, 2]
    # det(M) > 0 and a positive diagonal of K make R proper and K[2, 2] > 0
    t = np.linalg.solve(K, C[:, 3])
    K = K / scale
    return PinholeCamera(
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        rvec=tuple(rvec_from_rotation(R)),
        tvec=tuple(t),
        image_size=size,
    )


# --------------------------------------------------------------------------- refinement
_N_CAM = 14  # fx fy cx cy r(3) t(3) k1 k2 p1 p2


def _project_params(params: F64, X: F64) -> F64:
    fx, fy, cx, cy = params[:4]
    R = rotation_from_rvec(params[4:7])
    pc = X @ R.T + params[7:10]
    xy = pc[:, :2] / pc[:, 2:3]
    xyd = _distort(xy, params[10:14])
    return np.stack([fx * xyd[:, 0] + cx, fy * xyd[:, 1] + cy], axis=1)


def refine_camera(
    world: ArrayLike,
    image: ArrayLike,
    initial: PinholeCamera | MatrixCamera | None = None,
    distortion: bool = True,
    tangential: bool = True,
    square_pixels: bool = False,
) -> tuple[PinholeCamera, F64]:
    """Pinhole + distortion camera by non-linear least squares on the reprojection error.

    Parameters
    ----------
    world : (N, 3) float64, mm, target frame
    image : (N, 2) float64, px
    initial : starting camera; a MatrixCamera is decomposed, None runs :func:`calibrate_dlt`
    distortion : bool
        Estimate lens distortion. False keeps k1 = k2 = p1 = p2 = 0.
    tangential : bool
        With ``distortion``, also estimate p1, p2 (else only k1, k2).
    square_pixels : bool
        Constrain fx = fy.

    Returns
    -------
    camera : PinholeCamera (image_size from ``initial``)
    residuals : (N,) float64, px, reprojection distance of each point

    Raises
    ------
    CalibrationError
        As :func:`calibrate_dlt`, or when the optimisation fails.
    """
    X = as_points(world, 3, "world")
    x = as_points(image, 2, "image")
    if initial is None or isinstance(initial, MatrixCamera):
        if initial is None:
            initial, _ = calibrate_dlt(X, x)
        initial = decompose_camera(initial)
    if len(X) != len(x):
        raise CalibrationError(f"world has {len(X)} points but image has {len(x)}")
    if len(X) < MIN_DLT_POINTS:
        raise CalibrationError(f"refine_camera needs >= {MIN_DLT_POINTS} points, {len(X)} given")
    check_finite(X, "world")
    check_finite(x, "image")
    if np.median(initial.to_camera(X)[:, 2]) <= 0:
        raise CalibrationError(
            "the world points lie behind the initial camera: the target frame is mirrored "
            "(left-handed) with respect to the image; flip one world axis of the target"
        )
    p0 = np.concatenate(
        [
            [initial.fx, initial.fy, initial.cx, initial.cy],
            initial.rvec,
            initial.tvec,
            initial.dist if distortion else np.zeros(4),
        ]
    )
    free = np.ones(_N_CAM, bool)
    if square_pixels:
        free[1] = False
        p0[0] = p0[1] = 0.5 * (p0[0] + p0[1])
    if not distortion:
        free[10:14] = False
    elif not tangential:
        free[12:14] = False
        p0[12:14] = 0.0

    def expand(q: F64) -> F64:
        p = p0.copy()
        p[free] = q
        if square_pixels:
            p[1] = p[0]
        return p

    def fun(q: F64) -> F64:
        return (_project_params(expand(q), X) - x).ravel()

    if 2 * len(X) < int(free.sum()):
        raise CalibrationError(
            f"refine_camera: {len(X)} points give {2 * len(X)} equations for {int(free.sum())} "
            "parameters; add markers or pass distortion=False"
        )
    with np.errstate(all="ignore"):
        sol = least_squares(fun, p0[free], method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
    p = expand(sol.x)
    if not np.all(np.isfinite(p)) or p[0] <= 0 or p[1] <= 0:
        raise CalibrationError(f"camera refinement failed: {sol.message}")
    cam = PinholeCamera(
        fx=p[0],
        fy=p[1],
        cx=p[2],
        cy=p[3],
        rvec=tuple(p[4:7]),
        tvec=tuple(p[7:10]),
        dist=tuple(p[10:14]),
        image_size=initial.image_size,
    )
    res = np.linalg.norm(cam.project(X) - x, axis=1)
    return cam, res


def rms(residuals: ArrayLike) -> float:
    """Root mean square of the finite values of ``residuals`` (NaN if there are none)."""
    r = np.asarray(residuals, dtype=float)
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


# --------------------------------------------------------------------------- straight lines
def _line_residuals(q: F64, group: NDArray[np.intp], n_groups: int) -> F64:
    """Signed distance of each point (N, 2) to the total-least-squares line of its group."""
    cnt = np.bincount(group, minlength=n_groups).astype(float)
    cnt = np.maximum(cnt, 1.0)
    cx = np.bincount(group, q[:, 0], n_groups) / cnt
    cy = np.bincount(group, q[:, 1], n_groups) / cnt
    dx, dy = q[:, 0] - cx[group], q[:, 1] - cy[group]
    sxx = np.bincount(group, dx * dx, n_groups)
    syy = np.bincount(group, dy * dy, n_groups)
    sxy = np.bincount(group, dx * dy, n_groups)
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy) + 0.5 * np.pi  # normal of the line
    return dx * np.cos(theta)[group] + dy * np.sin(theta)[group]


def refine_camera_with_lines(
    world: ArrayLike,
    image: ArrayLike,
    initial: PinholeCamera,
    lines: Sequence[ArrayLike],
    outlier_sigma: float = 4.0,
) -> tuple[PinholeCamera, F64, F64]:
    """Camera from markers plus image curves that are straight lines in space (plumb lines).

    A stripe on a flat face (or on a reference board) is the intersection of two planes, a
    straight line, so its centre points must be collinear once the lens distortion is removed.
    Markers alone (a few clusters on the target) leave the distortion poorly determined away
    from them; thousands of stripe points over the image fix it. Both kinds of residual are in
    px; the line residuals do not depend on the pose, so the markers still fix the pose.

    Parameters
    ----------
    world, image : (M, 3) mm and (M, 2) px, the markers
    initial : starting camera (e.g. from :func:`refine_camera`)
    lines : sequence of (N_i, 2) px arrays, each the image points of one straight 3D line
    outlier_sigma : line points further than this many robust sigmas are dropped once

    Returns
    -------
    camera : PinholeCamera
    marker_residuals : (M,) px
    line_residuals : (sum N_i,) px, distances to the fitted lines (NaN for dropped points)
    """
    X = np.asarray(world, dtype=float)
    x = np.asarray(image, dtype=float)
    pts = [np.asarray(g, dtype=float).reshape(-1, 2) for g in lines]
    if not pts:
        raise CalibrationError("refine_camera_with_lines needs at least one line")
    P = np.concatenate(pts)
    group = np.concatenate([np.full(len(g), i, np.intp) for i, g in enumerate(pts)])
    n_groups = len(pts)
    p0 = np.concatenate(
        [[initial.fx, initial.fy, initial.cx, initial.cy], initial.rvec, initial.tvec, initial.dist]
    )
    use = np.ones(len(P), bool)

    def line_res(p: F64, Pu: F64, gu: NDArray[np.intp]) -> F64:
        xyd = np.stack([(Pu[:, 0] - p[2]) / p[0], (Pu[:, 1] - p[3]) / p[1]], axis=1)
        xy = _undistort(xyd, p[10:14], iterations=10) * p[:2]  # undistorted px (scale-free)
        return _line_residuals(xy, gu, n_groups)

    sol_x = p0
    for _ in range(2):
        Pu, gu = P[use], group[use]

        def fun(p: F64, Pu=Pu, gu=gu) -> F64:
            return np.concatenate([(_project_params(p, X) - x).ravel(), line_res(p, Pu, gu)])

        with np.errstate(all="ignore"):
            sol = least_squares(fun, sol_x, method="lm", x_scale="jac", xtol=1e-10, ftol=1e-10)
        sol_x = sol.x
        r = np.full(len(P), np.nan)
        r[use] = line_res(sol_x, Pu, gu)
        sig = 1.4826 * float(np.nanmedian(np.abs(r)))
        new = use & (np.abs(r) <= outlier_sigma * max(sig, 1e-3))
        if np.array_equal(new, use):
            break
        use = new
    p = sol_x
    if not np.all(np.isfinite(p)) or p[0] <= 0 or p[1] <= 0:
        raise CalibrationError(f"camera refinement with stripes failed: {sol.message}")
    cam = PinholeCamera(
        fx=p[0], fy=p[1], cx=p[2], cy=p[3], rvec=tuple(p[4:7]), tvec=tuple(p[7:10]),
        dist=tuple(p[10:14]), image_size=initial.image_size,
    )  # fmt: skip
    res = np.linalg.norm(cam.project(X) - x, axis=1)
    lr = np.full(len(P), np.nan)
    lr[use] = line_res(p, P[use], group[use])
    return cam, res, lr
