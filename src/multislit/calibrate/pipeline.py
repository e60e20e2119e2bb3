"""Capture-level calibration: a capture folder in, a :class:`~multislit.calibrate.Calibration` out.

:func:`calibrate_capture` runs the pipeline (paper section 5, Figs. 15, 17, 18):

1. **Camera** (:mod:`~multislit.calibrate.capture_camera`): the checker markers of
   ``calibration/markers.png`` give the paper's DLT matrix C, refined to a pinhole camera with
   lens distortion; the stripes, straight lines in space, pin the distortion down.
2. **Points on the slits** (:mod:`~multislit.calibrate.slit_points`), from one of two sources:
   ``"hand"``, the paper's readings of target.json ``slit_points``; ``"auto"``, the stripe
   centres of ``calibration/slits.png`` labelled by their order along each row and the dots
   (:func:`~multislit.calibrate.slit_labels.label_by_order`) and put on the target's faces.
3. **Projector** (:func:`~multislit.calibrate.projector.fit_projector`): one plane per slit
   through a common axis, fitted robustly, and the paper's 2x4 matrix for comparison.

Automatic planes that the points do not support are never returned: the calibration falls back
to the hand readings (and says so in the notes) or stops with an error.
:func:`write_calibration` saves the calibration with its report (the ``report`` key, which
:meth:`Calibration.load` ignores); :func:`format_report` gives the report as text lines.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from multislit.calibrate.capture_camera import CameraCalibration, camera_from_capture
from multislit.calibrate.model import Calibration
from multislit.calibrate.projector import ProjectorFit, auto_fit_problem, fit_projector
from multislit.calibrate.slit_labels import label_by_order
from multislit.calibrate.slit_points import (
    SlitPointSet,
    as_capture,
    auto_slit_points,
    hand_slit_points,
    read_capture_image,
)
from multislit.errors import CalibrationError, CaptureError
from multislit.io import Capture, json_safe, write_json

_SOURCES = ("auto", "hand")


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything :func:`calibrate_capture` found: the calibration and its report data.

    Attributes
    ----------
    calibration : Calibration, what the scans use (and :func:`write_calibration` saves)
    camera : CameraCalibration, the markers found and the camera's residuals
    points : SlitPointSet, the points on the slits the projector was fitted to
    projector : ProjectorFit, the robust fit of the slit planes and the 2x4 matrix
    source : "auto" or "hand", where the points came from (after any fallback)
    notes : remarks for people (fallbacks, slits left out or placed by the common axis)
    """

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


def calibrate_capture(
    capture: str | Path | Capture,
    *,
    source: str = "auto",
    labels: tuple[ArrayLike, ArrayLike, ArrayLike] | None = None,
) -> CalibrationResult:
    """Calibrate camera and projector from a capture folder; see the module docstring.

    Parameters
    ----------
    capture : capture folder or :class:`~multislit.io.Capture` (with target.json)
    source : "auto" or "hand"
        Where the points on the slits come from: "auto", the stripes of
        ``calibration/slits.png``; "hand", target.json ``slit_points``. When the automatic
        points do not support the planes, the hand readings are used if there are any (the
        result's ``source`` and ``notes`` say so). Default "auto".
    labels : (u, v, slit), each (K,), optional
        With "auto": the slit labels of stripe centres of ``calibration/slits.png`` (u, v in
        px, slit an int, -1 where unknown), e.g. known labels of a simulated capture. Default:
        :func:`~multislit.calibrate.slit_labels.label_by_order`.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Bad ``source``, too few markers, or no projector planes the data support.
    """
    if source not in _SOURCES:
        raise CalibrationError(f"source must be 'auto' or 'hand', got {source!r}")
    cap = as_capture(capture)
    cam = camera_from_capture(cap)
    notes: list[str] = []
    if source == "auto":
        pts, fit, problem = _auto_projector(cap, cam, labels)
    else:
        pts = hand_slit_points(cap)
        fit, problem = fit_projector(pts, cap.num_slits), None
    used_source = source
    if problem is not None:
        # never return planes the data do not support: fall back to the hand readings, or stop
        if cap.target is None or not cap.target.slit_points:
            raise CalibrationError(
                f"automatic projector calibration failed: {problem}; add hand readings of points "
                "on the slits to target.json (slit_points) and use --source hand"
            )
        used_source = "hand"
        notes.append(
            f"automatic projector calibration failed: {problem}; used the hand readings "
            "of target.json"
        )
        pts = hand_slit_points(cap)
        fit = fit_projector(pts, cap.num_slits)
    notes += _fit_notes(fit)
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


def _auto_projector(
    cap: Capture, cam: CameraCalibration, labels: tuple[ArrayLike, ArrayLike, ArrayLike] | None
) -> tuple[SlitPointSet, ProjectorFit | None, str | None]:
    """Automatic points and their projector fit, or why the fit cannot be trusted."""
    if labels is None:
        img = read_capture_image(cap, cap.slits_image, "slit image")
        lab = label_by_order(img, cap, camera=cam.from_markers)
        labels = (lab.u, lab.v, lab.slit)
    pts = auto_slit_points(cap, cam.refined, labels)
    try:
        fit = fit_projector(pts, cap.num_slits)
    except CalibrationError as exc:
        return pts, None, str(exc)
    return pts, fit, auto_fit_problem(fit, pts, cap.num_slits)


def _fit_notes(fit: ProjectorFit) -> list[str]:
    """Notes on the slits left out or given the plane through the common axis."""
    notes = [f"slit {j} left out: {why}" for j, why in fit.excluded if why != "no points"]
    sp = fit.slit_planes
    for j in sp.from_axis:
        notes.append(
            f"slit {j} is seen along one line only (one target face): its plane is the plane "
            f"through the common axis and that line (RMS {sp.rms_mm[j]:.3g} mm)"
        )
    missing = [j for j, why in fit.excluded if why == "no points"]
    if missing:
        notes.append(f"no points on slit(s) {missing}: their planes are unknown (NaN)")
    return notes


def write_calibration(result: CalibrationResult, path: str | Path) -> Path:
    """Write the calibration JSON with the report under the ``report`` key, whole or not at all.

    Returns the path; :class:`~multislit.errors.CaptureError` if it cannot be written.
    """
    d = result.calibration.to_dict()
    d["report"] = json_safe(result.report())
    p = Path(path)
    try:
        write_json(p, d)
    except OSError as exc:
        raise CaptureError(f"cannot write {p}: {exc.strerror or exc}") from None
    return p


def format_report(result: CalibrationResult) -> list[str]:
    """A short human-readable report of :func:`calibrate_capture`."""
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
