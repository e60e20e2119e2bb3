"""The refinement's compiled strip kernels against plain formulations: the strips' layout (the
centre line by least squares along each segment, the rows beyond its ends and the image's),
the opening along the centre line in image coordinates and the refill of the dots along it,
bit for bit, and Steger's steps in batches of points; the refinement whatever the order of
the points, and on leaning stripes with dots against the truth."""

from __future__ import annotations

import math

import cv2
import numpy as np

from multislit.stripes import extract_slits, refine_centres

from .test_refine_fast import _plain_refill, _segment_points
from .test_slits import Truth, _errors, render


def test_strip_layout_matches_polyfit():
    """Each stacked row's centre line, slope and bend are those of np.polyfit's parabola through the
    segment's points within W rows of the row (cut at the segment's ends; beyond them the end
    row's, read at the image row the stacked row repeats), on curved segments with gaps; the
    strips are those of the segments with an active point, each point in its own row."""
    from multislit.stripes.refine import _segment_rows, _strip_layout

    rng = np.random.default_rng(21)
    seg, rows, span = _segment_points(rng, n_seg=9, h=150, R=12)
    rows = rows.astype(np.int64)
    h, W, pad = 150, 12, 6
    _, order, skey, inner = _segment_rows(seg, rows, span, 2)
    u = 20.0 + 15.0 * seg + 0.2 * rows + 4e-3 * (rows - 70.0) ** 2 + rng.normal(0, 0.3, seg.size)
    active = (seg >= 0) & (inner >= 0) & (seg != 4)  # segment 4 has no active point: no strip
    got_rows, centre, slope, bend, bounds, where = _strip_layout(
        seg, order, skey, span, u, active, W, pad, h
    )
    kept = [g for g in np.unique(seg[seg >= 0]) if active[seg == g].any()]
    assert 4 not in kept and len(kept) == bounds.size - 1
    for s, g in enumerate(kept):
        on = seg == g
        rg, ug = rows[on], u[on]
        r0, r1 = rg.min(), rg.max()
        virtual = np.arange(r0 - pad, r1 + pad + 1)
        t = np.arange(bounds[s], bounds[s + 1])
        assert t.size == virtual.size
        np.testing.assert_array_equal(got_rows[t], np.clip(virtual, 0, h - 1))
        for j, vr in enumerate(virtual):
            sel = np.abs(rg - min(max(vr, r0), r1)) <= W
            p = np.polyfit(rg[sel] - r0, ug[sel], 2 if sel.sum() >= 3 else 1)
            x = got_rows[t[j]] - r0
            assert abs(centre[t[j]] - np.polyval(p, x)) < 1e-8
            assert abs(slope[t[j]] - np.polyval(np.polyder(p), x)) < 1e-9
            assert abs(bend[t[j]] - (p[0] if p.size == 3 else 0.0)) < 1e-10
    np.testing.assert_array_equal(where < 0, ~active)
    np.testing.assert_array_equal(got_rows[where[active]], rows[active])


def _strips(rng, n=400, d=21):
    """Random strips (N, D) float32 in three strips (one of one row), their first columns
    stepping by -1, 0 or 1 px a row, and a centre line (N,) px whose slope wanders from -1 to
    1 px a row (curved)."""
    strip = rng.normal(20, 10, (n, d)).astype(np.float32)
    bounds = np.array([0, 150, 151, n], np.int64)
    col0 = 300 + np.cumsum(rng.integers(-1, 2, n)).astype(np.int64)
    slope = np.clip(np.cumsum(rng.normal(0, 0.15, n)), -1, 1)
    return strip, bounds, col0, 300.0 + np.cumsum(slope)


def test_line_extreme_matches_pixel_by_pixel_line():
    """The min and max over each pixel's digital curve along the centre line (rows within its
    strip, columns in image coordinates, samples beyond the strip left out), made a run of rows
    at a time, equal the pixel-by-pixel values, bit for bit; with steps of the first column
    and leaning, curved and upright lines."""
    from multislit.stripes.refine import _line_extreme

    rng = np.random.default_rng(23)
    strip, bounds, col0, centre = _strips(rng)
    centre[200:300] = 310.0 + rng.uniform(-0.2, 0.2, 100)  # upright lines
    col0[200:260] = 310  # no steps: rows run together
    n, d = strip.shape
    strip_of = np.repeat(np.arange(bounds.size - 1), np.diff(bounds))
    for r in (1, 3):
        for take_max in (False, True):
            got = _line_extreme(strip, col0, bounds, centre, r, take_max)
            want = strip.copy()
            for t in range(n):
                for k in range(d):
                    for j in range(-r, r + 1):
                        q = t + j
                        x = centre[q] - centre[t] if 0 <= q < n else 0.0
                        dk = int(np.sign(x) * np.floor(abs(x) + 0.5))
                        kk = k + dk + col0[t] - col0[q] if 0 <= q < n else -1
                        if 0 <= q < n and strip_of[q] == strip_of[t] and 0 <= kk < d:
                            v = strip[q, kk]
                            want[t, k] = max(want[t, k], v) if take_max else min(want[t, k], v)
            np.testing.assert_array_equal(got, want)


def test_refill_strips_matches_plain_fill():
    """The compiled refill equals the plain one bit for bit on dense random dots: runs
    interpolated along each run's parabola between strips' rows with other first columns, runs longer
    than the limit and runs at a strip's first or last row kept at the opening."""
    from multislit.stripes.refine import _refill_strips

    rng = np.random.default_rng(22)
    strip, bounds, col0, centre = _strips(rng)
    slope = np.gradient(centre)
    bend = rng.normal(0, 0.02, centre.size)
    opened = strip - np.float32(3)
    mask = np.where(rng.random(strip.shape) < 0.45, 255, 0).astype(np.uint8)
    mask[100:140, 5] = 255  # a run longer than the limit
    mask[0] = 255  # runs at the first row
    got = _refill_strips(strip, opened, mask, slope, bend, col0, bounds, 10)
    want = _plain_refill(strip, opened, mask, slope, bend, col0, bounds, 10)
    np.testing.assert_array_equal(got, want)
    assert (got != strip).mean() > 0.15 and (got[mask == 0] == strip[mask == 0]).all()
    assert (got[100:140, 5] == opened[100:140, 5]).all()


def test_shrink_bend_takes_the_noise_off():
    """The bends the given centres' noise puts in the centre line are shrunk to nought, a
    curved stripe's kept: the noise scale from pairs of rows 2 W + 1 apart inside each strip's
    segment rows (the true bend there constant), against the truth."""
    from multislit.stripes.refine import _shrink_bend

    rng = np.random.default_rng(31)
    W, pad, s = 12, 6, 2e-4
    bounds = np.array([0, 300, 620, 900], np.int64)
    true = np.zeros(900)
    true[620:] = 0.005  # one strip on a curved stripe (u'' = 0.01 px/row^2)
    bend = true + rng.normal(0, s, 900)
    got = _shrink_bend(bend, bounds, pad, W)
    # straight strips: the noise shrunk, 68 % of the rows to nought (|b| < s), the rest by
    # 1 - s^2 / b^2: RMS 0.577 s for Gaussian noise (measured 0.571 s)
    assert np.mean(got[:620] == 0) > 0.6
    assert np.sqrt(np.mean(got[:620] ** 2)) < 0.62 * s
    # the curved strip within 0.5 % of its noisy bend (s^2 / b^2 ~ 2e-3)
    np.testing.assert_allclose(got[620:], bend[620:], rtol=5e-3)
    assert (got[620:] < bend[620:]).all()
    # too few pairs (windows wider than the strips): nought everywhere
    assert not _shrink_bend(bend, bounds, pad, 200).any()


def test_steger_batches_give_each_point_its_own_centre():
    """Steger's step for many points at once (batches, a part batch at the end) gives each
    point, bit for bit, what it gets alone; near the image's borders (the strip holding the
    clamped columns) too, and a point whose window leaves its strip is not usable."""
    from multislit.stripes.refine import _steger_kernel

    rng = np.random.default_rng(13)
    n_rows, w, ss, d = 30, 64, 1.7, 21
    rad = math.ceil(3.0 * ss) + 1
    u = rng.uniform(-0.5, w - 0.5, 45)
    u[:4] = (-0.5, 0.3, w - 1.2, w - 0.5)
    u[4:20] = 33.3 + rng.uniform(-1, 1, 16)  # on the stripe: steps that converge
    where = rng.integers(0, n_rows, u.size)
    col0 = np.full(n_rows, 23, np.int64)
    for i in range(4):  # the border points' rows hold the clamped columns about them
        col0[where[i]] = math.floor(min(max(u[i], 0), w - 1)) - rad - 3
    cols = np.clip(col0[:, None] + np.arange(d)[None, :], 0, w - 1)
    strip = rng.normal(0, 5, (n_rows, d)) + 80 * np.exp(-0.5 * ((cols - 33.3) / 2.0) ** 2)
    strip = strip.astype(np.float32)
    active = rng.random(u.size) < 0.9
    active[:4] = True
    idx = np.flatnonzero(active)
    m, ok = _steger_kernel(strip, col0, where, u, idx, ss, 1.0, w)
    assert ok.sum() > 10 and (~ok[active]).any() and ok[:4].any()
    np.testing.assert_array_equal(m[~active], u[~active])
    far = np.flatnonzero(active & (np.abs(u - 33.3) > 6))[4:]  # outside the strip
    assert far.size and not ok[far].any()
    for i in range(u.size):
        m1, ok1 = _steger_kernel(strip, col0, where, u, idx[idx == i], ss, 1.0, w)
        assert m1[i] == m[i] and ok1[i] == ok[i], i


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


def test_refine_leaning_stripes_with_dots_against_truth():
    """On stripes leaning ~19 deg with dense dots, the strips follow the stripes (the opening
    and the refill along them): the refined centres are unbiased and much less noisy than the
    extraction's; the extraction's noise sigma given or measured gives the same centres."""
    img0, truth = render(seed=15, n_stripes=5, dots_per_stripe=150)
    h, w = img0.shape
    shear = np.float32([[1, 0.35, -0.35 * h / 2], [0, 1, 0]])
    img = cv2.warpAffine(img0, shear, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    leaning = Truth(truth.u0, truth.tilt + 0.35, truth.curv, None, 0.0, truth.dots, h)
    ex = extract_slits(img, stripe_width_px=3.06, dot_size_px=1.9)
    args = (img, ex.u, ex.v, ex.segment, ex.stripe_width_px, ex.dot_size_px)
    u, ok = refine_centres(*args)
    u_n, ok_n = refine_centres(*args, noise_sigma=ex.noise_sigma)
    np.testing.assert_array_equal(u_n, u)
    np.testing.assert_array_equal(ok_n, ok)
    assert ok.mean() > 0.6, ok.mean()
    e_ex, _, near = _errors(ex.u[ok], ex.v[ok], leaning)
    e_ref = _errors(u[ok], ex.v[ok], leaning)[0][near]
    e_ex = e_ex[near]
    rms_ex, rms_ref = np.sqrt(np.mean(e_ex**2)), np.sqrt(np.mean(e_ref**2))
    assert abs(np.mean(e_ref)) < 0.03, np.mean(e_ref)
    assert rms_ref < 0.6 * rms_ex, (rms_ref, rms_ex)
