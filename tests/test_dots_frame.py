"""The frame's dots' compiled pieces against the whole-image definitions they stand for."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from multislit.identify.evidence import (
    BLOCK_PX,
    MATCH_TOL_PX,
    _block_counts,
    false_match_map,
)
from multislit.stripes.dots import (
    DotCentres,
    _nan_near_clipped,
    _response_noise,
    dots_off_stripes,
    find_dots,
    gaussian_f32,
    near_stripes,
    point_grid,
)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
@pytest.mark.parametrize(("sigma", "taps"), [(0.5, 5), (0.89, 7), (1.7, 11)])
def test_gaussian_f32_is_opencvs_blur_three_sigmas_wide(dtype, sigma, taps):
    """OpenCV's Gaussian of the kernel size it takes for 8-bit data (3 sigmas either side),
    computed in float32 whatever the data."""
    rng = np.random.default_rng(1)
    top = 255 if dtype == np.uint8 else 4095
    img = rng.integers(0, top + 1, (37, 53)).astype(dtype)
    want = cv2.GaussianBlur(img.astype(np.float32), (taps, taps), sigma)
    got = gaussian_f32(img, sigma)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * top)
    # within a fraction of a percent of the untruncated Gaussian
    full = cv2.GaussianBlur(img.astype(np.float64), (0, 0), sigma)
    assert np.abs(got - full).max() < 0.01 * top


def test_find_dots_takes_every_local_maximum_above_the_threshold():
    """The dots are the pixels of the smoothed image at least as high as their 8 neighbours and
    above the threshold (off the image's edge), centred by the parabola through the logarithms
    of their neighbours: checked on noise, where maxima touch and plateaus occur."""
    rng = np.random.default_rng(4)
    img = np.round(rng.gamma(0.6, 3.0, (290, 120))).astype(np.float32)  # three strips of rows
    noise, size, k = 1.0, 2.1, 4.0
    dots = find_dots(img, noise, size, k_sigma=k)
    sigma = size / 2.3548200450309493
    s = cv2.GaussianBlur(img, (7, 7), sigma)  # to 3 sigmas
    thr = np.float32(k * noise / (2.0 * math.sqrt(math.pi) * sigma))
    peak = (s >= cv2.dilate(s, np.ones((3, 3), np.uint8))) & (s > thr)
    peak[0, :] = peak[-1, :] = peak[:, 0] = peak[:, -1] = False
    r, c = np.nonzero(peak)  # row by row, as the dots come
    assert len(r) > 50
    np.testing.assert_array_equal(np.rint(dots.v), r)
    np.testing.assert_array_equal(np.floor(dots.u + 0.5), c)
    np.testing.assert_array_equal(dots.peak, s[r, c])
    lg = np.log(np.maximum(s.astype(np.float64), 1e-3 * float(thr)))

    def vertex(a, b, c_):
        den = a - 2.0 * b + c_
        off = np.where(den < 0, 0.5 * (a - c_) / np.where(den < 0, den, -1.0), 0.0)
        return np.clip(off, -0.5, 0.5)

    np.testing.assert_allclose(dots.u - c, vertex(lg[r, c - 1], lg[r, c], lg[r, c + 1]), atol=1e-9)
    np.testing.assert_allclose(dots.v - r, vertex(lg[r - 1, c], lg[r, c], lg[r + 1, c]), atol=1e-9)


def test_find_dots_finds_more_dots_than_it_first_makes_room_for():
    img = np.zeros((300, 600), np.float32)
    img[2:-2:3, 2:-2:3] = 50.0  # 99 x 199 separate peaks
    dots = find_dots(img, 1.0, 0.6)
    assert len(dots) == 99 * 199 > 1 << 14
    np.testing.assert_allclose(dots.u[:3], [2.0, 5.0, 8.0], atol=1e-3)


@pytest.mark.parametrize("cell", [1.0, 4.0, 7.5])
def test_point_grid_lists_each_point_once_in_its_cell(cell):
    rng = np.random.default_rng(5)
    u = rng.uniform(-3.0, 63.0, 400)
    v = rng.uniform(-3.0, 43.0, 400)
    order, start, nx, ny = point_grid(u, v, (40, 60), cell)
    assert (nx, ny) == (math.ceil(60 / cell), math.ceil(40 / cell))
    assert start[0] == 0 and start[-1] == 400
    np.testing.assert_array_equal(np.sort(order), np.arange(400))
    cx = np.clip((u / cell).astype(int), 0, nx - 1)
    cy = np.clip((v / cell).astype(int), 0, ny - 1)
    for g in range(nx * ny):
        members = order[start[g] : start[g + 1]]
        np.testing.assert_array_equal(members, np.flatnonzero(cy * nx + cx == g))


@pytest.mark.parametrize("clearance", [1.0, 2.96, 4.5])
def test_speckle_is_judged_by_the_stripe_peaks_in_the_disc(clearance):
    """A dot near a stripe is compared with the largest stripe peak whose centre's pixel lies
    in the disc (OpenCV's elliptic element) of the clearance around the dot's pixel."""
    rng = np.random.default_rng(6)
    shape = (50, 70)
    u, v = rng.uniform(0, 69, 300), rng.uniform(0, 49, 300)
    peak = rng.uniform(10.0, 100.0, 300)
    zone = near_stripes(u, v, shape, clearance)
    dots = DotCentres(rng.uniform(0, 69, 500), rng.uniform(0, 49, 500), rng.uniform(0, 40, 500))
    kept, near = dots_off_stripes(dots, zone, u, v, peak, clearance, 0.2)
    # the definition: the stripes' peaks spread by a dilation with the disc
    rad = max(1, math.ceil(clearance))
    pk = np.zeros(shape, np.float32)
    np.maximum.at(pk, (np.rint(v).astype(int), np.rint(u).astype(int)), peak.astype(np.float32))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
    spread = cv2.dilate(pk, disc, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    r = np.clip(np.rint(dots.v).astype(int), 0, 49)
    c = np.clip(np.rint(dots.u).astype(int), 0, 69)
    is_near = zone[r, c]
    keep = ~is_near | (dots.peak >= 0.2 * spread[r, c])
    assert 0 < np.count_nonzero(is_near & ~keep) and np.count_nonzero(is_near & keep) > 0
    np.testing.assert_array_equal(kept.u, dots.u[keep])
    np.testing.assert_array_equal(near, is_near[keep])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float64])
def test_nan_near_clipped_is_the_dilated_clipped_pixels(dtype):
    rng = np.random.default_rng(7)
    img = rng.integers(0, 200, (40, 50)).astype(dtype)
    img[0, 0] = img[39, 25] = img[17, 49] = img[20, 20] = img[21, 22] = 250
    for radius in (1, 2, 3):
        out = np.zeros(img.shape, np.float32)
        _nan_near_clipped(img, 249.5, radius, out)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        want = cv2.dilate((img >= 249.5).astype(np.uint8), disc) > 0
        np.testing.assert_array_equal(np.isnan(out), want)
    out = np.zeros(img.shape, np.float32)
    _nan_near_clipped(img, None, 2, out)
    assert not np.isnan(out).any()


def _noise_table_reference(x, level, bins):
    """The noise table's definition in numpy: quantile bins of the level, each bin's median
    and 1.4826 median absolute deviations, at least a quarter of their median."""
    e = np.quantile(level, np.linspace(0.0, 1.0, bins + 1))
    e[0], e[-1] = -np.inf, np.inf
    b = np.clip(np.searchsorted(e, level, side="right") - 1, 0, bins - 1)
    med = np.array([np.median(x[b == j]) for j in range(bins)])
    sig = np.array([1.4826 * np.median(np.abs(x[b == j] - med[j])) for j in range(bins)])
    return e, med, np.maximum(sig, 0.25 * np.median(sig))


def test_response_noise_is_the_quantile_bins_and_their_robust_spread():
    """Per zone, the levels' quantile bins and each bin's median and robust sigma; a zone of
    too few places takes every place's."""
    rng = np.random.default_rng(8)
    n = 3001
    level = rng.gamma(2.0, 30.0, n)
    zone = (rng.random(n) < 0.3).astype(np.uint8)
    x = rng.normal(0.5 * zone, 1.0 + level / 50.0 + zone)
    o = np.argsort(level)
    for zones, want_from in ((zone, (0, 1)), (np.zeros(n, np.uint8), (0, None))):
        edges = np.zeros((2, 13), np.float32)
        offset = np.zeros((2, 12), np.float32)
        sig = np.ones((2, 12), np.float32)
        _response_noise(x[o], level[o], zones[o], 0.3, edges, offset, sig)
        for z, src in enumerate(want_from):
            m = np.ones(n, bool) if src is None else zones == src
            e, med, s = _noise_table_reference(x[m], level[m], 12)
            np.testing.assert_allclose(edges[z, 1:-1], e[1:-1], rtol=1e-6)
            assert edges[z, 0] == -np.finfo(np.float32).max
            assert edges[z, -1] == np.finfo(np.float32).max
            np.testing.assert_allclose(offset[z], med, rtol=1e-6, atol=1e-6)
            np.testing.assert_allclose(sig[z], s, rtol=1e-6)
        assert sig[0, -1] > 1.5 * sig[0, 0]  # the noise grows with the level
    # too few places in all: unit bins and the given sigma
    edges = np.zeros((2, 13), np.float32)
    offset = np.zeros((2, 12), np.float32)
    sig = np.ones((2, 12), np.float32)
    _response_noise(x[o][:40], level[o][:40], zone[o][:40], 0.3, edges, offset, sig)
    np.testing.assert_allclose(edges, np.tile(np.linspace(0.0, 1.0, 13), (2, 1)), rtol=1e-6)
    np.testing.assert_array_equal(sig, 0.3 * np.ones((2, 12), np.float32))
    assert not offset.any()


@pytest.mark.parametrize("shape", [(16, 20), (37, 53)])
def test_block_counts_sum_each_block(shape):
    rng = np.random.default_rng(9)
    zone = (rng.random(shape) < 0.3).astype(np.uint8)
    hb, wb = -(-shape[0] // BLOCK_PX), -(-shape[1] // BLOCK_PX)
    out = np.full((hb, wb), -1.0, np.float32)
    _block_counts(zone, BLOCK_PX, out)
    pad = np.zeros((hb * BLOCK_PX, wb * BLOCK_PX), np.int64)
    pad[: shape[0], : shape[1]] = zone
    want = pad.reshape(hb, BLOCK_PX, wb, BLOCK_PX).sum(axis=(1, 3))
    np.testing.assert_array_equal(out, want)


@pytest.mark.parametrize("shape", [(200, 240), (198, 242)])
def test_false_match_chance_follows_the_local_density_of_each_zone(shape):
    """One dot per 4 x 4 px clear of the stripes and two near them (a band 40 px wide): inside
    each region the chance of a dot within the tolerance by chance is that of its density."""
    h, w = shape
    zone = np.zeros((h, w), bool)
    zone[:, 100:140] = True
    gu, gv = np.meshgrid(np.arange(2.0, w, 4.0), np.arange(2.0, h, 4.0))
    clear = (gu < 92) | (gu > 148)
    nu, nv = np.meshgrid(np.arange(102.0, 140.0, 4.0), np.arange(1.0, h, 2.0))
    u = np.r_[gu[clear], nu.ravel()]
    v = np.r_[gv[clear], nv.ravel()]
    near = np.r_[np.zeros(clear.sum(), bool), np.ones(nu.size, bool)]
    pf = false_match_map(DotCentres(u, v, np.ones(len(u))), near, zone, 24.0)
    assert pf.shape == (2, -(-h // BLOCK_PX), -(-w // BLOCK_PX))
    # the definition, block by block: the zone's dots and pixels in the square of 6 blocks
    # either side (24 px), the frame's density of the zone weighing as much as 400 px
    bv, bu = (v // BLOCK_PX).astype(int), (u // BLOCK_PX).astype(int)
    for z, pix in ((0, ~zone), (1, zone)):
        rho0 = np.count_nonzero(near == bool(z)) / pix.sum()
        for br in range(0, pf.shape[1], 7):
            for bc in list(range(0, pf.shape[2], 3)) + [pf.shape[2] - 1]:
                r0, r1 = max(br - 6, 0), br + 7
                c0, c1 = max(bc - 6, 0), bc + 7
                n = np.count_nonzero((near == bool(z)) & (bv >= r0) & (bv < r1) & (bu >= c0)
                                     & (bu < c1))  # fmt: skip
                a = pix[r0 * BLOCK_PX : r1 * BLOCK_PX, c0 * BLOCK_PX : c1 * BLOCK_PX].sum()
                rho = (n + 400.0 * rho0) / (a + 400.0)
                want = np.clip(1.0 - math.exp(-math.pi * MATCH_TOL_PX**2 * rho), 0.01, 0.5)
                assert pf[z, br, bc] == pytest.approx(want, rel=1e-5)
    # beside the band, where the clear zone holds no dots, the chance drops
    assert pf[0, 25, 24] < 0.85 * pf[0, 25, 10]
    assert pf.min() >= 0.01 and pf.max() <= 0.5
