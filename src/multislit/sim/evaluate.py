"""Scoring results against the simulator's ground truth (for tests, benchmarks and rig design)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from multislit.errors import MultislitError

#: A true stripe-centre pixel is resolvable where the slits' light there stands at least this
#: many noise sigmas out of the pixel's noise (the truth's ``stripe_snr``).
RESOLVABLE_SNR = 3.0


def _runs(t: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """The runs of equal labels along the rows of ``t`` (H, W): row, first column, length and
    label of each run (R,), and the length of its run at every pixel (H, W)."""
    h, w = t.shape
    x = t.ravel()
    new = np.ones(x.size, bool)
    new[1:] = x[1:] != x[:-1]
    new[::w] = True
    starts = np.flatnonzero(new)
    length = np.diff(np.r_[starts, x.size])
    return starts // w, starts % w, length, x[starts], np.repeat(length, length).reshape(h, w)


def _true_centres(truth_slit: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Every true stripe-centre pixel, taken across the stripe: the middle of each run (>= 2 px)
    of one slit label along a row where the stripe is nearer vertical than horizontal (its run
    along the row no longer than the one along the column at the run's middle), else the
    middle of each run along a column (a stripe leaning towards the horizontal, whose row runs
    are long and whose centres lie at whole columns).

    Returns
    -------
    row, col : (C,) float64, px (a row-run middle at a whole row, a column-run middle at a
        whole column)
    slit : (C,) int64
    by_column : (C,) bool, the middle of a column run
    """
    t = np.asarray(truth_slit)
    rr, rc, rn, rl, row_len = _runs(t)
    cc, cr, cn, cl, col_len_t = _runs(t.T)
    col_len = col_len_t.T
    ok = (rl >= 0) & (rn >= 2)
    ok &= rn <= col_len[rr, rc + (rn - 1) // 2]
    ok_c = (cl >= 0) & (cn >= 2)
    ok_c &= cn < row_len[cr + (cn - 1) // 2, cc]
    row = np.r_[rr[ok], cr[ok_c] + (cn[ok_c] - 1) / 2].astype(np.float64)
    col = np.r_[rc[ok] + (rn[ok] - 1) / 2, cc[ok_c]].astype(np.float64)
    slit = np.r_[rl[ok], cl[ok_c]].astype(np.int64)
    by_column = np.r_[np.zeros(int(ok.sum()), bool), np.ones(int(ok_c.sum()), bool)]
    return row, col, slit, by_column


def _centres_in(truth_slit: NDArray, mask: NDArray | None) -> tuple:
    """:func:`_true_centres` whose pixel lies in ``mask`` (all without one)."""
    row, col, slit, by_col = _true_centres(truth_slit)
    if mask is not None:
        h, w = truth_slit.shape
        r = np.clip(np.round(row).astype(int), 0, h - 1)
        c = np.clip(np.round(col).astype(int), 0, w - 1)
        inside = mask[r, c]
        row, col, slit, by_col = row[inside], col[inside], slit[inside], by_col[inside]
    return row, col, slit, by_col


def _near_centres(u: NDArray, v: NDArray, centres: tuple, h: int, w: int) -> list[NDArray]:
    """Per true centre (of :func:`_true_centres`), the indices of the points within 1.5 px of
    it across the stripe: in its row for a row-run middle, in its column for a column-run
    middle."""
    row, col, _, by_col = centres
    r = np.clip(np.round(v).astype(int), 0, h - 1)
    c = np.clip(np.round(u).astype(int), 0, w - 1)
    by_row_pts: dict[int, list[int]] = {}
    by_col_pts: dict[int, list[int]] = {}
    for i, (rr, cc) in enumerate(zip(r.tolist(), c.tolist(), strict=True)):
        by_row_pts.setdefault(rr, []).append(i)
        by_col_pts.setdefault(cc, []).append(i)
    out = []
    empty = np.zeros(0, int)
    for y, x, along_col in zip(row.tolist(), col.tolist(), by_col.tolist(), strict=True):
        if along_col:
            idx = np.asarray(by_col_pts.get(int(x), empty), int)
            out.append(idx[np.abs(v[idx] - y) <= 1.5])
        else:
            idx = np.asarray(by_row_pts.get(int(y), empty), int)
            out.append(idx[np.abs(u[idx] - x) <= 1.5])
    return out


def _score(
    ident, truth_slit: NDArray, mask: NDArray | None, stripe_snr: NDArray | None = None
) -> dict:
    """Points, correct, wrong (all and at confidence >= 0.5) and coverage, within ``mask``;
    with ``stripe_snr``, the coverage of the resolvable centres too."""
    h, w = truth_slit.shape
    ok = ident.identified
    u, v, k = ident.u[ok], ident.v[ok], ident.slit[ok]
    r = np.clip(np.round(v).astype(int), 0, h - 1)
    c = np.clip(np.round(u).astype(int), 0, w - 1)
    cand = np.stack([truth_slit[r, np.clip(c + d, 0, w - 1)] for d in (0, -1, 1)], 1)
    # a point on a stripe leaning towards the horizontal can round onto the pixel above or
    # below its run: where its row has no stripe, its column's neighbours count
    off_row = ~(cand >= 0).any(1)
    cand_col = np.stack([truth_slit[np.clip(r + d, 0, h - 1), c] for d in (-1, 1)], 1)
    cand = np.concatenate([cand, np.where(off_row[:, None], cand_col, -1)], axis=1)
    correct = (cand == k[:, None]).any(1)
    wrong = ~correct & (cand >= 0).any(1)
    hi = ident.confidence[ok] >= 0.5
    centres = _centres_in(truth_slit, mask)
    if mask is not None:
        inside = mask[r, c]
        u, v, k = u[inside], v[inside], k[inside]
        correct, wrong, hi = correct[inside], wrong[inside], hi[inside]
    near = _near_centres(u, v, centres, h, w)
    hit = np.array(
        [bool(np.any(k[idx] == lab)) for idx, lab in zip(near, centres[2], strict=True)], bool
    )
    n_pts = len(u)
    n = max(n_pts, 1)
    n_centres = len(centres[0])
    out = {
        "points": int(n_pts),
        "correct": float(correct.sum() / n),
        "wrong": float(wrong.sum() / n),
        "wrong_confident": float((wrong & hi).sum() / n),
        "coverage": float(hit.sum()) / max(n_centres, 1),
        "centres": n_centres,
    }
    if stripe_snr is not None:
        cr = np.clip(np.round(centres[0]).astype(int), 0, h - 1)
        cc = np.clip(np.round(centres[1]).astype(int), 0, w - 1)
        seen = np.asarray(stripe_snr)[cr, cc] >= RESOLVABLE_SNR
        out["coverage_resolvable"] = float(hit[seen].sum()) / max(int(seen.sum()), 1)
        out["centres_resolvable"] = int(seen.sum())
    return out


def identification_metrics(ident, truth_slit: NDArray) -> dict:
    """Score an identification against the simulator's per-pixel truth.

    correct : share of output points whose slit is the true one at their pixel (or a neighbour
        in the row: a centre can round onto the stripe's edge pixel)
    wrong_confident : share of output points that are wrong and have confidence >= 0.5
    coverage : share of true stripe-centre pixels that have an output point of that slit within
        1.5 px across the stripe. A true centre is taken across the stripe: the middle of each
        lit run of one slit along a row (the point within 1.5 px in the same row), or, where
        the stripe leans towards the horizontal (its runs along the rows are longer than those
        along the columns), the middle of each run along a column (the point within 1.5 px in
        the same column)
    """
    m = _score(ident, truth_slit, None)
    return {key: m[key] for key in ("points", "correct", "wrong_confident", "coverage")}


def object_metrics(
    ident, truth_slit: NDArray, truth_object: NDArray, stripe_snr: NDArray | None = None
) -> dict[str, dict]:
    """:func:`identification_metrics` on the objects and on the backdrop apart.

    Parameters
    ----------
    ident : an identification (``u``, ``v``, ``slit``, ``confidence``, ``identified``)
    truth_slit : (H, W) int, the truth's ``slit`` (-1: no stripe)
    truth_object : (H, W) bool, the truth's ``object`` (True: an object, False: the backdrop
        or nothing)
    stripe_snr : (H, W) float32, the truth's ``stripe_snr``: with it, each scores dict also
        holds ``coverage_resolvable``, the coverage of the true stripe-centre pixels where the
        stripe stands at least :data:`RESOLVABLE_SNR` noise sigmas out of the pixel's noise,
        and ``centres_resolvable``, how many there are

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
    return {
        "object": _score(ident, truth_slit, obj, stripe_snr),
        "backdrop": _score(ident, truth_slit, ~obj, stripe_snr),
    }


#: Why a true stripe-centre pixel has no point of its slit (:func:`coverage_losses`).
LOSSES = ("covered", "no_centre", "unlinked", "segment_unidentified", "point_left_out", "wrong")


def coverage_losses(
    ident, truth_slit: NDArray, mask: NDArray | None = None, counts: bool = False
) -> dict[str, float]:
    """Where the coverage of :func:`identification_metrics` is lost.

    Each true stripe-centre pixel (taken across the stripe, as the coverage takes it) is put in
    one class, by the output point nearest it across the stripe (in its row, or in its column
    where the stripe leans towards the horizontal; within 1.5 px): ``covered`` (a point of its slit), ``no_centre`` (no point at all),
    ``unlinked`` (a centre in no segment), ``segment_unidentified`` (no point of its segment
    was identified), ``point_left_out`` (its segment was identified, this point not: the rows
    at a segment's ends, or the order check) or ``wrong`` (another slit).

    Parameters
    ----------
    ident : an identification (``u``, ``v``, ``slit``, ``confidence``, ``segment``)
    truth_slit : (H, W) int, the truth's ``slit`` (-1: no stripe)
    mask : (H, W) bool, only the true stripe-centre pixels in it count (e.g. the truth's
        ``object``); default all
    counts : give the numbers of pixels instead of shares

    Returns
    -------
    dict class -> share of the true stripe-centre pixels (they sum to 1), or their number
    """
    h, w = truth_slit.shape
    seg = ident.segment
    seg_id = np.zeros(int(seg.max()) + 2 if len(seg) else 1, bool)
    seg_id[seg[(ident.slit >= 0) & (seg >= 0)]] = True
    u, v = np.asarray(ident.u, np.float64), np.asarray(ident.v, np.float64)
    count = dict.fromkeys(LOSSES, 0)
    centres = _centres_in(truth_slit, mask)
    near = _near_centres(u, v, centres, h, w)
    row, col, slit, by_col = centres
    for idx, y, x, lab, along_col in zip(
        near, row.tolist(), col.tolist(), slit.tolist(), by_col.tolist(), strict=True
    ):
        if idx.size == 0:
            count["no_centre"] += 1
            continue
        if np.any(ident.slit[idx] == lab):
            count["covered"] += 1
            continue
        i = idx[np.argmin(np.abs(v[idx] - y) if along_col else np.abs(u[idx] - x))]
        if ident.slit[i] >= 0:
            count["wrong"] += 1
        elif seg[i] < 0:
            count["unlinked"] += 1
        elif seg_id[seg[i]]:
            count["point_left_out"] += 1
        else:
            count["segment_unidentified"] += 1
    if counts:
        return {k: float(v) for k, v in count.items()}
    n = max(len(row), 1)
    return {k: v / n for k, v in count.items()}
