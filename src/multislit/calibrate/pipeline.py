"""Capture-level calibration: a capture folder in, a :class:`~multislit.calibration.Calibration` out.

The pipeline (paper section 5, Figs. 15, 17, 18):

1. **Camera** (:func:`calibrate_camera_from_capture`): the centre corners of the checker
   markers are found near their hints in ``calibration/markers.png`` (markers not found are
   reported by id and left out); >= 6 non-coplanar markers give the paper's DLT matrix C
   (eq. 1-2), refined to a pinhole camera with lens distortion. A marker whose reprojection
   residual is far above the others (a wrong corner or a mistyped ``xyz``) is dropped and
   reported.
2. **Points on the slits**, from one of two sources:

   - ``"hand"``: the paper's way, ``target.json`` ``slit_points`` (slit number and world xyz
     read off the target's scales);
   - ``"auto"``: from ``calibration/slits.png``. Stripe centres (:func:`multislit.slits.
     extract_slits`) are labelled with their slit numbers by a ``label_slits(image, capture)``
     callable (by default :func:`multislit.calibrate_labels.label_by_order`: the slits' order
     along each row on the target, anchored by the confident dot identifications of
     :mod:`multislit.identify`), the labelled centres are re-centred by
     :func:`multislit.slits.refine_centres` (Steger on a smoothed background, a line fitted
     along the stripe on each face; :data:`CALIBRATION_REFINE`), each centre's line
     of sight (refined camera, distortion removed) is intersected with the target face it
     falls on, and centres that are not trustworthy are dropped: outside every face, within
     ``edge_margin_px`` of a face's outline in the image (the stripe bends there), where the
     target's albedo changes under the stripe (the markers' squares shift the centre), and
     double detections in one row.

3. **Projector** (:func:`fit_projector`): one plane per slit through a common axis
   (:func:`~multislit.calibration.fit_slit_planes`), robustly: a RANSAC plane per slit
   first, then least squares with points further than ``outlier_sigma`` robust sigmas from
   their plane dropped and the planes refitted until nothing changes, so that mislabelled
   points cannot pull the planes. A slit seen on one target face only (its points along one
   line) is left out of the axis's fit and then gets the plane through the axis and its line,
   when its angle about the axis fits the other slits' (see
   :func:`~multislit.calibration.fit_slit_planes`). Slits with too few points are reported and
   get NaN planes; they are never guessed. The paper's 2x4 projector matrix (eq. 3-4) is fitted to the same
   points for comparison, and its per-slit RMS on them is its systematic error.

:func:`calibrate_capture` returns the :class:`Calibration`; :func:`run_calibration` returns it
with everything the report needs (:class:`CalibrationResult`), and
:func:`write_calibration` saves it with that report (the ``report`` key, which
:meth:`Calibration.load` ignores).

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter, maximum_filter, minimum_filter

from multislit.calibrate.models import (
    MIN_DLT_POINTS,
    Calibration,
    MarkerDetection,
    ProjectorMatrix,
    SlitPlanes,
    calibrate_dlt,
    find_marker_corners,
    fit_slit_planes,
    points_on_faces,
    refine_camera,
    rms,
    slit_plane_rms,
)
from multislit.errors import CalibrationError, CaptureError, MultislitError
from multislit.geometry.camera import F64, MatrixCamera, PinholeCamera
from multislit.io import Capture, Face

#: Extraction settings for the calibration image. The target's ramp shows the stripes slanted
#: by up to ~40 degrees; the default vertical opening (sized to remove dots) cuts such stripes
#: into two ridges either side of the true centre (1.5 px median error on the ramp of the
#: simulated target), a short opening keeps them whole (0.14 px). Dots left in the stripe image
#: make short segments (dropped) or outliers (rejected by the robust plane fit). Steger's
#: centres (zero of the derivative over the whole profile) are less shifted by laser speckle
#: than the default 3-point Gaussian fit at the peak: on the simulated full-size target the
#: per-slit residual falls from 0.093 to 0.067 mm (median) and the triangulation error of true
#: points from 0.041 to 0.031 mm RMS.
CALIBRATION_EXTRACT: dict[str, Any] = {"dot_size_px": 0.5, "method": "steger"}
#: Re-centring of the labelled calibration stripe points by :func:`multislit.slits.refine_centres`
#: (its keyword arguments; None keeps the extraction's centres). The fit along the stripe runs
#: within one target face (segments are cut where the stripe changes face), and the dot refill
#: uses the extraction's dot size (``dot_size_px`` of :data:`CALIBRATION_EXTRACT`: the stripe
#: width would cut the ramp's slanted stripes, per-slit residual 0.046 mm median but 0.13 max
#: and 0.039 mm triangulation error). Measured with ``benchmarks/bench_calibration.py``, full
#: size (seed 0): per-slit residual 0.067 -> 0.045 mm median (max 0.091 -> 0.054), true points
#: 0.031 -> 0.027 mm RMS (hand-read planes 0.022; seed 1: residual 0.064 -> 0.040, true points
#: 0.0375 -> 0.0373, hand 0.037: there the camera limits); half size (the tests' capture):
#: 0.15 -> 0.079 mm median (max 0.20 -> 0.11), true points 0.25 -> 0.16 mm RMS. Cutting the
#: segments at the faces' folds changes little (half size 0.165 -> 0.162 mm): the edge margin
#: already drops the centres near a fold.
CALIBRATION_REFINE: dict[str, Any] | None = {}
#: Centres closer than this to their face's outline in the image are dropped (px).
DEFAULT_EDGE_MARGIN_PX = 3.0
#: Centres where the target's albedo (markers image) varies by more than this fraction under
#: the stripe are dropped.
MAX_ALBEDO_VARIATION = 0.15
#: Points further than this many robust sigmas from their slit's plane are outliers.
DEFAULT_OUTLIER_SIGMA = 4.0
#: Least number of points for a slit's plane from automatic points (hand readings: 3).
MIN_AUTO_POINTS = 20
#: A marker whose refined residual exceeds max(this, 5 x the robust RMS) px is dropped.
MARKER_OUTLIER_PX = 1.0

LabelFn = Callable[[NDArray, Capture], Any]

_IDENTIFY_NAMES = ("label_slits", "label_points", "identify_slits", "identify_points", "identify")


# --------------------------------------------------------------------------- camera
class MarkerResiduals(NamedTuple):
    """Reprojection residuals of the markers used (px)."""

    ids: tuple[str, ...]
    dlt_px: F64
    refined_px: F64

    @property
    def dlt_rms_px(self) -> float:
        return rms(self.dlt_px)

    @property
    def refined_rms_px(self) -> float:
        return rms(self.refined_px)

    def worst(self, n: int = 3) -> list[tuple[str, float]]:
        """The ``n`` markers with the largest refined residual, worst first."""
        order = np.argsort(-self.refined_px)[:n]
        return [(self.ids[i], float(self.refined_px[i])) for i in order]


class CameraCalibration(NamedTuple):
    """Result of :func:`calibrate_camera_from_capture` (unpacks as a 4-tuple).

    Attributes
    ----------
    detection : MarkerDetection of all markers of target.json
    dlt : MatrixCamera, the paper's C from the markers used
    refined : PinholeCamera with distortion
    residuals : MarkerResiduals of the markers used
    """

    detection: MarkerDetection
    dlt: MatrixCamera
    refined: PinholeCamera
    residuals: MarkerResiduals

    @property
    def rejected(self) -> dict[str, str]:
        """Marker id -> reason for every marker of target.json that was not used."""
        used = set(self.residuals.ids)
        out = dict(self.detection.rejected)
        for i, ok in zip(self.detection.ids, self.detection.found, strict=True):
            if ok and i not in used:
                out[i] = "reprojection residual far above the others (wrong corner or xyz?)"
        return out


def _as_capture(capture: str | Path | Capture) -> Capture:
    return capture if isinstance(capture, Capture) else Capture.open(capture)


def _read(capture: Capture, path: Path, what: str) -> NDArray:
    if not path.is_file():
        raise CalibrationError(f"missing {what}: {path} (the capture folder must contain it)")
    return capture.image(path)


def _face_of(xyz: F64, faces: Sequence[Face], tol: float = 1.0) -> list[str]:
    out = []
    for p in xyz:
        ids = [f.id for f in faces if abs(np.dot(f.plane[:3], p) + f.plane[3]) < tol]
        out.append("/".join(ids) if ids else "-")
    return out


def _distortion_options(n: int) -> dict[str, bool]:
    """Distortion parameters the markers can carry: 2n equations, >= 4 to spare."""
    if 2 * n >= 14 + 4:
        return {"distortion": True, "tangential": True}
    if 2 * n >= 12 + 4:
        return {"distortion": True, "tangential": False}
    return {"distortion": False}


def calibrate_camera_from_capture(
    capture: str | Path | Capture, max_outliers: int = 3, use_stripes: bool = True
) -> CameraCalibration:
    """Camera calibration from ``calibration/markers.png`` and the markers of target.json.

    Parameters
    ----------
    capture : capture folder or opened :class:`Capture` (with target.json)
    max_outliers : int, at most this many found markers are dropped for large residuals
    use_stripes : bool
        Also make the stripes of ``calibration/slits.png`` and of the reference images straight
        (:func:`refine_camera_with_lines`): the markers alone leave the lens distortion poorly
        determined away from them.

    Returns
    -------
    CameraCalibration (detection, dlt, refined, residuals)

    Raises
    ------
    CalibrationError
        Missing image, fewer than 6 markers found, found markers all on one plane, failed fit.
        The message says how many markers were found and which were rejected and why.
    """
    cap = _as_capture(capture)
    if cap.target is None:
        raise CalibrationError(f"{cap.root}: calibration needs target.json (markers and faces)")
    t = cap.target
    img = _read(cap, cap.markers_image, "marker image")
    ids = [m.id for m in t.markers]
    det = find_marker_corners(img, t.marker_hints, ids)
    n_found = int(det.found.sum())

    def rejected_text() -> str:
        rej = det.rejected
        if not rej:
            return ""
        return "; rejected: " + ", ".join(f"{i} ({r})" for i, r in rej.items())

    if n_found < MIN_DLT_POINTS:
        raise CalibrationError(
            f"found {n_found} of {len(ids)} markers in {cap.markers_image}; the camera "
            f"calibration needs >= {MIN_DLT_POINTS} on at least two non-parallel faces"
            f"{rejected_text()}"
        )
    X = t.marker_xyz[det.found]
    x = det.uv[det.found]
    used = [i for i, f in zip(ids, det.found, strict=True) if f]
    c = X - X.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[2] < 1e-3 * s[0]:
        faces = sorted(set(_face_of(X, t.faces)))
        raise CalibrationError(
            f"the {n_found} markers found ({', '.join(used)}) all lie on one plane "
            f"(face {', '.join(faces)}); the DLT needs markers on at least two non-parallel "
            f"faces{rejected_text()}"
        )
    keep = np.ones(len(X), bool)
    for _ in range(max_outliers + 1):
        dlt, _ = calibrate_dlt(X[keep], x[keep], cap.image_size)
        refined, res = refine_camera(X[keep], x[keep], dlt, **_distortion_options(int(keep.sum())))
        limit = max(MARKER_OUTLIER_PX, 5.0 * 1.4826 * float(np.median(res)))
        worst = int(np.argmax(res))
        if res[worst] <= limit or keep.sum() <= MIN_DLT_POINTS or (~keep).sum() >= max_outliers:
            break
        keep[np.flatnonzero(keep)[worst]] = False
    dlt, dres = calibrate_dlt(X[keep], x[keep], cap.image_size)
    refined, rres = refine_camera(X[keep], x[keep], dlt, **_distortion_options(int(keep.sum())))
    if use_stripes:
        lines = stripe_lines(cap, refined)
        if len(lines) >= 3:
            start, _ = refine_camera(X[keep], x[keep], dlt, distortion=False)
            refined, rres, _ = refine_camera_with_lines(X[keep], x[keep], start, lines)
    ids_used = tuple(i for i, k in zip(used, keep, strict=True) if k)
    return CameraCalibration(det, dlt, refined, MarkerResiduals(ids_used, dres, rres))


# --------------------------------------------------------------------------- camera: straight stripes
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
    initial : starting camera (e.g. from :func:`~multislit.calibration.refine_camera`)
    lines : sequence of (N_i, 2) px arrays, each the image points of one straight 3D line
    outlier_sigma : line points further than this many robust sigmas are dropped once

    Returns
    -------
    camera : PinholeCamera
    marker_residuals : (M,) px
    line_residuals : (sum N_i,) px, distances to the fitted lines (NaN for dropped points)
    """
    from scipy.optimize import least_squares

    from multislit.calibrate.models import _project_params
    from multislit.geometry.camera import _undistort

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


def _straight_runs(
    u: F64, v: F64, key: NDArray[np.intp], min_points: int = 20, max_points: int = 80
) -> list[F64]:
    """Group points by ``key`` (>= 0) into (N, 2) arrays, each evenly thinned to max_points."""
    out = []
    for kk in np.unique(key[key >= 0]):
        idx = np.flatnonzero(key == kk)
        if len(idx) < min_points or np.ptp(v[idx]) < 2 * min_points:
            continue
        idx = idx[np.linspace(0, len(idx) - 1, min(max_points, len(idx))).round().astype(int)]
        out.append(np.stack([u[idx], v[idx]], axis=1))
    return out


def stripe_lines(
    capture: Capture, camera: PinholeCamera | MatrixCamera, edge_margin_px: float = 8.0
) -> list[F64]:
    """Image runs of stripe centres that are straight lines in space (see
    :func:`refine_camera_with_lines`): stripe segments on each target face in
    ``calibration/slits.png`` (away from the face outlines, albedo edges and double detections)
    and stripe segments on the reference boards. No slit identification is needed."""
    from multislit.stripes import extract_slits

    lines: list[F64] = []
    if capture.slits_image.is_file() and capture.target is not None and capture.target.faces:
        faces = capture.target.faces
        img = capture.image(capture.slits_image)
        ex = extract_slits(img, **CALIBRATION_EXTRACT)
        sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
        uv = np.stack([ex.u, ex.v], axis=1)
        keep = ex.segment >= 0
        face = np.full(len(uv), -1, np.intp)
        if np.any(keep):
            _, face[keep] = points_on_faces(camera, uv[keep], faces)
        keep &= face >= 0
        keep &= _edge_distance(camera, uv, face, faces) > edge_margin_px
        keep &= _row_gap(ex.u, ex.v) > 2.0 * sw
        if capture.markers_image.is_file():
            var = _albedo_variation(
                capture.image(capture.markers_image), ex.u, ex.v, int(math.ceil(1.5 * sw))
            )
            keep &= var <= MAX_ALBEDO_VARIATION
        key = np.where(keep, ex.segment * (len(faces) + 1) + face, -1)
        lines += _straight_runs(ex.u, ex.v, key)
    for path in capture.references:
        ex = extract_slits(capture.image(path))
        lines += _straight_runs(ex.u, ex.v, ex.segment)
    return lines


# --------------------------------------------------------------------------- slit points
@dataclass(frozen=True, eq=False)
class SlitPointSet:
    """Points on the slits for the projector calibration.

    Attributes
    ----------
    xyz : (N, 3) float64, mm, target frame
    slit : (N,) int, slit number 0..num_slits-1
    uv : (N, 2) float64, px, where the point is seen
    face : (N,) int, index of the target face (-1: unknown, e.g. hand readings)
    source : "hand" or "auto"
    steps : ordered (step, points left) of the automatic filtering, for the report
    """

    xyz: F64
    slit: NDArray[np.intp]
    uv: F64
    face: NDArray[np.intp]
    source: str
    steps: tuple[tuple[str, int], ...] = ()

    def __len__(self) -> int:
        return len(self.xyz)


def hand_slit_points(capture: str | Path | Capture) -> SlitPointSet:
    """The hand readings of target.json (``slit_points``), the paper's projector data."""
    cap = _as_capture(capture)
    sp = () if cap.target is None else cap.target.slit_points
    if not sp:
        raise CalibrationError(
            f"{cap.root / 'target.json'} has no slit_points (hand readings); add readings of "
            "points on the slits or use the automatic source"
        )
    xyz = np.array([p.xyz for p in sp], dtype=float)
    slit = np.array([p.slit for p in sp], dtype=np.intp)
    uv = np.array([p.uv for p in sp], dtype=float)
    return SlitPointSet(xyz, slit, uv, np.full(len(sp), -1, np.intp), "hand", (("read", len(sp)),))


def _find_identifier() -> LabelFn | None:
    """The default ``label_slits(image, capture)``: :func:`label_by_order`."""
    from multislit.calibrate.slit_labels import label_by_order

    return label_by_order


def _labelled_points(result: Any, image: NDArray) -> tuple[F64, F64, NDArray[np.intp]]:
    """Normalise a labeller's answer to (u, v, slit) of the points it labelled.

    Accepted: an object with ``u``, ``v`` and ``slit`` (or ``labels``) arrays, a tuple
    ``(uv (K, 2), slit (K,))``, or a bare (K,) array for the points of
    ``extract_slits(image)`` with default settings.
    """
    from multislit.stripes import extract_slits

    slit = None
    if isinstance(result, tuple) and len(result) == 2:
        uv = np.asarray(result[0], dtype=float).reshape(-1, 2)
        u, v, slit = uv[:, 0], uv[:, 1], np.asarray(result[1])
    elif hasattr(result, "u") and hasattr(result, "v"):
        u, v = np.asarray(result.u, float), np.asarray(result.v, float)
        for key in ("slit", "labels", "slits"):
            if hasattr(result, key):
                slit = np.asarray(getattr(result, key))
                break
        if slit is None:
            raise CalibrationError("the slit labelling returned points without slit numbers")
    else:
        slit = np.asarray(result)
        ex = extract_slits(image)
        u, v = ex.u, ex.v
        if slit.shape != u.shape:
            raise CalibrationError(
                f"the slit labelling returned {slit.shape} labels but extract_slits finds "
                f"{len(u)} centre points in the image; return one label per point (or the "
                "points with their labels)"
            )
    slit = np.asarray(slit).reshape(-1)
    if len(slit) != len(u) or len(v) != len(u):
        raise CalibrationError("the slit labelling returned arrays of different lengths")
    if slit.size and not np.issubdtype(slit.dtype, np.integer):
        raise CalibrationError(f"slit labels must be integers (-1 = unknown), got {slit.dtype}")
    return u, v, slit.astype(np.intp)


def transfer_labels(
    u_from: ArrayLike,
    v_from: ArrayLike,
    slit_from: ArrayLike,
    u: ArrayLike,
    v: ArrayLike,
    tol_px: float = 2.5,
) -> NDArray[np.intp]:
    """Label points (u, v) with the slit of the nearest labelled point in the same row.

    Points without a labelled point within ``tol_px`` in their row, or whose two nearest
    labelled neighbours in the row (within ``tol_px``) disagree, get -1.
    """
    uf, vf = np.asarray(u_from, float), np.round(np.asarray(v_from, float))
    sf = np.asarray(slit_from).astype(np.intp)
    good = (sf >= 0) & np.isfinite(uf) & np.isfinite(vf)
    uf, vf, sf = uf[good], vf[good], sf[good]
    uq, vq = np.asarray(u, float), np.round(np.asarray(v, float))
    out = np.full(len(uq), -1, np.intp)
    if not len(uf) or not len(uq):
        return out
    span = float(max(np.nanmax(np.abs(uf)), np.nanmax(np.abs(uq)))) * 4 + 10.0
    kf = vf * span + uf
    order = np.argsort(kf)
    kf, sf_s = kf[order], sf[order]
    kq = vq * span + uq
    j = np.searchsorted(kf, kq)
    lo = np.clip(j - 1, 0, len(kf) - 1)
    hi = np.clip(j, 0, len(kf) - 1)
    dlo, dhi = np.abs(kq - kf[lo]), np.abs(kq - kf[hi])
    best = np.where(dlo <= dhi, lo, hi)
    other = np.where(dlo <= dhi, hi, lo)
    dbest = np.minimum(dlo, dhi)
    dother = np.maximum(dlo, dhi)
    ok = dbest <= tol_px
    conflict = (dother <= tol_px) & (sf_s[other] != sf_s[best])
    out[ok & ~conflict] = sf_s[best][ok & ~conflict]
    return out


def _edge_distance(camera: PinholeCamera | MatrixCamera, uv: F64, face: NDArray, faces) -> F64:
    """Distance (px, distortion removed) of each point to the outline of its face."""
    if isinstance(camera, PinholeCamera):
        pin = PinholeCamera(
            camera.fx, camera.fy, camera.cx, camera.cy, camera.rvec, camera.tvec,
            image_size=camera.image_size,
        )  # fmt: skip
        und = camera.undistort_pixels(uv)
    else:
        pin, und = camera, uv
    out = np.full(len(uv), np.inf)
    for fi, f in enumerate(faces):
        sel = face == fi
        if not np.any(sel):
            continue
        V = pin.project(np.asarray(f.polygon, dtype=float))
        p = und[sel]
        best = np.full(len(p), np.inf)
        for a, b in zip(V, np.roll(V, -1, axis=0), strict=True):
            ab = b - a
            t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
        out[sel] = best
    return out


def _albedo_variation(markers_img: NDArray, u: F64, v: F64, half_width: int) -> F64:
    """Relative albedo variation (max - min) / max in a window around each point."""
    a = gaussian_filter(markers_img.astype(np.float32), 1.0)
    size = (7, 2 * half_width + 1)
    mx = maximum_filter(a, size=size)
    mn = minimum_filter(a, size=size)
    var = (mx - mn) / np.maximum(mx, 1e-6)
    h, w = a.shape
    iu = np.clip(np.round(u).astype(int), 0, w - 1)
    iv = np.clip(np.round(v).astype(int), 0, h - 1)
    return var[iv, iu]


def _row_gap(u: F64, v: F64) -> F64:
    """Distance (px) to the nearest other centre in the same row."""
    order = np.lexsort((u, v))
    uu, vv = u[order], v[order]
    gap = np.full(len(uu), np.inf)
    if len(uu) > 1:
        dg = np.where(vv[1:] == vv[:-1], uu[1:] - uu[:-1], np.inf)
        gap[:-1] = np.minimum(gap[:-1], dg)
        gap[1:] = np.minimum(gap[1:], dg)
    out = np.empty_like(gap)
    out[order] = gap
    return out


_DEFAULT = object()


def _refined_u(
    img: NDArray, ex: Any, face: NDArray[np.intp], n_faces: int, opts: dict[str, Any]
) -> F64:
    """Columns (K,) px of the extraction's centres after :func:`~multislit.slits.refine_centres`.

    Each linked segment is cut into its pieces on one face (``face`` (K,), -1: left as is), so
    the fit along the stripe never spans the fold between two faces.
    """
    from multislit.stripes import refine_centres

    seg = np.asarray(ex.segment, np.int64)
    piece = np.where((seg >= 0) & (face >= 0), seg * max(n_faces, 1) + face, -1)
    sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
    kw = dict(opts)
    if math.isfinite(ex.dot_size_px):
        kw.setdefault("dot_size_px", ex.dot_size_px)
    u, _ = refine_centres(img, ex.u, ex.v, piece, sw, **kw)
    return u


def auto_slit_points(
    capture: str | Path | Capture,
    camera: PinholeCamera | MatrixCamera,
    label_slits: LabelFn,
    edge_margin_px: float = DEFAULT_EDGE_MARGIN_PX,
    extract: dict[str, Any] | None = None,
    refine: dict[str, Any] | None | object = _DEFAULT,
) -> SlitPointSet:
    """Points on the slits from ``calibration/slits.png``, labelled by ``label_slits``.

    Parameters
    ----------
    capture : capture folder or Capture (with target.json faces)
    camera : the calibrated camera (distortion is removed through its rays)
    label_slits : ``label_slits(image, capture)`` -> slit numbers, see :func:`_labelled_points`
    edge_margin_px : px, centres nearer to their face's outline in the image are dropped
    extract : keyword arguments of :func:`multislit.slits.extract_slits`
        (default :data:`CALIBRATION_EXTRACT`)
    refine : keyword arguments of :func:`multislit.slits.refine_centres` for the labelled
        centres on the target's faces (default :data:`CALIBRATION_REFINE`); None keeps the
        extraction's centres. The labels are transferred before, from the extraction's centres.

    Returns
    -------
    SlitPointSet with ``source="auto"`` and the count after each filtering step
    """
    from multislit.stripes import extract_slits

    cap = _as_capture(capture)
    if cap.target is None or not cap.target.faces:
        raise CalibrationError(
            f"{cap.root / 'target.json'} lists no faces; automatic projector calibration needs "
            "the target's faces (or use the hand readings)"
        )
    faces = cap.target.faces
    img = _read(cap, cap.slits_image, "slit image")
    ex = extract_slits(img, **(CALIBRATION_EXTRACT if extract is None else extract))
    steps: list[tuple[str, int]] = [("stripe centres", len(ex.u))]
    keep = ex.segment >= 0
    steps.append(("in linked segments", int(keep.sum())))
    uf, vf, sf = _labelled_points(label_slits(img, cap), img)
    sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
    slit = transfer_labels(uf, vf, sf, ex.u, ex.v, tol_px=max(1.0, 0.8 * sw))
    bad = (slit >= cap.num_slits) | (slit < -1)
    if np.any(bad):
        raise CalibrationError(
            f"the slit labelling returned slit numbers outside 0..{cap.num_slits - 1} "
            f"(e.g. {int(slit[bad][0])})"
        )
    keep &= slit >= 0
    steps.append(("labelled", int(keep.sum())))
    uv = np.stack([ex.u, ex.v], axis=1)
    xyz = np.full((len(uv), 3), np.nan)
    face = np.full(len(uv), -1, np.intp)
    if np.any(keep):
        xyz[keep], face[keep] = points_on_faces(camera, uv[keep], faces)
    opts = CALIBRATION_REFINE if refine is _DEFAULT else refine
    if opts is not None and np.any(keep):
        uv[:, 0] = _refined_u(img, ex, np.where(keep, face, -1), len(faces), opts)
        xyz[keep], face[keep] = points_on_faces(camera, uv[keep], faces)
    keep &= face >= 0
    steps.append(("on a target face", int(keep.sum())))
    keep &= _edge_distance(camera, uv, face, faces) > edge_margin_px
    steps.append((f"> {edge_margin_px:g} px from the face outline", int(keep.sum())))
    keep &= _row_gap(uv[:, 0], ex.v) > 2.0 * sw
    steps.append(("single detection in the row", int(keep.sum())))
    if cap.markers_image.is_file():
        mimg = cap.image(cap.markers_image)
        var = _albedo_variation(mimg, uv[:, 0], ex.v, int(math.ceil(1.5 * sw)))
        keep &= var <= MAX_ALBEDO_VARIATION
        steps.append(("uniform albedo under the stripe", int(keep.sum())))
    return SlitPointSet(xyz[keep], slit[keep], uv[keep], face[keep], "auto", tuple(steps))


# --------------------------------------------------------------------------- projector
@dataclass(frozen=True, eq=False)
class ProjectorFit:
    """Result of :func:`fit_projector`.

    Attributes
    ----------
    slit_planes : SlitPlanes (common axis), NaN rows for slits left out
    projector : ProjectorMatrix, the paper's 2x4 model on the same points (None if not fitted)
    projector_rms_mm : (K,) float64, mm, per-slit RMS of the 2x4 model's planes on the points
    inlier : (N,) bool, points used in the final fit
    dropped : (K,) int, outliers dropped per slit
    excluded : tuple of (slit, reason), slits without a plane
    """

    slit_planes: SlitPlanes
    projector: ProjectorMatrix | None
    projector_rms_mm: F64
    inlier: NDArray[np.bool_]
    dropped: NDArray[np.int_]
    excluded: tuple[tuple[int, str], ...] = field(default=())


def _ransac_plane(
    X: F64, face: NDArray[np.intp], tol: float, rng: np.random.Generator, trials: int = 300
) -> NDArray[np.bool_] | None:
    """Inliers of the plane (through 3 of the points) that has the most within ``tol`` mm.

    When the points lie on several faces, only planes with inliers on >= 2 faces count: a
    face's own plane holds every point on that face, whichever slit it belongs to.
    """
    n = len(X)
    if n < 3:
        return None
    spread = float(np.linalg.norm(X - X.mean(axis=0), axis=1).max())
    idx = rng.integers(0, n, size=(trials, 3))
    a, b, c = X[idx[:, 0]], X[idx[:, 1]], X[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-3 * spread * spread
    if not np.any(ok):
        return None
    nrm = nrm[ok] / ln[ok, None]
    d = -np.einsum("ij,ij->i", nrm, a[ok])
    inl = np.abs(X @ nrm.T + d) <= tol  # (N, T)
    counts = inl.sum(axis=0)
    faces = np.unique(face[face >= 0])
    if len(faces) >= 2:
        per_face = np.stack([inl[face == f].sum(axis=0) for f in faces])  # (F, T)
        need = max(3, int(0.05 * n))
        counts = np.where((per_face >= need).sum(axis=0) >= 2, counts, -1)
    best = int(np.argmax(counts))
    if counts[best] < 3:
        return None
    return inl[:, best]


def _ransac_line(
    X: F64, tol: float, rng: np.random.Generator, trials: int = 300
) -> NDArray[np.bool_] | None:
    """Inliers of the line (through 2 of the points) that has the most points within ``tol`` mm."""
    n = len(X)
    if n < 3:
        return None
    idx = rng.integers(0, n, size=(trials, 2))
    a, b = X[idx[:, 0]], X[idx[:, 1]]
    d = b - a
    ln = np.linalg.norm(d, axis=1)
    spread = float(np.linalg.norm(X - X.mean(axis=0), axis=1).max())
    ok = ln > 0.1 * spread
    if not np.any(ok):
        return None
    a, d = a[ok], d[ok] / ln[ok, None]
    rel = X[:, None, :] - a[None, :, :]  # (N, T, 3)
    along = np.einsum("ntk,tk->nt", rel, d)
    dist2 = np.einsum("ntk,ntk->nt", rel, rel) - along * along
    inl = dist2 <= tol * tol
    best = int(np.argmax(inl.sum(axis=0)))
    return inl[:, best] if inl[:, best].sum() >= 3 else None


def fit_projector(
    points: SlitPointSet,
    num_slits: int,
    outlier_sigma: float = DEFAULT_OUTLIER_SIGMA,
    min_points: int | None = None,
    coarse_tol_mm: float = 1.0,
    min_sigma_mm: float = 0.002,
    max_iterations: int = 8,
    min_width_mm: float = 0.5,
) -> ProjectorFit:
    """Slit planes (common axis) and the paper's 2x4 matrix from points on the slits, robustly.

    Parameters
    ----------
    points : SlitPointSet
    num_slits : int
    outlier_sigma : points further than this many robust sigmas (1.4826 MAD of the slit's
        distances, at least ``min_sigma_mm``) from their plane are dropped
    min_points : least points for a slit's plane (default 3 for hand readings, else
        :data:`MIN_AUTO_POINTS`)
    coarse_tol_mm : inlier band of the first, RANSAC, plane (or line) of each slit (mm); must
        be well below the slit spacing on the target
    min_width_mm : a slit whose points spread less than this (RMS, mm) across their best line,
        or whose points lie on one target face (a few stray points on other faces are
        dropped), is seen along one line: it is left out of the common axis's fit and gets the
        plane through the axis and its line (:func:`~multislit.calibration.fit_slit_planes`)

    Returns
    -------
    ProjectorFit
    """
    X = np.asarray(points.xyz, dtype=float)
    s = np.asarray(points.slit, dtype=np.intp)
    k = int(num_slits)
    if min_points is None:
        min_points = 3 if points.source == "hand" else MIN_AUTO_POINTS
    n = len(X)
    if n == 0:
        raise CalibrationError("no points on the slits to calibrate the projector from")
    rng = np.random.default_rng(0)
    use = np.ones(n, bool)
    counts0 = np.bincount(s, minlength=k)
    fc = np.asarray(points.face)
    excluded: list[tuple[int, str]] = []
    one_face = np.zeros(k, bool)
    for j in range(k):
        if counts0[j] == 0:
            excluded.append((j, "no points"))
            continue
        if counts0[j] < min_points:
            excluded.append((j, f"only {counts0[j]} point(s), need >= {min_points}"))
            use[s == j] = False
            continue
        sel = np.flatnonzero(s == j)
        if np.any(fc[sel] >= 0):  # a plane needs points off one line, e.g. on two faces
            nf = np.bincount(fc[sel][fc[sel] >= 0])
            big = nf >= max(5, 0.02 * len(sel))
            if np.count_nonzero(big) < 2:
                one_face[j] = True
                main_face = int(np.argmax(nf))
                use[sel[fc[sel] != main_face]] = False  # stray points elsewhere
                sel = sel[fc[sel] == main_face]
        if points.source != "hand":
            if one_face[j]:
                inl = _ransac_line(X[sel], coarse_tol_mm, rng)
            else:
                inl = _ransac_plane(X[sel], fc[sel], coarse_tol_mm, rng)
            if inl is not None:
                use[sel[~inl]] = False
    own = np.zeros(k, bool)  # slits whose points determine a plane by themselves
    for j in range(k):
        m = use & (s == j)
        if m.sum() >= 3 and not one_face[j]:
            sv = np.linalg.svd(X[m] - X[m].mean(axis=0), compute_uv=False)
            own[j] = sv[1] / math.sqrt(m.sum()) >= min_width_mm
    n_ok = int(own.sum())
    if n_ok < 2 and np.any(use):
        lines = sorted(set(np.unique(s[use]).tolist()) - set(np.flatnonzero(own).tolist()))
        raise CalibrationError(
            f"only {n_ok} of {k} slits have points that determine a plane by themselves "
            "(>= 2 are needed for the common axis; "
            + (f"slits {lines}: points along one line, e.g. on one target face; " if lines else "")
            + "; ".join(f"slit {j}: {r}" for j, r in excluded[:5])
            + "); the slits must be seen on two target faces"
            + ("; try the hand readings (--source hand)" if points.source != "hand" else "")
        )
    if not np.any(use):
        raise CalibrationError(
            f"no slit has >= {min_points} points on the target; "
            + "; ".join(f"slit {j}: {r}" for j, r in excluded[:5])
        )
    sp = None
    for _ in range(max_iterations):
        sp = fit_slit_planes(X[use], s[use], k, common_axis=True, min_width_mm=min_width_mm)
        pl = sp.planes
        d = np.einsum("ij,ij->i", X, pl[s, :3]) + pl[s, 3]
        ad = np.abs(d)
        sig = np.full(k, np.nan)
        for j in np.flatnonzero(sp.valid):
            m = use & (s == j)
            if m.any():
                sig[j] = max(1.4826 * float(np.median(ad[m])), min_sigma_mm)
        glob = float(np.nanmedian(sig)) if np.any(np.isfinite(sig)) else min_sigma_mm
        sig = np.where(np.isfinite(sig), sig, glob)
        new = use & np.isfinite(ad) & (ad <= outlier_sigma * sig[s])
        if np.array_equal(new, use):
            break
        # never let the clipping drop a slit below min_points: keep its previous points then
        cnt = np.bincount(s[new], minlength=k)
        for j in np.flatnonzero((cnt < min_points) & (np.bincount(s[use], minlength=k) > 0)):
            new[use & (s == j)] = True
        if np.array_equal(new, use):
            break
        use = new
    assert sp is not None
    excluded += [e for e in sp.excluded if e[0] not in {x[0] for x in excluded}]
    dropped = np.bincount(s[~use], minlength=k) - np.bincount(
        s[~use & np.isin(s, [e[0] for e in excluded])], minlength=k
    )
    proj = None
    proj_rms = np.full(k, np.nan)
    fit_slits = sp.valid[s] & use
    try:
        proj, _ = ProjectorMatrix.fit(X[fit_slits], s[fit_slits], k)
        proj_rms, _ = slit_plane_rms(proj.planes(), X[fit_slits], s[fit_slits])
    except MultislitError:
        proj = None
    return ProjectorFit(sp, proj, proj_rms, use, dropped, tuple(sorted(excluded)))


# --------------------------------------------------------------------------- whole capture
@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything :func:`run_calibration` found: the calibration and its report data."""

    calibration: Calibration
    camera: CameraCalibration
    points: SlitPointSet
    projector: ProjectorFit
    source: str
    notes: tuple[str, ...] = ()

    def report(self) -> dict[str, Any]:
        """Figures for people (and the ``report`` key of the written file)."""
        res = self.camera.residuals
        sp = self.projector.slit_planes
        valid = sp.valid
        rms_mm = sp.rms_mm
        worst_slits = [
            (int(j), float(rms_mm[j])) for j in np.argsort(-np.nan_to_num(rms_mm, nan=-1))[:3]
        ]
        return {
            "source": self.source,
            "notes": list(self.notes),
            "markers": {
                "total": len(self.camera.detection.ids),
                "used": list(res.ids),
                "rejected": self.camera.rejected,
                "worst_px": res.worst(3),
            },
            "camera": {
                "dlt_rms_px": res.dlt_rms_px,
                "refined_rms_px": res.refined_rms_px,
                "distortion": list(self.camera.refined.dist),
            },
            "points": {"count": len(self.points), "steps": [list(x) for x in self.points.steps]},
            "slit_planes": {
                "fitted": int(valid.sum()),
                "num_slits": int(sp.num_slits),
                "median_rms_mm": float(np.nanmedian(rms_mm)) if valid.any() else float("nan"),
                "worst_rms_mm": worst_slits,
                "excluded": [[int(j), r] for j, r in self.projector.excluded],
                "from_axis": [int(j) for j in sp.from_axis],
                "outliers_dropped": int(self.projector.dropped.sum()),
            },
            "projector_matrix": {
                "median_rms_mm": float(np.nanmedian(self.projector.projector_rms_mm))
                if np.any(np.isfinite(self.projector.projector_rms_mm))
                else float("nan"),
                "rms_mm": self.projector.projector_rms_mm.tolist(),
            },
        }


def _nan_none(x: Any) -> Any:
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _nan_none(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_nan_none(v) for v in x]
    return x


def auto_fit_problem(fit: ProjectorFit, points: SlitPointSet, num_slits: int) -> str | None:
    """Why slit planes from automatic points cannot be trusted, or None when they can.

    Automatic points are noisy measurements labelled by identification; planes are trusted only
    when most slits get one, each from enough inliers that leave a real (non-zero) residual.
    A plane that fits its points exactly was fitted to too few points to check itself.
    """
    sp = fit.slit_planes
    s = np.asarray(points.slit, dtype=np.intp)
    inliers = np.bincount(s[fit.inlier], minlength=num_slits)
    ok = sp.valid & (inliers >= MIN_AUTO_POINTS) & (np.nan_to_num(sp.rms_mm) > 1e-6)
    need = max(3, math.ceil(0.5 * num_slits))
    if ok.sum() < need:
        return (
            f"only {int(ok.sum())} of {num_slits} slits got a well-supported plane from the "
            f"automatically identified stripes (need >= {need})"
        )
    return None


def run_calibration(
    capture: str | Path | Capture,
    source: str = "auto",
    label_slits: LabelFn | None = None,
    edge_margin_px: float = DEFAULT_EDGE_MARGIN_PX,
    outlier_sigma: float = DEFAULT_OUTLIER_SIGMA,
) -> CalibrationResult:
    """Calibrate camera and projector from a capture folder; see the module docstring.

    Parameters
    ----------
    capture : capture folder or Capture
    source : "auto" (points from calibration/slits.png) or "hand" (target.json slit_points).
        With "auto", no ``label_slits`` and no :mod:`multislit.identify`, the hand readings
        are used if there are any (the result's ``source`` and ``notes`` say so).
    label_slits : ``label_slits(image, capture)`` giving slit numbers of stripe centres
        (default: :mod:`multislit.identify`)
    edge_margin_px, outlier_sigma : see :func:`auto_slit_points`, :func:`fit_projector`
    """
    if source not in ("auto", "hand"):
        raise CalibrationError(f"source must be 'auto' or 'hand', got {source!r}")
    cap = _as_capture(capture)
    cam = calibrate_camera_from_capture(cap)
    notes: list[str] = []
    used_source = source
    if source == "auto":
        fn = label_slits if label_slits is not None else _find_identifier()
        if fn is None:
            if cap.target is not None and cap.target.slit_points:
                used_source = "hand"
                notes.append(
                    "automatic slit labelling is not available (no multislit.identify); "
                    "used the hand readings of target.json"
                )
            else:
                raise CalibrationError(
                    "automatic slit labelling is not available (no multislit.identify) and "
                    "target.json has no slit_points; add hand readings of points on the slits "
                    "and use --source hand"
                )
        else:
            pts = auto_slit_points(cap, cam.refined, fn, edge_margin_px)
    if used_source == "hand":
        pts = hand_slit_points(cap)
    try:
        fit = fit_projector(pts, cap.num_slits, outlier_sigma)
        problem = auto_fit_problem(fit, pts, cap.num_slits) if used_source == "auto" else None
    except CalibrationError as exc:
        if used_source != "auto":
            raise
        problem = str(exc)
    if problem is not None:
        # never return planes the data do not support: fall back to the hand readings, or stop
        if cap.target is not None and cap.target.slit_points:
            used_source = "hand"
            notes.append(
                f"automatic projector calibration failed: {problem}; used the hand readings "
                "of target.json"
            )
            pts = hand_slit_points(cap)
            fit = fit_projector(pts, cap.num_slits, outlier_sigma)
        else:
            raise CalibrationError(
                f"automatic projector calibration failed: {problem}; add hand readings of points "
                "on the slits to target.json (slit_points) and use --source hand"
            )
    for j, why in fit.excluded:
        if why != "no points":
            notes.append(f"slit {j} left out: {why}")
    sp = fit.slit_planes
    for j in sp.from_axis:
        notes.append(
            f"slit {j} is seen along one line only (one target face): its plane is the plane "
            f"through the common axis and that line (RMS {sp.rms_mm[j]:.3g} mm)"
        )
    missing = [j for j, why in fit.excluded if why == "no points"]
    if missing:
        notes.append(f"no points on slit(s) {missing}: their planes are unknown (NaN)")
    res = cam.residuals
    calib = Calibration(
        image_size=cap.image_size,
        dlt=cam.dlt,
        refined=cam.refined,
        projector=fit.projector,
        slit_planes=fit.slit_planes,
        camera_rms_px=res.refined_rms_px,
        dlt_rms_px=res.dlt_rms_px,
        marker_ids=res.ids,
        marker_residuals_px=res.refined_px,
    )
    return CalibrationResult(calib, cam, pts, fit, used_source, tuple(notes))


def calibrate_capture(
    capture: str | Path | Capture,
    source: str = "auto",
    label_slits: LabelFn | None = None,
    **kwargs: Any,
) -> Calibration:
    """The :class:`Calibration` of a capture folder (:func:`run_calibration` without report)."""
    return run_calibration(capture, source, label_slits, **kwargs).calibration


def write_calibration(result: CalibrationResult, path: str | Path) -> Path:
    """Write the calibration JSON with the report under the ``report`` key."""
    d = result.calibration.to_dict()
    d["report"] = _nan_none(result.report())
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(json.dumps(d, indent=1, allow_nan=False))
    except OSError as exc:
        raise CaptureError(f"cannot write {p}: {exc.strerror or exc}") from None
    return p


def format_report(result: CalibrationResult) -> list[str]:
    """A short human-readable report of :func:`run_calibration`."""
    r = result.report()
    m, c, s, pm = r["markers"], r["camera"], r["slit_planes"], r["projector_matrix"]
    lines = [f"markers: {len(m['used'])} of {m['total']} used"]
    for i, why in m["rejected"].items():
        lines.append(f"  rejected {i}: {why}")
    lines.append(
        f"camera: DLT RMS {c['dlt_rms_px']:.3f} px, refined RMS {c['refined_rms_px']:.3f} px; "
        "worst markers " + ", ".join(f"{i} {v:.3f}" for i, v in m["worst_px"])
    )
    src = (
        "hand readings (target.json slit_points)"
        if result.source == "hand"
        else ("automatic (calibration/slits.png)")
    )
    lines.append(f"projector points: {r['points']['count']} from {src}")
    if result.source == "auto":
        lines.append("  " + " -> ".join(f"{name} {n}" for name, n in r["points"]["steps"]))
    lines.append(
        f"slit planes: {s['fitted']} of {s['num_slits']} fitted, RMS median "
        f"{s['median_rms_mm']:.4f} mm; worst "
        + ", ".join(f"slit {j} {v:.4f}" for j, v in s["worst_rms_mm"] if math.isfinite(v))
        + f"; {s['outliers_dropped']} outlier point(s) dropped"
    )
    if result.projector.projector is not None:
        lines.append(
            f"paper's 2x4 projector matrix on the same points: RMS median "
            f"{pm['median_rms_mm']:.4f} mm (systematic error of the single-matrix model)"
        )
    for note in result.notes:
        lines.append(f"note: {note}")
    return lines
