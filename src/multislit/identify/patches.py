"""Bilinear patches of an image, normalised, and the window sums that give their moments.

The matching of dot templates (:mod:`~multislit.identify.matching`) and the epipole's dot
tracks (:func:`~multislit.identify.reference.estimate_epipole`) compare small patches of dot
images by normalised cross-correlation.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


def _corners_inside(
    centres: F64, half_w: int, half_h: int, shape: tuple[int, int]
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Each patch's top-left corner (x, y), px, and whether its bilinear cells (the patch and
    one pixel more to the right and below) lie inside an image of ``shape`` (H, W)."""
    h, w = shape
    x = centres[:, 0] - half_w
    y = centres[:, 1] - half_h
    with np.errstate(invalid="ignore"):
        inside = (x >= 0) & (np.floor(x) + 2 * half_w + 1 < w)
        inside &= (y >= 0) & (np.floor(y) + 2 * half_h + 1 < h)
    return x, y, inside


def sample_patches(image: F32, centres: F64, half_w: int, half_h: int) -> F32:
    """Bilinear patches of ``image`` around sub-pixel centres.

    Parameters
    ----------
    image : (H, W) float32
    centres : (M, 2) float64, px (u, v)
    half_w, half_h : patch half sizes, px

    Returns
    -------
    patches : (M, 2*half_h+1, 2*half_w+1) float32 (zero outside the image)
    """
    m = len(centres)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    if m == 0:
        return np.zeros((0, ph, pw), np.float32)
    image = np.asarray(image, dtype=np.float32)
    h, w = image.shape
    out = np.empty((m, ph, pw), np.float32)
    # patches whose pixel cells lie inside the image: integer windows blended in NumPy
    x, y, inside = _corners_inside(centres, half_w, half_h, (h, w))
    idx = np.flatnonzero(inside)
    if idx.size:
        x0 = np.floor(x[idx]).astype(np.intp)
        y0 = np.floor(y[idx]).astype(np.intp)
        fx = (x[idx] - x0).astype(np.float32)[:, None, None]
        fy = (y[idx] - y0).astype(np.float32)[:, None, None]
        whole_rows = not np.any(fy)  # stripe centres sit on whole rows: blend along x only
        win = np.lib.stride_tricks.sliding_window_view(image, (ph + int(not whole_rows), pw + 1))
        step = max(1, (4 << 20) // (4 * (ph + 1) * (pw + 1)))
        for a in range(0, idx.size, step):
            sl = slice(a, a + step)
            g = win[y0[sl], x0[sl]]
            rows = g[:, :, :-1] + fx[sl] * (g[:, :, 1:] - g[:, :, :-1])
            if not whole_rows:
                rows = rows[:, :-1] + fy[sl] * (rows[:, 1:] - rows[:, :-1])
            out[idx[sl]] = rows
    rest = np.flatnonzero(~inside)
    if rest.size:
        out[rest] = _remap_patches(image, centres[rest], half_w, half_h)
    return out


def sample_patch_columns(
    image: F32, centres: F64, half_w: int, half_h: int, *, image_t: F32 | None = None
) -> tuple[F32, F64, F64]:
    """:func:`sample_patches` with the patch axes swapped, and each patch's sum and sum of
    squares: the same values, made in one compiled pass where the patch lies inside the image.

    Many patches along a near-vertical curve (the candidates of a 1-D search along a slit) are
    made several times faster this way than by :func:`sample_patches`, and their moments come
    without another pass.

    Parameters
    ----------
    image : (H, W) float32
    centres : (M, 2) float64, px (u, v)
    half_w, half_h : patch half sizes, px
    image_t : (W, H) float32 C-contiguous, optional, ``image`` transposed (made here if not
        given: pass it when sampling one image many times)

    Returns
    -------
    columns : (M, 2*half_w+1, 2*half_h+1) float32, ``sample_patches(...)`` transposed per
        patch (equal values; zero outside the image)
    s1, s2 : (M,) float64, the sum of each patch's values and of their squares
    """
    image = np.asarray(image, dtype=np.float32)
    h, w = image.shape
    if image_t is None:
        image_t = image.T
    elif np.shape(image_t) != (w, h) or np.asarray(image_t).dtype != np.float32:
        raise ValueError(f"image_t must be the ({w}, {h}) float32 transpose of image")
    image_t = np.ascontiguousarray(image_t)
    m = len(centres)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    out = np.empty((m, pw, ph), np.float32)
    s1 = np.empty(m)
    s2 = np.empty(m)
    if m == 0:
        return out, s1, s2
    centres = np.asarray(centres, dtype=np.float64)
    x, y, inside = _corners_inside(centres, half_w, half_h, (h, w))
    idx = np.flatnonzero(inside)
    if idx.size:
        # the same float32 blends as sample_patches: along u first, then along v
        x0 = np.floor(x[idx])
        y0 = np.floor(y[idx])
        fx = (x[idx] - x0).astype(np.float32)
        fy = (y[idx] - y0).astype(np.float32)
        n = idx.size
        dst = (
            (out, s1, s2)
            if n == m
            else (np.empty((n, pw, ph), np.float32), np.empty(n), np.empty(n))
        )
        _patch_columns_kernel(image_t, x0.astype(np.intp), y0.astype(np.intp), fx, fy, *dst)
        if n < m:
            out[idx], s1[idx], s2[idx] = dst
    rest = np.flatnonzero(~inside)
    if rest.size:
        p = sample_patches(image, centres[rest], half_w, half_h).transpose(0, 2, 1)
        out[rest] = p
        q = p.reshape(len(rest), -1).astype(np.float64)
        s1[rest] = q.sum(axis=1)
        s2[rest] = np.einsum("ij,ij->i", q, q)
    return out, s1, s2


@njit(cache=True, fastmath={"reassoc", "nsz"})
def _add_moments(col, acc):
    """acc[0] += sum(col), acc[1] += sum(col**2), in float64 (any order: vectorised)."""
    a = 0.0
    b = 0.0
    for c in col:
        f = np.float64(c)
        a += f
        b += f * f
    acc[0] += a
    acc[1] += b


@njit(cache=True)
def _patch_columns_kernel(image_t, x0, y0, fx, fy, out, s1, s2):
    """Bilinear patches of the transposed image ``image_t`` (W, H) at whole-pixel corners
    (``x0``, ``y0``) and float32 fractions (``fx``, ``fy``), written column by column to ``out``
    (M, pw, ph) with the blends of :func:`sample_patches` (u first, then v); their sums and
    sums of squares to ``s1``, ``s2``."""
    pw, ph = out.shape[1], out.shape[2]
    acc = np.zeros(2)
    for m in range(x0.size):
        a0, b0, wx, wy = x0[m], y0[m], fx[m], fy[m]
        acc[0] = 0.0
        acc[1] = 0.0
        for i in range(pw):
            ca = image_t[a0 + i, b0 : b0 + ph + 1]
            cb = image_t[a0 + i + 1, b0 : b0 + ph + 1]
            o = out[m, i]
            for r in range(ph):
                p = ca[r]
                q = ca[r + 1]
                top = p + wx * (cb[r] - p)
                bottom = q + wx * (cb[r + 1] - q)
                o[r] = top + wy * (bottom - top)
            _add_moments(o, acc)
        s1[m] = acc[0]
        s2[m] = acc[1]


@njit(cache=True, fastmath={"contract"})
def _lerp(a, b, t):
    """a + t (b - a), float32, a fused multiply-add (as ``cv2.remap`` blends)."""
    return a + t * (b - a)


@njit(cache=True)
def _remap_edge_pixel(image, x, y0, ay):
    """One pixel of :func:`_remap_kernel` near the image's edge: image rows ``y0``, ``y0 + 1``
    blended by ``ay``, at column ``x`` (float32, px); 0 outside the image or where ``x`` is not
    finite."""
    h, w = image.shape
    zero = np.float32(0.0)
    if not np.isfinite(x):
        return zero
    xf = np.floor(x)
    ax = x - xf
    x0 = int(xf)
    c0, c1 = 0 <= x0 < w, 0 <= x0 + 1 < w
    q0, q1 = 0 <= y0 < h, 0 <= y0 + 1 < h
    p00 = image[y0, x0] if q0 and c0 else zero
    p01 = image[y0, x0 + 1] if q0 and c1 else zero
    p10 = image[y0 + 1, x0] if q1 and c0 else zero
    p11 = image[y0 + 1, x0 + 1] if q1 and c1 else zero
    return _lerp(_lerp(p00, p01, ax), _lerp(p10, p11, ax), ay)


@njit(cache=True)
def _remap_kernel(image, centres, row_shift, row_rise, col_scale, half_w, half_h, out, columns):
    """The patches of :func:`_remap_patches` into the C-contiguous ``out``: (M, pw, ph)
    float32, column by column, if ``columns``, else (M, ph, pw) row by row.

    Column i, row j of patch m samples x = float32(u_m) + float32(col_scale_m (i - half_w)) +
    float32(row_shift[m, j]), y = float32(v_m) + (j - half_h) + float32(row_rise[m, j]) (float32
    sums in that order), bilinearly as ``cv2.remap`` (``INTER_LINEAR``, ``BORDER_CONSTANT`` 0)
    does: along x, then y, each blend a fused multiply-add; 0 at non-finite positions.
    A patch whose pixel cells all lie inside the image is sampled row by row without checks
    (its x floors first, a vectorisable pass; unsigned indices, so no wraparound tests).
    """
    h, w = image.shape
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    zero = np.float32(0.0)
    one = np.uintp(1)
    xs = np.empty(pw, np.float32)  # the patch's column positions before the row shift, px
    ax = np.empty(pw, np.float32)  # one row's x fractions and whole columns
    x0 = np.empty(pw, np.int32)
    sx = np.empty(ph, np.float32)  # per row: shift, y fraction, whole row, finite y
    ay = np.empty(ph, np.float32)
    y0 = np.empty(ph, np.intp)
    finite = np.empty(ph, np.bool_)
    for m in range(centres.shape[0]):
        u = np.float32(centres[m, 0])
        v = np.float32(centres[m, 1])
        for i in range(pw):
            xs[i] = u + np.float32(col_scale[m] * np.float32(i - half_w))
        inside = True
        for j in range(ph):
            sx[j] = np.float32(row_shift[m, j])
            y = (v + np.float32(j - half_h)) + np.float32(row_rise[m, j])
            finite[j] = np.isfinite(y)
            if not finite[j]:
                inside = False
                continue
            yf = np.floor(y)
            ay[j] = y - yf
            y0[j] = int(yf)
            x_lo = xs[0] + sx[j]
            x_hi = xs[pw - 1] + sx[j]
            if not (0 <= y0[j] < h - 1 and min(x_lo, x_hi) >= 0 and max(x_lo, x_hi) < w - 1):
                inside = False
        o = out[m]
        if not inside:  # at the image's edge: 0 outside
            for j in range(ph):
                for i in range(pw):
                    p = _remap_edge_pixel(image, xs[i] + sx[j], y0[j], ay[j]) if finite[j] else zero
                    if columns:
                        o[i, j] = p
                    else:
                        o[j, i] = p
            continue
        for j in range(ph):
            for i in range(pw):
                x = xs[i] + sx[j]
                xf = np.floor(x)
                ax[i] = x - xf
                x0[i] = np.int32(xf)
            r0 = image[y0[j]]
            r1 = image[y0[j] + 1]
            wy = ay[j]
            for i in range(pw):
                c = np.uintp(x0[i])
                t = _lerp(r0[c], r0[c + one], ax[i])
                p = _lerp(t, _lerp(r1[c], r1[c + one], ax[i]), wy)
                if columns:
                    o[i, j] = p
                else:
                    o[j, i] = p


def _remap_patches(
    image: F32,
    centres: F64,
    half_w: int,
    half_h: int,
    row_shift: F64 | None = None,
    row_rise: F64 | None = None,
    col_scale: F64 | None = None,
) -> F32:
    """:func:`sample_patches` as ``cv2.remap`` samples them (the same float32 operations;
    zero outside the image); ``row_shift`` and ``row_rise`` (M, ph) move each patch row
    sideways and down, ``col_scale`` (M,) spaces its columns (see
    :func:`sample_sheared_patches`). Tall patches (ph > pw) come as the (M, ph, pw) transposed
    view of a C-contiguous (M, pw, ph) array (:func:`bilinear_ncc` reads them so)."""
    m = len(centres)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    zeros = np.broadcast_to(np.zeros(1), (m, ph))
    columns = ph > pw  # tall patches are laid out column by column, as bilinear_ncc reads them
    out = np.empty((m, pw, ph) if columns else (m, ph, pw), np.float32)
    _remap_kernel(
        np.ascontiguousarray(image, np.float32),
        np.asarray(centres, np.float64),
        zeros if row_shift is None else np.asarray(row_shift, np.float64),
        zeros if row_rise is None else np.asarray(row_rise, np.float64),
        np.ones(m) if col_scale is None else np.asarray(col_scale, np.float64),
        half_w,
        half_h,
        out,
        columns,
    )
    return out.transpose(0, 2, 1) if columns else out


def sample_sheared_patches(
    image: F32,
    centres: F64,
    half_w: int,
    half_h: int,
    row_shift: F64,
    *,
    row_rise: F64 | None = None,
    col_scale: F64 | None = None,
) -> F32:
    """Bilinear patches whose rows are shifted: row j of patch m is centred on column
    ``centres[m, 0] + row_shift[m, j]`` of image row ``centres[m, 1] + j - half_h +
    row_rise[m, j]``, its columns ``col_scale[m]`` px apart.

    This straightens a slanted or curved stripe in a template (the dots keep their place
    across the stripe), so that it can be compared with a reference patch of another slant.
    Where the dots move with depth along a line that is not a row (the dot projector's
    epipolar line), ``row_rise`` gives the motion's vertical part. Where a surface squeezes
    (or spreads) the pattern across the stripes, ``col_scale`` samples it at its own scale.

    Parameters
    ----------
    image : (H, W) float32
    centres : (M, 2) float64, px (u, v)
    half_w, half_h : patch half sizes, px
    row_shift : (M, 2*half_h+1) float64, px, sideways shift of each patch row
    row_rise : (M, 2*half_h+1) float64, px, downward shift of each patch row; default none
    col_scale : (M,) float64, > 0, the spacing of each patch's columns in the image, px per
        patch column; default 1

    Returns
    -------
    patches : (M, 2*half_h+1, 2*half_w+1) float32 (zero outside the image); for tall
        patches (half_h > half_w) a transposed view of (M, 2*half_w+1, 2*half_h+1) memory
    """
    ph = 2 * half_h + 1
    shift = np.asarray(row_shift, dtype=np.float64)
    if shift.shape != (len(centres), ph):
        raise ValueError(f"row_shift must have shape ({len(centres)}, {ph}), got {shift.shape}")
    if row_rise is not None:
        row_rise = np.asarray(row_rise, dtype=np.float64)
        if row_rise.shape != shift.shape:
            raise ValueError(f"row_rise must have shape {shift.shape}, got {row_rise.shape}")
    if col_scale is not None:
        col_scale = np.asarray(col_scale, dtype=np.float64)
        if col_scale.shape != (len(centres),):
            raise ValueError(f"col_scale must have shape ({len(centres)},), got {col_scale.shape}")
        if not np.all(col_scale > 0):
            raise ValueError(
                f"col_scale must be > 0 (px per patch column), got {col_scale.min():g} at least"
            )
    if len(centres) == 0:
        return np.zeros((0, ph, 2 * half_w + 1), np.float32)
    return _remap_patches(
        np.asarray(image, np.float32), centres, half_w, half_h, shift, row_rise, col_scale
    )


def normalise_patches(p: F32) -> F32:
    """Zero-mean, unit-norm patches (flattened to (M, K)); flat patches become all zero."""
    f = p.reshape(len(p), -1).astype(np.float32)  # a copy (or a new array) to work in
    f -= f.mean(axis=1, keepdims=True)
    n = np.sqrt(np.einsum("ij,ij->i", f, f))[:, None]
    f /= np.maximum(n, 1e-6)
    f[n[:, 0] <= 1e-6] = 0.0
    return f


#: Order of the sums in the last axis of :func:`window_sums`.
WINDOW_SUMS = ("sum", "sum_sq", "right", "down", "down_right", "down_left")


def window_sums(
    image: F32, half_w: int, half_h: int, *, x_major: bool = False, out: F32 | None = None
) -> F32:
    """Sums over every (2*half_h+1, 2*half_w+1) window of an image, of its pixels and of the
    products of neighbouring pixels: what the mean and norm of a bilinear patch need.

    The bilinear patch at a sub-pixel position blends the four integer windows at the corners
    of its pixel cell; its sum and sum of squares follow from these sums at those corners
    (:func:`bilinear_patch_moments`) without sampling the patch.

    Parameters
    ----------
    image : (H, W) float32 (other types are converted to float32 first)
    half_w, half_h : patch half sizes, px
    x_major : return the sums with the image axes swapped, (W', H', 6), so that the sums of
        windows down a column lie close together in memory (as
        :meth:`~multislit.identify.reference.ReferenceSet.window_sums` keeps them); default
        False, (H', W', 6)
    out : float32 C-contiguous array of the returned shape to write the sums into (every
        element is written); default None, a new array

    Returns
    -------
    sums : (H - 2*half_h, W - 2*half_w, 6) float32, indexed by the window's top-left pixel
        (y, x). With I the image and (j, i) over the window: ``sum`` = sum I[y+j, x+i],
        ``sum_sq`` = sum I^2, ``right`` = sum I[y+j, x+i] I[y+j, x+i+1], ``down`` = sum
        I[y+j, x+i] I[y+j+1, x+i], ``down_right`` = sum I[y+j, x+i] I[y+j+1, x+i+1],
        ``down_left`` = sum I[y+j, x+i+1] I[y+j+1, x+i]. Sums that would reach past the last
        row or column are 0 (they are never used: a bilinear patch's cell stays inside).
        Each is a difference of four float64 integral-image values (summed as
        ``cv2.integral`` sums them), rounded to float32.
    """
    im = np.ascontiguousarray(image, dtype=np.float32)
    h, w = im.shape
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    if h <= ph or w <= pw:
        raise ValueError(f"image {w}x{h} px is not larger than a {pw}x{ph} px window")
    nh, nw = h - ph + 1, w - pw + 1
    shape = (nw, nh, len(WINDOW_SUMS)) if x_major else (nh, nw, len(WINDOW_SUMS))
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}")
    _window_sums_kernel(im, ph, pw, bool(x_major), out)
    return out


#: Row offset and column offset of each product's second pixel (:data:`WINDOW_SUMS` order);
#: a product's image is (H - dy, W - dx)
_PRODUCT_SHIFTS = ((0, 0), (0, 0), (0, 1), (1, 0), (1, 1), (1, 1))
_SUMS_TILE = 64  # px; the transposed writes go tile by tile, to stay in cache


@njit(cache=True, inline="always")
def _product(im, c, y, x):
    """Product ``c`` (:data:`WINDOW_SUMS` order) at (y, x), float64 (exact for float32)."""
    a = np.float64(im[y, x])
    if c == 0:
        return a
    if c == 1:
        return a * a
    if c == 2:
        return a * np.float64(im[y, x + 1])
    if c == 3:
        return a * np.float64(im[y + 1, x])
    if c == 4:
        return a * np.float64(im[y + 1, x + 1])
    return np.float64(im[y, x + 1]) * np.float64(im[y + 1, x])


@njit(cache=True)
def _window_sums_kernel(im, ph, pw, x_major, out):
    """The sums of :func:`window_sums` into ``out`` ((H', W', 6) or x-major (W', H', 6)): per
    product, its float64 integral image as ``cv2.integral`` sums it (a running row sum added to
    the row above), then the box sums ((A - B) - C) + D, rounded to float32; 0 where a
    product's window would reach past the image."""
    h, w = im.shape
    ii = np.zeros((h + 1, w + 1))
    for c in range(6):
        dy, dx = _PRODUCT_SHIFTS[c]
        hq, wq = h - dy, w - dx
        for y in range(hq):
            s = 0.0
            for x in range(wq):
                s += _product(im, c, y, x)
                ii[y + 1, x + 1] = ii[y, x + 1] + s
        nh, nw = hq - ph + 1, wq - pw + 1
        zero = np.float32(0.0)
        if not x_major:
            out[nh:, :, c] = zero
            out[:, nw:, c] = zero
            for y in range(nh):
                for x in range(nw):
                    b = ii[y + ph, x + pw] - ii[y, x + pw] - ii[y + ph, x] + ii[y, x]
                    out[y, x, c] = np.float32(b)
            continue
        out[nw:, :, c] = zero
        out[:, nh:, c] = zero
        for y0 in range(0, nh, _SUMS_TILE):
            for x0 in range(0, nw, _SUMS_TILE):
                for x in range(x0, min(x0 + _SUMS_TILE, nw)):
                    for y in range(y0, min(y0 + _SUMS_TILE, nh)):
                        b = ii[y + ph, x + pw] - ii[y, x + pw] - ii[y + ph, x] + ii[y, x]
                        out[x, y, c] = np.float32(b)


def _cells(x: F64, n: int) -> tuple[NDArray[np.intp], F64]:
    """Left end of the interpolation cell of each ``x`` (...) float64 in 0..n-1 (floor(x), but
    n-2 at x = n-1) and the fraction ``x`` lies past it, in one compiled pass."""
    x = np.ascontiguousarray(x, np.float64)
    c = np.empty(x.shape, np.intp)
    f = np.empty(x.shape)
    _cells_kernel(x.reshape(-1), n, c.reshape(-1), f.reshape(-1))
    return c, f


@njit(cache=True, inline="always")
def cell_of(x, n):
    """Compiled :func:`_cells` of one position ``x`` (float64) in 0..n-1: the cell's left end
    (int) and the fraction (float64). For kernels without fast-math flags (inlined into one
    with them, the fraction's later uses may be reassociated and round differently)."""
    e = np.floor(x)
    e = n - 2.0 if e > n - 2.0 else e
    return int(e), x - e


@njit(cache=True)
def _cells_kernel(x, n, c, f):
    """:func:`_cells` of the flat ``x`` into ``c``, ``f``."""
    for k in range(x.size):
        c[k], f[k] = cell_of(x[k], n)


@njit(cache=True, inline="always")
def _cell_moments(q00, q10, q01, q11, fx, fy):
    """Sum and sum of squares of the bilinear patch at fractions (``fx``, ``fy``) of its pixel
    cell, from the :func:`window_sums` (length-6 rows) of the integer windows at the cell's
    corners (x, y offsets 00, 10, 01, 11)."""
    w00 = (1.0 - fx) * (1.0 - fy)
    w10 = fx * (1.0 - fy)
    w01 = (1.0 - fx) * fy
    w11 = fx * fy
    s1 = w00 * q00[0] + w10 * q10[0] + w01 * q01[0] + w11 * q11[0]
    s2 = (
        w00 * w00 * q00[1] + w10 * w10 * q10[1] + w01 * w01 * q01[1] + w11 * w11 * q11[1]
    ) + 2.0 * (
        w00 * (w10 * q00[2] + w01 * q00[3])
        + w11 * (w01 * q01[2] + w10 * q10[3])
        + w00 * w11 * q00[4]
        + w10 * w01 * q00[5]
    )
    return s1, s2


@njit(cache=True)
def _moments_kernel(sums, image, x0, y0, fx, fy, x_major, s1, s2):
    """:func:`_cell_moments` of each patch (flat arrays) from ``sums`` (R, n_slow, n_fast, 6)."""
    for k in range(x0.size):
        g = sums[image[k]]
        a, b = (x0[k], y0[k]) if x_major else (y0[k], x0[k])
        if x_major:
            q00, q10, q01, q11 = g[a, b], g[a + 1, b], g[a, b + 1], g[a + 1, b + 1]
        else:
            q00, q10, q01, q11 = g[a, b], g[a, b + 1], g[a + 1, b], g[a + 1, b + 1]
        s1[k], s2[k] = _cell_moments(q00, q10, q01, q11, fx[k], fy[k])


def bilinear_patch_moments(
    sums: F32, x: F64, y: F64, image: NDArray[np.intp] | None = None, x_major: bool = False
) -> tuple[F64, F64]:
    """Sum and sum of squares of bilinear patches, from :func:`window_sums`.

    Parameters
    ----------
    sums : (H', W', 6) float32, :func:`window_sums` of the image; or (R, H', W', 6), those of
        R images, with ``image`` saying which image each patch is in; with ``x_major`` the two
        image axes are swapped: (W', H', 6) or (R, W', H', 6)
    x, y : (...) float64, px, top-left sample position of each patch (``centre - half size``),
        0 <= x <= W' - 1 and 0 <= y <= H' - 1 (the patch inside the image)
    image : (...) intp, index into the first axis of a 4-D ``sums``
    x_major : the layout of ``sums`` (x-major keeps the sums down a near-vertical line close
        in memory)

    Returns
    -------
    s1, s2 : (...) float64, sum of the patch's values and of their squares (blended in float64
        from the float32 sums: relative error ~1e-6)
    """
    stack = sums if sums.ndim == 4 else sums[None]
    n_slow, n_fast = stack.shape[1:3]
    hs, ws = (n_fast, n_slow) if x_major else (n_slow, n_fast)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    shape = np.broadcast_shapes(x.shape, y.shape, () if image is None else np.shape(image))
    x, y = np.broadcast_to(x, shape).ravel(), np.broadcast_to(y, shape).ravel()
    (x0, fx), (y0, fy) = _cells(x, ws), _cells(y, hs)
    img = np.zeros(x.size, np.intp) if image is None else np.broadcast_to(image, shape).ravel()
    s1, s2 = np.empty(x.size), np.empty(x.size)
    _moments_kernel(stack, img.astype(np.intp), x0, y0, fx, fy, bool(x_major), s1, s2)
    return s1.reshape(shape), s2.reshape(shape)


#: Samples whose templates the NCC kernel keeps at hand at once: it takes their candidates
#: slit by slit, so that the windows of neighbouring samples (neighbouring rows of a stripe)
#: are read from cache.
_NCC_BLOCK = 16
#: Bytes of tall templates transposed at once for the NCC kernel.
_TRANSPOSE_BYTES = 1 << 20
#: Single-precision lanes of a vector register: the kernel's template rows are padded to this.
_LANES = 8
#: A patch whose values' variance times its size is at most this share of its sum of squares
#: is flat (NCC 0); a template whose values' norm about their mean is at most ``_FLAT_NORM``
#: is flat (as in :func:`normalise_patches`).
_FLAT_SHARE = 1e-6
_FLAT_NORM = 1e-6


@njit(cache=True)
def _load_template(patch, tq, tsh):
    """Template of ``patch`` (n0, n1) float32 for :func:`_ncc_kernel`: ``patch`` less its mean,
    over its norm about it, into ``tq`` (2G, n1q) and shifted one column right into ``tsh``
    (their other cells stay 0; all 0 for a flat patch)."""
    n0, n1 = patch.shape
    s1 = 0.0
    for i in range(n0):
        for j in range(n1):
            s1 += patch[i, j]
    mean = s1 / (n0 * n1)
    ss = 0.0
    for i in range(n0):
        for j in range(n1):
            d = patch[i, j] - mean
            ss += d * d
    norm = np.sqrt(ss)
    scale = 1.0 / norm if norm > _FLAT_NORM else 0.0
    for i in range(n0):
        for j in range(n1):
            v = np.float32((patch[i, j] - mean) * scale)
            tq[i, j] = v
            tsh[i, j + 1] = v


@njit(cache=True, fastmath={"reassoc", "nsz", "contract"})
def _ncc_kernel(src, patches, which, a0, b0, fa, fb, sums, tall, out):
    """NCC of templates with bilinear patches of ``src`` (see :func:`bilinear_ncc`).

    ``src`` (R, A, B) float32 holds the images with the patch's rows along A (the images
    themselves, or transposed for tall patches: ``tall``), ``patches`` (m, n0, n1) the samples'
    patches in that orientation (the templates); patch (s, c) lies in image ``which[s, c]`` with its cell's
    corner at (``a0``, ``b0``) and fractions (``fa``, ``fb``). A template row meets the blend
    of two image rows (fraction ``fa``), at two offsets along the row (0 and 1 px, blended by
    ``fb``): the template, and the template shifted by a pixel. The template is the sample's
    patch normalised (:func:`_load_template`). Two candidates of a sample are scored together
    (they share the template's loads). The moments come from the x-major ``sums``.
    """
    m, C = which.shape
    n0, n1 = patches.shape[1], patches.shape[2]
    K = n0 * n1
    G = (n0 + 1) // 2  # row pairs
    n1q = (n1 + _LANES) // _LANES * _LANES  # > n1: room for the shifted template
    last = src.shape[1] - 1
    L = src.shape[2]
    tq = np.zeros((_NCC_BLOCK, 2 * G, n1q), np.float32)
    tsh = np.zeros((_NCC_BLOCK, 2 * G, n1q), np.float32)
    for s0 in range(0, m, _NCC_BLOCK):
        nb = min(_NCC_BLOCK, m - s0)
        for q in range(nb):
            _load_template(patches[s0 + q], tq[q], tsh[q])
        for c0 in range(0, C, 2):
            c1 = min(c0 + 1, C - 1)
            for q in range(nb):
                s = s0 + q
                t = tq[q]
                u = tsh[q]
                ia = src[which[s, c0]]
                ib = src[which[s, c1]]
                a, b, f = a0[s, c0], b0[s, c0], np.float32(fa[s, c0])
                a_, b_, f_ = a0[s, c1], b0[s, c1], np.float32(fa[s, c1])
                # whole padded rows, except a patch at the end of the rows
                nj = n1q if max(b, b_) + n1q <= L else n1 + 1
                dla = 0.0
                dra = 0.0
                dlb = 0.0
                drb = 0.0
                for g in range(G):
                    i, i_ = a + 2 * g, a_ + 2 * g
                    x0 = ia[i, b : b + nj]
                    x1 = ia[i + 1, b : b + nj]
                    x2 = ia[min(i + 2, last), b : b + nj]
                    y0 = ib[i_, b_ : b_ + nj]
                    y1 = ib[i_ + 1, b_ : b_ + nj]
                    y2 = ib[min(i_ + 2, last), b_ : b_ + nj]
                    t0, t1, u0, u1 = t[2 * g], t[2 * g + 1], u[2 * g], u[2 * g + 1]
                    la = np.float32(0.0)
                    ra = np.float32(0.0)
                    lb = np.float32(0.0)
                    rb = np.float32(0.0)
                    for j in range(nj):
                        p0, p1, p2 = x0[j], x1[j], x2[j]
                        v0 = p0 + f * (p1 - p0)
                        v1 = p1 + f * (p2 - p1)
                        p0, p1, p2 = y0[j], y1[j], y2[j]
                        w0 = p0 + f_ * (p1 - p0)
                        w1 = p1 + f_ * (p2 - p1)
                        T0, T1, U0, U1 = t0[j], t1[j], u0[j], u1[j]
                        la += T0 * v0 + T1 * v1
                        ra += U0 * v0 + U1 * v1
                        lb += T0 * w0 + T1 * w1
                        rb += U0 * w0 + U1 * w1
                    dla += la
                    dra += ra
                    dlb += lb
                    drb += rb
                for c, dl, dr in ((c0, dla, dra), (c1, dlb, drb)):
                    g_ = sums[which[s, c]]
                    a, b = a0[s, c], b0[s, c]
                    x, y = (a, b) if tall else (b, a)
                    fx, fy = (fa[s, c], fb[s, c]) if tall else (fb[s, c], fa[s, c])
                    s1, s2 = _cell_moments(
                        g_[x, y], g_[x + 1, y], g_[x, y + 1], g_[x + 1, y + 1], fx, fy
                    )
                    var = s2 - s1 * s1 / K
                    if var <= _FLAT_SHARE * max(s2, 1e-12):
                        out[s, c] = 0.0
                    else:
                        w = fb[s, c]
                        out[s, c] = ((1.0 - w) * dl + w * dr) / np.sqrt(var)


def bilinear_ncc(
    images: F32,
    patches: F32,
    which: NDArray[np.intp],
    x: F64,
    y: F64,
    sums: F32,
    half_w: int,
    half_h: int,
    *,
    images_t: F32 | None = None,
) -> F64:
    """Normalised cross-correlation of the samples' patches with bilinear patches of a stack of
    images.

    Equal (to float32 rounding) to ``normalise_patches(sample_patches(images[which], centres,
    half_w, half_h))`` dotted with ``normalise_patches(patches)``, without sampling the image
    patches: one compiled pass blends the image rows under each template row and takes the
    template's dot products with them at the cell's two offsets along the row; the image
    patch's mean and norm come from the window sums (:func:`bilinear_patch_moments`).

    Parameters
    ----------
    images : (R, H, W') float32, C-contiguous, the images, W' >= W: each row may be followed
        by padding (finite values; reading whole vector lanes is then faster, and rows a page
        long are best avoided: :meth:`~multislit.identify.reference.ReferenceSet.padded_dots`)
    patches : (m, 2*half_h+1, 2*half_w+1) float32, the samples' patches (the templates before
        :func:`normalise_patches`, which is done here in float64)
    which : (m, C) intp, the image of each of a sample's C patches
    x, y : (m, C) float64, px, each patch's top-left sample position (centre - half size),
        with the patch inside the image: 0 <= x <= W - 1 - 2*half_w, 0 <= y <= H - 1 - 2*half_h
    sums : (R, W - 2*half_w, H - 2*half_h, 6) float32, :func:`window_sums` of each image,
        x-major (:meth:`~multislit.identify.reference.ReferenceSet.window_sums`)
    half_w, half_h : patch half sizes, px
    images_t : (R, W, H') float32 C-contiguous, the images transposed (rows padded likewise),
        optional: a tall patch (more rows than columns) is read from it along its columns
        (made here if not given)

    Returns
    -------
    ncc : (m, C) float64, 0 for a flat (all equal) image patch or sample patch
    """
    ws, hs = sums.shape[1:3]
    x0, fx = _cells(x, ws)
    y0, fy = _cells(y, hs)
    out = np.zeros(np.shape(which))
    bilinear_ncc_cells(
        images, patches, which, x0, y0, fx, fy, sums, half_w, half_h, out, images_t=images_t
    )
    return out


def bilinear_ncc_cells(
    images: F32,
    patches: F32,
    which: NDArray[np.intp],
    x0: NDArray[np.intp],
    y0: NDArray[np.intp],
    fx: F64,
    fy: F64,
    sums: F32,
    half_w: int,
    half_h: int,
    out: F64,
    *,
    images_t: F32 | None = None,
) -> None:
    """:func:`bilinear_ncc` with the patches' positions given by their pixel cells (as
    :func:`cell_of` makes them from ``x``, ``y``, with ``n`` the window counts ``sums.shape[1]``
    and ``sums.shape[2]``), written into ``out``.

    Parameters
    ----------
    images, patches, which, sums, half_w, half_h, images_t : as for :func:`bilinear_ncc`
    x0, y0 : (m, C) intp, px, the left (top) end of the cell of each patch's top-left sample
        position
    fx, fy : (m, C) float64, in [0, 1], the position's fraction past it
    out : (m, C) float64, the NCC (0 for a flat image patch or sample patch)
    """
    m, C = np.shape(which)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    if m == 0 or C == 0:
        return
    p3 = np.asarray(patches, np.float32).reshape(m, ph, pw)
    which = np.asarray(which, np.intp)
    tall = ph > pw
    if not tall:
        src = np.ascontiguousarray(images, np.float32)
        _ncc_kernel(src, np.ascontiguousarray(p3), which, y0, x0, fy, fx, sums, tall, out)
        return
    src = images.transpose(0, 2, 1) if images_t is None else images_t
    src = np.ascontiguousarray(src, np.float32)
    step = max(1, _TRANSPOSE_BYTES // (4 * ph * pw))  # samples whose patches are transposed at once
    for a in range(0, m, step):
        sl = slice(a, a + step)
        pt = np.ascontiguousarray(p3[sl].transpose(0, 2, 1))
        _ncc_kernel(src, pt, which[sl], x0[sl], y0[sl], fx[sl], fy[sl], sums, tall, out[sl])


def compile_kernels() -> None:
    """Compile this module's Numba kernels now: the patch samplers
    (:func:`sample_patch_columns`, :func:`sample_sheared_patches`), :func:`bilinear_ncc` for
    tall and wide patches and :func:`bilinear_patch_moments`.

    Numba compiles them on first use (a few seconds) and caches the machine code on disk beside
    the package, so only the first run after an install pays it. The identification's other
    kernels are compiled by :func:`~multislit.identify.labelling.compile_kernels`, which calls
    this one.
    """
    img = np.zeros((16, 16), np.float32)
    one = np.array([[8.0, 8.0]])
    sample_patch_columns(img, one, 2, 3)
    sample_patches(img, np.array([[0.5, 0.5]]), 2, 3)  # at the edge
    sample_sheared_patches(
        img, one, 2, 3, np.zeros((1, 7)), row_rise=np.zeros((1, 7)), col_scale=np.ones(1)
    )
    stack = np.zeros((1, 16, 16), np.float32)
    for hw, hh in ((2, 3), (3, 2)):
        sums = window_sums(stack[0], hw, hh, x_major=True)[None]
        t = np.zeros((1, (2 * hw + 1) * (2 * hh + 1)), np.float32)
        bilinear_ncc(
            stack, t, np.zeros((1, 1), np.intp), np.ones((1, 1)), np.ones((1, 1)), sums, hw, hh
        )
        bilinear_patch_moments(sums, np.ones(1), np.ones(1), np.zeros(1, np.intp), x_major=True)
