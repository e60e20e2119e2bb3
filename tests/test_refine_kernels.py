"""The refinement's compiled slope and dot-refill kernels against plain formulations, bit for
bit: the slope Gaussian's pass along u (several taps per pass over the sums), its pass along v
at the runs' middles (several runs at a time), the refill made only in the rows the
windows read, whatever the order of the points, long runs met row after row, Steger's steps
in batches of points, and the opening along leaning stripes made only where it is read."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from multislit.stripes import extract_slits, opening_length, refine_centres, refine_half_rows
from multislit.stripes.separation import noise_from_difference

from .test_refine_fast import _plain_fill, _plain_slope_pass, _steger_setup
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


def test_refill_long_runs_met_row_after_row_keep_the_opening():
    """Runs of dot pixels longer than 2 ``length`` (stripe tops the opening cuts) met by the
    windows row after row, in row order and shuffled: every dot pixel the windows hold gets
    the plain fill_dots value (the opening), and the short runs around them their
    interpolation."""
    from multislit.stripes.refine import _refill_dots

    rng = np.random.default_rng(12)
    h, w, rad, length = 90, 60, 5, 3
    hp = rng.normal(0, 20, (h, w)).astype(np.float32)
    mask = np.where(rng.random((h, w)) < 0.3, 255, 0).astype(np.uint8)
    mask[10:70, 24:29] = 255  # runs of 60 rows, > 2 length
    mask[40, 26] = 0  # one cut in two, both still long
    opened = hp - np.float32(5)
    put, pvt = rng.random((w, h), np.float32), rng.normal(0, 0.3, (w, h)).astype(np.float32)
    g = cv2.getGaussianKernel(9, 2.0, cv2.CV_32F).ravel()
    r = np.arange(5, 80)
    u = 26.0 + rng.uniform(-2, 2, r.size)
    hx, hy = _plain_slope_pass(put, pvt, g)
    for perm in (np.arange(r.size), rng.permutation(r.size)):
        slope = (put, pvt, g, np.zeros((w, h), np.float32), np.zeros((w, h), np.float32))
        slit = np.where(mask > 0, np.nan, hp).astype(np.float32)
        _refill_dots(
            hp, mask, opened, *slope, slit, u[perm], r[perm], np.ones(r.size, bool), rad, length
        )
        long_seen = 0
        for q, c0 in zip(r, np.floor(u).astype(int), strict=True):
            for c in range(c0 - 1 - rad, c0 + 2 + rad):
                if mask[q, c]:
                    want = _plain_fill(hp, mask, opened, hx, hy, g, q, c, 2 * length)
                    assert slit[q, c] == want, (q, c)
                    long_seen += 24 <= c < 29 and 10 <= q < 70
        assert long_seen > 200


def test_steger_batches_give_each_point_its_own_centre():
    """Steger's steps for many points at once (batches, a part batch at the end) give each
    point, bit for bit, what it gets alone, near the image's left and right borders too."""
    from multislit.stripes.refine import _steger_kernel

    rng = np.random.default_rng(13)
    h, w, ss = 30, 64, 1.7
    slit = rng.normal(0, 5, (h, w)).astype(np.float32)
    u = rng.uniform(-0.5, w - 0.5, 45)
    u[:4] = (-0.5, 0.3, w - 1.2, w - 0.5)
    cols = np.arange(w)
    slit += (80 * np.exp(-0.5 * ((cols - 33.3) / 2.0) ** 2)).astype(np.float32)
    u[4:20] = 33.3 + rng.uniform(-1, 1, 16)  # on the stripe: steps that converge
    r = rng.integers(0, h, u.size)
    active = rng.random(u.size) < 0.9
    m, ok = _steger_kernel(slit, u, r, active, ss, 1.0)
    assert ok.sum() > 10 and (~ok[active]).any()
    np.testing.assert_array_equal(m[~active], u[~active])
    for i in range(u.size):
        one = np.zeros(u.size, bool)
        one[i] = active[i]
        m1, ok1 = _steger_kernel(slit, u, r, one, ss, 1.0)
        assert m1[i] == m[i] and ok1[i] == ok[i], i


def test_opening_cells_hold_every_pixel_the_mask_reads():
    """The cells whose opening follows a leaning stripe hold every pixel whose opening the
    dot mask can be read at (the windows' columns, 2 length + 1 rows above to 2 length below
    the point, widened by the mask's 1 px dilation), and not the whole image."""
    from multislit.stripes.refine import _opening_cells
    from multislit.stripes.slope import LEAN_DECIMATION as f

    rng = np.random.default_rng(14)
    h, w, rad, length = 203, 150, 6, 4
    u = rng.uniform(-0.5, w - 0.5, 40)
    u[:3] = (-0.5, w - 0.5, 75.0)
    r = rng.integers(0, h, u.size)
    r[:3] = (0, h - 1, h - 1)
    active = rng.random(u.size) < 0.8
    active[:3] = True
    shape = (h // f, w // f)
    got = _opening_cells(u, r, active, rad, length, h, w)
    read = np.zeros((h, w), bool)
    lim = 2 * length
    for ui, ri in zip(u[active], r[active], strict=True):
        c0 = math.floor(min(max(ui, 0.0), w - 1.0))
        read[max(ri - lim - 2, 0) : ri + lim + 2, max(c0 - 2 - rad, 0) : c0 + 3 + rad] = True
    qs, cs = np.nonzero(read)
    want = np.zeros(shape, bool)
    want[np.minimum(qs // f, shape[0] - 1), np.minimum(cs // f, shape[1] - 1)] = True
    assert got.shape == shape
    assert not (want & ~got).any()
    assert got.mean() < 0.9  # not the whole image


def test_refine_opens_along_leaning_stripes_only_where_read(monkeypatch):
    """On stripes leaning ~19 deg, the opening along them, made only in the cells the dot
    mask is read at, gives the refined centres of the whole-image opening bit for bit; the
    whole-image one also changes the opening outside those cells (the restriction leaves
    work out)."""
    from multislit.stripes import refine as refine_mod
    from multislit.stripes.openings import stripe_opening, vertical_opening
    from multislit.stripes.refine import _highpass_and_tensor
    from multislit.stripes.slope import LEAN_DECIMATION as f

    img0, _ = render(seed=15, n_stripes=5, dots_per_stripe=150)
    h, w = img0.shape
    shear = np.float32([[1, 0.35, -0.35 * h / 2], [0, 1, 0]])
    img = cv2.warpAffine(img0, shear, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    ex = extract_slits(img, stripe_width_px=3.06, dot_size_px=1.9)
    args = (img, ex.u, ex.v, ex.segment, ex.stripe_width_px, ex.dot_size_px)
    got = [refine_centres(*args, degree=d) for d in ("auto", 1)]
    cells = []
    real = refine_mod._opening_cells

    def everywhere(*a):
        cells.append(real(*a))
        return np.ones_like(cells[-1])

    monkeypatch.setattr(refine_mod, "_opening_cells", everywhere)
    whole = [refine_centres(*args, degree=d) for d in ("auto", 1)]
    for (u, ok), (u_w, ok_w) in zip(got, whole, strict=True):
        assert ok.mean() > 0.5
        np.testing.assert_array_equal(u, u_w)
        np.testing.assert_array_equal(ok, ok_w)
    # the opening along the stripes differs from the vertical one inside and outside the cells
    sw, length = ex.stripe_width_px, opening_length(ex.dot_size_px)
    hp = _highpass_and_tensor(img, sw, refine_half_rows(sw), length)[0]
    tau = 3.0 * noise_from_difference(img)
    moved = stripe_opening(hp, length, tau) != vertical_opening(hp, length)
    qs, cs = np.nonzero(moved)
    inside = cells[0][
        np.minimum(qs // f, cells[0].shape[0] - 1), np.minimum(cs // f, cells[0].shape[1] - 1)
    ]
    assert inside.sum() > 50 and (~inside).sum() > 50
