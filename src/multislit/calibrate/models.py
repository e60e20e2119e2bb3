"""Calibration of the camera and of the multiple-slit projector (paper section 5).

Camera
    :func:`calibrate_dlt` is the paper's eq. (1)-(2): a 3x4 matrix C by linear least squares
    (Hartley-normalised DLT) from >= 6 non-coplanar markers. :func:`decompose_camera` splits C
    into K [R | t]; :func:`refine_camera` adds lens distortion (k1, k2, p1, p2) and minimises the
    reprojection error from the DLT start.

Markers
    :func:`find_marker_corners` finds the centre corner of each 2x2 checker marker near its hint
    (sub-pixel) and verifies that it really is a checker corner.

Projector
    :func:`fit_projector_matrix` is the paper's eq. (3)-(4): one 2x4 matrix P for all slits,
    the plane of slit X_p being (P_1 - X_p P_2) . [X, 1] = 0. :func:`fit_slit_planes` is our
    model: one plane per slit, optionally constrained to share one common line (the grating's
    axis). :func:`slit_plane_rms` measures how well any set of slit planes explains points on the
    slits, e.g. the systematic error of the 2x4 model for a diffraction grating.

:class:`Calibration` holds the result and reads/writes ``multislit-calibration/1`` JSON.

Units: mm in the world (target) frame, px in the image; pixel (0, 0) is the centre of the
top-left pixel.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter, map_coordinates, maximum_filter, spline_filter
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from multislit.errors import CalibrationError, MultislitError
from multislit.geometry.camera import (
    F64,
    MatrixCamera,
    PinholeCamera,
    _distort,
    as_points,
    camera_from_dict,
    rotation_from_rvec,
    rvec_from_rotation,
)
from multislit.io import Face

SCHEMA = "multislit-calibration/1"
MIN_DLT_POINTS = 6
MIN_PROJECTOR_POINTS = 8


# --------------------------------------------------------------------------- helpers
def _finite(a: F64, name: str) -> None:
    if not np.all(np.isfinite(a)):
        bad = np.flatnonzero(~np.all(np.isfinite(a.reshape(len(a), -1)), axis=1))
        raise CalibrationError(
            f"{name} contains NaN or infinite values (rows {bad[:10].tolist()}"
            f"{' ...' if len(bad) > 10 else ''}); remove those points"
        )


def _normalisation(points: F64, name: str) -> F64:
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


def _homog(p: F64) -> F64:
    return np.concatenate([p, np.ones((len(p), 1))], axis=1)


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, float):
        return None if not math.isfinite(x) else x
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def _array(x: Any, name: str, shape: tuple[int, ...] | None = None) -> F64:
    try:
        a = np.array([np.nan if v is None else v for v in np.ravel(np.array(x, dtype=object))])
        a = a.astype(float).reshape(np.shape(np.array(x, dtype=object)))
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"calibration JSON: {name} is malformed: {exc}") from None
    if shape is not None and a.shape != shape:
        raise CalibrationError(f"calibration JSON: {name} must have shape {shape}, got {a.shape}")
    return a


# --------------------------------------------------------------------------- camera: DLT
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
    _finite(X, "world")
    _finite(x, "image")
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if s[2] < coplanar_tol * s[0]:
        raise CalibrationError(
            f"the {len(X)} world points are coplanar: the DLT needs markers on at least two "
            f"non-parallel faces (singular values of the centred points {s[0]:.3g}, {s[1]:.3g}, "
            f"{s[2]:.3g})"
        )
    U = _normalisation(X, "world")
    T = _normalisation(x, "image")
    Xn = _homog(X) @ U.T
    xn = _homog(x) @ T.T
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
    if np.median(_homog(X) @ C[2]) < 0:
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


# --------------------------------------------------------------------------- camera: refinement
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
    _finite(X, "world")
    _finite(x, "image")
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


# --------------------------------------------------------------------------- markers
@dataclass(frozen=True, eq=False)
class MarkerDetection:
    """Result of :func:`find_marker_corners`.

    Attributes
    ----------
    ids : tuple of str, (M,)
    uv : (M, 2) float64, px, sub-pixel centre corner; NaN where not found
    found : (M,) bool
    reasons : tuple of str, (M,), why a marker was not found ('' where found)
    contrast : (M,) float64, grey levels, |bright - dark| around the corner (NaN if not measured)
    """

    ids: tuple[str, ...]
    uv: F64
    found: NDArray[np.bool_]
    reasons: tuple[str, ...]
    contrast: F64

    @property
    def rejected(self) -> dict[str, str]:
        """Marker id -> reason, for the markers that were not found."""
        return {i: r for i, r, f in zip(self.ids, self.reasons, self.found, strict=True) if not f}


def _noise_sigma(img: F64) -> float:
    """Robust estimate of the image noise (grey levels) from a Laplacian-like high-pass."""
    # Immerkaer's operator; flat and smooth regions dominate the median
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    h = cv2.filter2D(img.astype(np.float32), -1, k, borderType=cv2.BORDER_REFLECT)
    return float(1.4826 * np.median(np.abs(h[1:-1, 1:-1])) / 6.0)


def _ring_check(
    img: F64, uv: F64, radii: Sequence[float], noise: float, min_contrast: float
) -> tuple[NDArray[np.bool_], list[str], F64]:
    """Verify that each (u, v) is a 2x2 checker corner from intensity rings around it.

    On every ring the profile must alternate bright/dark/bright/dark (4 sectors: diagonal
    quadrants alike, adjacent ones different) with a contrast well above the noise.
    """
    n_ang = 72
    ang = np.linspace(0, 2 * np.pi, n_ang, endpoint=False)
    r = np.asarray(radii, float)
    # samples (M, R, A)
    us = uv[:, 0, None, None] + r[None, :, None] * np.cos(ang)[None, None, :]
    vs = uv[:, 1, None, None] + r[None, :, None] * np.sin(ang)[None, None, :]
    prof = map_coordinates(img, [vs.ravel(), us.ravel()], order=1, mode="nearest")
    prof = prof.reshape(us.shape)
    lo = np.percentile(prof, 10, axis=2, keepdims=True)
    hi = np.percentile(prof, 90, axis=2, keepdims=True)
    mid = 0.5 * (lo + hi)
    span = hi - lo
    # hysteresis classification: +1 bright, -1 dark, 0 undecided
    cls = np.where(prof > mid + 0.2 * span, 1, np.where(prof < mid - 0.2 * span, -1, 0))
    ok = np.ones(len(uv), bool)
    reasons = [""] * len(uv)
    contrast = np.full(len(uv), np.nan)
    for i in range(len(uv)):  # markers are few; the per-ring work is vectorised above
        c_all = []
        why = ""
        for j in range(len(r)):
            c = cls[i, j]
            c = c[c != 0]
            if c.size < 8:
                why = "no structure around the corner"
                break
            changes = int(np.count_nonzero(c != np.roll(c, 1)))
            if changes != 4:
                kind = {0: "a blank patch", 2: "an edge or an L-corner"}.get(
                    changes, f"{changes} bright/dark sectors instead of 4"
                )
                why = f"not a checker corner ({kind} at radius {r[j]:g} px)"
                break
            p = prof[i, j]
            bright = p[cls[i, j] == 1]
            dark = p[cls[i, j] == -1]
            c_all.append(np.median(bright) - np.median(dark))
        if not why:
            contrast[i] = float(np.min(c_all))
            if contrast[i] < max(min_contrast, 8.0 * noise):
                why = (
                    f"contrast {contrast[i]:.3g} too low (noise {noise:.2g}, "
                    f"need >= {max(min_contrast, 8.0 * noise):.3g})"
                )
        if why:
            ok[i] = False
            reasons[i] = why
    return ok, reasons, contrast


def _sector_balance(img: F64, uv: F64, radius: float) -> F64:
    """Max relative difference between the two bright (and the two dark) sectors (0 = equal)."""
    n_ang = 72
    ang = np.linspace(0, 2 * np.pi, n_ang, endpoint=False)
    us = uv[:, 0, None] + radius * np.cos(ang)[None, :]
    vs = uv[:, 1, None] + radius * np.sin(ang)[None, :]
    prof = map_coordinates(img, [vs.ravel(), us.ravel()], order=1, mode="nearest").reshape(us.shape)
    out = np.full(len(uv), np.inf)
    for i, p in enumerate(prof):
        mid = 0.5 * (p.max() + p.min())
        b = p > mid
        # rotate so the profile starts at a transition, then split into runs
        start = int(np.flatnonzero(b != np.roll(b, 1))[0]) if np.any(b != np.roll(b, 1)) else 0
        pr, br = np.roll(p, -start), np.roll(b, -start)
        edges = np.flatnonzero(br != np.roll(br, 1))
        if len(edges) != 4:
            continue
        runs = np.split(pr, edges[1:])
        lv = np.array([np.median(s) for s in runs])
        span = abs(lv[0] - lv[1]) + 1e-12
        out[i] = max(abs(lv[0] - lv[2]), abs(lv[1] - lv[3])) / span
    return out


def _saddle_refine(coef: F64, q: F64, half: int = 3, iterations: int = 6) -> tuple[F64, F64]:
    """Polish corners to the saddle point of a quadratic fitted to the smoothed image.

    A 2x2 checker is point-symmetric about its corner, so is its smoothed image, and the fitted
    quadratic's stationary point is the corner (no pixel-locking, unlike gradient criteria).

    Parameters
    ----------
    coef : (H, W) cubic-spline coefficients of the smoothed image
    q : (M, 2) float64, px, starting points

    Returns
    -------
    q : (M, 2) float64, px (NaN where the fit is not a saddle)
    det : (M,) float64, determinant of the fitted Hessian (< 0 for a saddle)
    """
    g = np.arange(-half, half + 1, dtype=float)
    dy, dx = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    sw = np.exp(-(dx * dx + dy * dy) / (4.0 * (half / 1.5) ** 2))  # sqrt of Gaussian weights
    A = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=1) * sw[:, None]
    pinv = np.linalg.pinv(A)
    q = np.array(q, dtype=float)
    det = np.full(len(q), np.nan)
    for _ in range(iterations):  # Newton steps on all corners at once
        # corners that diverged are NaN: never pass NaN coordinates to map_coordinates (SciPy
        # 1.17 can crash on them); sample them at 0 and let q + step keep them NaN
        live = np.all(np.isfinite(q), axis=1)
        qs = np.where(live[:, None], q, 0.0)
        vals = map_coordinates(
            coef,
            [qs[:, 1, None] + dy, qs[:, 0, None] + dx],
            order=3,
            prefilter=False,
            mode="nearest",
        )
        co = (vals * sw) @ pinv.T
        hxx, hxy, hyy = 2 * co[:, 3], co[:, 4], 2 * co[:, 5]
        det = hxx * hyy - hxy * hxy
        with np.errstate(divide="ignore", invalid="ignore"):
            step_u = -(hyy * co[:, 1] - hxy * co[:, 2]) / det
            step_v = -(-hxy * co[:, 1] + hxx * co[:, 2]) / det
        step = np.stack([step_u, step_v], axis=1)
        big = ~np.all(np.isfinite(step), axis=1) | (np.abs(step).max(axis=1) > 1.5)
        q = np.where(big[:, None], np.nan, q + step)
        if np.all(np.isnan(q) | (np.abs(step) < 1e-5)):
            break
    q[~(det < 0)] = np.nan
    return q, det


def find_marker_corners(
    image: ArrayLike,
    hints: ArrayLike,
    ids: Sequence[str] | None = None,
    search_radius: float = 15.0,
    window: int = 5,
    zero_zone: int = -1,
    saddle_half: int = 3,
    check_radii: Sequence[float] = (3.0, 5.0),
    min_contrast: float | None = None,
    max_sector_imbalance: float = 0.35,
) -> MarkerDetection:
    """Find the centre corner of 2x2 checker markers near their hints, to sub-pixel accuracy.

    For each marker the saddle points (local maxima of -det(Hessian) of the smoothed image)
    within ``search_radius`` of the hint are refined with ``cv2.cornerSubPix``, polished to the
    saddle point of a quadratic fitted to the smoothed image (which removes cornerSubPix's
    pixel-locking bias on sharp edges, ~0.1 px, to ~0.03 px), and verified,
    nearest first: on rings of ``check_radii`` around the corner the image must show four
    sectors, bright/dark/bright/dark, the two bright (and the two dark) alike, with a contrast
    well above the image noise. The first candidate that passes is the marker's corner; markers
    without one are reported with a reason and get NaN.

    Parameters
    ----------
    image : (H, W) uint8 or uint16, grayscale
    hints : (M, 2) float64, px, approximate corner positions
    ids : M marker ids (default "0", "1", ...)
    search_radius : float, px
    window : int, px, half size of cornerSubPix's window (keep it inside the marker's squares)
    zero_zone : int, px, half size of the window's centre left out by cornerSubPix (-1: none);
    saddle_half : int, px, half size of the window of the final saddle-point fit
    check_radii : radii (px) of the verification rings; keep them inside the squares
    min_contrast : grey levels; default 4 % of the type's range (10 for uint8)
    max_sector_imbalance : float
        Largest allowed difference of the two bright (or two dark) sectors, relative to the
        bright-dark contrast.

    Returns
    -------
    MarkerDetection
    """
    img0 = np.asarray(image)
    if img0.ndim != 2 or img0.dtype not in (np.uint8, np.uint16):
        raise CalibrationError(
            f"image must be a (H, W) uint8 or uint16 grayscale array, got {img0.dtype} {img0.shape}"
        )
    hints = as_points(hints, 2, "hints")
    m = len(hints)
    if ids is None:
        ids = [str(i) for i in range(m)]
    ids = tuple(str(i) for i in ids)
    if len(ids) != m:
        raise CalibrationError(f"ids has {len(ids)} entries but hints has {m} points")
    if search_radius <= 0:
        raise CalibrationError(f"search_radius must be > 0 px, got {search_radius}")
    if min_contrast is None:
        min_contrast = 0.04 * (255.0 if img0.dtype == np.uint8 else 65535.0)
    img = img0.astype(np.float32)
    h, w = img.shape
    noise = _noise_sigma(img)
    smooth = gaussian_filter(img, 1.5)
    gy, gx = np.gradient(smooth)
    gyy, gyx = np.gradient(gy)
    _, gxx = np.gradient(gx)
    saddle = np.maximum(-(gxx * gyy - gyx * gyx), 0.0)
    coef = spline_filter(smooth.astype(np.float64), order=3)
    peaks = (saddle == maximum_filter(saddle, size=5)) & (saddle > 0)

    uv = np.full((m, 2), np.nan)
    found = np.zeros(m, bool)
    reasons = [""] * m
    contrast = np.full(m, np.nan)
    term = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    finite = np.all(np.isfinite(hints), axis=1)
    inside = finite & (hints[:, 0] >= 0) & (hints[:, 0] <= w - 1)
    inside &= (hints[:, 1] >= 0) & (hints[:, 1] <= h - 1)
    for i in range(m):
        if not inside[i]:
            reasons[i] = (
                f"hint ({hints[i, 0]:.1f}, {hints[i, 1]:.1f}) is off the image ({w}x{h} px)"
                if finite[i]
                else "hint is not finite"
            )
            continue
        u0, v0 = hints[i]
        r = int(math.ceil(search_radius))
        x0, x1 = max(int(u0) - r, 0), min(int(u0) + r + 2, w)
        y0, y1 = max(int(v0) - r, 0), min(int(v0) + r + 2, h)
        pv, pu = np.nonzero(peaks[y0:y1, x0:x1])
        pu, pv = pu + x0, pv + y0
        d = np.hypot(pu - u0, pv - v0)
        sel = d <= search_radius
        pu, pv, d, resp = pu[sel], pv[sel], d[sel], saddle[pv[sel], pu[sel]]
        if resp.size:
            # drop weak maxima (noise) relative to the strongest saddle in the search area
            strong = resp >= 0.1 * resp.max()
            pu, pv, d = pu[strong], pv[strong], d[strong]
        if pu.size == 0:
            reasons[i] = f"no corner within {search_radius:g} px of the hint"
            continue
        order = np.argsort(d)[:5]
        cand = np.stack([pu[order], pv[order]], axis=1).astype(np.float32)
        margin = window + 2
        okpos = (
            (cand[:, 0] >= margin)
            & (cand[:, 0] <= w - 1 - margin)
            & (cand[:, 1] >= margin)
            & (cand[:, 1] <= h - 1 - margin)
        )
        if not np.any(okpos):
            reasons[i] = "the corner is too close to the image border"
            continue
        cand = cand[okpos]
        ref = cv2.cornerSubPix(
            img, cand.reshape(-1, 1, 2).copy(), (window, window), (zero_zone, zero_zone), term
        )
        ref = ref.reshape(-1, 2).astype(float)
        polished, _ = _saddle_refine(coef, ref, half=saddle_half)
        ref = np.where(np.isfinite(polished), polished, ref)
        moved = np.hypot(*(ref - cand).T)
        ok, why, con = _ring_check(img, ref, check_radii, noise, min_contrast)
        bal = _sector_balance(img, ref, float(np.max(check_radii)))
        last = ""
        for j in range(len(ref)):
            if moved[j] > 3.0:
                last = "sub-pixel refinement did not converge on a corner"
                continue
            if np.hypot(ref[j, 0] - u0, ref[j, 1] - v0) > search_radius:
                last = f"no corner within {search_radius:g} px of the hint"
                continue
            if not ok[j]:
                last = why[j]
                continue
            if not bal[j] <= max_sector_imbalance:
                last = (
                    "not a checker corner (diagonal quadrants differ by "
                    f"{bal[j]:.0%} of the contrast)"
                )
                continue
            uv[i] = ref[j]
            found[i] = True
            contrast[i] = con[j]
            break
        if not found[i]:
            reasons[i] = last or "no checker corner near the hint"
    return MarkerDetection(ids, uv, found, tuple(reasons), contrast)


# --------------------------------------------------------------------------- projector: 2x4
def _normalise_pointwise_1d(xp: F64) -> F64:
    c = xp.mean()
    s = np.abs(xp - c).mean()
    if not s > 0:
        raise CalibrationError(
            "all points have the same X_p: the projector matrix needs points on >= 2 slits"
        )
    return np.array([[1 / s, -c / s], [0.0, 1.0]])


def fit_projector_matrix(points: ArrayLike, xp: ArrayLike) -> tuple[F64, F64]:
    """Projector matrix P of eq. (3) by linear least squares on eq. (4), normalised.

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame, points on slits; N >= 8
    xp : (N,) float64, slit coordinate X_p of each point (e.g. the slit number)

    Returns
    -------
    P : (2, 4) float64, scaled to unit Frobenius norm; the plane of slit X_p is
        (P[0] - X_p P[1]) . [X, Y, Z, 1] = 0
    residuals : (N,) float64, mm, signed distance of each point to the plane of its X_p

    Raises
    ------
    CalibrationError
        Fewer than 8 points, non-finite input, all on one slit, or a degenerate solution
        (e.g. all points on one line).
    """
    X = as_points(points, 3, "points")
    x = np.asarray(xp, dtype=float).reshape(-1)
    if len(x) != len(X):
        raise CalibrationError(f"points has {len(X)} rows but xp has {len(x)} values")
    if len(X) < MIN_PROJECTOR_POINTS:
        raise CalibrationError(
            f"the projector matrix needs >= {MIN_PROJECTOR_POINTS} points on the slits, "
            f"{len(X)} given; read more points off the slits"
        )
    _finite(X, "points")
    _finite(x[:, None], "xp")
    U = _normalisation(X, "points")
    T = _normalise_pointwise_1d(x)
    Xn = _homog(X) @ U.T
    xn = x * T[0, 0] + T[0, 1]
    A = np.concatenate([Xn, -xn[:, None] * Xn], axis=1)
    _, sv, vt = np.linalg.svd(A, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise CalibrationError(
            "the projector matrix is not determined by these points (use points spread along "
            "several slits and over at least two faces)"
        )
    Pn = vt[-1].reshape(2, 4)
    P = np.linalg.inv(T) @ Pn @ U
    P /= np.linalg.norm(P)
    pl = _pencil_planes(P, x)
    res = np.einsum("ij,ij->i", pl[:, :3], X) + pl[:, 3]
    return P, res


def _pencil_planes(P: F64, xp: F64) -> F64:
    raw = P[0][None, :] - xp[:, None] * P[1][None, :]
    n = np.linalg.norm(raw[:, :3], axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return raw / n


@dataclass(frozen=True, eq=False)
class ProjectorMatrix:
    """The paper's projector model, eq. (3): one 2x4 matrix P for all slits.

    Parameters
    ----------
    P : (2, 4) float64
    xp_values : (K,) float64, the X_p value of each slit 0..K-1 (default: the slit number)
    """

    P: F64
    xp_values: F64

    def __post_init__(self) -> None:
        P = np.asarray(self.P, dtype=float)
        if P.shape != (2, 4) or not np.all(np.isfinite(P)):
            raise CalibrationError(f"P must be a finite (2, 4) matrix, got shape {P.shape}")
        xv = np.asarray(self.xp_values, dtype=float).reshape(-1)
        if not np.all(np.isfinite(xv)):
            raise CalibrationError("xp_values must be finite")
        object.__setattr__(self, "P", P)
        object.__setattr__(self, "xp_values", xv)

    @classmethod
    def fit(
        cls,
        points: ArrayLike,
        slits: ArrayLike,
        num_slits: int,
        xp_values: ArrayLike | None = None,
    ) -> tuple[ProjectorMatrix, F64]:
        """Fit P from points with slit numbers (X_p = ``xp_values[slit]``, default the number).

        Returns the model and the residuals (N,) mm of :func:`fit_projector_matrix`.
        """
        s = _slit_indices(slits, num_slits)
        xv = (
            np.arange(num_slits, dtype=float) if xp_values is None else np.asarray(xp_values, float)
        )
        if xv.shape != (num_slits,):
            raise CalibrationError(f"xp_values must have {num_slits} values, got {xv.shape}")
        P, res = fit_projector_matrix(points, xv[s])
        return cls(P, xv), res

    @property
    def num_slits(self) -> int:
        return len(self.xp_values)

    def planes(self) -> F64:
        """(K, 4) float64: the plane of each slit from eq. (4), unit normals, n.X + d = 0."""
        return _pencil_planes(self.P, self.xp_values)

    def to_dict(self) -> dict[str, Any]:
        return {"P": self.P.tolist(), "xp_values": self.xp_values.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ProjectorMatrix:
        try:
            return cls(np.array(d["P"], dtype=float), np.array(d["xp_values"], dtype=float))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"malformed projector matrix: {exc!r}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, s: str) -> ProjectorMatrix:
        return cls.from_dict(json.loads(s))


# --------------------------------------------------------------------------- projector: planes
def _slit_indices(slits: ArrayLike, num_slits: int, name: str = "slits") -> NDArray[np.intp]:
    if int(num_slits) < 1:
        raise CalibrationError(f"num_slits must be >= 1, got {num_slits}")
    s = np.asarray(slits).reshape(-1)
    if s.size and not np.issubdtype(s.dtype, np.integer):
        if not np.all(np.isfinite(s.astype(float))) or np.any(s != np.round(s)):
            raise CalibrationError(f"{name} must be integer slit numbers")
    s = s.astype(np.intp)
    bad = (s < 0) | (s >= num_slits)
    if np.any(bad):
        raise CalibrationError(
            f"{name} has values outside 0..{num_slits - 1} (e.g. {int(s[bad][0])}); "
            "check the slit numbering or num_slits"
        )
    return s


@dataclass(frozen=True, eq=False)
class SlitPlanes:
    """One plane per slit (our projector model).

    Attributes
    ----------
    planes : (K, 4) float64, unit normals, n.X + d = 0 (mm); NaN rows for slits without a fit
    rms_mm : (K,) float64, mm, RMS distance of each slit's points to its plane (NaN: no fit)
    counts : (K,) int, number of points used per slit
    axis_point, axis_direction : (3,) float64 mm / unit, the common line (None if not fitted)
    excluded : tuple of (slit, reason) for slits left out
    from_axis : tuple of int, slits seen along one line only, whose plane is the plane through
        the common axis and their points (see :func:`fit_slit_planes`)
    """

    planes: F64
    rms_mm: F64
    counts: NDArray[np.int_]
    axis_point: F64 | None = None
    axis_direction: F64 | None = None
    excluded: tuple[tuple[int, str], ...] = field(default=())
    from_axis: tuple[int, ...] = field(default=())

    @property
    def num_slits(self) -> int:
        return len(self.planes)

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(K,) bool, slits with a plane."""
        return np.all(np.isfinite(self.planes), axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "planes": _nan_to_none(self.planes.tolist()),
            "rms_mm": _nan_to_none(self.rms_mm.tolist()),
            "counts": [int(c) for c in self.counts],
            "axis_point": None if self.axis_point is None else self.axis_point.tolist(),
            "axis_direction": None if self.axis_direction is None else self.axis_direction.tolist(),
            "excluded": [[int(k), r] for k, r in self.excluded],
            "from_axis": [int(j) for j in self.from_axis],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SlitPlanes:
        try:
            planes = _array(d["planes"], "slit_planes.planes")
            k = len(planes)
            planes = planes.reshape(k, 4)
            ap, ad = d.get("axis_point"), d.get("axis_direction")
            return cls(
                planes=planes,
                rms_mm=_array(d["rms_mm"], "slit_planes.rms_mm", (k,)),
                counts=np.asarray(d["counts"], dtype=int).reshape(k),
                axis_point=None if ap is None else _array(ap, "axis_point", (3,)),
                axis_direction=None if ad is None else _array(ad, "axis_direction", (3,)),
                excluded=tuple((int(a), str(b)) for a, b in d.get("excluded", [])),
                from_axis=tuple(int(j) for j in d.get("from_axis", [])),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"malformed slit planes: {exc!r}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, s: str) -> SlitPlanes:
        return cls.from_dict(json.loads(s))


def _orthonormal_basis(u: F64) -> tuple[F64, F64]:
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def common_line(planes: ArrayLike) -> tuple[F64, F64]:
    """Least-squares common line of planes (K, 4) (unit normals): (point (3,) mm, direction (3,)).

    The direction minimises sum (n_k . u)^2; the point minimises sum (n_k . a + d_k)^2 and is
    the one closest to the origin.
    """
    pl = as_points(planes, 4, "planes")
    n = pl[:, :3]
    _, _, vt = np.linalg.svd(n, full_matrices=False)
    u = vt[-1]
    A = np.vstack([n, u[None, :]])
    b = np.concatenate([-pl[:, 3], [0.0]])
    a = np.linalg.lstsq(A, b, rcond=None)[0]
    return a, u


def _line_width(pts: F64) -> float:
    """RMS distance (mm) of points (N, 3) from their total-least-squares line."""
    sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return float(np.sqrt(np.sum(sv[1:] ** 2) / len(pts)))


def fit_slit_planes(
    points: ArrayLike,
    slits: ArrayLike,
    num_slits: int,
    common_axis: bool = True,
    min_width_mm: float = 0.0,
    weights: ArrayLike | None = None,
) -> SlitPlanes:
    """Fit one plane per slit, optionally all through one common line.

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame, points on the slits
    slits : (N,) int, slit number 0..num_slits-1 of each point
    num_slits : int
    common_axis : bool
        Constrain all planes to contain one line (the grating's axis through the projector's
        source): parameters are the axis (point + direction) and one angle per slit, fitted by
        non-linear least squares from independent total-least-squares planes.
    min_width_mm : float, mm
        A slit whose points spread less than this (RMS distance from their best line) across
        their line counts as seen along one line (e.g. on one flat face of the target), like a
        slit with exactly collinear points. One line does not determine a plane by itself.
    weights : (N,) float64 >= 0, optional
        Weight of each point in the least-squares fits (e.g. 1 / variance, mm^-2); default
        all 1. The reported ``rms_mm`` stays the plain (unweighted) RMS.

    Returns
    -------
    SlitPlanes
        Slits with fewer than 3 points get NaN and are listed in ``excluded`` with the reason.
        Slits seen along one line are left out of the axis fit. With ``common_axis`` they get
        the plane through the fitted axis and their points (the axis and a line off it span
        one plane, also when the line is parallel to the axis) and are listed in
        ``from_axis``; their ``rms_mm`` is the RMS distance of their points to that plane.
        They stay excluded (NaN, with the reason) when the axis is fitted from fewer than
        :data:`MIN_AXIS_SLITS` slits, when their points are too close to the axis (RMS
        distance below :data:`MIN_AXIS_LEVER` times the other slits' median) for the angle
        to be determined, or when the plane's angle about the axis is more than
        :data:`MAX_AXIS_ANGLE_DEVIATION` slit spacings from where the other slits' angles put
        that slit number (mislabelled points). Without ``common_axis`` they are excluded.

    Raises
    ------
    CalibrationError
        Bad input, no slit with a plane, or ``common_axis`` with fewer than 2 fitted slits.
    """
    X = as_points(points, 3, "points")
    s = _slit_indices(slits, num_slits)
    if len(s) != len(X):
        raise CalibrationError(f"points has {len(X)} rows but slits has {len(s)} values")
    _finite(X, "points")
    if not (math.isfinite(min_width_mm) and min_width_mm >= 0):
        raise CalibrationError(f"min_width_mm must be a finite value >= 0 mm, got {min_width_mm}")
    if weights is None:
        wt = np.ones(len(X))
    else:
        wt = np.asarray(weights, dtype=float).reshape(-1)
        if len(wt) != len(X) or not np.all(np.isfinite(wt)) or np.any(wt < 0):
            raise CalibrationError(
                f"weights must be {len(X)} finite values >= 0 (one per point), got {len(wt)} values"
            )
    k = int(num_slits)
    counts = np.bincount(s, minlength=k)
    planes = np.full((k, 4), np.nan)
    excluded: list[tuple[int, str]] = []
    line_why: dict[int, str] = {}  # slits seen along one line -> why they have no own plane
    order = np.argsort(s, kind="stable")
    starts = np.searchsorted(s[order], np.arange(k + 1))
    for j in range(k):  # one TLS fit per slit (vectorised over its points)
        if counts[j] == 0:
            continue
        if counts[j] < 3:
            excluded.append((j, f"only {counts[j]} point(s); a plane needs >= 3"))
            continue
        pts = X[order[starts[j] : starts[j + 1]]]
        try:
            planes[j] = _weighted_plane(pts, wt[order[starts[j] : starts[j + 1]]])
        except MultislitError:
            line_why[j] = "its points are collinear"
            continue
        if min_width_mm > 0:
            width = _line_width(pts)
            if width < min_width_mm:
                planes[j] = np.nan
                line_why[j] = (
                    f"its points lie along one line (spread {width:.2g} mm across it, "
                    f"< min_width_mm {min_width_mm:g})"
                )
    ok = np.all(np.isfinite(planes), axis=1)
    if not np.any(ok):
        raise CalibrationError(
            "no slit has >= 3 points off one line; read points along each slit on two faces"
        )
    # consistent normal orientation: agree with the middle valid slit
    ref = planes[np.flatnonzero(ok)[np.count_nonzero(ok) // 2], :3]
    flip = (planes[:, :3] @ ref) < 0
    planes[flip] *= -1
    axis_point = axis_dir = None
    from_axis: list[int] = []
    if common_axis:
        if np.count_nonzero(ok) < 2:
            raise CalibrationError(
                "common_axis=True needs >= 2 slits with planes to define the axis; "
                "read more slits or pass common_axis=False"
            )
        planes, axis_point, axis_dir = _fit_common_axis(X, s, planes, ok, wt)
        for j, why in _planes_from_axis(
            X, wt, order, starts, planes, ok, sorted(line_why), axis_point, axis_dir, ref
        ).items():
            if why:
                excluded.append((j, f"{line_why[j]}: no plane of its own, and {why}"))
            else:
                from_axis.append(j)
    else:
        excluded += [
            (j, f"{why}: no unique plane (common_axis=False)") for j, why in line_why.items()
        ]
    excluded.sort()
    ok = np.all(np.isfinite(planes), axis=1)
    valid_pt = ok[s]
    d = np.einsum("ij,ij->i", X[valid_pt], planes[s[valid_pt], :3]) + planes[s[valid_pt], 3]
    ssq = np.bincount(s[valid_pt], weights=d * d, minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms_mm = np.where(ok, np.sqrt(ssq / np.maximum(counts, 1)), np.nan)
    return SlitPlanes(
        planes, rms_mm, counts, axis_point, axis_dir, tuple(excluded), tuple(from_axis)
    )


#: Least number of slits with planes of their own for the common axis to give planes to slits
#: seen along one line.
MIN_AXIS_SLITS = 3
#: A slit seen along one line gets the plane through the axis only if its points are at least
#: this fraction of the other slits' median RMS distance from the axis.
MIN_AXIS_LEVER = 0.2
#: ... and only if that plane's angle about the axis is within this many local slit spacings of
#: where a smooth curve through the other slits' angles puts its slit number.
MAX_AXIS_ANGLE_DEVIATION = 0.25


def _planes_from_axis(
    X: F64,
    wt: F64,
    order: NDArray[np.intp],
    starts: NDArray[np.intp],
    planes: F64,
    ok: NDArray[np.bool_],
    lines: Sequence[int],
    axis_point: F64,
    axis_dir: F64,
    ref: F64,
) -> dict[int, str]:
    """Give slits seen along one line the plane through the common axis and their points.

    Fills ``planes[j]`` (in place) for each slit ``j`` of ``lines`` that is determined; returns
    slit -> "" for those, or slit -> why not.
    """
    out: dict[int, str] = {}
    if not lines:
        return out
    idx = np.flatnonzero(ok)
    if len(idx) < MIN_AXIS_SLITS:
        why = (
            f"the common axis is fitted from only {len(idx)} slit(s) (>= {MIN_AXIS_SLITS} "
            "with planes of their own give it the plane through the axis)"
        )
        return dict.fromkeys(lines, why)
    # angle of each plane about the axis, measured from the reference normal
    b1 = ref - (ref @ axis_dir) * axis_dir
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(axis_dir, b1)

    def cross_section(j: int) -> F64:
        q = X[order[starts[j] : starts[j + 1]]] - axis_point
        return np.stack([q @ b1, q @ b2], axis=1)  # (n, 2) mm, perpendicular to the axis

    phi = np.arctan2(planes[idx, :3] @ b2, planes[idx, :3] @ b1)
    lever = np.array([math.sqrt(np.mean(np.sum(cross_section(j) ** 2, axis=1))) for j in idx])
    ref_lever = float(np.median(lever))
    deg = min(3, len(idx) - 1)
    t = (idx - idx.mean()) / max(float(np.ptp(idx)), 1.0)
    coef = np.polyfit(t, phi, deg)
    for j in lines:
        c = cross_section(j)
        wj = wt[order[starts[j] : starts[j + 1]]]
        w, V = np.linalg.eigh((c * wj[:, None]).T @ c / max(float(wj.sum()), 1e-300))
        lev = math.sqrt(max(float(w[1]), 0.0))
        if lev < MIN_AXIS_LEVER * ref_lever:
            out[j] = (
                f"its points pass within {lev:.3g} mm (RMS) of the common axis (the other slits' "
                f"points: {ref_lever:.3g} mm): the plane through the axis is undetermined"
            )
            continue
        n2 = V[:, 0]
        n = n2[0] * b1 + n2[1] * b2
        if n @ ref < 0:
            n = -n
        phi_j = math.atan2(n @ b2, n @ b1)
        tj = (j - idx.mean()) / max(float(np.ptp(idx)), 1.0)
        pred = float(np.polyval(coef, tj))
        spacing = abs(float(np.polyval(np.polyder(coef), tj))) / max(float(np.ptp(idx)), 1.0)
        dev = abs(phi_j - pred) / max(spacing, 1e-12)
        if not dev <= MAX_AXIS_ANGLE_DEVIATION:
            out[j] = (
                f"the plane through the common axis and its points is {dev:.2g} slit spacings "
                f"from where the other slits' planes put slit {j} (mislabelled points?)"
            )
            continue
        planes[j, :3] = n
        planes[j, 3] = -(n @ axis_point)
        out[j] = ""
    return out


def _weighted_plane(pts: F64, w: F64) -> F64:
    """Weighted total-least-squares plane (4,) of points (N, 3); MultislitError if collinear."""
    if not np.any(w > 0):
        raise MultislitError("all weights are 0")
    c = (w[:, None] * pts).sum(axis=0) / w.sum()
    _, sv, vt = np.linalg.svd(np.sqrt(w)[:, None] * (pts - c), full_matrices=False)
    if sv[1] < 1e-9 * max(sv[0], 1e-300):
        raise MultislitError("the points are collinear, no unique plane")
    return np.append(vt[2], -vt[2] @ c)


def _fit_common_axis(X: F64, s: NDArray[np.intp], planes: F64, ok: NDArray[np.bool_], wt: F64):
    idx = np.flatnonzero(ok)
    a0, u0 = common_line(planes[idx])
    e1, e2 = _orthonormal_basis(u0)
    frame0 = np.stack([e1, e2, u0])  # rows
    phi0 = np.arctan2(planes[idx, :3] @ e2, planes[idx, :3] @ e1)
    pos = np.full(len(planes), -1)
    pos[idx] = np.arange(len(idx))
    use = ok[s]
    Xu, col, sw = X[use], pos[s[use]], np.sqrt(wt[use])
    scale = max(float(np.abs(Xu - a0).max()), 1.0)

    def unpack(q: F64):
        R = rotation_from_rvec(q[0] * e1 + q[1] * e2)
        f = frame0 @ R.T  # rotated basis vectors as rows
        a = a0 + scale * (q[2] * e1 + q[3] * e2)
        n = np.cos(q[4:, None]) * f[0] + np.sin(q[4:, None]) * f[1]
        return a, f[2], n

    def fun(q: F64) -> F64:
        a, _, n = unpack(q)
        return sw * np.einsum("ij,ij->i", Xu - a, n[col])

    m = len(idx)
    J = lil_matrix((len(Xu), 4 + m), dtype=int)
    J[:, :4] = 1
    J[np.arange(len(Xu)), 4 + col] = 1
    q0 = np.concatenate([np.zeros(4), phi0])
    sol = least_squares(fun, q0, jac_sparsity=J, method="trf", x_scale="jac", xtol=1e-12)
    a, u, n = unpack(sol.x)
    out = np.full_like(planes, np.nan)
    out[idx, :3] = n
    out[idx, 3] = -(n @ a)
    # closest point of the axis to the origin
    a = a - (a @ u) * u
    return out, a, u


def slit_plane_rms(planes: ArrayLike, points: ArrayLike, slits: ArrayLike) -> tuple[F64, F64]:
    """How well a set of slit planes explains points on the slits.

    Use it to measure a model's systematic error: with noise-free points on the true slit planes
    (e.g. a diffraction grating whose planes are not equally spaced in the projective sense),
    the per-slit RMS of the paper's 2x4 model (:meth:`ProjectorMatrix.planes`) is its systematic
    plane error, while per-slit planes (:func:`fit_slit_planes`) leave only the noise.

    Parameters
    ----------
    planes : (K, 4) float64, unit normals, n.X + d = 0
    points : (N, 3) float64, mm
    slits : (N,) int, 0..K-1

    Returns
    -------
    rms_mm : (K,) float64, mm, RMS distance of each slit's points to its plane (NaN: no points
        or no plane)
    distances : (N,) float64, mm, signed distance of each point to its slit's plane
    """
    pl = as_points(planes, 4, "planes")
    X = as_points(points, 3, "points")
    s = _slit_indices(slits, len(pl))
    if len(s) != len(X):
        raise CalibrationError(f"points has {len(X)} rows but slits has {len(s)} values")
    d = np.einsum("ij,ij->i", X, pl[s, :3]) + pl[s, 3]
    good = np.isfinite(d)
    cnt = np.bincount(s[good], minlength=len(pl))
    ssq = np.bincount(s[good], weights=d[good] ** 2, minlength=len(pl))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(cnt > 0, np.sqrt(ssq / np.maximum(cnt, 1)), np.nan)
    return r, d


# --------------------------------------------------------------------------- points on faces
def _polygon_contains(poly: F64, plane: F64, pts: F64) -> NDArray[np.bool_]:
    """Points (N, 3) on ``plane`` inside the convex polygon (V, 3) (boundary counts as inside)."""
    n = plane[:3]
    e1, e2 = _orthonormal_basis(n / np.linalg.norm(n))
    p2 = np.stack([poly @ e1, poly @ e2], axis=1)
    q2 = np.stack([pts @ e1, pts @ e2], axis=1)
    edge = np.roll(p2, -1, axis=0) - p2  # (V, 2)
    rel = q2[:, None, :] - p2[None, :, :]  # (N, V, 2)
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    tol = 1e-9 * max(float(np.abs(p2).max()), 1.0) ** 2
    return np.all(cross >= -tol, axis=1) | np.all(cross <= tol, axis=1)


def points_on_faces(
    camera: PinholeCamera | MatrixCamera, uv: ArrayLike, faces: Sequence[Face]
) -> tuple[F64, NDArray[np.intp]]:
    """Intersect lines of sight with the target's faces.

    Parameters
    ----------
    camera : a calibrated camera (its ``rays``)
    uv : (N, 2) float64, px
    faces : sequence of :class:`~multislit.capture.Face` (unit-normal plane, convex polygon)

    Returns
    -------
    xyz : (N, 3) float64, mm, target frame; NaN where the ray hits no face inside its polygon
    face_index : (N,) int, index into ``faces`` of the face hit (the nearest one), -1 where none
    """
    p = as_points(uv, 2, "uv")
    o, d = camera.rays(p)
    best_t = np.full(len(p), np.inf)
    xyz = np.full((len(p), 3), np.nan)
    face_index = np.full(len(p), -1, dtype=np.intp)
    for fi, f in enumerate(faces):  # faces are few; each is vectorised over all rays
        plane = np.asarray(f.plane, dtype=float)
        n = plane[:3] / np.linalg.norm(plane[:3])
        dd = plane[3] / np.linalg.norm(plane[:3])
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(o @ n + dd) / denom
        hit = np.isfinite(t) & (t > 0) & (np.abs(denom) > 1e-12)
        pts = o + np.where(hit, t, 0.0)[:, None] * d
        inside = hit & _polygon_contains(np.asarray(f.polygon, dtype=float), plane, pts)
        better = inside & (t < best_t)
        best_t[better] = t[better]
        xyz[better] = pts[better]
        face_index[better] = fi
    return xyz, face_index


# --------------------------------------------------------------------------- calibration model
@dataclass(frozen=True, eq=False)
class Calibration:
    """A complete rig calibration (``multislit-calibration/1``).

    Attributes
    ----------
    image_size : (W, H) int, px
    dlt : MatrixCamera, the paper's camera matrix C
    refined : PinholeCamera with distortion, or None
    projector : ProjectorMatrix (the paper's 2x4 model), or None
    slit_planes : SlitPlanes (our per-slit model), or None
    camera_rms_px : float, px, reprojection RMS of :attr:`camera` on the markers
    dlt_rms_px : float, px, reprojection RMS of the DLT on the markers
    marker_ids : tuple of str, (M,), markers used
    marker_residuals_px : (M,) float64, px, reprojection distance of :attr:`camera` per marker
    """

    image_size: tuple[int, int]
    dlt: MatrixCamera
    refined: PinholeCamera | None = None
    projector: ProjectorMatrix | None = None
    slit_planes: SlitPlanes | None = None
    camera_rms_px: float = float("nan")
    dlt_rms_px: float = float("nan")
    marker_ids: tuple[str, ...] = ()
    marker_residuals_px: F64 = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))
        object.__setattr__(self, "marker_ids", tuple(str(i) for i in self.marker_ids))
        r = np.asarray(self.marker_residuals_px, dtype=float).reshape(-1)
        if len(r) != len(self.marker_ids):
            raise CalibrationError(
                f"marker_residuals_px has {len(r)} values but marker_ids has {len(self.marker_ids)}"
            )
        object.__setattr__(self, "marker_residuals_px", r)

    @property
    def camera(self) -> PinholeCamera | MatrixCamera:
        """The refined camera if present, else the DLT camera."""
        return self.refined if self.refined is not None else self.dlt

    @property
    def slit_rms_mm(self) -> F64:
        """(K,) float64, mm, per-slit plane RMS (empty without slit planes)."""
        return np.zeros(0) if self.slit_planes is None else self.slit_planes.rms_mm

    def check_image_size(self, size: tuple[int, int]) -> None:
        """Raise :class:`CalibrationError` if ``size`` (W, H) differs from the calibration's."""
        w, h = int(size[0]), int(size[1])
        if (w, h) != self.image_size:
            raise CalibrationError(
                f"the images are {w}x{h} px but the calibration was made for "
                f"{self.image_size[0]}x{self.image_size[1]} px; recalibrate with this camera "
                "setting or use images of the calibrated size"
            )

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "units": {"length": "mm", "image": "px", "angle": "rad"},
            "image_size": list(self.image_size),
            "camera_dlt": self.dlt.to_dict(),
            "camera_refined": None if self.refined is None else self.refined.to_dict(),
            "projector_matrix": None if self.projector is None else self.projector.to_dict(),
            "slit_planes": None if self.slit_planes is None else self.slit_planes.to_dict(),
            "residuals": {
                "camera_rms_px": _nan_to_none(float(self.camera_rms_px)),
                "dlt_rms_px": _nan_to_none(float(self.dlt_rms_px)),
                "markers_px": {
                    i: _nan_to_none(float(r))
                    for i, r in zip(self.marker_ids, self.marker_residuals_px, strict=True)
                },
            },
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, allow_nan=False)

    @classmethod
    def from_dict(cls, d: Any) -> Calibration:
        if not isinstance(d, dict):
            raise CalibrationError("calibration JSON must be an object")
        schema = d.get("schema")
        if schema != SCHEMA:
            raise CalibrationError(
                f"calibration schema is {schema!r}; this version reads {SCHEMA!r} "
                "(recalibrate, or convert the file)"
            )
        try:
            dlt = camera_from_dict(d["camera_dlt"])
            if not isinstance(dlt, MatrixCamera):
                raise CalibrationError("camera_dlt must be a 'matrix' camera")
            ref = d.get("camera_refined")
            refined = None if ref is None else camera_from_dict(ref)
            if refined is not None and not isinstance(refined, PinholeCamera):
                raise CalibrationError("camera_refined must be a 'pinhole' camera")
            pm = d.get("projector_matrix")
            sp = d.get("slit_planes")
            res = d.get("residuals") or {}
            markers = res.get("markers_px") or {}

            def num(v: Any) -> float:
                return float("nan") if v is None else float(v)

            return cls(
                image_size=tuple(d["image_size"]),
                dlt=dlt,
                refined=refined,
                projector=None if pm is None else ProjectorMatrix.from_dict(pm),
                slit_planes=None if sp is None else SlitPlanes.from_dict(sp),
                camera_rms_px=num(res.get("camera_rms_px")),
                dlt_rms_px=num(res.get("dlt_rms_px")),
                marker_ids=tuple(markers),
                marker_residuals_px=np.array([num(v) for v in markers.values()]),
            )
        except MultislitError as exc:
            if isinstance(exc, CalibrationError):
                raise
            raise CalibrationError(f"malformed calibration: {exc}") from None
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise CalibrationError(f"malformed calibration: missing or bad {exc!r}") from None

    @classmethod
    def from_json(cls, s: str) -> Calibration:
        try:
            d = json.loads(s)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"calibration is not valid JSON: {exc}") from None
        return cls.from_dict(d)

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON (folders are created). Returns the path."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(self.to_json())
        return p

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration JSON file written by :meth:`save`."""
        p = Path(path)
        if not p.is_file():
            raise CalibrationError(
                f"calibration file not found: {p}; run the calibration first or fix the path"
            )
        try:
            return cls.from_json(p.read_text())
        except CalibrationError as exc:
            raise CalibrationError(f"{p}: {exc}") from None
