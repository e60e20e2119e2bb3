"""The centre finder's compiled steps give what their NumPy formulations give."""

from __future__ import annotations

import numpy as np
import pytest

from multislit.stripes.centres import (
    _binomial_weights,
    _gather,
    _peak_samples,
    _row_maxima,
    _three_point,
)
from multislit.stripes.sizes import FWHM_PER_SIGMA


@pytest.mark.parametrize("dtype", (np.uint8, np.uint16, np.float32))
def test_peak_samples_match_gather_and_argmax(dtype):
    rng = np.random.default_rng(11)
    for h, w in ((1, 3), (5, 4), (40, 57)):
        img = rng.random((h, w)) * 200
        img[:, ::3] = np.round(img[:, ::3] / 50) * 50  # equal neighbours: ties
        img = img.astype(dtype)
        r = rng.integers(0, h, 300)
        c = rng.integers(0, w, 300)
        for taps in (1, 3, 5, 7):
            vals = _gather(img, r, c, np.arange(-2, 3), taps)
            j = 1 + np.argmax(vals[:, 1:4], axis=1)
            k = np.arange(r.size)
            cm, a, b, cc = _peak_samples(img, r, c, _binomial_weights(taps), np.zeros(0))
            np.testing.assert_array_equal(cm, c + (j - 2))
            np.testing.assert_array_equal(a, vals[k, j - 1])
            np.testing.assert_array_equal(b, vals[k, j])
            np.testing.assert_array_equal(cc, vals[k, j + 1])


def _three_point_ref(a, b, c, method):
    """The sub-pixel fit as NumPy array expressions."""
    ok = (a > 0) & (c > 0) & (b > 0)
    la = np.log(np.where(ok, a, 1.0))
    lb = np.log(np.where(ok, b, 1.0))
    lc = np.log(np.where(ok, c, 1.0))
    den_g = la - 2 * lb + lc
    ok &= den_g < 0
    width = np.where(ok, FWHM_PER_SIGMA * np.sqrt(-1.0 / np.where(ok, den_g, -1.0)), np.nan)
    den_p = a - 2 * b + c
    delta = np.where(den_p < 0, 0.5 * (a - c) / np.where(den_p < 0, den_p, -1.0), 0.0)
    if method == "gaussian":
        delta = np.where(ok, 0.5 * (la - lc) / np.where(ok, den_g, -1.0), delta)
    return np.clip(delta, -0.5, 0.5), width


def test_three_point_matches_array_expressions():
    rng = np.random.default_rng(12)
    a = rng.normal(50, 60, 4000)
    b = a + rng.normal(5, 20, a.size)
    c = rng.normal(50, 60, a.size)
    a[:500] = np.round(a[:500] / 20) * 20  # zeros and equal samples
    c[:500] = np.round(c[:500] / 20) * 20
    for method in ("gaussian", "parabolic"):
        for got, exp in zip(
            _three_point(a, b, c, method), _three_point_ref(a, b, c, method), strict=True
        ):
            np.testing.assert_array_equal(got, exp)
            np.testing.assert_array_equal(np.signbit(got), np.signbit(exp))


@pytest.mark.parametrize("dtype", (np.uint8, np.uint16, np.float32))
def test_row_maxima_threshold_in_image_type(dtype):
    rng = np.random.default_rng(13)
    img = (rng.integers(0, 6, (23, 31)) * 50).astype(dtype)  # plateaus and exact levels
    near = rng.random(img.shape) < 0.2
    mid = img[:, 1:-1]
    peak = (mid > img[:, :-2]) & (mid >= img[:, 2:])
    for thr in (-np.inf, -3.5, 0.0, 49.5, 50.0, float(np.float32(99.9)), 99.9, 250.0, 1e40, np.nan):
        for use_near in (False, True):
            expected = peak & (mid.astype(np.float64) > thr)
            if use_near:
                expected &= ~near[:, 1:-1]
            er, ec = np.nonzero(expected)
            rr, cc = _row_maxima(img, thr, near, use_near)
            np.testing.assert_array_equal(rr, er)
            np.testing.assert_array_equal(cc, ec + 1)
