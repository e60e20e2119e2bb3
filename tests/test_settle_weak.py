"""The weak centres (found by the ridge response alone) kept or dropped by their segment."""

import numpy as np

from multislit.stripes.chains import WEAK_LENGTH_FACTOR, WEAK_TAIL_FACTOR, settle_weak


def _segment(n_strong: int, n_tail: int):
    """One segment along rows: ``n_strong`` strong centres, then ``n_tail`` weak ones."""
    n = n_strong + n_tail
    along = np.arange(n, dtype=float)
    strong = np.r_[np.ones(n_strong, bool), np.zeros(n_tail, bool)]
    return along, np.zeros(n, np.int64), strong


def test_a_weak_tail_is_kept_from_min_length_and_dropped_below():
    m = 10
    tail = int(WEAK_TAIL_FACTOR * m)
    along, seg, strong = _segment(30, tail)
    assert np.all(settle_weak(along, seg, strong, m) == 0)
    along, seg, strong = _segment(30, tail - 1)
    out = settle_weak(along, seg, strong, m)
    assert np.all(out[strong] == 0) and np.all(out[~strong] == -1)


def test_a_segment_of_weak_centres_only_needs_the_longer_run():
    m = 10
    need = int(WEAK_LENGTH_FACTOR * m)
    assert need > WEAK_TAIL_FACTOR * m  # a lone faint streak must run longer than a tail
    along, seg, strong = _segment(0, need)
    assert np.all(settle_weak(along, seg, strong, m) == 0)
    along, seg, strong = _segment(0, need - 1)
    assert np.all(settle_weak(along, seg, strong, m) == -1)


def test_a_much_fainter_tail_is_cut_from_its_stripe():
    along, seg, strong = _segment(30, 15)
    peak = np.r_[np.full(30, 100.0), np.full(15, 30.0)]  # below 0.4 of the stripe's peak
    out = settle_weak(along, seg, strong, 10, peak=peak)
    assert np.all(out[:30] == 0) and np.all(out[30:] == -1)
