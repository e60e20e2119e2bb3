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
4. **Reference boards** (:mod:`~multislit.calibrate.boards`): the boards of the reference
   images, posed by the slits calibrated on the target, give every slit they show points at
   several depths; all planes are refitted with them. The result says per slit where its plane
   came from (``origin``), and a slit the boards show that ends without a plane is an error.
5. **Bundle adjustment** (:mod:`~multislit.calibrate.bundle`): the camera, the slit planes
   (through their common axis) and the boards' poses adjusted together on the markers, the
   target's folds, the stripes on the target (or the hand readings) and on the boards.
6. **Dot projector** (:mod:`~multislit.calibrate.dots`): a point source and one ray per dot,
   fitted on the dots of the boards as the bundle adjustment posed them (none, with a note,
   without prepared reference boards: scans then identify by the template matching).

Automatic planes that the points do not support are never returned: the calibration falls back
to the hand readings (and says so in the notes) or stops with an error. So are planes that pass
through the camera (``calibration/slits.png`` showing a flat surface instead of the target) and
hand readings of one slit that do not lie on one plane (a slit number off by one).
:func:`write_calibration` saves the calibration with its report (the ``report`` key, which
:meth:`Calibration.load` ignores); :func:`format_report` gives the report as text lines.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from multislit.calibrate.boards import (
    BoardPoints,
    ReferenceStripes,
    fit_with_boards,
    plane_origins,
    reference_stripes,
)
from multislit.calibrate.bundle import (
    CaptureBundle,
    CaptureObservations,
    adjust_capture,
    bundle_report,
)
from multislit.calibrate.camera import rms
from multislit.calibrate.capture_camera import CameraCalibration, camera_from_capture
from multislit.calibrate.dots import DotFit, capture_dot_projector
from multislit.calibrate.edges import fold_points
from multislit.calibrate.model import Calibration
from multislit.calibrate.projector import ProjectorFit, auto_fit_problem, fit_projector
from multislit.calibrate.slit_labels import label_by_order
from multislit.calibrate.slit_planes import (
    MAX_AXIS_ANGLE_DEVIATION,
    axis_order_deviation,
    planes_between,
)
from multislit.calibrate.slit_points import (
    SlitPointSet,
    as_capture,
    auto_slit_points,
    hand_slit_points,
    read_capture_image,
)
from multislit.errors import (
    CalibrationError,
    CaptureError,
    IdentificationError,
    ReferenceImageError,
)
from multislit.identify import ReferenceSet, capture_reference
from multislit.io import Capture, json_safe, write_json
from multislit.summaries import Summarised

_SOURCES = ("auto", "hand")

#: Lines of sight must meet the slit planes at this angle or more, degrees (the scans' default
#: ``min_angle_deg``): planes through the camera centre come from a flat surface, not the target.
_MIN_VIEW_ANGLE_DEG = 2.0

#: The hand readings of one slit may lie this many local slit spacings (RMS) from its plane.
_MAX_READING_SPACING = 0.25


@dataclass(frozen=True, eq=False, repr=False)
class CalibrationResult(Summarised):
    """Everything :func:`calibrate_capture` found: the calibration and its report data.

    Attributes
    ----------
    calibration : Calibration, what the scans use (and :func:`write_calibration` saves)
    camera : CameraCalibration, the markers found and the camera's residuals
    points : SlitPointSet, the points on the slits the projector was fitted to
    projector : ProjectorFit, the robust fit of the slit planes and the 2x4 matrix
    source : "auto" or "hand", where the points came from (after any fallback)
    notes : remarks for people (fallbacks, slits left out or placed by the common axis)
    boards : BoardPoints, the reference boards as posed and their points (None: not used)
    origin : (K,) str, where each slit's plane came from (:func:`plane_origins`; "" = none)
    reference : the capture's prepared :class:`~multislit.identify.ReferenceSet` (None: the
        reference boards were not used); scans of the capture can reuse it
    bundle : CaptureBundle, the bundle adjustment whose camera and slit planes the calibration
        holds (residuals per source, image and region, standard errors, 3D uncertainty)
    dots : DotFit, the dot projector fitted on the reference boards (None: not calibrated, the
        notes say why)
    """

    calibration: Calibration
    camera: CameraCalibration
    points: SlitPointSet
    projector: ProjectorFit
    source: str
    notes: tuple[str, ...] = ()
    boards: BoardPoints | None = None
    origin: tuple[str, ...] = ()
    reference: ReferenceSet | None = None
    bundle: CaptureBundle | None = None
    dots: DotFit | None = None

    def summary(self) -> str:
        """The report's lines (:func:`format_report`)."""
        return "\n".join(format_report(self))

    def report(self) -> dict[str, Any]:
        """Figures for people (and the ``report`` key of the written file)."""
        res = self.camera.residuals
        sp = self.projector.slit_planes
        valid = sp.valid
        rms_mm = sp.rms_mm
        dev = axis_order_deviation(sp)
        worst_slits = [
            (int(j), float(rms_mm[j])) for j in np.argsort(-np.nan_to_num(rms_mm, nan=-1))[:3]
        ]
        cal = self.calibration
        mres = cal.marker_residuals_px
        worst = [(cal.marker_ids[i], float(mres[i])) for i in np.argsort(-mres)[:3]]
        camera = cal.camera
        return {
            "source": self.source,
            "notes": list(self.notes),
            "markers": {
                "total": len(self.camera.detection.ids),
                "used": list(res.ids),
                "rejected": self.camera.rejected,
                "worst_px": worst,
            },
            "camera": {
                "dlt_rms_px": res.dlt_rms_px,
                "markers_only_rms_px": res.refined_rms_px,
                "refined_rms_px": float(cal.camera_rms_px),
                "distortion": list(getattr(camera, "dist", ())),
            },
            "bundle": None
            if self.bundle is None
            else bundle_report(self.bundle, np.flatnonzero(self.bundle.slit_item >= 0).tolist()),
            "points": {"count": len(self.points), "steps": [list(x) for x in self.points.steps]},
            "slit_planes": {
                "fitted": int(valid.sum()),
                "num_slits": int(sp.num_slits),
                "median_rms_mm": float(np.nanmedian(rms_mm)) if valid.any() else float("nan"),
                "worst_rms_mm": worst_slits,
                "excluded": [[int(j), r] for j, r in self.projector.excluded],
                "from_axis": [int(j) for j in sp.from_axis],
                "outliers_dropped": int(self.projector.dropped.sum()),
                "per_slit": [
                    {
                        "slit": j,
                        "origin": self.origin[j] if j < len(self.origin) else "",
                        "rms_mm": float(rms_mm[j]),
                        "points": int(sp.counts[j]),
                        "axis_deviation": float(dev[j]),
                    }
                    for j in range(sp.num_slits)
                ],
            },
            "reference_boards": None
            if self.boards is None
            else {
                "planes": (
                    self.bundle.board_planes if self.bundle is not None else self.boards.planes
                ).tolist(),
                "rms_mm": self.boards.rms_mm.tolist(),
            },
            "dot_projector": None if self.dots is None else self.dots.report(),
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
    references: bool = True,
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
    references : bool
        Use the reference boards as well (:func:`~multislit.calibrate.boards.fit_with_boards`):
        every slit they show gets a plane. False: the target's faces alone, as when the
        reference images were not taken with this rig set-up. Default True.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Bad ``source``, too few markers, no projector planes the data support, a slit seen
        on the reference boards that ends without a plane (named, with the reason), hand
        readings of one slit that do not lie on one plane (the slit and the readings named:
        a slit number off by one), or slit planes that pass through the camera (points of a
        flat surface, not the target: every line of sight would graze them).
    """
    if source not in _SOURCES:
        raise CalibrationError(f"source must be 'auto' or 'hand', got {source!r}")
    cap = as_capture(capture)
    cam = camera_from_capture(cap, use_stripes=False)
    notes: list[str] = []
    reference = _reference(cap, notes) if references else None
    if source == "auto":
        pts, fit, problem = _auto_projector(cap, cam, labels, reference)
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
    boards, origin = None, plane_origins(fit, pts)
    target_pts = pts
    stripes = _board_stripes(cap, reference, notes) if references else None
    if stripes is not None:
        pts, fit, boards, origin = _add_boards(cap, cam, pts, fit, notes, stripes)
    if used_source == "hand":
        bad = _hand_reading_problem(hand_slit_points(cap), fit.slit_planes.planes)
        if bad:
            raise CalibrationError(f"{cap.root / 'target.json'}: {bad}")
    grazing = _grazing_problem(fit.slit_planes.planes, cam, pts)
    if grazing:
        raise CalibrationError(grazing + "; check calibration/slits.png and the slit readings")
    bundle = _bundle(cap, cam, target_pts, used_source, fit, boards, stripes)
    if bundle.problems:
        raise CalibrationError("calibration does not fit: " + "; ".join(bundle.problems))
    fit, origin = _bundle_planes(fit, bundle, origin, notes)
    notes += _fit_notes(fit)
    marker_px = _marker_residuals(cap, cam, bundle)
    dots = _dot_projector(cap, reference, stripes, bundle, fit, notes)
    calib = Calibration(
        image_size=cap.image_size,
        dlt=cam.dlt,
        refined=bundle.camera,
        projector=fit.projector,
        slit_planes=fit.slit_planes,
        camera_rms_px=rms(marker_px),
        dlt_rms_px=cam.residuals.dlt_rms_px,
        marker_ids=cam.residuals.ids,
        marker_residuals_px=marker_px,
        dot_projector=None if dots is None else dots.projector,
    )
    return CalibrationResult(
        calib, cam, pts, fit, used_source, tuple(notes), boards, origin, reference, bundle, dots
    )


def _marker_faces(cap: Capture) -> np.ndarray:
    """(F, 4) the target's face planes with unit normals."""
    f = np.array([face.plane for face in cap.target.faces], float).reshape(-1, 4)
    return f / np.linalg.norm(f[:, :3], axis=1, keepdims=True)


def _bundle(
    cap: Capture,
    cam: CameraCalibration,
    target_pts: SlitPointSet,
    source: str,
    fit: ProjectorFit,
    boards: BoardPoints | None,
    stripes: ReferenceStripes | None,
) -> CaptureBundle:
    """The bundle adjustment (:func:`~multislit.calibrate.bundle.adjust_capture`) of the
    capture's markers and the target's folds (:func:`~multislit.calibrate.edges.fold_points`),
    the stripes on the target (or hand readings) and on the reference boards."""
    det = cam.detection
    sel = [det.ids.index(i) for i in cam.residuals.ids]
    faces = _marker_faces(cap)
    e3, e2, ei = np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.intp)
    t_uv, t_slit, t_face = e2, ei, ei
    r_xyz, r_slit, r_uv = e3, ei, e2
    if source == "auto":
        # the points the starting fit kept: its per-slit RANSAC planes drop mislabelled ones
        # (the target's points come first in the fit's points)
        on = (target_pts.face >= 0) & (target_pts.face < len(faces))
        on &= fit.inlier[: len(target_pts)]
        t_uv, t_slit, t_face = target_pts.uv[on], target_pts.slit[on], target_pts.face[on]
    else:
        hand = hand_slit_points(cap)
        r_xyz, r_slit, r_uv = hand.xyz, hand.slit, hand.uv
    rel = [_relative(cap, p) for p in (cap.markers_image, cap.slits_image)]
    folds = fold_points(cap.image(cap.markers_image), cam.refined, cap.target.faces)
    obs = CaptureObservations(
        image_size=cap.image_size,
        marker_xyz=cap.target.marker_xyz[sel],
        marker_uv=det.uv[sel],
        faces=faces,
        target_uv=t_uv,
        target_slit=t_slit,
        target_face=t_face,
        readings_xyz=r_xyz,
        readings_slit=r_slit,
        readings_uv=r_uv,
        board_uv=tuple(stripes.uv) if stripes is not None else (),
        board_slit=tuple(stripes.slit) if stripes is not None else (),
        fold_uv=folds.uv,
        fold_line=folds.fold,
        fold_P=folds.P,
        fold_D=folds.D,
        names=(
            *rel,
            "target.json (slit_points)",
            *(_reference_paths(cap, stripes.names) if stripes is not None else []),
        ),
    )
    board_planes = boards.planes if boards is not None and stripes is not None else e3[:, :0]
    return adjust_capture(obs, cam.refined, fit.slit_planes.planes, board_planes.reshape(-1, 4))


def _reference_paths(cap: Capture, stems: tuple[str, ...]) -> list[str]:
    """The reference images named ``stems`` (file stems), relative to the capture folder."""
    by_stem = {p.stem: p for p in cap.references}
    return [_relative(cap, by_stem[s]) for s in stems]


def _relative(cap: Capture, path: Path) -> str:
    """``path`` relative to the capture folder (as given if outside it)."""
    try:
        return str(Path(path).relative_to(cap.root))
    except ValueError:
        return str(path)


def _bundle_planes(
    fit: ProjectorFit, bundle: CaptureBundle, origin: tuple[str, ...], notes: list[str]
) -> tuple[ProjectorFit, tuple[str, ...]]:
    """The projector fit with the bundle's slit planes, and where each plane came from (the
    sources of its observations); slits the bundle left out keep their plane from the points
    (or, between planed slits, the common axis model's)."""
    sp = fit.slit_planes
    fitted = np.all(np.isfinite(bundle.slit_planes), axis=1)
    planes = np.where(fitted[:, None], bundle.slit_planes, sp.planes)
    rms_mm = np.where(fitted, bundle.slit_rms_mm, sp.rms_mm)
    counts = np.where(fitted, bundle.slit_counts, sp.counts)
    a, u = bundle.axis
    new = replace(sp, planes=planes, rms_mm=rms_mm, counts=counts, axis_point=a, axis_direction=u)
    names = {"target stripes": "target faces", "hand readings": "hand readings",
             "board stripes": "reference boards"}  # fmt: skip
    out = list(origin)
    for j in np.flatnonzero(fitted):
        if out[j] == "common axis model":  # placed between its neighbours to start
            notes[:] = [n for n in notes if not n.startswith(f"slit {j} has no plane from its")]
            notes.append(
                f"slit {j} gave no plane from its points: its observations lie along one line, "
                "and its plane passes through the common axis and that line (fitted in the "
                "adjustment)"
            )
        out[j] = " + ".join(
            names[src] for src, n in bundle.slit_sources.items() if n[j] > 0 and src in names
        )
    return replace(fit, slit_planes=new), tuple(out)


def _marker_residuals(cap: Capture, cam: CameraCalibration, bundle: CaptureBundle) -> np.ndarray:
    """(M,) px, the reprojection distance of each marker used by the bundle's camera."""
    det = cam.detection
    sel = [det.ids.index(i) for i in cam.residuals.ids]
    uv = bundle.camera.project(cap.target.marker_xyz[sel])
    return np.linalg.norm(uv - det.uv[sel], axis=1)


def _reference(cap: Capture, notes: list[str]) -> ReferenceSet | None:
    """The capture's prepared reference set, or None (with a note) if it cannot be had."""
    if not cap.references:
        notes.append("no reference images: slit planes from the target alone")
        return None
    try:
        return capture_reference(cap)
    except ReferenceImageError as exc:
        notes.append(
            f"the reference set cannot be prepared ({exc}); the boards' stripes are numbered "
            "image by image"
        )
        return None


def _dot_projector(
    cap: Capture,
    reference: ReferenceSet | None,
    stripes: ReferenceStripes | None,
    bundle: CaptureBundle,
    fit: ProjectorFit,
    notes: list[str],
) -> DotFit | None:
    """The dot projector fitted on the reference boards as the bundle adjustment posed them,
    or None with a note saying why there is none."""
    if reference is None or stripes is None:
        notes.append(
            "no dot projector without prepared reference boards; scans can use the template "
            "identification only"
        )
        return None
    try:
        return capture_dot_projector(
            [cap.image(p) for p in cap.references],
            stripes,
            bundle.camera,
            fit.slit_planes,
            reference.stripe_width_px,
            reference.dot_size_px,
            board_planes=bundle.board_planes if len(bundle.board_planes) else None,
        )
    except CalibrationError as exc:
        notes.append(f"{exc}; scans can use the template identification only")
        return None


def _board_stripes(
    cap: Capture, reference: ReferenceSet | None, notes: list[str]
) -> ReferenceStripes | None:
    """The numbered stripe centres of the reference boards (:func:`reference_stripes`; without
    a prepared reference set, each image's own curves), or None with a note."""
    if not cap.references:
        return None
    try:
        stripes = reference_stripes(cap, reference)
    except ReferenceImageError as exc:
        notes.append(f"reference boards not used ({exc}); slit planes from the target alone")
        return None
    notes += list(stripes.notes)
    return stripes


def _auto_projector(
    cap: Capture,
    cam: CameraCalibration,
    labels: tuple[ArrayLike, ArrayLike, ArrayLike] | None,
    reference: ReferenceSet | None,
) -> tuple[SlitPointSet, ProjectorFit | None, str | None]:
    """Automatic points and their projector fit, or why the fit cannot be trusted (also when
    the stripes cannot be labelled: the labels' dots need the prepared reference images)."""
    if labels is None:
        img = read_capture_image(cap, cap.slits_image, "slit image")
        try:
            if reference is not None and reference.epipole_problem:
                raise IdentificationError(
                    f"the dots could not be followed between them: {reference.epipole_problem}"
                )
            lab = label_by_order(img, cap, camera=cam.from_markers, reference=reference)
        except (ReferenceImageError, IdentificationError) as exc:
            # the labels' anchors are the template matching's: it needs the reference images
            # and the dot projector's epipole from them
            e3, e2, ei = np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.intp)
            empty = SlitPointSet(e3, ei, e2, ei, "auto", (("labelled", 0),))
            return (
                empty,
                None,
                f"the target's stripes cannot be labelled by the dots of the reference images "
                f"({exc})",
            )
        labels = (lab.u, lab.v, lab.slit)
    pts = auto_slit_points(cap, cam.refined, labels)
    try:
        fit = fit_projector(pts, cap.num_slits)
    except CalibrationError as exc:
        return pts, None, str(exc)
    problem = auto_fit_problem(fit, pts, cap.num_slits)
    if problem is None:
        problem = _grazing_problem(fit.slit_planes.planes, cam, pts)
        if problem:
            problem += (
                ": calibration/slits.png does not show the stripes on the target (a flat board "
                "or another scene?)"
            )
    return pts, fit, problem


def _view_angles(planes: np.ndarray, centre: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K,) degrees: the angle at which lines of sight from the camera centre (3,) mm to
    points at the median range of ``points`` (N, 3) mm meet each slit plane (K, 4) (NaN rows
    give NaN)."""
    rng = float(np.median(np.linalg.norm(points - centre, axis=1))) if len(points) else 1.0
    dist = np.abs(planes[:, :3] @ centre + planes[:, 3])
    return np.degrees(np.arcsin(np.clip(dist / max(rng, 1e-9), 0.0, 1.0)))


def _grazing_problem(planes: np.ndarray, cam: CameraCalibration, pts: SlitPointSet) -> str | None:
    """Why the slit planes cannot be triangulated with (they pass through the camera), or None.

    Points of one flat surface seen by the camera, put on the target's faces, lie on the
    planes through the camera centre and their stripes: planes fitted to them look perfect but
    every line of sight grazes them, and scans keep no point.
    """
    valid = np.all(np.isfinite(planes), axis=1)
    if not valid.any():
        return None
    camera = cam.refined if cam.refined is not None else cam.dlt
    ang = _view_angles(planes[valid], camera.centre, pts.xyz)
    med = float(np.median(ang))
    if med >= _MIN_VIEW_ANGLE_DEG:
        return None
    return (
        f"the slit planes pass through the camera: lines of sight meet them at {med:.2f} "
        f"degrees (median over {int(valid.sum())} slits; a scan needs >= {_MIN_VIEW_ANGLE_DEG:g})"
    )


def _hand_reading_problem(pts: SlitPointSet, planes: np.ndarray) -> str | None:
    """Which slits' hand readings do not lie on their slit's plane, and why, or None.

    A reading of slit k lies on plane k; one given its neighbour's number lies a slit spacing
    away and pulls plane k off the others. Slits whose readings lie more than
    :data:`_MAX_READING_SPACING` local slit spacings (RMS) from their plane are named, with the
    readings that lie nearer a neighbour's plane than their own.
    """
    k_all = len(planes)
    X = np.c_[pts.xyz, np.ones(len(pts.xyz))]
    signed = X @ planes.T  # (N, K) mm, NaN for slits without a plane
    idx = np.arange(len(X))
    own = np.abs(signed[idx, pts.slit])
    lo = np.where(pts.slit > 0, signed[idx, np.maximum(pts.slit - 1, 0)], np.nan)
    hi = np.where(pts.slit < k_all - 1, signed[idx, np.minimum(pts.slit + 1, k_all - 1)], np.nan)
    mine = signed[idx, pts.slit]
    spacing = np.where(
        np.isfinite(lo) & np.isfinite(hi),
        np.abs(hi - lo) / 2,
        np.fmax(np.abs(lo - mine), np.abs(hi - mine)),
    )
    found = []
    for k in np.unique(pts.slit):
        m = (pts.slit == k) & np.isfinite(own)
        sp = spacing[m][np.isfinite(spacing[m])]
        if not m.any() or not len(sp):
            continue
        rms = float(np.sqrt(np.mean(own[m] ** 2)))
        frac = rms / float(np.median(sp))
        if frac <= _MAX_READING_SPACING:
            continue
        near = [
            (int(i), k - 1 if abs(lo[i]) < abs(hi[i]) else k + 1)
            for i in np.flatnonzero(m)
            if np.nanmin([abs(lo[i]), abs(hi[i])]) < own[i]
        ]
        msg = f"slit {k}'s readings lie {rms:.2f} mm RMS ({frac:.2f} slit spacings) off one plane"
        if near:
            msg += ", and " + ", ".join(
                f"slit_points[{i}] lies nearer slit {j}'s plane" for i, j in near[:4]
            )
        found.append(msg)
    if not found:
        return None
    return (
        "hand readings of different slits under one number? "
        + "; ".join(found[:3])
        + " (fix the 'slit' numbers of slit_points)"
    )


def _add_boards(
    cap: Capture,
    cam: CameraCalibration,
    pts: SlitPointSet,
    fit: ProjectorFit,
    notes: list[str],
    stripes: ReferenceStripes,
) -> tuple[SlitPointSet, ProjectorFit, BoardPoints | None, tuple[str, ...]]:
    """The fit with the reference boards' points (:func:`fit_with_boards`), and each plane's origin.

    Appends to ``notes``; raises :class:`CalibrationError` naming the slits the references show
    that end without a plane.
    """
    camera = cam.refined if cam.refined is not None else cam.dlt
    n_faces = len(cap.target.faces) if cap.target is not None else 0
    bf = fit_with_boards(pts, fit, stripes, camera, n_faces)
    notes += list(bf.boards.notes)
    fit, why = bf.fit, dict(bf.fit.excluded)
    origin = list(plane_origins(fit, bf.points, bf.first_board_face))
    if np.any(stripes.shown() & ~fit.slit_planes.valid):
        sp, filled = planes_between(fit.slit_planes)
        kept = tuple(e for e in fit.excluded if e[0] not in filled)
        fit = replace(fit, slit_planes=sp, excluded=kept)
        for j in filled:
            origin[j] = "common axis model"
            notes.append(
                f"slit {j} has no plane from its points ({why.get(j, 'no points')}): its plane is "
                "the common axis model's, between its neighbours' (no points check it)"
            )
    lost = np.flatnonzero(stripes.shown() & ~fit.slit_planes.valid)
    if len(lost):
        raise CalibrationError(
            f"slit(s) {lost.tolist()} are seen on the reference boards but got no plane ("
            + "; ".join(f"slit {j}: {why.get(int(j), 'no points')}" for j in lost[:5])
            + ")"
            + "".join(f"; {n}" for n in bf.boards.notes)
            + "; check the reference images (every slit on every board) and the target image"
        )
    return bf.points, fit, bf.boards, tuple(origin)


def _fit_notes(fit: ProjectorFit) -> list[str]:
    """Notes on the slits left out or given the plane through the common axis."""
    notes = [f"slit {j} left out: {why}" for j, why in fit.excluded if why != "no points"]
    sp = fit.slit_planes
    for j in sp.from_axis:
        notes.append(
            f"slit {j} is seen along one line only (one target face): its plane is the plane "
            f"through the common axis and that line (RMS {sp.rms_mm[j]:.3g} mm)"
        )
    dev = axis_order_deviation(sp)
    for j in np.flatnonzero(np.abs(np.nan_to_num(dev)) > MAX_AXIS_ANGLE_DEVIATION):
        notes.append(
            f"slit {j}'s plane is {dev[j]:+.2f} slit spacings from where the other slits' planes "
            "put it about the common axis (mislabelled points?)"
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
        f"camera: DLT RMS {c['dlt_rms_px']:.3f} px, markers alone {c['markers_only_rms_px']:.3f} "
        f"px, adjusted {c['refined_rms_px']:.3f} px; worst markers "
        + ", ".join(f"{i} {v:.3f}" for i, v in m["worst_px"])
    )
    src = (
        "hand readings (target.json slit_points)"
        if result.source == "hand"
        else ("automatic (calibration/slits.png)")
    )
    lines.append(f"projector points: {r['points']['count']} from {src}")
    if result.source == "auto":
        lines.append("  " + " -> ".join(f"{name} {n}" for name, n in r["points"]["steps"]))
    if r["bundle"] is not None:
        lines += _bundle_lines(r["bundle"])
    lines.append(
        f"slit planes: {s['fitted']} of {s['num_slits']} fitted, RMS median "
        f"{s['median_rms_mm']:.4f} mm; worst "
        + ", ".join(f"slit {j} {v:.4f}" for j, v in s["worst_rms_mm"] if math.isfinite(v))
        + f"; {s['outliers_dropped']} outlier point(s) dropped before the adjustment"
    )
    for row in _origin_rows(s["per_slit"]):
        lines.append("  " + row)
    d = r["dot_projector"]
    if d is not None:
        by_seen = ", ".join(f"{n} on {k}" for k, n in sorted(d["rays_by_boards_seen"].items()))
        lines.append(
            f"dot projector: {d['rays']} rays ({by_seen} boards; "
            + "/".join(str(n) for n in d["dots_found_per_board"])
            + " seen per board, of "
            + "/".join(str(n) for n in d["spots_per_board"])
            + f" dots fitted), each board's dots {d['rms_px']:.3f} px RMS from their rays; "
            f"source at {', '.join(f'{x:.1f}' for x in d['source_mm'])} mm "
            f"(the rays' lines {d['source_rms_mm']:.2f} mm RMS from it)"
        )
    if result.projector.projector is not None:
        lines.append(
            f"paper's 2x4 projector matrix on the same points: RMS median "
            f"{pm['median_rms_mm']:.4f} mm (systematic error of the single-matrix model)"
        )
    for note in result.notes:
        lines.append(f"note: {note}")
    return lines


def _bundle_lines(b: dict[str, Any]) -> list[str]:
    """Report lines of the bundle adjustment: residuals per source and region, standard errors
    of the camera, the predicted 3D uncertainty."""
    n_obs = sum(v["kept"] for v in b["sources"].values())
    lines = [
        f"bundle adjustment: {b['parameters']} parameters, {n_obs} observations, slit planes "
        f"{'through a common axis' if b['slit_model'] == 'common axis' else 'free'}, "
        f"{'converged' if b['converged'] else 'NOT converged'} in {b['rounds']} round(s)"
    ]
    for name, v in b["sources"].items():
        u = v["unit"]
        lines.append(
            f"  {name}: {v['kept']} of {v['count']} kept, RMS {v['rms']:.4f} {u} (noise "
            f"{v['sigma']:.4f} {u}"
            + (
                f", correlated along the stripes: x{v['inflation']:.1f} variance"
                if v["inflation"] > 1.05
                else ""
            )
            + ")"
        )
        if len(v["regions"]) > 1:
            lines.append(
                "    by region: "
                + ", ".join(f"{reg} {x[1]:.3f}" for reg, x in v["regions"].items())
            )
    cam = b["camera"]
    lines.append(
        "  camera (value +- standard error): "
        + ", ".join(
            f"{k} {v:.6g} +- {se:.2g}" for k, (v, se) in cam.items() if not k.startswith(("r", "t"))
        )
    )
    for name, t in b["tests"].items():
        moved = (
            f", moving a plane by up to {t['change']:.4f} mm (matters above {t['matters_mm']:.4f})"
            if "change" in t
            else ""
        )
        lines.append(
            f"  {name}: chi-square {t['chi2']:.0f} would drop by {t['gain']:.1f} with "
            f"{t['dof']} more parameter(s) (significant above {t['limit']:.1f}){moved}: "
            + ("added" if t["added"] else "not supported")
        )
    if b["uncertainty"]:
        lines.append(
            "  predicted 3D error (1 sigma) of triangulated points: "
            + "; ".join(
                f"{u['board']} at {u['distance_mm']:.0f} mm: median {u['median_mm']:.4f}, "
                f"95 % {u['p95_mm']:.4f} mm"
                for u in b["uncertainty"]
            )
        )
    return lines


def _origin_rows(per_slit: list[dict[str, Any]]) -> list[str]:
    """Report lines: runs of slits whose planes came from the same source, with their RMS."""
    rows: list[str] = []
    i = 0
    while i < len(per_slit):
        j = i
        while j + 1 < len(per_slit) and per_slit[j + 1]["origin"] == per_slit[i]["origin"]:
            j += 1
        run = per_slit[i : j + 1]
        what = run[0]["origin"] or "no plane"
        slits = f"slit {i}" if i == j else f"slits {i}-{j}"
        rms = [x["rms_mm"] for x in run if math.isfinite(x["rms_mm"])]
        res = ""
        if rms:
            res = f", RMS {min(rms):.4f}" + (f"-{max(rms):.4f}" if len(rms) > 1 else "") + " mm"
        rows.append(f"{slits}: {what}{res}")
        i = j + 1
    return rows
