"""Slit labels for the automatic projector calibration: stripe order plus dot identification.

The dot identification (:mod:`multislit.identify`) labels the stripe centres of
``calibration/slits.png`` reliably where it labels them, but the target's 45 degree faces
foreshorten the dot pattern, so it leaves many centres (most of the ramp) unlabelled, and the
slits then lie on one face each: their planes are undetermined.

:func:`label_by_order` uses the order of the stripes instead. The target is concave (two walls
and a ramp meeting in a corner), so along an image row the stripes on it appear in their slit
order, without occlusions. Per row, the centres on the target's faces are sorted by u and cut
into *runs* where the gap to the next centre is far above the local spacing (a marker's dark
square or a shadow hides a stripe there) or far below it (a double detection). Within a run,
consecutive centres belong to consecutive slits, so each run only needs one offset
``slit - rank``:

1. from the dots: the confidence-weighted mode of ``slit - rank`` over the run's identified
   centres, accepted only when enough of them agree (:class:`OrderParams`);
2. from the rows above and below (repeated until nothing changes): a centre of an unlabelled
   run whose nearest centre in the neighbouring row (within a stripe width) is labelled votes
   for that label; again the run needs agreeing votes.

Runs without agreeing evidence stay unlabelled (-1); nothing is guessed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from multislit.calibrate.capture_camera import camera_from_capture
from multislit.calibrate.row_order import OrderParams, apply_run_offsets, row_runs, run_offsets
from multislit.calibrate.slit_points import EXTRACT_OPTIONS, points_on_faces, transfer_labels
from multislit.geometry.camera import F64
from multislit.identify import capture_reference, identify_template
from multislit.io import Capture
from multislit.stripes import extract_slits


@dataclass(frozen=True, eq=False)
class OrderLabels:
    """Result of :func:`label_by_order`.

    u, v : (K,) float64, px, stripe centres (extraction of the calibration settings)
    slit : (K,) int, slit number, -1 where unlabelled
    face : (K,) int, target face of the centre (-1: none; 0 for all when the faces are unknown)
    run : (K,) int, run id (-1: centre left out of the runs)
    dot_slit : (K,) int, the dot identification's label transferred to the centres (-1: none)
    stats : counts for reports
    """

    u: F64
    v: F64
    slit: NDArray[np.intp]
    face: NDArray[np.intp]
    run: NDArray[np.intp]
    dot_slit: NDArray[np.intp]
    stats: dict[str, int] = field(default_factory=dict)


def _nearest_in_row(u_from: F64, v_from: F64, u: F64, v: F64, tol_px: float) -> NDArray[np.intp]:
    """Index of the nearest (u_from, v_from) point in the same row within ``tol_px`` (-1: none).

    A point with two candidates within ``tol_px`` gets -1 (ambiguous).
    """
    return transfer_labels(u_from, v_from, np.arange(len(u_from)), u, v, tol_px=tol_px)


def _identification(image: NDArray, cap: Capture, reference: Any) -> Any:
    if reference is None:
        reference = capture_reference(cap)
    # the anchors: the dots' own evidence (the template matching's segment votes)
    return identify_template(image, reference)


def _faces(cap: Capture, uv: F64, camera: Any) -> NDArray[np.intp]:
    if cap.target is None or not cap.target.faces:
        return np.zeros(len(uv), np.intp)
    if camera is None:
        camera = camera_from_capture(cap, use_stripes=False).from_markers
    return points_on_faces(camera, uv, cap.target.faces)[1]


def label_by_order(
    image: NDArray,
    capture: str | Path | Capture,
    *,
    camera: Any = None,
    identification: Any = None,
    reference: Any = None,
    params: OrderParams | None = None,
) -> OrderLabels:
    """Label the stripe centres of a calibration image by their order in the row and the dots.

    Parameters
    ----------
    image : (H, W) the calibration slit image (``calibration/slits.png``)
    capture : capture folder or Capture (references, faces, num_slits)
    camera : a calibrated camera to tell which face each centre is on (default: calibrated here
        from the markers); without target faces all centres count as one surface
    identification : an :class:`~multislit.identify.Identification` of ``image`` (default: made
        here from the capture's references, or from ``reference``)
    reference : a prepared :class:`~multislit.identify.ReferenceSet` (default: prepared here)
    params : :class:`~multislit.calibrate.row_order.OrderParams` (default ``OrderParams()``)

    Returns
    -------
    OrderLabels (u, v, slit, ...), -1 for centres left unlabelled
    """
    p = params or OrderParams()
    cap = capture if isinstance(capture, Capture) else Capture.open(capture)
    img = np.asarray(image)
    n_slits = int(cap.num_slits)
    ex = extract_slits(img, **EXTRACT_OPTIONS)
    u, v = np.asarray(ex.u, float), np.asarray(ex.v, float)
    K = len(u)
    sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
    tol = p.match_px if p.match_px is not None else max(1.0, sw)
    empty = np.full(K, -1, np.intp)
    if K == 0:
        return OrderLabels(u, v, empty, empty, empty, empty, {"centres": 0})
    ident = identification if identification is not None else _identification(img, cap, reference)
    iu, iv = np.asarray(ident.u, float), np.asarray(ident.v, float)
    islit = np.asarray(ident.slit).astype(np.intp)
    iconf = np.asarray(ident.confidence, float)
    good = islit >= 0
    j = _nearest_in_row(iu[good], iv[good], u, v, max(1.0, 0.8 * sw))
    dot_slit = np.where(j >= 0, islit[good][np.maximum(j, 0)], -1).astype(np.intp)
    dot_conf = np.where(j >= 0, iconf[good][np.maximum(j, 0)], 0.0)

    face = _faces(cap, np.stack([u, v], axis=1), camera)
    run, rank = row_runs(u, v, (face >= 0) & (np.asarray(ex.segment) >= 0), p)
    n_runs = int(run.max()) + 1 if (run >= 0).any() else 0
    offset = run_offsets(run, rank, dot_slit, dot_conf, n_runs, p)
    slit = apply_run_offsets(run, rank, offset, n_slits)
    n_dots = int((slit >= 0).sum())

    # row-to-row propagation into runs the dots left unlabelled
    NONE = np.iinfo(np.intp).min
    rows = v.astype(np.int64)
    for _ in range(p.max_rounds):
        lab = slit >= 0
        free = (run >= 0) & ~lab & (offset[np.maximum(run, 0)] == NONE)
        if not free.any() or not lab.any():
            break
        vote = np.full(K, -1, np.intp)
        for dv in (-1, 1):
            jj = _nearest_in_row(u[lab], rows[lab] - dv, u[free], rows[free], tol)
            cand = np.where(jj >= 0, slit[lab][np.maximum(jj, 0)], -1)
            fi = np.flatnonzero(free)
            cur = vote[fi]
            vote[fi] = np.where(cur < 0, cand, np.where((cand >= 0) & (cand != cur), -2, cur))
        vote[vote == -2] = -1
        new = run_offsets(run, rank, vote, np.ones(K), n_runs, p)
        took = (new != NONE) & (offset == NONE)
        if not took.any():
            break
        offset = np.where(took, new, offset)
        slit = apply_run_offsets(run, rank, offset, n_slits)
    stats = {
        "centres": K,
        "on faces": int((face >= 0).sum()),
        "dot labels": int((dot_slit >= 0).sum()),
        "runs": n_runs,
        "labelled by dots": n_dots,
        "labelled": int((slit >= 0).sum()),
    }
    return OrderLabels(u, v, slit, face, run, dot_slit, stats)
