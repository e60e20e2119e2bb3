"""The stages of the identification by the dots' geometry, against the simulator's truth."""

from __future__ import annotations

import itertools
import os
import subprocess
import sys

import cv2
import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import multislit as ms
from multislit.calibrate import calibrate_capture
from multislit.errors import IdentificationError, MeasurementError
from multislit.identify import IdentifyOptions, identify
from multislit.identify.evidence import dot_evidence, frame_dots, window_stripes
from multislit.identify.frame import synthetic_rig
from multislit.identify.geometric import _brightness_ratio, _near_changes, _regularity
from multislit.identify.graph import label_pieces
from multislit.identify.pieces import continuations, gaps, gaps_across, group_medians, windows
from multislit.identify.result import SOURCES
from multislit.reconstruct import ScanOptions, rig_of
from multislit.sim.evaluate import identification_metrics
from multislit.stripes import extract_slits


@pytest.fixture(scope="module", params=["steps", "holes"])
def frame(request, small_calibrated, small_capture):
    """One scan of the half-size capture: its image, truth, extraction and rig."""
    cap = ms.Capture.open(small_capture)
    img = cap.image(small_capture / "scans" / f"{request.param}.png")
    ref = small_calibrated.reference
    ex = extract_slits(img, ref.stripe_width_px, ref.dot_size_px)
    truth = np.load(small_capture / "truth" / f"{request.param}.npz")["slit"]
    return img, truth, ex, rig_of(small_calibrated.calibration), ref


def _true_slit(truth, u, v):
    h, w = truth.shape
    return truth[
        np.clip(np.rint(v).astype(int), 0, h - 1), np.clip(np.rint(u).astype(int), 0, w - 1)
    ]


def test_a_window_s_own_dots_prefer_its_slit(frame):
    """Each window of 24 stripe points on one slit, scored alone by the dots the calibrated
    dot projector puts beside it: the true slit scores best in most (half size, holes and
    steps: 84-85 %; by chance 1 in 25)."""
    _, truth, ex, rig, ref = frame
    _, rays = rig.camera.rays(np.stack([ex.u, ex.v], axis=1))
    win = windows(ex.segment.astype(np.int64), ex.v, 24)
    direction, peak = window_stripes(ex, win.order, win.start)
    frame = frame_dots(ex, ref.spacing_px)
    ev = dot_evidence(rig, rays, win.order, win.start, frame, direction, peak)
    assert ev.llr.shape == (win.num_windows, rig.num_slits, 2)
    right = []
    for i in range(win.num_windows):
        p = win.order[win.start[i] : win.start[i + 1]]
        t = _true_slit(truth, ex.u[p], ex.v[p])
        t = t[t >= 0]
        vals, n = np.unique(t, return_counts=True)
        if len(p) < 12 or len(t) < 0.8 * len(p) or n.max() < 0.9 * len(t):
            continue  # not one slit's stripe
        s = ev.llr[i].sum(axis=1)
        right.append(np.argmax(np.where(np.isfinite(s), s, -np.inf)) == vals[n.argmax()])
    assert len(right) > 200
    assert np.mean(right) >= 0.75, np.mean(right)


def test_the_frame_s_labels_say_where_they_came_from(frame):
    img, truth, ex, rig, ref = frame
    ident = identify(img, ref, rig, extraction=ex)
    assert ident.method == "geometry" and ident.pieces is not None
    pl = ident.pieces
    assert len(pl.slit) == ident.num_segments
    assert set(np.unique(pl.source)) <= set(range(len(SOURCES)))
    # a piece left out carries no slit; one given a slit names its dots or its neighbours
    assert np.all((pl.slit >= 0) == (pl.source > 0))
    lab = ident.slit >= 0
    assert np.all(pl.slit[ident.segment[lab]] == ident.slit[lab])
    # every piece left out is counted once, under one reason
    assert set(ident.dropped) == {
        "out_of_volume",
        "rests_on_a_cut",
        "too_little_evidence",
        "low_confidence",
    }
    assert sum(ident.dropped.values()) == np.count_nonzero(pl.slit < 0) > 0
    # and the labels are right: the wall and the objects of the half-size scans together
    t = _true_slit(truth, ident.u[lab], ident.v[lab])
    known = t >= 0
    assert np.mean(ident.slit[lab][known] != t[known]) < 0.01
    assert np.count_nonzero(lab) > 0.8 * len(ident.u)


def test_a_prior_is_refused_by_the_geometry(frame, small_calibrated):
    img, _, ex, rig, ref = frame
    first = identify(img, ref, rig, extraction=ex)
    with pytest.raises(IdentificationError, match="previous"):
        identify(img, ref, rig, extraction=ex, previous=first)
    res = ms.scan_image(img, ref, small_calibrated.calibration)
    with pytest.raises(MeasurementError, match="template"):
        ms.scan_image(img, ref, small_calibrated.calibration, ScanOptions(), previous=res)
    options = ScanOptions(identification=IdentifyOptions(method="template"))
    ms.scan_image(img, ref, small_calibrated.calibration, options, previous=res)


def test_gaps_pair_the_pieces_side_by_side_and_measure_their_spacing():
    """Three vertical stripes over 20 rows, 10 px apart, then 25 px to a fourth: the gaps
    pair neighbours only, and the wide one is 2.5 times the one beside it."""
    v = np.repeat(np.arange(20.0), 4)
    u = np.tile([100.0, 110.0, 120.0, 145.0], 20)
    piece = np.tile(np.arange(4), 20).astype(np.int64)
    g = gaps(u, v, piece, max_gap_px=30.0, min_rows=3)
    assert sorted(zip(g.a.tolist(), g.b.tolist(), strict=True)) == [(0, 1), (1, 2), (2, 3)]
    assert np.all(g.rows == 20)
    pairs = list(zip(g.a.tolist(), g.b.tolist(), strict=True))
    ratio = dict(zip(pairs, g.spacing_ratio.tolist(), strict=True))
    assert ratio[(0, 1)] == pytest.approx(1.0) and ratio[(2, 3)] == pytest.approx(2.5)
    assert ratio[(1, 2)] == pytest.approx(10.0 / 17.5)
    # farther apart than max_gap_px: no gap
    near = gaps(u, v, piece, 20.0, 3)
    assert (2, 3) not in zip(near.a.tolist(), near.b.tolist(), strict=True)


def test_a_gap_between_unlike_stripes_couples_less():
    """Four vertical stripes 10 px apart over 20 rows, the third twice and the fourth six
    times as bright as the first (their peaks varying along them): each gap's brightness ratio
    is that of its stripes' geometric mean peaks, and a gap's coupling weight falls with the
    ratio as with an irregular width; a gap of like stripes and regular width weighs 1."""
    v = np.repeat(np.arange(20.0), 4)
    u = np.tile([100.0, 110.0, 120.0, 130.0], 20)
    piece = np.tile(np.arange(4), 20).astype(np.int64)
    shade = np.repeat(np.linspace(0.5, 1.5, 20), 4)  # the same along every stripe
    peak = np.tile([10.0, 10.0, 20.0, 120.0], 20) * shade
    g = gaps(u, v, piece, max_gap_px=30.0, min_rows=3)
    pairs = list(zip(g.a.tolist(), g.b.tolist(), strict=True))
    ratio = dict(zip(pairs, _brightness_ratio(peak, g), strict=True))
    assert ratio[(0, 1)] == pytest.approx(1.0)
    assert ratio[(1, 2)] == pytest.approx(0.5) and ratio[(2, 3)] == pytest.approx(1 / 6)
    w = _regularity(np.array([1.0, 1.0, 1.0, 1.3, np.nan]), np.array([1.0, 0.5, 1 / 6, 1.0, 2.0]))
    assert w[0] == pytest.approx(1.0)
    assert 1.0 > w[1] > w[2] > 0.0 and w[2] < 0.4
    assert w[3] == pytest.approx(np.exp(-0.5))  # a width off by the spacing tolerance
    assert w[1] == pytest.approx(w[4])  # no gap beside: the brightness alone


def test_gaps_across_stripes_that_lean_towards_the_horizontal():
    """Three near-horizontal stripes found along the columns (rows 10, 20, 30 over columns
    0-39) and a vertical one beside them (column 60): the horizontal ones pair along the
    columns, the lower slit's side first (below for stripes leaning right going down, above
    for those leaning left), their points paired column by column; no pieces: no gaps."""
    cols = np.arange(40.0)
    u = np.r_[np.tile(cols, 3), np.full(40, 60.0)]
    v = np.r_[np.repeat([10.0, 20.0, 30.0], 40), np.arange(40.0)]
    piece = np.repeat(np.arange(4), 40).astype(np.int64)
    by_col = np.r_[np.ones(120, bool), np.zeros(40, bool)]
    for lean, pairs in ((1.5, {(1, 0), (2, 1)}), (-1.5, {(0, 1), (1, 2)})):
        angle = np.where(by_col, lean, 0.0)
        g = gaps_across(u, v, piece, by_col, angle, max_gap_px=30.0, min_rows=3)
        got = set(zip(g.a.tolist(), g.b.tolist(), strict=True))
        # along the rows a horizontal stripe meets the vertical one in one row: no gap
        assert got == pairs
        for i, (a, b) in enumerate(zip(g.a, g.b, strict=True)):
            pa = g.a_order[g.a_start[i] : g.a_start[i + 1]]
            pb = g.b_order[g.b_start[i] : g.b_start[i + 1]]
            assert np.all(piece[pa] == a) and np.all(piece[pb] == b)
            assert len(pa) == 40 and np.array_equal(u[pa], u[pb])
    # without pieces found along the columns: the gaps along the rows alone
    g = gaps_across(u, v, piece, np.zeros(160, bool), np.zeros(160), 30.0, 3)
    assert g.num_gaps == gaps(u, v, piece, 30.0, 3).num_gaps
    none = gaps(u, v, np.full(160, -1), 30.0, 3)
    assert none.num_gaps == 0 and none.a_start.tolist() == [0]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(-1, 6), st.integers(0, 40), st.floats(0.0, 30.0)),
        max_size=60,
    )
)
def test_continuations_are_the_pieces_that_start_below_another_s_end(points):
    """Piece b continues piece a when b's first point lies 0 < dv <= 12 rows below a's last
    and within 4 px + dv / 2 of its column: every such pair, each once per (a, b), none else."""
    piece = np.array([p[0] for p in points], np.int64)
    v = np.array([p[1] for p in points], np.float64)
    u = np.array([p[2] for p in points], np.float64)
    a, b = continuations(u, v, piece, 12, 4.0)
    want = set()
    ids = np.unique(piece[piece >= 0])
    for pa in ids:
        m = np.flatnonzero(piece == pa)
        last = m[np.lexsort((m, v[m]))][-1]
        for pb in ids:
            if pb == pa:
                continue
            n = np.flatnonzero(piece == pb)
            first = n[np.lexsort((n, v[n]))][0]
            dv = v[first] - v[last]
            if 0 < dv <= 12 and abs(u[first] - u[last]) <= 4.0 + 0.5 * dv:
                want.add((int(pa), int(pb)))
    got = list(zip(a.tolist(), b.tolist(), strict=True))
    assert len(got) == len(set(got))
    assert set(got) == want


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 5), st.one_of(st.floats(-1e3, 1e3), st.just(float("nan")))),
        max_size=40,
    )
)
def testgroup_medians_are_numpy_s_medians_of_the_finite_values(rows):
    g = np.array([r[0] for r in rows], np.int64)
    x = np.array([r[1] for r in rows], float)
    got = group_medians(x, g, 6)
    for k in range(6):
        y = x[(g == k) & np.isfinite(x)]
        if y.size:
            assert got[k] == pytest.approx(np.median(y), rel=1e-12, abs=1e-12)
        else:
            assert np.isnan(got[k])


@pytest.fixture(scope="module")
def scenes(scenes_capture):
    """The half-size identification scenes (25 slits, seed 11), calibrated, identified by the
    dots' geometry: per scene its metrics against the truth."""
    res = calibrate_capture(scenes_capture)
    rig = rig_of(res.calibration)
    cap = ms.Capture.open(scenes_capture)
    out = {}
    for p in cap.scans:
        ident = identify(cap.image(p), res.reference, rig)
        truth = np.load(scenes_capture / "truth" / f"{p.stem}.npz")["slit"]
        out[p.stem] = identification_metrics(ident, truth)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["holes", "spheres", "steps", "freeform", "textured"])
def test_the_scenes_meet_the_identification_bars(scenes, scene):
    """>= 99.5 % of the points correct, <= 0.1 % wrong with confidence >= 0.5, >= 90 % of the
    lit stripe-centre pixels with a point (measured, correct / wrong / coverage %: holes
    99.89/0.07/95.1, spheres 99.93/0.05/94.9, steps 99.91/0.03/97.8, freeform 99.99/0.00/93.6,
    textured 100/0/97.8; benchmarks/bench_identify.py --scale 0.5 --seed 11)."""
    m = scenes[scene]
    assert m["points"] > 3000
    assert m["correct"] >= 0.995, m
    assert m["wrong_confident"] <= 0.001, m
    assert m["coverage"] >= 0.90, m


def test_the_kernels_warm_up_frame_is_identified_by_the_geometry():
    """The frame that compiles the kernels runs the whole identification: every stripe gets its
    slit (stripe k, slit k) and dots are matched, with one stripe's dots missing too."""
    reference, images, rig = synthetic_rig()
    for image in images:
        ident = identify(image, reference, rig)
        ok = ident.slit >= 0
        assert set(ident.slit[ok].tolist()) == set(range(5))
        stripe = np.rint((ident.u[ok] - 31.0) / 25.0).astype(int)
        assert np.mean(stripe == ident.slit[ok]) > 0.99
        assert ident.dots is not None and len(ident.dots) > 100


def test_the_dots_are_matched_only_when_asked():
    """``match_dots=False`` leaves the identification's dots out and changes no label."""
    reference, images, rig = synthetic_rig()
    with_dots = identify(images[0], reference, rig)
    without = identify(images[0], reference, rig, match_dots=False)
    assert with_dots.dots is not None and len(with_dots.dots) > 100
    assert without.dots is None
    np.testing.assert_array_equal(without.slit, with_dots.slit)
    np.testing.assert_array_equal(without.confidence, with_dots.confidence)
    with pytest.raises(IdentificationError, match="match_dots must be True or False"):
        identify(images[0], reference, rig, match_dots="no")


def test_two_stripes_side_by_side_couple_once_however_long():
    """Four windows of a stripe (continuing one another) beside four of a stripe the dots
    put at slit 1: each window's own dots say 2 nats for slit 5. Coupled gap by gap, the
    neighbouring slit 2 wins (4 gaps x 6 nats x 24/40 rows); as one pair sharing a coupling of
    6 nats, the dots' 8 nats win."""
    n = 8
    unary = np.zeros((8, n))
    unary[:4, 1] = 50.0  # the left stripe's windows: slit 1
    unary[4:, 5] = 2.0  # the right stripe's: a little for slit 5
    ga, gb = np.arange(4), np.arange(4, 8)
    ca, cb = np.r_[0, 1, 2, 4, 5, 6], np.r_[1, 2, 3, 5, 6, 7]
    common = {
        "gap_a": ga,
        "gap_b": gb,
        "gap_bonus": np.zeros((4, n)),
        "gap_continuous": np.ones((4, n), bool),
        "gap_rows": np.full(4, 24),
        "cont_a": ca,
        "cont_b": cb,
        "cont_bonus": np.full(6, 10.0),
        "cont_change": np.full(6, 10.0),
        "coupling": 6.0,
        "repeat_penalty": 30.0,
        "split_penalty": 0.0,
    }
    each = label_pieces(unary, **common)
    once = label_pieces(unary, **common, gap_pair=np.zeros(4, np.int64))
    assert each.slit[4:].tolist() == [2] * 4
    assert once.slit[4:].tolist() == [5] * 4
    assert each.slit[:4].tolist() == once.slit[:4].tolist() == [1] * 4


@pytest.mark.parametrize("vouches", [False, True])
def test_a_slit_that_rests_on_a_cut_alone_is_named_so(vouches):
    """Two pieces joined by a continuation: the first one's dots say slit 2 (20 nats), the
    second's say nothing. Across a continuation that vouches the second takes slit 2 with it;
    across one that does not (a cut, where two slits' stripes may meet) its slit 2 rests on
    the continuation alone: confidence 0, and the labelling says why."""
    n = 5
    unary = np.zeros((2, n))
    unary[0, 2] = 20.0
    none = np.zeros(0, np.int64)
    lab = label_pieces(
        unary,
        none,
        none,
        np.zeros((0, n)),
        np.zeros((0, n), bool),
        none,
        np.array([0]),
        np.array([1]),
        np.array([5.0]),
        np.array([0.0]),
        coupling=6.0,
        repeat_penalty=30.0,
        split_penalty=1.5,
        cont_ties=np.array([vouches]),
    )
    assert lab.slit.tolist() == [2, 2]
    assert lab.rests_on_cut.tolist() == [False, not vouches]
    assert (lab.confidence[1] == 0.0) == (not vouches)
    assert lab.confidence[0] > 0.99


def _chain_score(labels, unary, kinds, coupling, penalty, split, bonus, change):
    """The labelling's total log-likelihood on a chain of pieces (piece i and i + 1 joined
    by a gap, kind 0, or a continuation, kind 1), as the labelling's terms define it."""
    total = sum(unary[i, k] for i, k in enumerate(labels))
    for i, kind in enumerate(kinds):
        a, b = labels[i], labels[i + 1]
        if kind == 1:
            total += bonus if a == b else -change
        elif b == a + 1:
            total += coupling
        else:
            total -= penalty if a == b else split
    return total


@settings(max_examples=40, deadline=None)
@given(
    unary=st.lists(st.floats(-10, 10), min_size=20, max_size=20),
    kinds=st.lists(st.integers(0, 1), min_size=4, max_size=4),
    terms=st.lists(st.floats(0, 12), min_size=5, max_size=5),
)
def test_the_labelling_of_a_chain_is_its_max_marginals(unary, kinds, terms):
    """On a graph without loops max-product belief propagation is exact: each piece's
    beliefs are the best total log-likelihood of the labellings that give it each slit (up to
    a constant), worked out here over every labelling of five pieces and four slits."""
    n, m = 4, 5
    u = np.array(unary).reshape(m, n)
    coupling, penalty, split, bonus, change = terms
    gaps_ = [i for i, kind in enumerate(kinds) if kind == 0]
    conts = [i for i, kind in enumerate(kinds) if kind == 1]
    lab = label_pieces(
        u,
        np.array(gaps_, np.int64),
        np.array(gaps_, np.int64) + 1,
        np.zeros((len(gaps_), n)),
        np.ones((len(gaps_), n), bool),
        np.full(len(gaps_), 40),
        np.array(conts, np.int64),
        np.array(conts, np.int64) + 1,
        np.full(len(conts), bonus),
        np.full(len(conts), change),
        coupling=coupling,
        repeat_penalty=penalty,
        split_penalty=split,
    )
    best = np.full((m, n), -np.inf)
    for labels in itertools.product(range(n), repeat=m):
        x = _chain_score(labels, u, kinds, coupling, penalty, split, bonus, change)
        for i, k in enumerate(labels):
            best[i, k] = max(best[i, k], x)
    got = lab.belief - lab.belief.max(axis=1, keepdims=True)
    want = best - best.max(axis=1, keepdims=True)
    np.testing.assert_allclose(got, want, atol=0.02)


@pytest.mark.parametrize(
    ("cut", "labels", "left_out"),
    [
        (False, (3, 4), (16, 31)),  # two windows of one piece: the rows next to the change
        (True, (3, 4), (16, 31)),  # across a cut of the linked stripe: the same
        (True, (3, 3), None),  # one slit across the cut: nothing left out
        (True, (3, -1), None),  # the window after the cut not labelled: nothing to leave out
    ],
)
def test_rows_next_to_a_change_of_slit_along_a_stripe_are_left_out(cut, labels, left_out):
    """A linked stripe of 48 rows in two windows of 24 (one piece, or two pieces across a cut
    at row 24): where their slits differ, the points within 8 rows of their boundary (rows 16
    to 31) are left out, whether or not the stripe was cut there."""
    along = np.arange(48, dtype=np.float64)
    segment = np.where(along < 24, 0, 1) if cut else np.zeros(48, np.int64)
    win = windows(segment.astype(np.int64), along, 24)
    assert win.num_windows == 2
    out = _near_changes(along, win, np.array(labels), np.zeros(2, np.int64))
    want = np.zeros(48, bool)
    if left_out is not None:
        want[left_out[0] : left_out[1] + 1] = True
    assert out.tolist() == want.tolist()
    # two stripes that only follow one another in the index are not one stripe
    assert not _near_changes(along, win, np.array(labels), np.array([0, 1])).any()


def test_the_evidence_does_not_depend_on_the_threads(frame):
    """The windows' and the gaps' evidence spread over Numba's threads: one thread and two give
    the same identification, bit for bit."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one core: nothing to spread")
    img, _, ex, rig, ref = frame
    before = numba.get_num_threads(), cv2.getNumThreads()
    try:
        ms.set_threads(1)
        one = identify(img, ref, rig, extraction=ex)
        ms.set_threads(2)
        two = identify(img, ref, rig, extraction=ex)
    finally:
        numba.set_num_threads(before[0])
        cv2.setNumThreads(before[1])
    assert np.count_nonzero(one.slit >= 0) > 100
    np.testing.assert_array_equal(one.slit, two.slit)
    np.testing.assert_array_equal(one.confidence, two.confidence)


@pytest.mark.parametrize("threads", [0, -1, 2.0, True, "2", 10**6])
def test_set_threads_refuses_what_is_not_a_count_of_threads(threads):
    with pytest.raises(ms.MultislitError, match="threads must be"):
        ms.set_threads(threads)


def test_set_threads_takes_numpy_s_integers():
    before = numba.get_num_threads(), cv2.getNumThreads()
    try:
        ms.set_threads(np.int64(1))
        assert numba.get_num_threads() == 1
        assert cv2.getNumThreads() == 1
    finally:
        numba.set_num_threads(before[0])
        cv2.setNumThreads(before[1])


@pytest.mark.slow
def test_frames_identified_on_two_threads_at_once_on_numba_s_work_queue(tmp_path):
    """Numba's work-queue threading layer (where a machine has neither OpenMP nor TBB) aborts
    the process when two threads enter a parallel kernel at once; the identification's
    parallel kernels take turns there."""
    script = tmp_path / "two_threads.py"
    script.write_text(
        "import threading\n"
        "import numba\n"
        "from multislit.identify import identify\n"
        "from multislit.identify.frame import synthetic_rig\n"
        "reference, images, rig = synthetic_rig()\n"
        "def work():\n"
        "    for _ in range(3):\n"
        "        for image in images:\n"
        "            identify(image, reference, rig)\n"
        "threads = [threading.Thread(target=work) for _ in range(2)]\n"
        "[t.start() for t in threads]\n"
        "[t.join() for t in threads]\n"
        "print('layer', numba.threading_layer())\n"
    )
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue", "NUMBA_NUM_THREADS": "2"}
    run = subprocess.run(
        [sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "layer workqueue" in run.stdout
