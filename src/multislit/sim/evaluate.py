"""Scoring results against the simulator's ground truth (for tests, benchmarks and rig design)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from multislit.errors import MultislitError


def _true_centres(truth_slit: NDArray) -> list[tuple[int, float, int]]:
    """(row, column, slit) of every true stripe-centre pixel: the middle of each run (>= 2 px)
    of one slit label along a row."""
    h = truth_slit.shape[0]
    pad = np.full((h, 1), -1, truth_slit.dtype)
    t = np.hstack([pad, truth_slit, pad])
    rows, cols = np.nonzero(np.diff(t, axis=1) != 0)
    centres = []
    for row in np.unique(rows):
        b = cols[rows == row]
        for a, e in zip(b[:-1], b[1:], strict=True):
            lab = truth_slit[row, a]
            if lab >= 0 and e - a >= 2:
                centres.append((int(row), (a + e - 1) / 2, int(lab)))
    return centres


def _score(ident, truth_slit: NDArray, mask: NDArray | None) -> dict:
    """Points, correct, wrong (all and at confidence >= 0.5) and coverage, within ``mask``."""
    h, w = truth_slit.shape
    ok = ident.identified
    u, v, k = ident.u[ok], ident.v[ok], ident.slit[ok]
    r = np.clip(np.round(v).astype(int), 0, h - 1)
    cand = np.stack(
        [truth_slit[r, np.clip(np.round(u).astype(int) + d, 0, w - 1)] for d in (0, -1, 1)], 1
    )
    correct = (cand == k[:, None]).any(1)
    wrong = ~correct & (cand >= 0).any(1)
    hi = ident.confidence[ok] >= 0.5
    centres = _true_centres(truth_slit)
    if mask is not None:
        inside = mask[r, np.clip(np.round(u).astype(int), 0, w - 1)]
        u, v, k = u[inside], v[inside], k[inside]
        correct, wrong, hi = correct[inside], wrong[inside], hi[inside]
        centres = [c for c in centres if mask[c[0], min(int(round(c[1])), w - 1)]]
    got = 0
    pts: dict = {}
    for uu, vv, kk in zip(u, np.round(v).astype(int), k, strict=True):
        pts.setdefault((vv, kk), []).append(uu)
    for row, c, lab in centres:
        us = pts.get((row, lab))
        got += bool(us) and min(abs(x - c) for x in us) <= 1.5
    n_pts = len(u)
    n = max(n_pts, 1)
    return {
        "points": int(n_pts),
        "correct": float(correct.sum() / n),
        "wrong": float(wrong.sum() / n),
        "wrong_confident": float((wrong & hi).sum() / n),
        "coverage": got / max(len(centres), 1),
        "centres": len(centres),
    }


def identification_metrics(ident, truth_slit: NDArray) -> dict:
    """Score an identification against the simulator's per-pixel truth.

    correct : share of output points whose slit is the true one at their pixel (or a neighbour
        in the row: a centre can round onto the stripe's edge pixel)
    wrong_confident : share of output points that are wrong and have confidence >= 0.5
    coverage : share of true stripe-centre pixels (the middle of each lit run of one slit in a
        row) that have an output point of that slit within 1.5 px in the same row
    """
    m = _score(ident, truth_slit, None)
    return {key: m[key] for key in ("points", "correct", "wrong_confident", "coverage")}


def object_metrics(ident, truth_slit: NDArray, truth_object: NDArray) -> dict[str, dict]:
    """:func:`identification_metrics` on the objects and on the backdrop apart.

    Parameters
    ----------
    ident : an identification (``u``, ``v``, ``slit``, ``confidence``, ``identified``)
    truth_slit : (H, W) int, the truth's ``slit`` (-1: no stripe)
    truth_object : (H, W) bool, the truth's ``object`` (True: an object, False: the backdrop
        or nothing)

    Returns
    -------
    ``{"object": scores, "backdrop": scores}``; each scores dict holds ``points`` (output points
    whose pixel is in the region), ``correct``, ``wrong`` (points on another slit's stripe, all
    confidences) and ``wrong_confident`` (those with confidence >= 0.5) as shares of these
    points, ``coverage`` (share of the region's true stripe-centre pixels with a point of their
    slit within 1.5 px in the row) and ``centres`` (how many true stripe-centre pixels the
    region has).
    """
    obj = np.asarray(truth_object, bool)
    if obj.shape != np.shape(truth_slit):
        raise MultislitError(
            f"truth_object must have the shape of truth_slit {np.shape(truth_slit)}, got {obj.shape}"
        )
    return {"object": _score(ident, truth_slit, obj), "backdrop": _score(ident, truth_slit, ~obj)}


#: Why a true stripe-centre pixel has no point of its slit (:func:`coverage_losses`).
LOSSES = ("covered", "no_centre", "unlinked", "segment_unidentified", "point_left_out", "wrong")


def coverage_losses(ident, truth_slit: NDArray, mask: NDArray | None = None) -> dict[str, float]:
    """Where the coverage of :func:`identification_metrics` is lost.

    Each true stripe-centre pixel is put in one class, by the output point nearest it in its
    row (within 1.5 px): ``covered`` (a point of its slit), ``no_centre`` (no point at all),
    ``unlinked`` (a centre in no segment), ``segment_unidentified`` (no point of its segment
    was identified), ``point_left_out`` (its segment was identified, this point not: the rows
    at a segment's ends, or the order check) or ``wrong`` (another slit).

    Parameters
    ----------
    ident : an identification (``u``, ``v``, ``slit``, ``confidence``, ``segment``)
    truth_slit : (H, W) int, the truth's ``slit`` (-1: no stripe)
    mask : (H, W) bool, only the true stripe-centre pixels in it count (e.g. the truth's
        ``object``); default all

    Returns
    -------
    dict class -> share of the true stripe-centre pixels (they sum to 1)
    """
    h = truth_slit.shape[0]
    seg = ident.segment
    seg_id = np.zeros(int(seg.max()) + 2 if len(seg) else 1, bool)
    seg_id[seg[(ident.slit >= 0) & (seg >= 0)]] = True
    rows = np.clip(np.round(ident.v).astype(int), 0, h - 1)
    by_row: dict[int, NDArray] = {}
    order = np.argsort(rows, kind="stable")
    starts = np.flatnonzero(np.r_[True, rows[order][1:] != rows[order][:-1]])
    for a, e in zip(starts, np.r_[starts[1:], len(order)], strict=True):
        by_row[int(rows[order][a])] = order[a:e]
    count = dict.fromkeys(LOSSES, 0)
    centres = _true_centres(truth_slit)
    if mask is not None:
        w = truth_slit.shape[1]
        centres = [c for c in centres if mask[c[0], min(int(round(c[1])), w - 1)]]
    for row, c, lab in centres:
        idx = by_row.get(row, np.zeros(0, int))
        idx = idx[np.abs(ident.u[idx] - c) <= 1.5]
        if idx.size == 0:
            count["no_centre"] += 1
            continue
        if np.any(ident.slit[idx] == lab):
            count["covered"] += 1
            continue
        i = idx[np.argmin(np.abs(ident.u[idx] - c))]
        if ident.slit[i] >= 0:
            count["wrong"] += 1
        elif seg[i] < 0:
            count["unlinked"] += 1
        elif seg_id[seg[i]]:
            count["point_left_out"] += 1
        else:
            count["segment_unidentified"] += 1
    n = max(len(centres), 1)
    return {k: v / n for k, v in count.items()}
