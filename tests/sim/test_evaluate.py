"""Scoring against the truth: true stripe centres taken across the stripe, at any lean."""

from types import SimpleNamespace

import numpy as np
import pytest

from multislit.sim import coverage_losses, identification_metrics, object_metrics
from multislit.sim.evaluate import _true_centres


def _stripe(shape, angle_deg, width, label, offset=0.0):
    """(H, W) int16 truth: one straight stripe of ``width`` px across, leaning ``angle_deg``
    from the vertical (positive: right going down) through the image's centre, shifted
    ``offset`` px across; -1 elsewhere."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(float)
    a = np.radians(angle_deg)
    # signed distance across the stripe (its direction is (sin a, cos a) in (u, v))
    d = (u - w / 2) * np.cos(a) - (v - h / 2) * np.sin(a) - offset
    t = np.full(shape, -1, np.int16)
    t[np.abs(d) <= width / 2] = label
    return t


def _ident(u, v, slit, conf=None, segment=None):
    u = np.asarray(u, float)
    slit = np.asarray(slit)
    return SimpleNamespace(
        u=u,
        v=np.asarray(v, float),
        slit=slit,
        confidence=np.ones(len(u)) if conf is None else np.asarray(conf, float),
        identified=slit >= 0,
        segment=np.zeros(len(u), int) if segment is None else np.asarray(segment),
    )


def test_near_vertical_stripes_keep_the_row_run_middles():
    truth = np.full((30, 40), -1, np.int16)
    truth[:, 3:6] = 0  # vertical, 3 px: centres at u = 4
    truth[:, 10:14] = 1  # 4 px: centres at u = 11.5
    for r in range(30):  # leaning 0.5 px per row (27 degrees)
        truth[r, 18 + r // 2 : 21 + r // 2] = 2
    truth[:, 37] = 3  # a run of 1 px: not a centre
    row, col, slit, by_col = _true_centres(truth)
    got = sorted(zip(slit.tolist(), col.tolist(), row.tolist(), by_col.tolist(), strict=True))
    assert got[:60] == [(0, 4.0, r, False) for r in range(30)] + [
        (1, 11.5, r, False) for r in range(30)
    ]
    # the leaning stripe: one row centre per row, away from its ends (where it is cut off,
    # its last columns cross less of it than a row does)
    lean = [(c, r) for k, c, r, b in got if k == 2 and 2 <= r <= 27]
    assert sorted(lean) == [(19.0 + r // 2, r) for r in range(2, 28)]
    assert not any(b for k, c, r, b in got if k == 2 and 2 <= r <= 27)
    assert 3 not in slit


@pytest.mark.parametrize("angle", [60.0, 75.0, 85.0, 90.0, -70.0])
def test_a_stripe_leaning_towards_the_horizontal_is_centred_along_the_columns(angle):
    truth = _stripe((60, 120), angle, 3.0, 7)
    row, col, slit, by_col = _true_centres(truth)
    assert (slit == 7).all()
    # one centre per column it crosses, on its centre line, taken along the column
    inner = (col > 20) & (col < 100)
    assert by_col[inner].all()
    a = np.radians(angle)
    on_line = (col - 60) * np.cos(a) - (row - 30) * np.sin(a)
    assert np.abs(on_line[inner]).max() <= 0.5
    assert len(np.unique(col[inner])) == inner.sum()


@pytest.mark.parametrize("angle", [0.0, 20.0, 40.0, -40.0])
def test_a_stripe_nearer_the_vertical_is_centred_along_the_rows(angle):
    truth = _stripe((80, 60), angle, 3.0, 2)
    row, col, slit, by_col = _true_centres(truth)
    inner = (row > 15) & (row < 65)
    assert not by_col[inner].any()
    assert len(np.unique(row[inner])) == inner.sum()


def test_coverage_of_a_leaning_stripe_counts_points_in_the_column():
    truth = _stripe((40, 100), 80.0, 3.0, 4)
    row, col, _, by_col = _true_centres(truth)
    keep = by_col
    row, col = row[keep], col[keep]
    # a point on every true centre (sub-pixel in v, whole columns): full coverage; the same
    # points 2 px off across the stripe cover nothing
    m = identification_metrics(_ident(col, row + 0.4, np.full(len(col), 4)), truth)
    assert m["coverage"] == pytest.approx(keep.sum() / len(keep))
    assert m["correct"] == 1.0
    off = identification_metrics(_ident(col, row + 2.0, np.full(len(col), 4)), truth)
    assert off["coverage"] == 0.0
    # half of them with the wrong slit: half covered, those wrong
    slit = np.where(np.arange(len(col)) % 2 == 0, 4, 5)
    half = object_metrics(_ident(col, row, slit), truth, np.ones(truth.shape, bool))["object"]
    assert half["coverage"] == pytest.approx(np.mean(slit == 4) * keep.sum() / len(keep))
    assert half["wrong"] == pytest.approx(np.mean(slit == 5))


def test_coverage_losses_follow_the_columns_of_a_leaning_stripe():
    truth = _stripe((40, 100), 80.0, 3.0, 1)
    row, col, _, by_col = _true_centres(truth)
    row, col = row[by_col], col[by_col]
    n = len(col)
    third = n // 3
    # the first third covered, the second unlinked, the rest without a point
    ident = _ident(
        col[: 2 * third],
        row[: 2 * third],
        np.r_[np.full(third, 1), np.full(third, -1)],
        segment=np.r_[np.zeros(third, int), np.full(third, -1)],
    )
    got = coverage_losses(ident, truth)
    total = len(_true_centres(truth)[0])
    assert got["covered"] == pytest.approx(third / total)
    assert got["unlinked"] == pytest.approx(third / total)
    assert got["no_centre"] == pytest.approx(1 - 2 * third / total)
    n = coverage_losses(ident, truth, counts=True)
    assert n["covered"] == third and sum(n.values()) == total
    assert sum(got.values()) == pytest.approx(1.0)


def test_resolvable_coverage_counts_the_centres_that_stand_out_of_the_noise():
    truth = _stripe((60, 40), 0.0, 3.0, 2)
    row, col, _, _ = _true_centres(truth)
    snr = np.zeros(truth.shape, np.float32)
    snr[truth >= 0] = 10.0
    snr[40:] = 1.0  # the stripe's lower third too faint to see
    # points on the upper half only: a third of the resolvable centres have none
    up = row < 30
    ident = _ident(col[up], row[up], np.full(up.sum(), 2))
    m = object_metrics(ident, truth, np.ones(truth.shape, bool), snr)["object"]
    assert m["coverage"] == pytest.approx(30 / 60)
    assert m["centres_resolvable"] == 40
    assert m["coverage_resolvable"] == pytest.approx(30 / 40)
    assert (
        "coverage_resolvable"
        not in object_metrics(ident, truth, np.ones(truth.shape, bool))["object"]
    )
