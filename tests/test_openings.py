"""The opening that follows leaning stripes (multislit.stripes.openings)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from multislit.stripes.openings import FOLLOW_ANGLES_DEG, follow_stripe_opening, line_kernel


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_follow_stripe_opening_is_opencvs_line_opening(dtype):
    # at every pixel, borders included, the opening along the slope's nearest direction equals
    # OpenCV's erosion with that line followed by the dilation with the line reflected (the
    # opening proper: some digital lines are not symmetric about their centre); upright slopes
    # (within 7.5 deg) leave ``opened`` alone
    rng = np.random.default_rng(3)
    hp = rng.integers(0, 200, (40, 50)).astype(dtype)
    rows, cols = (a.ravel() for a in np.mgrid[0:40, 0:50])
    for length in (5, 7, 9):
        for a in FOLLOW_ANGLES_DEG:
            slope = np.full(rows.size, np.tan(np.radians(a + 3.0)))  # binned to a
            opened = np.zeros_like(hp)
            follow_stripe_opening(hp, opened, length, rows, cols, slope)
            k = line_kernel(length, a)
            ref = cv2.dilate(cv2.erode(hp, k), k[::-1, ::-1])
            if a == 0.0:
                assert not opened.any()
            else:
                np.testing.assert_array_equal(opened, np.maximum(ref, 0))


def test_follow_stripe_opening_only_raises():
    # the result is the larger of the given opening and the one along the stripe
    rng = np.random.default_rng(4)
    hp = rng.integers(0, 200, (30, 30)).astype(np.uint8)
    opened = np.full_like(hp, 150)
    rows, cols = (a.ravel() for a in np.mgrid[0:30, 0:30])
    follow_stripe_opening(hp, opened, 7, rows, cols, np.ones(rows.size))
    ref = cv2.morphologyEx(hp, cv2.MORPH_OPEN, line_kernel(7, 45.0))  # a symmetric line
    np.testing.assert_array_equal(opened, np.maximum(ref, 150))
