"""The compiled refinement and triangulation give the results of plain NumPy reference
implementations kept here (the strips along the segments built, opened and refilled row by
row, Steger's centres and the along-stripe fits vectorised over all points; the camera's rays
intersected with the planes)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import scipy.stats

from multislit.geometry import MatrixCamera, PinholeCamera, intersect_rays_planes
from multislit.reconstruct import triangulate
from multislit.stripes import (
    FWHM_PER_SIGMA,
    extract_slits,
    median_stride,
    opening_length,
    refine_centres,
    refine_half_rows,
)
from multislit.stripes.refine import _BEND_WINDOWS, _CURVED_ALPHA
from multislit.stripes.separation import noise_from_difference, row_median_background

from .test_slits import render
from .test_triangulation import make_camera, points_on, slit_planes


# --------------------------------------------------------------------------- reference
def _steger_on_strips(slit, col0, where, u, ss):
    """Steger's first and second derivative sums at ``u`` (K,) px for points in stacked rows
    ``where`` (K,) of the strips ``slit`` (N, D) (row t holding image columns ``col0[t]``
    ..), and whether the samples lie in the strip; points with ``where`` < 0 get 0."""
    rad = math.ceil(3.0 * ss) + 1
    d = slit.shape[1]
    c = np.floor(u).astype(np.intp)
    x = np.arange(-rad, rad + 1)
    t = np.maximum(where, 0)
    j = c[:, None] + x[None, :] - col0[t][:, None]
    within = (j.min(axis=1) >= 0) & (j.max(axis=1) < d)
    p = slit[t[:, None], np.clip(j, 0, d - 1)].astype(np.float64)
    tt = (c - u)[:, None] + x[None, :]
    g = np.exp(-0.5 * (tt / ss) ** 2)
    d1 = np.einsum("kn,kn->k", p, tt * g) / ss**2
    d2 = np.einsum("kn,kn->k", p, (tt * tt / ss**4 - 1.0 / ss**2) * g)
    on = where >= 0
    return np.where(on, d1, 0.0), np.where(on, d2, 0.0), within | ~on


def _plain_refill(strip, opened, mask, slope, bend, col0, bounds, lim):
    """The refill of :func:`_refill_strips` on the strips (N, D) in NumPy float32 scalars,
    run by run and pixel by pixel, each pixel reading the rows above and below its run along
    the parabola of the run's middle row (``slope`` px/row, ``bend`` px/row^2 (N,) there)."""
    d = strip.shape[1]
    out = strip.copy()

    def sample(t, x):
        x = min(max(x, 0.0), d - 1.0)
        k = min(math.floor(x), d - 2)
        a = strip[t, k]
        return np.float32(a + np.float32(np.float32(strip[t, k + 1] - a) * np.float32(x - k)))

    for t0, t1 in zip(bounds[:-1], bounds[1:], strict=True):
        for k in range(d):
            on = np.r_[False, mask[t0:t1, k] > 0, False]
            edges = np.flatnonzero(np.diff(on.astype(int)))
            for start, stop in zip(edges[0::2] + t0, edges[1::2] + t0, strict=True):
                n = stop - start
                if start == t0 or stop == t1 or n > lim:
                    out[start:stop, k] = opened[start:stop, k]
                    continue
                a, mid = start - 1, start + n // 2

                def f(x, mid=mid):
                    return slope[mid] * (x - mid) + bend[mid] * (x - mid) * (x - mid)

                for q in range(start, stop):
                    c = col0[q] + k - f(q)
                    above = sample(a, c + f(a) - col0[a])
                    below = sample(stop, c + f(stop) - col0[stop])
                    frac = (q - a) * (1.0 / float(np.float32(n + 1)))
                    val = float(above) + float(np.float32(below - above)) * frac
                    out[q, k] = np.float32(min(val, float(strip[q, k])))
    return out


def _reference_strips(img, u, r, seg, active, sw, ds, R):
    """The strips of refine_centres row by row: per segment with an active point, its rows
    and ``opening_length - 1`` more beyond each end (the image's first or last row repeated
    beyond it), each row's centre line from np.polyfit's parabola through the segment's points
    within ``_BEND_WINDOWS`` R rows (cut at its ends), the highpass gathered about it; the opening
    along the centre line (row t + j at round(centre[t + j] - centre[t]) columns over) and the
    dot mask's 3 x 3 dilation made pixel by pixel in image coordinates, within the strip; each
    run of dot pixels in a strip's column refilled along the parabola of its middle row, its
    bend shrunk by the bends' noise (pairs of rows 2 W + 1 apart inside a strip's segment
    rows). The refilled
    strips (N, D), each row's first image column (N,) and each point's stacked row (K,), -1
    where not active."""
    h, w = img.shape
    length = opening_length(ds)
    pad, W, lim, ro = length - 1, _BEND_WINDOWS * R, 2 * length, length // 2
    ss = max(1.25 * sw / FWHM_PER_SIGMA, 0.7)
    half = math.ceil(3.0 * ss) + 4
    d = 2 * half + 1
    stride = median_stride(sw)
    bg = row_median_background(img, stride).astype(np.float32)
    bg = cv2.blur(bg, (2 * stride + 1, 2 * R + 1), borderType=cv2.BORDER_REFLECT)
    hp = img.astype(np.float32) - bg
    where = np.full(u.size, -1)
    rows, centre, slope, bend, bounds = [], [], [], [], [0]
    for g in np.unique(seg[active]):
        on = np.flatnonzero(seg == g)
        rg, ug = r[on], u[on]
        r0, r1 = rg.min(), rg.max()
        for vr in range(r0 - pad, r1 + pad + 1):
            ir = min(max(vr, 0), h - 1)
            sel = np.abs(rg - min(max(vr, r0), r1)) <= W
            p = np.polyfit(rg[sel] - r0, ug[sel], 2 if sel.sum() >= 3 else 1)
            rows.append(ir)
            centre.append(np.polyval(p, ir - r0))
            slope.append(np.polyval(np.polyder(p), ir - r0))
            bend.append(p[0] if p.size == 3 else 0.0)
        pts = on[active[on]]
        where[pts] = bounds[-1] + r[pts] - (r0 - pad)
        bounds.append(len(rows))
    rows, centre, slope, bend = np.array(rows), np.array(centre), np.array(slope), np.array(bend)
    col0 = np.rint(centre).astype(np.int64) - half
    cols = np.clip(col0[:, None] + np.arange(d)[None, :], 0, w - 1)
    strip = hp[rows[:, None], cols]
    strip_of = np.repeat(np.arange(len(bounds) - 1), np.diff(bounds))

    def line(src, t, k, offsets, fn):
        """fn of src over (row offset, column offset) pairs from (t, k), image coordinates."""
        vals = []
        for j, dk in offsets:
            q = t + j
            if 0 <= q < len(rows) and strip_of[q] == strip_of[t]:
                kk = k + dk + col0[t] - col0[q]
                if 0 <= kk < d:
                    vals.append(src[q, kk])
        return fn(vals)

    def offsets(t):
        out = []
        for j in range(-ro, ro + 1):
            x = centre[min(max(t + j, 0), len(rows) - 1)] - centre[t]
            out.append((j, int(np.sign(x) * np.floor(abs(x) + 0.5))))
        return out

    def opening_of(src):
        ero = np.array(
            [[line(src, t, k, offsets(t), min) for k in range(d)] for t in range(len(rows))]
        )
        return np.array(
            [[line(ero, t, k, offsets(t), max) for k in range(d)] for t in range(len(rows))]
        )

    opened = opening_of(strip).astype(np.float32)
    tau = 3.0 * noise_from_difference(img)
    above = strip - opened > opened * np.float32(0.05) + np.float32(tau)
    square = [(j, dk) for j in (-1, 0, 1) for dk in (-1, 0, 1)]
    mask = np.array([[line(above, t, k, square, any) for k in range(d)] for t in range(len(rows))])
    mask = mask.astype(np.uint8)
    bounds = np.array(bounds)
    pairs = [
        (t, t + 2 * W + 1)
        for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True)
        for t in range(b0 + pad, b1 - pad - 2 * W - 1)
    ]
    bend_used = np.zeros_like(bend)
    if len(pairs) >= 50:
        d2 = np.array([(bend[a] - bend[b]) ** 2 for a, b in pairs])
        s2 = np.median(d2) / (2 * scipy.stats.chi2.median(1))
        for t in range(len(bend)):
            if bend[t] ** 2 > s2:
                bend_used[t] = bend[t] * (1 - s2 / bend[t] ** 2)
    out = _plain_refill(strip, opened, mask, slope, bend_used, col0, bounds, lim)
    return out, col0, where


def _poly_fit(mom, rhs, count, base, deg, need):
    """Each point's least-squares polynomial of ``deg`` at dv = 0 from the moments, where
    ``base`` and the window has ``need`` rows: value, ok, (A^-1)_00."""
    n = deg + 1
    idx = np.arange(n)
    A = mom[:, idx[:, None] + idx[None, :]]
    ok = base & (count >= need)
    ok &= np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(mom[:, 0], 1.0) ** n
    A[~ok] = np.eye(n)
    delta = np.linalg.solve(A, np.where(ok[:, None], rhs[:, :n], 0.0)[..., None])[:, 0, 0]
    return delta, ok, np.linalg.inv(A)[:, 0, 0]


def _moments(key, skey, order, has, inner, row_ok, m, u, R, n):
    """Each point's normal equations over its segment's rows v - R .. v + R (symmetric, shrunk
    at the ends): the moments sum(dv^k) (K, 2 n - 1), right-hand sides (K, n), the rows used
    and the window's half height."""
    K = u.size
    reach = np.minimum(inner, R)
    mom, rhs, count = np.zeros((K, 2 * n - 1)), np.zeros((K, n)), np.zeros(K, np.int64)
    powers = np.arange(2 * n - 1)
    for dv in range(-R, R + 1):
        j = np.minimum(np.searchsorted(skey, key + dv), K - 1)
        nb = order[j]
        found = has & (skey[j] == key + dv) & (abs(dv) <= reach) & row_ok[nb] & (inner[nb] >= 0)
        wt = found.astype(float)
        p = float(dv) ** powers
        mom += wt[:, None] * p[None, :]
        rhs += (wt * (m[nb] - u))[:, None] * p[None, :n]
        count += found
    return mom, rhs, count, reach


def _reference_auto(mom, rhs, count, base, R, seg, r, wide):
    """degree="auto": degree 2 where d = u2 - u1 is significant, d^2 / g > s^2 chi2_1(1 - a)
    (g = var(u2 - u1) per unit noise, s^2 from pairs of windows 2 R + 1 rows apart), and so
    is d, of the same sign, R rows before or after on the segment; elsewhere the line less c
    times its value on dv^2, c the dv^2 coefficient of the parabola over the ``wide`` window
    (its moments, right-hand sides, rows and base), where there is one."""
    d1, ok, v1 = _poly_fit(mom, rhs, count, base, 1, min(3, 2 * R + 1))
    # the line's value on u = dv^2 and the wide parabola's curvature
    bend, _, _ = _poly_fit(mom, mom[:, 2:4], count, base, 1, min(3, 2 * R + 1))
    wmom, wrhs, wcount, wbase = wide
    A = wmom[:, np.arange(3)[:, None] + np.arange(3)[None, :]]
    wok = wbase & (wcount >= 4) & ok
    wok &= np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(wmom[:, 0], 1.0) ** 3
    A[~wok] = np.eye(3)
    curv = np.linalg.solve(A, np.where(wok[:, None], wrhs, 0.0)[..., None])[:, 2, 0]
    line = np.where(wok, d1 - curv * bend, d1)
    d2, ok2, v2 = _poly_fit(mom, rhs, count, base & ok, 2, 4)
    gain = np.where(ok2, v2 - v1, np.nan)
    has = np.isfinite(gain) & (gain > 0)
    at = {(s, q): i for i, (s, q) in enumerate(zip(seg, r, strict=True)) if has[i]}
    pairs = [(i, at[s, q + 2 * R + 1]) for (s, q), i in at.items() if (s, q + 2 * R + 1) in at]
    if len(pairs) < 50:
        return line, ok
    a, b = np.array(pairs).T
    d = d2 - d1
    s2 = np.median((d[a] - d[b]) ** 2 / (gain[a] + gain[b])) / scipy.stats.chi2.ppf(0.5, 1)
    sig = has & (d**2 > np.where(has, gain, 0) * s2 * scipy.stats.chi2.isf(_CURVED_ALPHA, 1))
    out = line.copy()
    for (s, q), i in at.items():
        nbs = [at.get((s, q + off)) for off in (-R, R)]
        if sig[i] and any(j is not None and sig[j] and d[j] * d[i] > 0 for j in nbs):
            out[i] = d2[i]
    return out, ok


def _reference_refine(img, u, v, seg, sw, ds, R=None, deg="auto", max_shift=1.0, end=None):
    """refine_centres on the reference strips (:func:`_reference_strips`), all points
    vectorised."""
    h, w = img.shape
    u = np.asarray(u, float)
    r = np.rint(v).astype(np.intp)
    seg = np.asarray(seg, np.int64)
    R = refine_half_rows(sw) if R is None else R
    end = opening_length(ds) if end is None else end
    sigma = sw / FWHM_PER_SIGMA
    ss = max(1.25 * sigma, 0.7)
    K = u.size
    has = seg >= 0
    span = h + 2 * max(1, _BEND_WINDOWS) * R + 2
    key = np.where(has, seg * span + r, -1)
    order = np.argsort(key, kind="stable")
    skey, sseg = key[order], seg[order]
    first = np.r_[True, sseg[1:] != sseg[:-1]]
    last = np.r_[sseg[1:] != sseg[:-1], True]
    first_i = np.maximum.accumulate(np.where(first, np.arange(K), 0))
    last_i = np.minimum.accumulate(np.where(last, np.arange(K), K)[::-1])[::-1]
    v_first, v_last = np.empty(K, np.intp), np.empty(K, np.intp)
    v_first[order] = r[order][first_i]
    v_last[order] = r[order][last_i]
    inner = np.minimum(r - v_first, v_last - r) - end
    active = has & (inner >= 0)
    slit, col0, where = _reference_strips(img, u, r, seg, active, sw, ds, R)
    d1, d2, inside = _steger_on_strips(slit, col0, where, np.clip(u, 0, w - 1), ss)
    good = d2 < 0
    m = u + np.clip(np.where(good, -d1 / np.where(good, d2, -1.0), 0.0), -1.0, 1.0)
    m = np.where(active, m, u)
    row_ok = active & good & inside & (np.abs(m - u) <= max_shift)
    n = 3 if deg == "auto" else deg + 1
    mom, rhs, count, reach = _moments(key, skey, order, has, inner, row_ok, m, u, R, n)
    base = has & (reach >= R // 2) & (inner >= 0)
    if deg == "auto":
        W = _BEND_WINDOWS * R
        wmom, wrhs, wcount, wreach = _moments(key, skey, order, has, inner, row_ok, m, u, W, 3)
        wide = (wmom, wrhs, wcount, has & (wreach >= W // 2) & (inner >= 0))
        delta, ok = _reference_auto(mom, rhs, count, base, R, seg, r, wide)
    else:
        delta, ok, _ = _poly_fit(mom, rhs, count, base, deg, min(deg + 2, 2 * R + 1))
    o = np.lexsort((u, r))
    du = np.where(r[o][1:] == r[o][:-1], np.diff(u[o]), np.inf)
    gap = np.full(K, np.inf)
    gap[o[:-1]] = du
    gap[o[1:]] = np.minimum(gap[o[1:]], du)
    ok &= gap >= 3.0 * ss + 2.5 * sigma
    ok &= np.abs(delta) <= max_shift
    out = u.copy()
    out[ok] += delta[ok]
    return out, ok


# --------------------------------------------------------------------------- tests
@pytest.mark.parametrize(
    ("seed", "kw", "opts"),
    [
        (0, {}, {}),
        (3, {"jump": 4.0, "dots_per_stripe": 120}, {"degree": 2}),
        (7, {"h": 200, "w": 257, "n_stripes": 11, "saturate": True}, {"half_rows": 3}),
    ],
)
def test_refine_matches_reference_strips(seed, kw, opts):
    """Same refined centres and the same points refined as the reference strips, on images
    with dots (windows meet dot runs, slopes, image borders and segment ends)."""
    img, _ = render(seed=seed, **kw)
    ex = extract_slits(img, stripe_width_px=3.06, dot_size_px=1.9)
    args = (img, ex.u, ex.v, ex.segment, ex.stripe_width_px, ex.dot_size_px)
    u, ok = refine_centres(*args, **opts)
    ref_kw = {"R": opts.get("half_rows"), "deg": opts.get("degree", "auto")}
    u_ref, ok_ref = _reference_refine(*args, **ref_kw)
    assert ok.sum() > 0.5 * len(u)
    np.testing.assert_array_equal(ok, ok_ref)
    # float32 sums in another order: the refined centres agree to ~1e-7 px
    assert np.abs(u - u_ref).max() < 1e-5, np.abs(u - u_ref).max()


def test_refine_matches_reference_on_uint16_and_float32():
    img8, _ = render(seed=11)
    ex = extract_slits(img8, stripe_width_px=3.06, dot_size_px=1.9)
    for img in (img8.astype(np.uint16) * 16, img8.astype(np.float32) / 255):
        args = (img, ex.u, ex.v, ex.segment, ex.stripe_width_px, ex.dot_size_px)
        u, ok = refine_centres(*args)
        u_ref, ok_ref = _reference_refine(*args)
        np.testing.assert_array_equal(ok, ok_ref)
        assert np.abs(u - u_ref).max() < 1e-5


def test_triangulate_pinhole_matches_rays_and_planes():
    """The compiled pinhole path equals the camera's rays intersected with the planes, with
    unidentified points, slits without a plane and grazing rays rejected alike."""
    rng = np.random.default_rng(4)
    cam = make_camera(dist=(-0.15, 0.08, 5e-4, -2e-4, 0.01))
    planes = slit_planes()
    X, s = points_on(planes, rng)
    uv = cam.project(X) + rng.normal(0, 0.3, (len(X), 2))
    s = s.copy()
    s[::17] = -1
    planes[3] = np.nan
    pts, valid = triangulate(cam, planes, uv, s, min_angle_deg=20.0)
    o, d = cam.rays(uv)
    per = np.full((len(uv), 4), np.nan)
    per[s >= 0] = planes[s[s >= 0]]
    ref, _ = intersect_rays_planes(o, d, per, min_cos=math.sin(math.radians(20.0)))
    ref_valid = np.isfinite(ref).all(axis=1)
    np.testing.assert_array_equal(valid, ref_valid)
    assert 0 < valid.sum() < (s >= 0).sum()  # some grazing rays rejected at 20 deg
    assert np.isnan(pts[~valid]).all()
    np.testing.assert_allclose(pts[valid], ref[valid], rtol=0, atol=1e-9)


def test_triangulate_other_cameras_use_their_rays():
    cam = make_camera()
    planes = slit_planes()
    X, s = points_on(planes, np.random.default_rng(5))
    mc = MatrixCamera(cam.matrix)
    pts, valid = triangulate(mc, planes, mc.project(X), s)
    assert valid.all() and not isinstance(mc, PinholeCamera)
    np.testing.assert_allclose(pts, X, atol=1e-6)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
@pytest.mark.parametrize(("w", "stride"), [(97, 4), (13, 4), (5, 1)])
def test_row_median_is_the_median_of_nine_samples(dtype, w, stride):
    """The compiled row median is the median of the 9 samples ``stride`` px apart, the
    border reflected (or replicated when the samples reach past a narrow image)."""
    from multislit.stripes.separation import row_median_background

    img = np.random.default_rng(w).integers(0, 250, (9, w)).astype(dtype)
    pad = 4 * stride
    padded = np.pad(img, ((0, 0), (pad, pad)), mode="reflect" if pad < w else "edge")
    samples = np.stack([padded[:, pad + j * stride : pad + j * stride + w] for j in range(-4, 5)])
    want = np.median(samples, axis=0).astype(dtype)
    np.testing.assert_array_equal(row_median_background(img, stride), want)


@pytest.mark.parametrize("c", [0.01, -0.01])
def test_refine_row_centres_unbiased_on_curved_leaning_stripe(c):
    """On a stripe that leans and curves as the arcs near a sphere's outline do (du/dv 0.6,
    d2u/dv2 = 2c = 0.02 px/row^2), speckled, the row centres are not pulled to the inside of the
    curve: the opening that finds the dots and the refill follow the curve, so the stripe's
    outer flank is not taken for dots (the curve's bend is far above its noise, and kept). The
    parabola along the stripe (degree 2, unbiased by the curve) shows the row centres' own
    bias."""
    from .test_slits import _one_stripe

    h = 120
    v = np.arange(h, dtype=float)
    seg = np.zeros(h, np.int64)
    errs = []
    for seed in range(6):
        img, uc = _one_stripe(
            lambda v: 80.0 + 0.6 * (v - h / 2) + c * (v - h / 2) ** 2,
            h,
            w=170,
            speckle=0.12,
            noise=2.0,
            seed=seed,
        )
        u0 = uc + np.random.default_rng(seed + 10).normal(0, 0.2, h)
        u, ok = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9, degree=2)
        assert ok.mean() > 0.75
        errs.append((u - uc)[ok])
    # measured mean error over the 6 seeds +0.0010 px (c = 0.01), +0.0002 px (c = -0.01); with
    # the opening and refill along the slope's straight line +0.058 and -0.063 px (fill_dots
    # on the whole image, its opening no lower than the vertical one: +0.042 and -0.043 px)
    bias = np.mean(np.concatenate(errs))
    assert abs(bias) < 0.015, bias


def test_refine_auto_degree_follows_curved_stripe_keeps_straight_one():
    """degree="auto" fits a parabola where the stripe is curved (a 40 mm sphere's arc bends by
    ~0.01 px/row^2) and a line where it is straight, on speckled stripes."""
    from .test_slits import _one_stripe

    # u = u0 + c (v - h/2)^2, c = 8e-3 px/row^2: degree 1 biased by c R (R + 1) / 3 = 0.19 px
    # (R = 8); the row centres' own bias on the curve is small (the dots' opening and refill
    # follow it)
    h, c, R = 120, 8e-3, 8
    v = np.arange(h, dtype=float)
    seg = np.zeros(h, np.int64)
    kw = {"speckle": 0.12, "noise": 2.0, "seed": 5}
    img, uc = _one_stripe(lambda v: 30.0 + c * (v - h / 2) ** 2, h, w=100, **kw)
    u0 = uc + np.random.default_rng(3).normal(0, 0.2, h)
    ua, oka = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9)
    u1, ok1 = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9, degree=1)
    np.testing.assert_array_equal(oka, ok1)
    assert oka.mean() > 0.8
    ea, e1 = (ua - uc)[oka], (u1 - uc)[ok1]
    # measured mean error +0.018 px (auto), +0.197 px (degree 1; +0.011 px degree 2 at every
    # point); RMS 0.081 vs 0.209 px
    assert abs(np.mean(e1) - c * R * (R + 1) / 3) < 0.02, np.mean(e1)
    assert abs(np.mean(ea)) < 0.15, np.mean(ea)
    assert np.sqrt(np.mean(ea**2)) < 0.7 * np.sqrt(np.mean(e1**2))
    # the same choice of degree as the whole-image reference (most points take degree 2)
    assert np.mean(ua[oka] != u1[ok1]) > 0.5
    u_ref, ok_ref = _reference_refine(img, u0, v, seg, 3.06, 1.9)
    np.testing.assert_array_equal(oka, ok_ref)
    assert np.abs(ua - u_ref).max() < 1e-5, np.abs(ua - u_ref).max()
    # a slanted straight stripe: (almost) everywhere the line
    h = 240
    v = np.arange(h, dtype=float)
    seg = np.zeros(h, np.int64)
    img, uc = _one_stripe(lambda v: 40.0 + 0.1 * (v - h / 2), h, w=100, **kw)
    u0 = uc + np.random.default_rng(4).normal(0, 0.2, h)
    ua, oka = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9)
    u1, ok1 = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9, degree=1)
    u2, ok2 = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9, degree=2)
    np.testing.assert_array_equal(oka, ok1)
    # measured: the parabola at 1 % of the points, the line less its (near nought) curvature's
    # bias at the others: RMS 0.0362 px against the line's 0.0348 (the parabola's 0.0570)
    assert np.mean(ua[oka] == u2[oka]) < 0.02
    ea, e1 = (ua - uc)[oka], (u1 - uc)[oka]
    assert np.sqrt(np.mean(ea**2)) < 1.1 * np.sqrt(np.mean(e1**2))


@pytest.mark.parametrize("seed", [5, 6])
def test_refine_takes_a_gentle_curve_s_bias_off_the_line(seed):
    """Where the stripe bends too little for the parabola's test (u = u0 + 0.0015 dv^2, as on
    the arcs of a 120 mm sphere at 0.9 m), the line is biased towards the arc's inside by
    0.0015 R (R + 1) / 3 = 0.036 px (R = 8); degree="auto" takes that off with the curvature of
    the wide window, keeping (nearly) the line's noise."""
    from .test_slits import _one_stripe

    h = 240
    v = np.arange(h, dtype=float)
    seg = np.zeros(h, np.int64)
    img, uc = _one_stripe(
        lambda v: 40.0 + 0.0015 * (v - h / 2) ** 2, h, w=100, speckle=0.12, noise=2.0, seed=seed
    )
    u0 = uc + np.random.default_rng(seed).normal(0, 0.2, h)
    err = {}
    for degree in ("auto", 1, 2):
        u, ok = refine_centres(img, u0, v, seg, 3.06, dot_size_px=1.9, degree=degree)
        assert ok.mean() > 0.85
        err[degree] = (u - uc)[ok]
    mean = {d: float(np.mean(e)) for d, e in err.items()}
    rms = {d: float(np.sqrt(np.mean(e**2))) for d, e in err.items()}
    # measured (seeds 5, 6): mean error +0.003, +0.024 px (auto), +0.036, +0.058 (the line),
    # +0.000, +0.021 (the parabola: unbiased by the curve, the rest is the speckle's); RMS
    # 0.036, 0.052 (auto), 0.049, 0.071 (line), 0.050, 0.063 (parabola)
    assert mean[1] - mean[2] > 0.025, mean
    assert abs(mean["auto"] - mean[2]) < 0.01, mean
    assert rms["auto"] < rms[1] and rms["auto"] < 0.9 * rms[2], rms


@pytest.mark.parametrize("degree", ["cubic", 3, -1])
def test_refine_rejects_bad_degree(degree):
    img = np.zeros((20, 20), np.uint8)
    with pytest.raises(ValueError, match="degree must be"):
        refine_centres(img, [5.0], [5.0], [0], 3.0, degree=degree)


# --------------------------------------------------------------------------- fast paths
# Each compiled shortcut of the refinement against a plain formulation kept here, bit for bit.
def _fit_reference(seg, key, skey, order, inner, m, u, row_ok, R, deg, bend_of=False):
    """The along-stripe fits point by point: neighbours by np.searchsorted, the normal
    equations' moments and right-hand sides accumulated as powers of dv in order of dv, solved
    by cofactors (as ``_fit_kernel``)."""
    K = seg.size
    auto = deg < 0
    n = 3 if auto else deg + 1
    delta, delta2 = np.zeros(K), np.zeros(K)
    gain, ok, bend = np.full(K, np.nan), np.zeros(K, bool), np.full(K, np.nan)
    need = min(3 if auto else deg + 2, 2 * R + 1)
    for i in range(K):
        reach = min(inner[i], R)
        if seg[i] < 0 or inner[i] < 0 or reach < R // 2:
            continue
        mom, rhs, count = np.zeros(2 * n - 1), np.zeros(n), 0
        for dv in range(-reach, reach + 1):
            q = min(int(np.searchsorted(skey, key[i] + dv)), K - 1)
            nb = order[q]
            if skey[q] != key[i] + dv or not row_ok[nb] or inner[nb] < 0:
                continue
            count += 1
            for k in range(2 * n - 1):
                mom[k] += float(dv) ** k
                if k < n:
                    rhs[k] += (m[nb] - u[i]) * float(dv) ** k
        if count < need:
            continue
        if n == 1:
            if abs(mom[0]) > 1e-9 * max(mom[0], 1.0):
                delta[i], ok[i] = rhs[0] / mom[0], True
            continue
        det = mom[0] * mom[2] - mom[1] * mom[1]
        line = abs(det) > 1e-9 * max(mom[0], 1.0) ** 2
        if n == 2 or auto:
            if line:
                delta[i], ok[i] = (rhs[0] * mom[2] - mom[1] * rhs[1]) / det, True
                if auto:
                    bend[i] = (mom[2] * mom[2] - mom[1] * mom[3]) / det
            if n == 2 or not line or count < 4:
                continue
        c0 = mom[2] * mom[4] - mom[3] * mom[3]
        c1 = mom[2] * mom[3] - mom[1] * mom[4]
        c2 = mom[1] * mom[3] - mom[2] * mom[2]
        det3 = mom[0] * c0 + mom[1] * c1 + mom[2] * c2
        if abs(det3) <= 1e-9 * max(mom[0], 1.0) ** 3:
            continue
        d2 = (c0 * rhs[0] + c1 * rhs[1] + c2 * rhs[2]) / det3
        if auto:
            delta2[i], gain[i] = d2, c0 / det3 - mom[2] / det
        elif bend_of:
            c21 = mom[1] * mom[2] - mom[0] * mom[3]
            delta[i], ok[i] = (c2 * rhs[0] + c21 * rhs[1] + det * rhs[2]) / det3, True
        else:
            delta[i], ok[i] = d2, True
    return delta, ok, delta2, gain, bend


def _pick_curved_reference(delta1, delta2, gain, key, R):
    """degree="auto"'s choice with NumPy sorts and searches throughout."""
    from multislit.stripes.refine import _CURVED_MIN_PAIRS

    has = np.flatnonzero(np.isfinite(gain) & (gain > 0))
    d = delta2 - delta1
    order = has[np.argsort(key[has], kind="stable")]
    sk = key[order]

    def partner(off):
        j = np.clip(np.searchsorted(sk, sk + off), 0, max(sk.size - 1, 0))
        return sk[j] == sk + off, order[j]

    pair, b = partner(2 * R + 1)
    if pair.sum() < _CURVED_MIN_PAIRS:
        return delta1
    a, b = order[pair], b[pair]
    s2 = np.median((d[a] - d[b]) ** 2 / (gain[a] + gain[b])) / scipy.stats.chi2.median(1)
    sig = np.zeros(d.size, bool)
    sig[has] = d[has] ** 2 > gain[has] * s2 * scipy.stats.chi2.isf(_CURVED_ALPHA, 1)
    confirmed = np.zeros(order.size, bool)
    for off in (-R, R):
        there, nb = partner(off)
        confirmed |= there & sig[nb] & (np.sign(d[nb]) == np.sign(d[order]))
    curved = order[sig[order] & confirmed]
    out = delta1.copy()
    out[curved] = delta2[curved]
    return out


def _segment_points(rng, n_seg=14, h=120, R=4):
    """Row-ordered points on ``n_seg`` segments with gaps (one point per row and segment) and
    some off any segment: seg, rows, and the span of ``_segment_rows``'s keys."""
    seg, rows = [], []
    for s in range(n_seg):
        a = int(rng.integers(0, h // 2))
        q = np.arange(a, min(h, a + int(rng.integers(10, h))))
        q = q[rng.random(q.size) > 0.1]  # gaps
        seg.append(np.full(q.size, s))
        rows.append(q)
    q = rng.integers(0, h, 30)
    seg, rows = np.concatenate([*seg, np.full(30, -1)]), np.concatenate([*rows, q])
    o = np.argsort(rows, kind="stable")  # row order, as from the extraction
    return seg[o].astype(np.int64), rows[o].astype(np.intp), h + 2 * R + 2


def test_segment_rows_sort_matches_numpy_stable_argsort():
    """The counting sort of row-ordered points, and the merge sort otherwise (shuffled points,
    a segment id below -1), give NumPy's stable argsort and the same keys and ends."""
    from multislit.stripes.refine import _segment_rows

    rng = np.random.default_rng(1)
    seg, rows, span = _segment_points(rng)
    shuffled = rng.permutation(seg.size)
    for s, r in ((seg, rows), (seg[shuffled], rows[shuffled]), (np.where(seg == 3, -4, seg), rows)):
        key, order, skey, inner = _segment_rows(s, r, span, 2)
        want_key = np.where(s >= 0, s * span + r, -1)
        want_order = np.argsort(want_key, kind="stable")
        np.testing.assert_array_equal(key, want_key)
        np.testing.assert_array_equal(order, want_order)
        np.testing.assert_array_equal(skey, want_key[want_order])
        for g in np.unique(s[s >= 0]):
            on = s == g
            want = np.minimum(r[on] - r[on].min(), r[on].max() - r[on]) - 2
            np.testing.assert_array_equal(inner[on], want)


@pytest.mark.parametrize("deg", [-1, 0, 1, 2])
def test_fit_kernel_matches_pointwise_reference(deg):
    """The compiled along-stripe fits (one forward walk for the neighbours, moments in
    registers) give the point-by-point reference's shifts, bit for bit."""
    from multislit.stripes.refine import _fit_kernel, _segment_rows

    rng = np.random.default_rng(2)
    R = 4
    seg, rows, span = _segment_points(rng, R=R)
    key, order, skey, inner = _segment_rows(seg, rows, span, 2)
    u = rng.uniform(10, 90, seg.size)
    m = u + rng.normal(0, 0.3, seg.size)
    row_ok = rng.random(seg.size) > 0.15
    got = _fit_kernel(seg, key, order, skey, inner, m, u, row_ok, R, deg)
    want = _fit_reference(seg, key, skey, order, inner, m, u, row_ok, R, deg)
    assert got[1].sum() > 0.5 * seg.size
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("W", [3, 12])
def test_bend_kernel_matches_pointwise_parabola(W):
    """The curvature from running sums equals that of the parabola fitted point by point
    (neighbours by np.searchsorted, the normal equations solved by cofactors) within float
    rounding, on segments with gaps and bad rows, far from the image's origin."""
    from multislit.stripes.refine import _bend_kernel, _segment_rows

    rng = np.random.default_rng(7)
    seg, rows, span = _segment_points(rng, h=400, R=W)
    rows = rows + 600  # rows far from 0: the sums' powers of the row must not lose the curve
    span += 600
    key, order, skey, inner = _segment_rows(seg, rows, span, 2)
    # stripes across a 1500 px wide image, leaning, bent by -2e-3 .. 2e-3 px/row^2
    curve = 2e-3 * (rows - 800.0) ** 2 * (seg % 3 - 1)
    m = 100.0 + 100.0 * seg + 0.3 * (rows - 800.0) + curve + rng.normal(0, 0.3, seg.size)
    u = m + rng.normal(0, 0.3, seg.size)
    row_ok = rng.random(seg.size) > 0.15
    got, ok = _bend_kernel(seg, order, skey, inner, m, row_ok, W)
    want, ok_want, *_ = _fit_reference(seg, key, skey, order, inner, m, u, row_ok, W, 2, True)
    np.testing.assert_array_equal(ok, ok_want)
    assert ok.sum() > 0.5 * seg.size
    # the curvatures' noise is 0.003 (W = 12) to 0.05 px/row^2 (W = 3); measured rounding
    # 5e-10 and 5e-8
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-6)


def test_pick_curved_matches_numpy_reference():
    """degree="auto"'s choice by merge walks and a compiled loop equals the NumPy version
    (sorts, searchsorted), bit for bit, with both choices made."""
    from multislit.stripes.refine import _pick_curved, _segment_rows

    rng = np.random.default_rng(3)
    R = 3
    seg, rows, span = _segment_points(rng, n_seg=20, h=200, R=R)
    key, order, *_ = _segment_rows(seg, rows, span, 0)
    K = seg.size
    delta1 = rng.normal(0, 0.1, K)
    # d = delta2 - delta1: a curvature per segment, from none to well above the noise, so
    # that many points lie near the test's threshold
    bend = np.r_[rng.uniform(-0.4, 0.4, seg.max() + 1), 0.0][seg]
    delta2 = delta1 + rng.normal(0, 0.05, K) + bend
    gain = np.where(seg >= 0, rng.uniform(0.01, 0.05, K), np.nan)
    gain[rng.random(K) < 0.05] = np.nan  # points without a degree-2 fit
    got = _pick_curved(delta1, delta2, gain, key, order, R, delta1)
    want = _pick_curved_reference(delta1, delta2, gain, key, R)
    np.testing.assert_array_equal(got, want)
    assert 0 < np.mean(got != delta1) < 1


def test_refine_same_in_threads_and_after_other_sizes():
    """Each thread's reused work arrays: the same results from two threads at once, and
    after a call on an image of another size, as from one call alone."""
    from concurrent.futures import ThreadPoolExecutor

    cases = []
    for seed, kw in ((0, {}), (7, {"h": 200, "w": 257, "n_stripes": 11})):
        img, _ = render(seed=seed, **kw)
        ex = extract_slits(img, stripe_width_px=3.06, dot_size_px=1.9)
        cases.append((img, ex.u, ex.v, ex.segment, ex.stripe_width_px, ex.dot_size_px))
    alone = [refine_centres(*c) for c in cases]
    again = [refine_centres(*c) for c in cases[::-1]][::-1]
    with ThreadPoolExecutor(2) as pool:
        threads = list(pool.map(lambda c: refine_centres(*c), cases * 3))
    for got in (again, threads[:2], threads[2:4], threads[4:]):
        for (u, ok), (u0, ok0) in zip(got, alone, strict=True):
            np.testing.assert_array_equal(u, u0)
            np.testing.assert_array_equal(ok, ok0)
