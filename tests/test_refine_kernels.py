"""The refinement's compiled slope and dot-refill kernels against plain formulations, bit for
bit: the slope Gaussian's pass along u (several taps per pass over the sums), its pass along v
at the runs' middles (several runs at a time), and the refill made only in the rows the
windows read, whatever the order of the points."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from multislit.stripes import extract_slits, refine_centres

from .test_refine_fast import _plain_slope_pass, _steger_setup
from .test_slits import render


def _reflect101(i: int, n: int) -> int:
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * n - 2 - i
    return i


@pytest.mark.parametrize("taps", [3, 5, 9, 37])
def test_slope_rows_match_tap_by_tap_sums(taps):
    """The pass along u, four taps per pass over the sums, equals the sums made tap by tap
    in order (NumPy float32), over whole columns and over a few rows, at the image's left and
    right borders (reflected columns) too; tap counts with and without a remainder of 4."""
    from multislit.stripes.refine import _slope_rows

    rng = np.random.default_rng(taps)
    w, h = 41, 70
    put = rng.random((w, h), np.float32) * 50
    pvt = rng.normal(0, 20, (w, h)).astype(np.float32)
    g = cv2.getGaussianKernel(taps, taps / 8.0, cv2.CV_32F).ravel()
    want_x, want_y = _plain_slope_pass(put, pvt, g)
    hx, hy = np.full((w, h), np.nan, np.float32), np.full((w, h), np.nan, np.float32)
    for c in range(w):
        _slope_rows(put, pvt, g, hx, hy, c, 0, h)
    np.testing.assert_array_equal(hx, want_x)
    np.testing.assert_array_equal(hy, want_y)
    part_x, part_y = np.full((w, h), np.nan, np.float32), np.full((w, h), np.nan, np.float32)
    for c in (0, 1, w // 2, w - 1):
        _slope_rows(put, pvt, g, part_x, part_y, c, 13, 45)
        np.testing.assert_array_equal(part_x[c, 13:45], want_x[c, 13:45])
        np.testing.assert_array_equal(part_y[c, 13:45], want_y[c, 13:45])
        assert np.isnan(part_x[c, :13]).all() and np.isnan(part_x[c, 45:]).all()


@pytest.mark.parametrize("n", [1, 3, 4, 9, 30])
def test_run_slopes_match_plain_sums(n):
    """The pass along v at the runs' middles, four runs at a time away from the borders,
    equals one run at a time summed in order of rows (NumPy float32), near the borders
    (reflected rows) too, with slopes clipped at +-1 and J_uu <= 0 among them."""
    from multislit.stripes.refine import _run_slopes

    rng = np.random.default_rng(n)
    w, h = 23, 90
    hx = rng.random((w, h), np.float32) * 10
    hx[3] = -1.0  # J_uu below its floor of 1e-6
    hy = rng.normal(0, 6, (w, h)).astype(np.float32)
    g = cv2.getGaussianKernel(37, 4.5, cv2.CV_32F).ravel()
    rk = g.size // 2
    edge = np.array([0, 5, rk - 1, rk, h - rk - 1, h - rk, h - 1])
    mids = np.concatenate([edge, rng.integers(0, h, n)])[: max(n, 1) + 3]
    cols = rng.integers(0, w, mids.size)
    cols[1] = 3
    got = _run_slopes(hx, hy, g, cols.astype(np.intp), mids.astype(np.intp))
    want = []
    for c, mid in zip(cols, mids, strict=True):
        juu = juv = np.float32(0.0)
        for i in range(-rk, rk + 1):
            q = _reflect101(mid + i, h)
            juu += g[i + rk] * hx[c, q]
            juv += g[i + rk] * hy[c, q]
        s = np.float32(-juv / max(juu, np.float32(1e-6)))
        want.append(min(max(s, np.float32(-1.0)), np.float32(1.0)))
    np.testing.assert_array_equal(got, np.array(want, np.float32))
    if mids.size > 8:
        assert (np.abs(got) == 1).any() and (np.abs(got) < 1).any()


def test_refill_covers_the_windows_in_any_point_order():
    """The dots are refilled in the rows the windows read, found per run from the points in
    row order or shuffled (a run met again after another in its column): every dot pixel a
    window holds is refilled, with the same values either way."""
    from multislit.stripes.refine import _refill_dots

    img, _ = render(seed=8)
    ex = extract_slits(img, stripe_width_px=3.06, dot_size_px=1.9)
    hp, mask, opened, slope, r, active, ss, length = _steger_setup(img, ex)
    rad = math.ceil(3.0 * ss) + 1
    u = ex.u.astype(float)
    dots = mask > 0
    w = img.shape[1]

    def refilled(perm):
        slit = np.where(dots, np.nan, hp).astype(np.float32)
        _refill_dots(hp, mask, opened, *slope(), slit, u[perm], r[perm], active[perm], rad, length)
        return slit

    in_order = refilled(np.arange(u.size))
    shuffled = refilled(np.random.default_rng(0).permutation(u.size))
    np.testing.assert_array_equal(shuffled, in_order)
    c0 = np.floor(np.clip(u, 0, w - 1)).astype(int)
    cols = np.clip(c0[:, None] + np.arange(-1 - rad, rad + 2)[None, :], 0, w - 1)
    rows = np.broadcast_to(r[:, None], cols.shape)
    read = in_order[rows[active], cols[active]]
    assert dots[rows[active], cols[active]].mean() > 0.1  # windows meet many dots
    assert np.isfinite(read).all()
    assert np.isnan(in_order[dots]).any()  # and only they are refilled


def test_refine_same_whatever_the_point_order():
    """refine_centres gives each point the same refined centre and ok, bit for bit, when the
    points come shuffled instead of in row order."""
    img, _ = render(seed=9, dots_per_stripe=100)
    ex = extract_slits(img, stripe_width_px=3.06, dot_size_px=1.9)
    perm = np.random.default_rng(1).permutation(ex.u.size)
    for degree in ("auto", 1, 2):
        u, ok = refine_centres(img, ex.u, ex.v, ex.segment, 3.06, 1.9, degree=degree)
        u_p, ok_p = refine_centres(
            img, ex.u[perm], ex.v[perm], ex.segment[perm], 3.06, 1.9, degree=degree
        )
        assert ok.mean() > 0.5
        np.testing.assert_array_equal(u_p, u[perm])
        np.testing.assert_array_equal(ok_p, ok[perm])
