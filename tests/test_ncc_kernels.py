"""The identification's compiled kernels against straightforward NumPy computations: the NCC of
templates with bilinear reference patches, the Newton steps of the epipolar intersections,
the nearest reference per hypothesis, the candidates' split into scored and sampled ones, the
sheared patches' sample maps and the template rows' lookup."""

import cv2
import numpy as np
import pytest

from multislit.identify import curve_du, curve_u, normalise_patches, sample_patches
from multislit.identify.matching import (
    _fast_cells,
    _nearest_candidates,
    _sorted_positions,
)
from multislit.identify.patches import (
    _remap_patches,
    bilinear_ncc,
    bilinear_patch_moments,
    window_sums,
)
from multislit.identify.reference import intersect_line_curves


def _dot_images(rng, r, h, w):
    """Sparse blurred dots, like the separated dot images (mostly exactly 0)."""
    img = np.where(rng.random((r, h, w)) < 0.04, rng.uniform(20, 230, (r, h, w)), 0.0)
    img = np.stack([cv2.GaussianBlur(d.astype(np.float32), (3, 3), 0.6) for d in img])
    return img.astype(np.float32)


def _straightforward_ncc(images, templates, which, x, y, half_w, half_h):
    """Each patch sampled and normalised, dotted with its sample's normalised template."""
    m, C = which.shape
    tmpl = normalise_patches(templates)
    out = np.zeros((m, C))
    for s in range(m):
        for c in range(C):
            centre = np.array([[x[s, c] + half_w, y[s, c] + half_h]])
            p = normalise_patches(sample_patches(images[which[s, c]], centre, half_w, half_h))
            out[s, c] = float(p[0].astype(np.float64) @ tmpl[s].astype(np.float64))
    return out


@pytest.mark.parametrize(("half_w", "half_h"), [(3, 8), (7, 2), (4, 4)])
def test_bilinear_ncc_equals_sampled_patches(rng, half_w, half_h):
    R, H, W, m, C = 3, 48, 56, 9, 5
    images = _dot_images(rng, R, H, W)
    sums = np.stack([window_sums(d, half_w, half_h).transpose(1, 0, 2) for d in images])
    xmax, ymax = W - 1 - 2 * half_w, H - 1 - 2 * half_h
    x = rng.uniform(0, xmax, (m, C))
    y = rng.uniform(0, ymax, (m, C))
    x[0, :3], y[0, :3] = [0.0, xmax, xmax], [0.0, ymax, 7.0]  # at the image's ends
    y[1] = np.round(y[1])  # whole rows
    which = rng.integers(0, R, (m, C))
    templates = _dot_images(rng, m, 2 * half_h + 1, 2 * half_w + 1)
    templates[2] = 0.0  # a flat template: no dots around the sample
    want = _straightforward_ncc(images, templates, which, x, y, half_w, half_h)
    got = bilinear_ncc(images, templates, which, x, y, sums, half_w, half_h)
    assert got.shape == (m, C) and np.abs(want).max() > 0.2
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert np.all(got[2] == 0)
    # padded rows and the transposed images passed in: the same numbers
    pad = np.zeros((R, H, W + 16), np.float32)
    pad[:, :, :W] = images
    pad_t = np.zeros((R, W, H + 16), np.float32)
    pad_t[:, :, :H] = images.transpose(0, 2, 1)
    again = bilinear_ncc(pad, templates, which, x, y, sums, half_w, half_h, images_t=pad_t)
    np.testing.assert_allclose(again, want, atol=2e-5)


def test_bilinear_ncc_of_a_flat_patch_is_zero(rng):
    images = np.zeros((1, 30, 30), np.float32)
    images[0, :, 20:] = 7.0  # flat on the left, an edge on the right
    sums = window_sums(images[0], 2, 3).transpose(1, 0, 2)[None].copy()
    templates = rng.uniform(0, 10, (2, 7, 5)).astype(np.float32)
    x = np.array([[3.2, 17.0], [1.0, 18.5]])
    y = np.full((2, 2), 10.4)
    got = bilinear_ncc(images, templates, np.zeros((2, 2), np.intp), x, y, sums, 2, 3)
    assert np.all(got[:, 0] == 0) and np.all(got[:, 1] != 0)


def test_patch_moments_equal_sampled_patches_in_both_layouts(rng):
    images = _dot_images(rng, 2, 40, 50)
    hw, hh = 3, 6
    sums = np.stack([window_sums(d, hw, hh) for d in images])
    x = rng.uniform(0, 50 - 1 - 2 * hw, 60)
    y = rng.uniform(0, 40 - 1 - 2 * hh, 60)
    which = rng.integers(0, 2, 60)
    p = np.stack(
        [
            sample_patches(images[k], np.array([[a + hw, b + hh]]), hw, hh)[0]
            for a, b, k in zip(x, y, which, strict=True)
        ]
    ).reshape(60, -1)
    s1, s2 = bilinear_patch_moments(sums, x, y, which)
    t1, t2 = bilinear_patch_moments(sums.transpose(0, 2, 1, 3).copy(), x, y, which, x_major=True)
    np.testing.assert_allclose(s1, p.sum(axis=1, dtype=np.float64), rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(s2, (p.astype(np.float64) ** 2).sum(axis=1), rtol=1e-5, atol=1e-2)
    np.testing.assert_allclose(t1, s1, rtol=1e-12)
    np.testing.assert_allclose(t2, s2, rtol=1e-12)


def _numpy_newton(lines, coeffs, v0, iterations=6, tol=1e-6):
    """The Newton steps in NumPy, all points together, stopping when no step exceeds tol."""
    v = np.array(v0, dtype=float, copy=True)
    a, b, c = lines[..., 0], lines[..., 1], lines[..., 2]
    for _ in range(iterations):
        f = a * curve_u(coeffs, v) + b * v + c
        df = a * curve_du(coeffs, v) + b
        with np.errstate(divide="ignore", invalid="ignore"):
            dv = f / np.where(np.abs(df) > 1e-12, df, np.nan)
            v = v - dv
            if not np.any(np.abs(dv) > tol):
                break
    return v


def _lines_and_curves(rng, R, M, N):
    uv = np.c_[rng.uniform(0, 600, M), rng.uniform(0, 500, M)]
    e = np.array([3000.0, 200.0, 1.0])
    h = np.c_[uv, np.ones(M)]
    ln = np.cross(h, e)
    ln /= np.linalg.norm(ln[:, :2], axis=1, keepdims=True)
    coeffs = np.zeros((R, N, 4))
    coeffs[..., 0] = rng.normal(0, 1e-8, (R, N))
    coeffs[..., 1] = rng.normal(0, 1e-5, (R, N))
    coeffs[..., 2] = rng.normal(0.05, 0.02, (R, N))
    coeffs[..., 3] = np.linspace(20, 600, N)[None] + rng.uniform(-5, 5, (R, N))
    coeffs[0, 0, 2] = 1e9  # a curve the lines never meet in a sensible place (NaN or far)
    return uv, ln, coeffs


def test_intersections_equal_numpy_newton(rng):
    R, M, N = 3, 40, 7
    uv, ln, coeffs = _lines_and_curves(rng, R, M, N)
    v0 = np.broadcast_to(uv[None, :, 1:2], (R, M, N))
    args = (ln[None, :, None, :], coeffs[:, None, :, :], v0)
    got = intersect_line_curves(*args)
    want = _numpy_newton(*args)
    assert got.shape == (R, M, N) and np.isfinite(want).mean() > 0.9
    assert np.array_equal(got, want, equal_nan=True)  # the same float64 operations
    # in blocks of lines, each stopping on its own: the same as one call per block
    blocks = intersect_line_curves(*args, block=6)
    for a in range(0, M, 6):
        sl = slice(a, a + 6)
        part = _numpy_newton(ln[None, sl, None, :], coeffs[:, None, :, :], v0[:, sl])
        assert np.array_equal(blocks[:, sl], part, equal_nan=True)
    # lines and curves that vary along the same axis, and more iterations without a tolerance
    lv = np.broadcast_to(ln[:, None, :], (M, N, 3))
    cv = np.broadcast_to(coeffs[1][None], (M, N, 4))
    got = intersect_line_curves(lv, cv, v0[0], iterations=20, tol=0.0)
    assert np.array_equal(got, _numpy_newton(lv, cv, v0[0], 20, 0.0), equal_nan=True)


def test_fast_cells_equal_numpy_cells(rng):
    M, K, hw, hh, w, h = 40, 7, 3, 5, 60, 50
    ws, hs = w - 2 * hw, h - 2 * hh
    # candidates lie inside the image (where the template fits), or are missing (NaN)
    cu = rng.uniform(hw, w - 1 - hw, (M, K))
    cv = rng.uniform(hh, h - 1 - hh, (M, K))
    cu[0, :3] = [hw, w - 1 - hw, np.nan]  # the last cells: n - 2, fraction 1
    cv[0, :3] = [h - 1 - hh, hh, np.nan]
    rr = rng.integers(0, 3, (M, K))
    ok = (rng.random((M, K)) < 0.8) & np.isfinite(cu)
    ok[0, :2] = True
    cu[~ok & (rng.random((M, K)) < 0.5)] = np.nan
    r_f = np.empty((M, K), np.intp)
    cells = (
        np.empty((M, K), np.intp),
        np.empty((M, K), np.intp),
        np.empty((M, K)),
        np.empty((M, K)),
    )
    n_max = _fast_cells(cu, cv, rr, ok, hw, hh, ws, hs, r_f, cells)
    assert n_max == ok.sum(axis=1).max()
    assert np.array_equal(r_f, np.where(ok, rr, 0))
    for x, n, c, f in (
        (np.where(ok, cu, hw) - hw, ws, *cells[::2]),
        (np.where(ok, cv, hh) - hh, hs, *cells[1::2]),
    ):
        want = np.minimum(np.floor(x), n - 2).astype(np.intp)
        assert np.array_equal(c, want) and np.array_equal(f, x - want)
    assert cells[2][0, 1] == 1.0 and cells[3][0, 0] == 1.0


def test_nearest_candidates_equal_argmin_of_hypot(rng):
    R, M, N = 3, 30, 6
    uv = rng.uniform(0, 100, (M, 2))
    uu = rng.uniform(0, 100, (R, M, N))
    vv = rng.uniform(0, 100, (R, M, N))
    gone = rng.random((R, M, N)) < 0.3
    uu[gone] = vv[gone] = np.nan
    uu[:, 0, 0] = vv[:, 0, 0] = np.nan  # no candidate at all
    # equal distances in two references: the first counts
    uu[1, 1, 1], vv[1, 1, 1] = uv[1, 0] + 3.0, uv[1, 1] + 4.0
    uu[2, 1, 1], vv[2, 1, 1] = uv[1, 0] - 4.0, uv[1, 1] - 3.0
    uu[0, 1, 1] = vv[0, 1, 1] = np.nan
    r_sel = np.empty((M, N), np.intp)
    cu, cv = np.empty((M, N)), np.empty((M, N))
    valid = np.empty((M, N), bool)
    _nearest_candidates(uu, vv, uv, r_sel, cu, cv, valid)
    disp = np.hypot(uu - uv[None, :, 0:1], vv - uv[None, :, 1:2])
    want = np.argmin(np.where(np.isfinite(disp), disp, np.inf), axis=0)
    assert np.array_equal(r_sel, want) and r_sel[1, 1] == 1 and r_sel[0, 0] == 0
    ii, kk = np.ogrid[:M, :N]
    assert np.array_equal(cu, uu[want, ii, kk], equal_nan=True)
    assert np.array_equal(cv, vv[want, ii, kk], equal_nan=True)
    assert np.array_equal(valid, np.isfinite(vv).any(axis=0))


def test_sheared_patches_equal_cv2_remap(rng):
    m, hw, hh = 40, 3, 5
    ph, pw = 2 * hh + 1, 2 * hw + 1
    centres = rng.uniform(-2, 52, (m, 2))  # some patches leave the image
    centres[:3] = [[25.0, 25.0], [0.0, 0.0], [49.0, 49.0]]
    shift = rng.normal(0, 2, (m, ph))
    rise = rng.normal(0, 1, (m, ph))
    scale = rng.uniform(0.5, 1.5, m)
    img = _dot_images(rng, 1, 50, 50)[0] + rng.uniform(0, 1, (50, 50)).astype(np.float32)
    # the sample positions, as float32 sums in their order
    du = np.arange(-hw, hw + 1, dtype=np.float32)
    dv = np.arange(-hh, hh + 1, dtype=np.float32)
    cols = (scale[:, None, None] * du[None, None, :]).astype(np.float32)
    mx = (centres[:, 0, None, None].astype(np.float32) + cols).repeat(ph, axis=1)
    mx += shift.astype(np.float32)[:, :, None]
    my = (centres[:, 1, None, None].astype(np.float32) + dv[None, :, None]).repeat(pw, axis=2)
    my += rise.astype(np.float32)[:, :, None]
    want = cv2.remap(
        img,
        mx.reshape(m * ph, pw),
        my.reshape(m * ph, pw),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    ).reshape(m, ph, pw)
    got = _remap_patches(img, centres, hw, hh, shift, rise, scale)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-4)  # (cv2's float32 blends)
    # upright patches: sample_patches, also at the image's edges (to the float32 positions)
    up = _remap_patches(img, centres, hw, hh)
    np.testing.assert_allclose(up, sample_patches(img, centres, hw, hh), rtol=1e-5, atol=1e-3)
    assert np.all(got[2, -3:, -3:] == 0)  # beyond the image


def test_sorted_positions_equal_searchsorted(rng):
    keys = np.sort(rng.integers(0, 200, 150)).astype(np.float64)
    start = rng.integers(-10, 210, 40).astype(np.float64)
    want_in = start[:, None] + np.arange(-5, 6)[None, :]
    pos = np.empty(want_in.shape, np.intp)
    _sorted_positions(keys, want_in, pos)
    assert np.array_equal(pos, np.clip(np.searchsorted(keys, want_in), 0, len(keys) - 1))
