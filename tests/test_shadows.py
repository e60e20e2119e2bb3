"""Shadows in the labelling: a stripe broken off on one surface wants a caster in front."""

from __future__ import annotations

import numpy as np

from multislit.identify.graph import label_pieces
from multislit.identify.shadows import SHADOW_COST, shadow_factors


def _span(rows: list[tuple[int, int, float, float, float]], w: int, n: int) -> np.ndarray:
    span = np.full((w, n, 3), np.nan)
    for win, k, lo, hi, r in rows:
        span[win, k] = (lo, hi, r)
    return span


def test_a_gap_at_one_range_wants_a_caster_in_front_of_it():
    """Slit 3 lights a wall (range 1000 mm) from psi 0 to 0.1 and from 0.2 on: its rays in
    between lit something nearer. Window 2 under slit 3 lies there at 900 mm (a caster);
    window 4 under slit 3 lies outside the gap. A window that under slit 3 lies in the gap at
    the wall's range would be the wall's stripe there: no gap."""
    span = _span(
        [
            (0, 3, 0.0, 0.1, 1000.0),
            (1, 3, 0.2, 0.3, 1000.0),
            (2, 3, 0.12, 0.18, 900.0),
            (4, 3, 0.31, 0.35, 900.0),
        ],
        5,
        6,
    )
    label = np.array([3, 3, -1, -1, -1])
    sure = np.array([True, True, False, False, False])
    slit, cost, start, cand = shadow_factors(span, label, sure)
    assert slit.tolist() == [3] and cost.tolist() == [SHADOW_COST]
    assert cand[start[0] : start[1]].tolist() == [2]
    span[3, 3] = (0.1, 0.2, 998.0)
    slit, _, _, _ = shadow_factors(span, label, sure)
    assert slit.size == 0


def test_no_gap_where_the_stripe_resumes_on_another_surface():
    span = _span(
        [(0, 3, 0.0, 0.1, 1000.0), (1, 3, 0.2, 0.3, 1100.0), (2, 3, 0.12, 0.18, 900.0)], 3, 6
    )
    slit, _, _, cand = shadow_factors(span, np.array([3, 3, -1]), np.array([True, True, False]))
    assert slit.size == 0 and cand.size == 0


def test_one_of_the_candidates_casts_the_shadow():
    """Two candidates prefer slit 0 by 1 and by 3 nats over slit 2; a gap in slit 2 that
    costs 4 nats unexplained goes to the one that gives up least (the first), and the other
    keeps its slit."""
    n = 4
    unary = np.zeros((2, n))
    unary[0, 0], unary[1, 0] = 1.0, 3.0
    none = np.zeros(0, np.int64)
    common = {
        "gap_a": none,
        "gap_b": none,
        "gap_bonus": np.zeros((0, n)),
        "gap_continuous": np.zeros((0, n), bool),
        "gap_rows": none,
        "cont_a": none,
        "cont_b": none,
        "cont_bonus": np.zeros(0),
        "cont_change": np.zeros(0),
        "coupling": 6.0,
        "repeat_penalty": 30.0,
        "split_penalty": 0.0,
    }
    alone = label_pieces(unary, **common)
    assert alone.slit.tolist() == [0, 0]
    factors = (np.array([2]), np.array([4.0]), np.array([0, 2]), np.array([0, 1]))
    cast = label_pieces(unary, **common, factors=factors)
    assert cast.slit.tolist() == [2, 0]


def test_a_slit_missing_between_its_neighbours_wants_a_caster():
    """Slits 2 and 4 run on at 1000 mm over psi 0 to 0.3 and slit 3 is not there between 0.1
    and 0.2 (it lights the wall elsewhere): something nearer took it. Window 5 under slit 3
    lies in front of the stretch (a caster); window 6, a stripe at the wall's range under slit
    3, would mean slit 3 is there."""
    span = _span(
        [
            (0, 2, 0.0, 0.3, 1000.0),
            (1, 4, 0.0, 0.3, 1000.0),
            (2, 3, 0.0, 0.1, 1000.0),
            (3, 3, 0.2, 0.3, 1000.0),
            (5, 3, 0.12, 0.18, 900.0),
        ],
        7,
        6,
    )
    label = np.array([2, 4, 3, 3, -1, -1, -1])
    sure = np.array([True, True, True, True, False, False, False])
    slit, _, start, cand = shadow_factors(span, label, sure)
    assert slit.tolist() == [3] and cand[start[0] : start[1]].tolist() == [5]
    # without the break in slit 3's own stripe, its neighbours alone say it is missing
    sure[3] = False
    label[3] = -1
    span[3] = np.nan
    slit, _, start, cand = shadow_factors(span, label, sure)
    assert slit.tolist() == [3] and cand[start[0] : start[1]].tolist() == [5]
    # a stripe there at the wall's range under slit 3: not missing
    span[6, 3] = (0.1, 0.3, 1000.0)
    slit, _, _, _ = shadow_factors(span, label, sure)
    assert slit.size == 0
