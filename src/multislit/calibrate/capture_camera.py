"""The camera of a capture: markers of ``calibration/markers.png`` and straight stripes.

The centre corners of the checker markers are found near their hints (markers not found are
reported by id and left out); >= 6 non-coplanar markers give the paper's DLT matrix C
(eq. 1-2), refined to a pinhole camera with lens distortion. A marker whose reprojection
residual is far above the others (a wrong corner or a mistyped ``xyz``) is dropped and
reported. The stripes of the calibration and reference images, straight lines in space, then
pin the lens distortion down over the whole image.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from multislit.calibrate.camera import (
    MIN_DLT_POINTS,
    calibrate_dlt,
    refine_camera,
    refine_camera_with_lines,
    rms,
)
from multislit.calibrate.markers import MarkerDetection, find_marker_corners
from multislit.calibrate.slit_points import as_capture, read_capture_image, stripe_lines
from multislit.errors import CalibrationError
from multislit.geometry import MatrixCamera, PinholeCamera
from multislit.geometry.camera import F64
from multislit.io import Capture, Face

#: A marker whose refined residual exceeds max(this, 5 x the robust RMS) px is dropped.
_MARKER_OUTLIER_PX = 1.0
#: At most this many found markers are dropped for large residuals.
_MAX_OUTLIERS = 3


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


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Result of :func:`camera_from_capture`.

    Attributes
    ----------
    detection : MarkerDetection of all markers of target.json
    dlt : MatrixCamera, the paper's C from the markers used
    refined : PinholeCamera with distortion (markers and, by default, straight stripes)
    residuals : MarkerResiduals of the markers used
    from_markers : PinholeCamera refined from the markers alone
    """

    detection: MarkerDetection
    dlt: MatrixCamera
    refined: PinholeCamera
    residuals: MarkerResiduals
    from_markers: PinholeCamera

    @property
    def rejected(self) -> dict[str, str]:
        """Marker id -> reason for every marker of target.json that was not used."""
        used = set(self.residuals.ids)
        out = dict(self.detection.rejected)
        for i, ok in zip(self.detection.ids, self.detection.found, strict=True):
            if ok and i not in used:
                out[i] = "reprojection residual far above the others (wrong corner or xyz?)"
        return out


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


def camera_from_capture(
    capture: str | Path | Capture, *, use_stripes: bool = True
) -> CameraCalibration:
    """Camera calibration from ``calibration/markers.png`` and the markers of target.json.

    Parameters
    ----------
    capture : capture folder or opened :class:`~multislit.io.Capture` (with target.json)
    use_stripes : bool
        Also make the stripes of ``calibration/slits.png`` and of the reference images straight
        (:func:`~multislit.calibrate.camera.refine_camera_with_lines`): the markers alone leave
        the lens distortion poorly determined away from them. Default True.

    Returns
    -------
    CameraCalibration

    Raises
    ------
    CalibrationError
        Missing image, fewer than 6 markers found, found markers all on one plane, failed fit.
        The message says how many markers were found and which were rejected and why.
    """
    cap = as_capture(capture)
    if cap.target is None:
        raise CalibrationError(f"{cap.root}: calibration needs target.json (markers and faces)")
    t = cap.target
    img = read_capture_image(cap, cap.markers_image, "marker image")
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
    for _ in range(_MAX_OUTLIERS + 1):
        dlt, _ = calibrate_dlt(X[keep], x[keep], cap.image_size)
        refined, res = refine_camera(X[keep], x[keep], dlt, **_distortion_options(int(keep.sum())))
        limit = max(_MARKER_OUTLIER_PX, 5.0 * 1.4826 * float(np.median(res)))
        worst = int(np.argmax(res))
        if res[worst] <= limit or keep.sum() <= MIN_DLT_POINTS or (~keep).sum() >= _MAX_OUTLIERS:
            break
        keep[np.flatnonzero(keep)[worst]] = False
    dlt, dres = calibrate_dlt(X[keep], x[keep], cap.image_size)
    refined, rres = refine_camera(X[keep], x[keep], dlt, **_distortion_options(int(keep.sum())))
    from_markers = refined
    if use_stripes:
        lines = stripe_lines(cap, refined)
        if len(lines) >= 3:
            start, _ = refine_camera(X[keep], x[keep], dlt, distortion=False)
            refined, rres, _ = refine_camera_with_lines(X[keep], x[keep], start, lines)
    ids_used = tuple(i for i, k in zip(used, keep, strict=True) if k)
    residuals = MarkerResiduals(ids_used, dres, rres)
    return CameraCalibration(det, dlt, refined, residuals, from_markers)
