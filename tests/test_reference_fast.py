"""The reference's dot search made fast: the same patches, scores and tracks as the direct
search (every candidate sampled and normalised for every template)."""

import cv2
import numpy as np
import pytest

from multislit.identify import curve_u, normalise_patches, sample_patches
from multislit.identify.patches import compile_kernels, sample_patch_columns
from multislit.identify.reference import (
    _dot_tracks,
    _search_scores,
    _track_epipole,
    estimate_epipole,
)


def _dot_image(rng, h, w, n):
    """Gaussian dots (sigma 1.2 px) at random places: a float32 dot image."""
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w))
    for x, y in rng.uniform([0, 0], [w, h], (n, 2)):
        img += 100 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2**2))
    return img.astype(np.float32)


def test_patch_columns_are_sample_patches_transposed(rng):
    img = _dot_image(rng, 60, 50, 40)
    centres = np.r_[
        rng.uniform([8, 10], [42, 50], (30, 2)),  # inside
        np.c_[rng.uniform(8, 42, 5), np.arange(10.0, 15.0)],  # whole rows (no blend along v)
        [[1.5, 30.2], [48.7, 30.0], [20.0, 1.0], [20.3, 58.9], [-9.0, -9.0]],  # at the edges
    ]
    cols, s1, s2 = sample_patch_columns(img, centres, 4, 7)
    want = sample_patches(img, centres, 4, 7)
    assert cols.shape == (len(centres), 9, 15)
    assert np.array_equal(cols, want.transpose(0, 2, 1))  # the same float32 values
    flat = want.reshape(len(want), -1).astype(np.float64)
    np.testing.assert_allclose(s1, flat.sum(axis=1), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(s2, (flat**2).sum(axis=1), rtol=1e-12, atol=1e-9)
    # the transposed image may be passed in; a wrong one is refused
    again, _, _ = sample_patch_columns(img, centres, 4, 7, image_t=np.ascontiguousarray(img.T))
    assert np.array_equal(again, cols)
    with pytest.raises(ValueError, match="image_t"):
        sample_patch_columns(img, centres, 4, 7, image_t=img)
    compile_kernels()


def test_search_scores_are_normalised_dot_products(rng):
    hw, hh, step, n_offs, m = 3, 6, 8, 21, 5
    img = _dot_image(rng, 120, 40, 60)
    tmpl = normalise_patches(sample_patches(img, rng.uniform([10, 10], [30, 30], (m, 2)), hw, hh))
    n_rows = (m - 1) * step + n_offs
    centres = np.c_[20 + 0.05 * np.arange(n_rows), 12.3 + np.arange(n_rows)]
    cols, s1, s2 = sample_patch_columns(img, centres, hw, hh)
    cols[4] = 7.0  # a flat candidate scores 0
    flat = cols[4].astype(np.float64)
    s1[4], s2[4] = flat.sum(), (flat**2).sum()
    got = _search_scores(tmpl, hw, hh, cols, s1, s2, step, n_offs)
    cand = normalise_patches(cols.transpose(0, 2, 1))  # back to (rows, columns) patches
    rows = np.arange(m)[:, None] * step + np.arange(n_offs)
    want = np.einsum("mk,mjk->mj", tmpl, cand[rows])
    assert got.dtype == np.float32 and got.shape == (m, n_offs)
    np.testing.assert_allclose(got, want, atol=2e-6)
    assert got[0, 4] == 0.0


def _direct_tracks(curves, vrange, dots, spacing_px):
    """The dot search written directly: every candidate of every template sampled."""
    hw = max(3, int(round(0.35 * spacing_px)))
    hh = max(6, int(round(0.6 * spacing_px)))
    search = int(round(2.5 * spacing_px))
    tracks = []
    for a in range(len(dots)):
        for b in range(a + 1, len(dots)):
            for k in range(curves.shape[1]):
                lo = max(vrange[a, k, 0], vrange[b, k, 0]) + hh + search
                hi = min(vrange[a, k, 1], vrange[b, k, 1]) - hh - search
                vs = np.arange(lo, hi, max(hh, 8.0))
                ua = curve_u(curves[a, k], vs)
                tmpl = normalise_patches(sample_patches(dots[a], np.c_[ua, vs], hw, hh))
                offs = np.arange(-search, search + 1, 1.0)
                vb = (vs[:, None] + offs[None, :]).ravel()
                cand = normalise_patches(
                    sample_patches(dots[b], np.c_[curve_u(curves[b, k], vb), vb], hw, hh)
                )
                score = np.einsum("mk,mjk->mj", tmpl, cand.reshape(len(vs), len(offs), -1))
                j = np.argmax(score, axis=1)
                best = score[np.arange(len(vs)), j]
                third = np.sort(score, axis=1)[:, -3]
                ok = (best > 0.5) & (best - third > 0.15) & (j > 0) & (j < len(offs) - 1)
                for i in np.flatnonzero(ok):
                    s0, s1, s2 = score[i, j[i] - 1 : j[i] + 2]
                    den = s0 - 2 * s1 + s2
                    v2 = vs[i] + offs[j[i]] + (0.5 * (s0 - s2) / den if den < 0 else 0.0)
                    tracks.append((ua[i], vs[i], curve_u(curves[b, k], v2), v2))
    return np.array(tracks)


def test_dot_tracks_match_the_direct_search(rng):
    """Three boards: the dots and slits move away from an epipole e between them."""
    h, w, e = 300, 120, np.array([60.0, -400.0])
    base = _dot_image(rng, h, w, 250)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    scales = (0.0, 0.01, 0.02)
    dots = []
    for s in scales:
        # the board at another distance: a point at p shows at e + (1 + s) (p - e)
        mx = (e[0] + (xx - e[0]) / (1 + s)).astype(np.float32)
        my = (e[1] + (yy - e[1]) / (1 + s)).astype(np.float32)
        dots.append(cv2.remap(base, mx, my, cv2.INTER_LINEAR))
    dots = np.array(dots)
    # three slightly slanted slits u = c + 0.02 v (sub-pixel columns along them), mapped alike
    c0 = np.array([35.0, 60.0, 85.0])
    curves = np.zeros((3, 3, 4))
    curves[:, :, 2] = 0.02
    for r, s in enumerate(scales):
        curves[r, :, 3] = e[0] + (1 + s) * (c0 - e[0]) + 0.02 * s * e[1]
    vrange = np.tile([5.0, h - 6.0], (3, 3, 1))
    spacing = 14.0
    got = _dot_tracks(curves, vrange, dots, spacing)
    want = _direct_tracks(curves, vrange, dots, spacing)
    assert len(got) > 30 and got.shape == want.shape
    assert np.array_equal(got[:, :2], want[:, :2])  # the same templates matched
    np.testing.assert_allclose(got[:, 2:], want[:, 2:], atol=1e-4)  # float32 scores' rounding
    epi, rms = estimate_epipole(curves, vrange, dots, spacing, h)
    assert np.linalg.norm(epi[:2] / epi[2] - e) < 0.03 * np.linalg.norm(e) and rms < 0.3


def _tracks_towards(rng, e, starts, length, noise):
    """(T, 4) tracks from ``starts`` (T, 2) ``length`` px away from the epipole ``e`` (3,)
    (homogeneous) along their lines through it, the ends moved by ``noise`` px (Gaussian)."""
    d = e[:2] - starts * e[2]  # towards the epipole (its direction when e is at infinity)
    d = -d / np.linalg.norm(d, axis=1, keepdims=True) * np.sign(e[2] if e[2] else 1.0)
    ends = starts + length[:, None] * d + rng.normal(0.0, noise, starts.shape)
    return np.c_[starts, ends]


def _line_offsets(e_true, e_got, size, reach):
    """px: for points across an image of ``size`` (W, H), how far the point ``reach`` px along
    the true epipolar line lies from the estimated line through the same point."""
    u, v = np.meshgrid(np.linspace(0, size[0], 9), np.linspace(0, size[1], 7))
    p = np.c_[u.ravel(), v.ravel()]
    d = e_true[:2] - p * e_true[2]
    q = p + reach * d / np.linalg.norm(d, axis=1, keepdims=True)
    ln = np.cross(np.c_[p, np.ones(len(p))], e_got)
    ln /= np.linalg.norm(ln[:, :2], axis=1, keepdims=True)
    return np.abs(np.einsum("ij,ij->i", ln, np.c_[q, np.ones(len(q))]))


@pytest.mark.parametrize(
    ("epipole", "wrong_share"),
    (((5600.0, -450.0, 1.0), 0.3), ((700.0, -3000.0, 1.0), 0.45), ((1.0, 0.08, 0.0), 0.4)),
)
def test_track_epipole_survives_wrong_tracks(rng, epipole, wrong_share):
    """A few dozen tracks, up to 45 % of them wrong matches: nearly level ones, as a template
    matched to the wrong place along its slit gives, crossing the right ones' lines. The
    epipole comes out within 0.5 px over 100 px of every true epipolar line across the image
    (the right tracks' ends are 0.15 px off; they alone give up to 0.45 px over 200 draws),
    and the residual is their noise."""
    e = np.array(epipole) / np.linalg.norm(epipole)
    size = (1440, 1080)
    n = 20
    n_wrong = int(round(wrong_share * n / (1 - wrong_share)))
    good = _tracks_towards(
        rng, e, rng.uniform([300, 100], [1100, 1000], (n, 2)), rng.uniform(90, 140, n), 0.15
    )
    starts = rng.uniform([300, 100], [1100, 1000], (n_wrong, 2))
    step = rng.uniform(100, 270, n_wrong)
    wrong = np.c_[starts, starts[:, 0] - step, starts[:, 1] + rng.uniform(-6, 6, n_wrong)]
    tracks = rng.permutation(np.r_[good, wrong])
    got, rms = _track_epipole(tracks)
    assert got.shape == (3,) and np.isclose(np.linalg.norm(got), 1.0)
    assert _line_offsets(e, got, size, 100.0).max() < 0.5
    assert 0.05 < rms < 0.3
