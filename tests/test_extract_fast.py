"""The extraction's compiled kernels give exactly what the vectorised NumPy formulation gives.

Each reference below is the NumPy formulation of the step (fancy indexing, searchsorted, a
sparse graph's connected components); the kernels must match it bit for bit on random small
images and points of every pixel type, so that speeding the extraction up changes no result.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from multislit.stripes import (
    find_stripe_centres,
    link_segments,
    stripe_slope,
    texture_sigma,
    vertical_opening,
)
from multislit.stripes.centres import _gather, _row_maxima
from multislit.stripes.openings import _running_extreme, stripe_opening
from multislit.stripes.ridges import merge_dots
from multislit.stripes.separation import (
    _at_least,
    _median_of_counts,
    clip_level,
    fill_dots,
    mask_runs,
    noise_from_difference,
    quantisation_step,
    separate_validated,
)
from multislit.stripes.sizes import _best_scale, opening_length, ridge_contrast
from multislit.stripes.slope import (
    _blur_is_opencvs,
    _slopes_at,
    _tensor_at,
    slope_sigma,
)

DTYPES = (np.uint8, np.uint16, np.float32)


def _image(rng: np.random.Generator, dtype, h: int, w: int) -> np.ndarray:
    """Sparse bright pixels, a leaning stripe and a few dots: runs of every kind."""
    img = rng.random((h, w)) ** 4 * 180
    rows = np.arange(h)
    img[rows, np.clip((w // 3 + 0.3 * rows).astype(int), 0, w - 1)] += 150
    return img.astype(dtype)


def _row_sample_ref(img, r, u):
    w = img.shape[1]
    u = np.clip(u, 0.0, w - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.intp), w - 2) if w > 1 else np.zeros(u.shape, np.intp)
    f = (u - u0).astype(np.float32)
    a = img[r, u0].astype(np.float32)
    b = img[r, np.minimum(u0 + 1, w - 1)].astype(np.float32)
    return a + (b - a) * f


def _fill_dots_ref(hp, opened, tau, length, slope=None):
    """fill_dots by fancy indexing over all runs at once."""
    h, w = hp.shape
    diff = cv2.subtract(hp, opened)
    thr = cv2.addWeighted(opened, 0.05, opened, 0.0, tau)
    mask = cv2.dilate(cv2.compare(diff, thr, cv2.CMP_GT), np.ones((3, 3), np.uint8))
    out = hp.copy()
    if not mask.any():
        return out
    mt = np.zeros((w, h + 2), np.int8)
    mt[:, 1:-1] = cv2.transpose(mask) != 0
    col, start, stop = mask_runs(np.diff(mt, axis=1))
    n = stop - start
    ok = (start > 0) & (stop < h) & (n <= 2 * length)
    np.copyto(out, opened, where=mask != 0)
    col, start, stop, n = col[ok], start[ok], stop[ok], n[ok]
    if n.size == 0:
        return out
    run = np.repeat(np.arange(n.size), n)
    t = np.arange(run.size) - np.repeat(np.cumsum(n) - n, n) + 1
    frac = t / (n[run] + 1).astype(np.float32)
    rows, cols = start[run] + t - 1, col[run]
    if slope is None:
        above = hp[start - 1, col].astype(np.float32)[run]
        below = hp[stop, col].astype(np.float32)[run]
    else:
        s = slope[start + n // 2, col].astype(np.float32)[run]
        above = _row_sample_ref(hp, start[run] - 1, cols - s * t)
        below = _row_sample_ref(hp, stop[run], cols + s * (n[run] + 1 - t))
    val = above + (below - above) * frac
    if np.issubdtype(hp.dtype, np.integer):
        val = np.rint(val)
    out[rows, cols] = np.minimum(val, hp[rows, cols]).astype(hp.dtype)
    return out


@pytest.mark.parametrize("dtype", DTYPES)
def test_fill_dots_matches_vectorised_reference(dtype):
    rng = np.random.default_rng(3)
    for h, w in ((37, 48), (29, 45), (1, 9), (12, 1), (64, 64)):
        hp = _image(rng, dtype, h, w)
        opened = vertical_opening(hp, 5)
        slope = stripe_slope(hp, 2.5)
        for tau, length in ((1.5, 5), (0.2, 1), (40.0, 3)):
            got = fill_dots(hp, opened, tau, length, slope)
            assert got.dtype == hp.dtype
            np.testing.assert_array_equal(got, _fill_dots_ref(hp, opened, tau, length, slope))
            np.testing.assert_array_equal(
                fill_dots(hp, opened, tau, length), _fill_dots_ref(hp, opened, tau, length)
            )
        wild = rng.uniform(-3, 3, (h, w))  # any slope image, clamped samples at the borders
        np.testing.assert_array_equal(
            fill_dots(hp, opened, 0.5, 4, wild), _fill_dots_ref(hp, opened, 0.5, 4, wild)
        )


@pytest.mark.parametrize("dtype", DTYPES)
def test_row_maxima_and_gather_match_numpy(dtype):
    rng = np.random.default_rng(4)
    img = _image(rng, dtype, 41, 53)
    threshold = 30.7 if dtype == np.float32 else 30.0
    near = rng.random(img.shape) < 0.2
    # the peaks by NumPy: greater than the left, not less than the right neighbour, above thr
    # (a float32 image is compared with the threshold in float32), outside ``near``
    mid = img[:, 1:-1]
    thr = threshold if dtype == np.float32 else math.floor(threshold)
    is_max = (mid > img[:, :-2]) & (mid >= img[:, 2:]) & (mid > thr)
    r, c = np.nonzero(is_max)
    assert r.size > 20
    thr_exact = float(np.float32(threshold)) if dtype == np.float32 else float(thr)
    for use_near, expected in ((False, is_max), (True, is_max & ~near[:, 1:-1])):
        rr, cc = _row_maxima(img, thr_exact, near, use_near)
        er, ec = np.nonzero(expected)
        np.testing.assert_array_equal(rr, er)
        np.testing.assert_array_equal(cc, ec + 1)
    assert find_stripe_centres(img, threshold, k_sigma=1.0).u.size > 0
    c = c + 1
    offsets = np.arange(-3, 4)
    wts = np.array([1.0, 2.0, 1.0]) / 4.0
    ref = np.zeros((r.size, offsets.size))
    cols = np.clip(c[:, None] + offsets[None, :], 0, img.shape[1] - 1)
    for i, dv in enumerate((-1, 0, 1)):
        ref += wts[i] * img[np.clip(r + dv, 0, img.shape[0] - 1)[:, None], cols]
    np.testing.assert_array_equal(_gather(img, r, c, offsets, 3), ref)
    np.testing.assert_array_equal(_gather(img, r, c, offsets, 1), img[r[:, None], cols])


def _link_ref(u, v, max_du, max_gap, min_length):
    """link_segments by binary searches and a sparse graph's weak components."""
    rows = np.rint(v)
    n = u.size
    order = np.lexsort((u, rows))
    us = u[order] - u.min()
    rs = rows[order] - rows.min()
    max_g = max_gap + 1
    span = float(us.max()) + 2 * max_du * max_g + 2.0
    key = rs * span + us

    def first(sign):
        found = np.full(n, -1, np.int64)
        done = np.zeros(n, bool)
        for g in range(1, max_g + 1):
            centre = key + sign * g * span
            lo = np.searchsorted(key, centre - max_du * g, "left")
            hi = np.searchsorted(key, centre + max_du * g, "right")
            new = ~done & (hi > lo)
            found[new] = np.where(hi[new] - lo[new] == 1, lo[new], -2)
            done |= new
        return found

    nxt, prv = first(1), first(-1)
    src = np.flatnonzero(nxt >= 0)
    dst = nxt[src]
    keep = prv[dst] == src
    graph = coo_matrix((np.ones(keep.sum(), np.int8), (src[keep], dst[keep])), shape=(n, n))
    _, comp = connected_components(graph, directed=True, connection="weak")
    size = np.bincount(comp)
    mean_u = np.bincount(comp, weights=us) / size
    kept = np.flatnonzero(size >= min_length)
    new_id = np.full(size.size, -1, np.int64)
    new_id[kept[np.argsort(mean_u[kept], kind="stable")]] = np.arange(kept.size)
    labels = np.empty(n, np.int64)
    labels[order] = new_id[comp]
    return labels


def test_link_segments_matches_searchsorted_and_graph_reference():
    rng = np.random.default_rng(6)
    for k in range(40):
        n = int(rng.integers(1, 300))
        rows = rng.integers(0, 40, n).astype(float)
        u = np.round(rng.uniform(0, 30, n), 1 + k % 3)  # ties and near-ties
        if k % 2:  # sorted by (row, u), as the centres come
            o = np.lexsort((u, rows))
            u, rows = u[o], rows[o]
        v = rows + rng.uniform(-0.4, 0.4, n) * (k % 3 == 0)
        du, gap, ml = (0.0, 0.7, 1.5, 3.0)[k % 4], k % 4, 1 + k % 5
        np.testing.assert_array_equal(
            link_segments(u, v, max_du=du, max_gap=gap, min_length=ml),
            _link_ref(u, v, du, gap, ml),
        )


@pytest.mark.parametrize("dtype", (np.uint8, np.uint16))
def test_noise_histogram_matches_bincount(dtype):
    rng = np.random.default_rng(8)
    for h, w in ((31, 40), (2, 5), (64, 33)):
        img = _image(rng, dtype, h, w)
        d = cv2.absdiff(img[1::2], img[:-1:2])
        med = float(np.median(d))
        expected = max(1.4826 * med / math.sqrt(2.0), 1.0)
        assert noise_from_difference(img) == pytest.approx(expected, rel=1e-12, abs=0)


def test_texture_sigma_is_read_beside_the_line():
    """A bright line on a clean background leaves the texture beside it at the noise; texture
    on either side raises it there, and the line's own structure never counts."""
    rng = np.random.default_rng(9)
    h, w, sw = 120, 160, 4.0
    img = rng.normal(0, 1.0, (h, w)).astype(np.float32)
    u = np.arange(w)
    c = 80 + 2.0 * np.sin(np.arange(h) / 12)  # a bending line: its own differences are large
    img += 200 * np.exp(-0.5 * ((u[None, :] - c[:, None]) / 1.7) ** 2)
    on_line = (np.arange(h), np.rint(c).astype(int))
    level = texture_sigma(img, sw)
    assert level.shape == (h, w) and level.dtype == np.float32
    lag = np.abs(img[4:] - img[:-4])[:, 78:82]
    assert np.median(lag) > 10  # the line's own bends: large differences over the lag
    assert 0.5 < np.median(level[on_line]) < 2.5  # ~ the noise, not the line's bends
    rough = img.copy()
    rough[:, 95:110] += rng.normal(0, 20, (h, 15)).astype(np.float32)  # texture right of it
    assert np.median(texture_sigma(rough, sw)[on_line]) > 10 * np.median(level[on_line])
    assert texture_sigma(np.zeros((3, 10), np.uint8), 4.0).max() == 0  # shorter than the lag


def _ridge_contrast_ref(profiles, r, c, fwhm_px, reach_px):
    n = profiles.shape[1]
    fw = np.broadcast_to(np.asarray(fwhm_px, np.float64), r.shape)
    d0 = np.maximum(1, np.ceil(fw)).astype(np.intp)
    d1 = np.maximum(d0 + 1, np.ceil(2.0 * fw).astype(np.intp))
    off = np.arange(int(d1.max(initial=2)) + 1)
    reach = np.rint(np.broadcast_to(np.asarray(reach_px, np.float64), r.shape)).astype(np.intp)
    use = (off[None, :] >= d0[:, None]) & (off[None, :] <= d1[:, None])
    peak = profiles[r, np.clip(c, 0, n - 1)].astype(np.float64)
    hi = np.full(r.shape, -np.inf)
    for sign in (-1, 1):
        cols = (c + sign * reach)[:, None] + sign * off[None, :]
        inside = use & (cols >= 0) & (cols <= n - 1)
        vals = profiles[r[:, None], np.clip(cols, 0, n - 1)].astype(np.float64)
        side = np.where(inside, vals, np.inf).min(axis=1)
        hi = np.maximum(hi, np.where(np.isinf(side), -np.inf, side))
    hi = np.where(np.isinf(hi), 0.0, hi)
    return np.where(peak > 0, (peak - hi) / np.where(peak > 0, peak, 1.0), 0.0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_ridge_contrast_matches_vectorised_reference(dtype):
    rng = np.random.default_rng(10)
    for w in (1, 7, 60):
        prof = _image(rng, dtype, 25, w)
        k = 200
        r = rng.integers(0, 25, k)
        c = rng.integers(0, w, k)
        for fwhm, reach in ((3.0, 0.0), (rng.uniform(0.5, 9, k), rng.uniform(0, 4, k))):
            np.testing.assert_array_equal(
                ridge_contrast(prof, r, c, fwhm, reach),
                _ridge_contrast_ref(prof, r, c, fwhm, reach),
            )


def test_best_scale_is_argmax_over_scales():
    rng = np.random.default_rng(11)
    resp = rng.normal(size=(12, 9, 31)).astype(np.float32)
    resp[3, :4] = resp[5, :4] = 50.0  # ties: the first scale, as argmax
    best, strength, peak = _best_scale(resp)
    np.testing.assert_array_equal(best, resp.argmax(axis=0))
    np.testing.assert_array_equal(strength, resp.max(axis=0))
    assert peak == float(np.abs(resp).max())


@pytest.mark.parametrize("dtype", DTYPES + (np.float64,))
def test_vertical_opening_matches_running_extremes(dtype):
    rng = np.random.default_rng(12)
    for h, w in ((40, 30), (3, 17), (1, 5)):
        x = _image(rng, dtype, h, w)
        for length in (2, 5, 7, 9):
            ref = _running_extreme(_running_extreme(x, length, "min"), length, "max")
            got = vertical_opening(x, length)
            assert got.dtype == x.dtype
            np.testing.assert_array_equal(got, ref)


def _slope_ref(hp, sigma):
    """The stripe slope of the whole image: the structure tensor by cv2.Sobel and
    cv2.GaussianBlur over every pixel."""
    gu = cv2.Sobel(hp, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(hp, cv2.CV_32F, 0, 1, ksize=3)
    juu = cv2.GaussianBlur(gu * gu, (0, 0), sigma)
    juv = cv2.GaussianBlur(gu * gv, (0, 0), sigma)
    return np.clip(-juv / np.maximum(juu, np.float32(1e-6)), np.float32(-1.0), np.float32(1.0))


@pytest.mark.parametrize("dtype", DTYPES)
def test_slopes_at_points_equal_whole_image_structure_tensor(dtype):
    rng = np.random.default_rng(13)
    shapes = ((37, 48), (29, 45), (70, 61), (12, 1), (1, 9), (5, 3), (40, 203))
    for h, w in shapes:
        hp = _image(rng, dtype, h, w)
        for sigma in (1.5, 2.5, 4.5):
            ref = _slope_ref(hp, sigma)
            k = min(h * w, 300)
            flat = rng.choice(h * w, size=k, replace=False)
            mids, cols = np.divmod(flat, w)
            got = _slopes_at(hp, sigma, mids, cols)
            assert got.dtype == np.float32
            np.testing.assert_array_equal(got, ref[mids, cols])
        # every pixel, in any order, with repeats
        mids, cols = (a.ravel() for a in np.indices((h, w)))
        order = rng.permutation(np.r_[np.arange(h * w), np.arange(h * w)[: h * w // 3]])
        np.testing.assert_array_equal(
            _slopes_at(hp, 2.5, mids[order], cols[order]), _slope_ref(hp, 2.5)[mids, cols][order]
        )
    assert (
        _slopes_at(_image(rng, dtype, 9, 9), 2.5, np.empty(0, np.intp), np.empty(0, np.intp)).size
        == 0
    )


def test_tensor_kernel_reproduces_opencv_gaussian():
    """The compiled Gaussian at points gives cv2.GaussianBlur's float32 values bit for bit,
    on widths that reach OpenCV's vector loops and its scalar tail, near every border."""
    if not _blur_is_opencvs():
        pytest.skip("this OpenCV build rounds its Gaussian otherwise: cv2.GaussianBlur is used")
    rng = np.random.default_rng(14)
    for h, w, sigma in ((50, 77, 3.5), (8, 1280, 4.5), (61, 13, 1.5), (2, 40, 2.5)):
        x = rng.normal(0.0, 500.0, (h, w)).astype(np.float32)
        y = rng.normal(0.0, 50.0, (h, w)).astype(np.float32)
        mids, cols = (a.ravel() for a in np.indices((h, w)))
        taps = cv2.getGaussianKernel(round(sigma * 8 + 1) | 1, sigma, cv2.CV_32F).ravel()
        juu, juv = _tensor_at(x, x, y, taps, mids, cols)
        np.testing.assert_array_equal(juu, cv2.GaussianBlur(x * x, (0, 0), sigma).ravel())
        np.testing.assert_array_equal(juv, cv2.GaussianBlur(x * y, (0, 0), sigma).ravel())


def _clip_level_ref(img, step):
    """clip_level by a boolean selection, np.rint and np.bincount."""
    top = float(img.max())
    x = img[img >= top - (64 - 0.5) * step].astype(np.float64)
    k = np.minimum(np.rint((top - x) / step).astype(np.intp), 63)
    counts = np.bincount(k, minlength=64)
    tail = float(np.median(counts[16:]))
    if counts[0] < max(20, 4.0 * tail):
        return None
    excess = 2.0 * tail + 3.0 * math.sqrt(tail) + 2.0
    j = 0
    while j + 1 < 12 and counts[j + 1] > excess:
        j += 1
    return top - j * step


@pytest.mark.parametrize("dtype", DTYPES)
def test_clip_level_matches_selection_and_bincount(dtype):
    rng = np.random.default_rng(15)
    scale = 1.0 if dtype == np.float32 else 250.0
    levels = 0
    for k in range(12):
        img = (rng.random((40, 57)) ** (0.2 + 0.1 * k) * scale).astype(dtype)
        img[: 2 + k, :20] = img.max()  # a pile-up at the top (a clip), or too few pixels
        if dtype == np.uint16:
            img <<= 4
        for step in (quantisation_step(img), 1.0, 0.37, 3.0 / (k + 1)):
            got = clip_level(img, step)
            assert got == _clip_level_ref(img, step)
            levels += got is not None
    assert levels > 0


@pytest.mark.parametrize("dtype", DTYPES)
def test_saturation_compare_in_image_type_equals_float_compare(dtype):
    rng = np.random.default_rng(16)
    top = 1.0 if dtype == np.float32 else float(np.iinfo(dtype).max)
    img = (rng.random((30, 41)) * top).astype(dtype)
    for level in (-3.0, 0.0, 0.5, 17.2, top - 0.5, top, top + 0.5, 2 * top + 9, np.inf, np.nan):
        np.testing.assert_array_equal(_at_least(img, level), img >= level)


@pytest.mark.parametrize("dtype", DTYPES)
def test_slit_image_equals_refill_with_whole_image_slope(dtype):
    """The extraction's slit image (the slope only at the runs that need it) is fill_dots with
    the whole image's stripe slope (on the opening that follows leaning stripes)."""
    rng = np.random.default_rng(17)
    for h, w, ds in ((64, 80, 1.5), (57, 45, 2.1)):
        img = _image(rng, dtype, h, w)
        hp, slits, _, noise = separate_validated(img, 3.0, ds, None)
        length = opening_length(ds)
        slope = stripe_slope(hp, slope_sigma(length))
        ref = fill_dots(hp, stripe_opening(hp, length, 3.0 * noise), 3.0 * noise, length, slope)
        assert slits.dtype == hp.dtype
        assert np.any(slits != hp)  # dots were refilled
        np.testing.assert_array_equal(slits, ref)


def test_merge_dots_equals_the_whole_images_reach():
    """The dot image near the column pass's centres, made on their bounding box, is the one
    made over the whole image: the column pass's within the reach of a centre, the row
    pass's elsewhere."""
    rng = np.random.default_rng(21)
    h, w, sw = 90, 120, 3.2
    row_dots = rng.random((h, w)).astype(np.float32)
    col_dots = rng.random((h, w)).astype(np.float32) + 2.0
    for u, v in (
        (rng.uniform(30, 60, 25), rng.uniform(20, 40, 25)),
        (np.array([0.2, w - 0.6]), np.array([h - 0.6, 0.3])),  # at the corners
        (np.array([57.0]), np.array([44.0])),
    ):
        mark = np.zeros((h, w), np.uint8)
        mark[
            np.clip(np.rint(v).astype(np.intp), 0, h - 1), np.clip(u.astype(np.intp), 0, w - 1)
        ] = 1
        rad = math.ceil(1.5 * sw)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1,) * 2)
        ref = np.where(cv2.dilate(mark, disc).view(bool), col_dots, row_dots)
        got = merge_dots(row_dots, col_dots, u, v, sw)
        np.testing.assert_array_equal(got, ref)
        assert (got == col_dots).sum() > 0.5 * np.pi * rad**2


def test_median_of_counts_is_numpys_median():
    """The median read from the values' counts (the background's lift, the noise's pair
    differences) is NumPy's median of the values, odd and even counts alike."""
    rng = np.random.default_rng(23)
    for n in [*range(1, 30), 1000, 1001, 77777]:
        for top in (3, 255, 4000):
            x = rng.integers(0, top, n)
            assert _median_of_counts(np.bincount(x)) == float(np.median(x))
