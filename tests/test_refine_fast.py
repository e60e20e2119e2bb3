"""The compiled, windowed refinement and triangulation give the results of whole-image NumPy
reference implementations kept here (the slit image of ``refine_slit_image`` everywhere,
Steger's centres and the along-stripe fits vectorised over all points; the camera's rays
intersected with the planes)."""

from __future__ import annotations

import math

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
    refine_slit_image,
)
from multislit.stripes.refine import _CURVED_ALPHA

from .test_slits import render
from .test_triangulation import make_camera, points_on, slit_planes


# --------------------------------------------------------------------------- reference
def _steger_at(img, u, r, ss):
    w = img.shape[1]
    rad = math.ceil(3.0 * ss) + 1
    c = np.floor(u).astype(np.intp)
    x = np.arange(-rad, rad + 1)
    cols = np.clip(c[:, None] + x[None, :], 0, w - 1)
    p = img[r[:, None], cols].astype(np.float64)
    t = (c - u)[:, None] + x[None, :]
    g = np.exp(-0.5 * (t / ss) ** 2)
    d1 = np.einsum("kn,kn->k", p, t * g) / ss**2
    d2 = np.einsum("kn,kn->k", p, (t * t / ss**4 - 1.0 / ss**2) * g)
    return d1, d2


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


def _reference_auto(mom, rhs, count, base, R, seg, r):
    """degree="auto": degree 2 where d = u2 - u1 is significant, d^2 / g > s^2 chi2_1(1 - a)
    (g = var(u2 - u1) per unit noise, s^2 from pairs of windows 2 R + 1 rows apart), and so
    is d, of the same sign, R rows before or after on the segment."""
    d1, ok, v1 = _poly_fit(mom, rhs, count, base, 1, min(3, 2 * R + 1))
    d2, ok2, v2 = _poly_fit(mom, rhs, count, base & ok, 2, 4)
    gain = np.where(ok2, v2 - v1, np.nan)
    has = np.isfinite(gain) & (gain > 0)
    at = {(s, q): i for i, (s, q) in enumerate(zip(seg, r, strict=True)) if has[i]}
    pairs = [(i, at[s, q + 2 * R + 1]) for (s, q), i in at.items() if (s, q + 2 * R + 1) in at]
    if len(pairs) < 50:
        return d1, ok
    a, b = np.array(pairs).T
    d = d2 - d1
    s2 = np.median((d[a] - d[b]) ** 2 / (gain[a] + gain[b])) / scipy.stats.chi2.ppf(0.5, 1)
    sig = has & (d**2 > np.where(has, gain, 0) * s2 * scipy.stats.chi2.isf(_CURVED_ALPHA, 1))
    out = d1.copy()
    for (s, q), i in at.items():
        nbs = [at.get((s, q + off)) for off in (-R, R)]
        if sig[i] and any(j is not None and sig[j] and d[j] * d[i] > 0 for j in nbs):
            out[i] = d2[i]
    return out, ok


def _reference_refine(img, u, v, seg, sw, ds, R=None, deg="auto", max_shift=1.0, end=None):
    """refine_centres on the whole-image slit image, all points vectorised."""
    h, w = img.shape
    u = np.asarray(u, float)
    r = np.rint(v).astype(np.intp)
    seg = np.asarray(seg, np.int64)
    R = refine_half_rows(sw) if R is None else R
    end = opening_length(ds) if end is None else end
    sigma = sw / FWHM_PER_SIGMA
    ss = max(1.25 * sigma, 0.7)
    slit = refine_slit_image(img, sw, ds, 2 * R + 1, 2 * median_stride(sw) + 1)
    m = u.copy()
    for _ in range(2):
        d1, d2 = _steger_at(slit, np.clip(m, 0, w - 1), r, ss)
        good = d2 < 0
        m = m + np.clip(np.where(good, -d1 / np.where(good, d2, -1.0), 0.0), -1.0, 1.0)
    row_ok = good & (np.abs(m - u) <= max_shift)
    K = u.size
    has = seg >= 0
    span = h + 2 * R + 2
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
    reach = np.minimum(inner, R)
    n = 3 if deg == "auto" else deg + 1
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
    base = has & (reach >= R // 2) & (inner >= 0)
    if deg == "auto":
        delta, ok = _reference_auto(mom, rhs, count, base, R, seg, r)
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
def test_refine_matches_whole_image_reference(seed, kw, opts):
    """Same refined centres and the same points refined as the whole-image reference, on
    images with dots (windows meet dot runs, slopes, image borders and segment ends)."""
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


def test_refine_auto_degree_follows_curved_stripe_keeps_straight_one():
    """degree="auto" fits a parabola where the stripe is curved (a 40 mm sphere's arc bends by
    ~0.01 px/row^2) and a line where it is straight, on speckled stripes."""
    from .test_slits import _one_stripe

    # u = u0 + c (v - h/2)^2, c = 8e-3 px/row^2: degree 1 biased by c R (R + 1) / 3 = 0.19 px
    # (R = 8) plus the row centres' own bias on a curved stripe
    h, c = 120, 8e-3
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
    # measured mean error +0.113 px (auto), +0.267 px (degree 1; +0.082 px degree 2 at every
    # point); RMS 0.151 vs 0.273 px
    assert np.mean(e1) > 0.2, np.mean(e1)
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
    np.testing.assert_array_equal(oka, ok1)
    # measured: the line at every point
    assert np.mean(ua[oka] != u1[ok1]) < 0.02


@pytest.mark.parametrize("degree", ["cubic", 3, -1])
def test_refine_rejects_bad_degree(degree):
    img = np.zeros((20, 20), np.uint8)
    with pytest.raises(ValueError, match="degree must be"):
        refine_centres(img, [5.0], [5.0], [0], 3.0, degree=degree)
