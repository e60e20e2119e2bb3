"""The opening that follows leaning stripes (multislit.stripes.openings)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from multislit.stripes.openings import (
    FOLLOW_ANGLES_DEG,
    _follow_lines,
    follow_stripe_opening,
    line_kernel,
    stripe_opening,
    vertical_opening,
)
from multislit.stripes.slope import lean_map, slope_sigma


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_follow_stripe_opening_is_opencvs_line_opening(dtype):
    # at every pixel the dot threshold selects (here all: opened 0, tau < 0), borders included,
    # the opening along the cell's direction equals OpenCV's erosion with that line followed by
    # the dilation with the line reflected (the opening proper: some digital lines are not
    # symmetric about their centre); upright cells (within 7.5 deg) are left alone
    rng = np.random.default_rng(3)
    hp = rng.integers(1, 200, (42, 50)).astype(dtype)
    for length in (5, 7, 9):
        for a in FOLLOW_ANGLES_DEG:
            ang = np.full((10, 12), a + 3.0)  # cells of 4 px, binned to a; the last take 6 px
            opened = np.zeros_like(hp)
            follow_stripe_opening(hp, opened, length, ang, 4, -0.5)
            k = line_kernel(length, a)
            ref = cv2.dilate(cv2.erode(hp, k), k[::-1, ::-1])
            if a == 0.0:
                assert not opened.any()
            else:
                np.testing.assert_array_equal(opened, ref)


def test_follow_stripe_opening_only_where_cut_and_leaning():
    rng = np.random.default_rng(4)
    hp = rng.integers(0, 200, (32, 32)).astype(np.uint8)
    opened = np.full_like(hp, 100)
    ang = np.full((8, 8), np.nan)
    ang[:4] = 45.0  # the top half leans; the bottom half has no direction
    out = opened.copy()
    follow_stripe_opening(hp, out, 7, ang, 4, 10.0)
    ref = cv2.morphologyEx(hp, cv2.MORPH_OPEN, line_kernel(7, 45.0))  # a symmetric line
    cut = hp.astype(float) - 100 > 10.0 + 5.0
    top = np.zeros(hp.shape, bool)
    top[:16] = True
    want = np.where(top & cut, np.maximum(ref, 100), 100)
    np.testing.assert_array_equal(out, want)


def test_lean_map_reads_the_stripes_direction():
    yy, xx = np.mgrid[0:200, 0:200].astype(np.float32)
    for a in (-45.0, -30.0, -15.0, 0.0, 15.0, 30.0, 45.0):
        u = xx - 100 - np.tan(np.radians(a)) * (yy - 100)
        img = 100 * np.exp(-(((u % 20) - 10) ** 2) / 4)  # stripes 20 px apart
        m = lean_map(img.astype(np.float32), 4.5)
        assert m.shape == (50, 50)
        assert abs(np.nanmedian(m[5:45, 5:45]) - a) < 4.0, a
    assert np.isnan(lean_map(np.zeros((64, 64), np.float32), 4.5)).all()


def test_stripe_opening_cells_limit_where_it_follows_stripes():
    rng = np.random.default_rng(3)
    hp = (rng.random((64, 48)) * 200).astype(np.uint8)
    whole = stripe_opening(hp, 7, 5.0)
    shape = lean_map(hp, slope_sigma(7)).shape
    np.testing.assert_array_equal(stripe_opening(hp, 7, 5.0, cells=np.ones(shape, bool)), whole)
    np.testing.assert_array_equal(
        stripe_opening(hp, 7, 5.0, cells=np.zeros(shape, bool)), vertical_opening(hp, 7)
    )
    with pytest.raises(ValueError, match="cells must have the lean map's shape"):
        stripe_opening(hp, 7, 5.0, cells=np.ones((3, 3), bool))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_follow_lines_round_angles_as_numpy(rng, dtype):
    ang = rng.uniform(-100, 100, (23, 31)).astype(dtype)
    ang.flat[:40] = np.arange(-97.5, 200.0, 7.5)[:40]  # half steps: rounded half to even
    ang.flat[rng.integers(0, ang.size, 30)] = np.nan
    line, leaning = _follow_lines(ang)
    step = FOLLOW_ANGLES_DEG[1] - FOLLOW_ANGLES_DEG[0]
    mid = len(FOLLOW_ANGLES_DEG) // 2
    want = np.rint(np.nan_to_num(ang.astype(np.float64)) / step).astype(np.int64) + mid
    want = np.clip(want, 0, len(FOLLOW_ANGLES_DEG) - 1)
    want[want == mid] = -1
    assert np.array_equal(line, want) and leaning
    assert np.all(line[np.isnan(ang)] == -1) and line.flat[1] == 0  # -90 deg: the outermost
    none, leaning = _follow_lines(np.where(np.abs(ang) < 7.5, ang, np.nan))
    assert not leaning and np.all(none == -1)
