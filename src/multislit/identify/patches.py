"""Bilinear patches of an image, normalised, and the window sums that give their moments.

The matching of dot templates (:mod:`~multislit.identify.matching`) and the epipole's dot
tracks (:func:`~multislit.identify.reference.estimate_epipole`) compare small patches of dot
images by normalised cross-correlation.
"""

from __future__ import annotations

import cv2
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


def _remap_patches(
    image: F32,
    centres: F64,
    half_w: int,
    half_h: int,
    row_shift: F64 | None = None,
    row_rise: F64 | None = None,
    col_scale: F64 | None = None,
) -> F32:
    """:func:`sample_patches` by ``cv2.remap`` (zero outside the image); ``row_shift`` and
    ``row_rise`` (M, ph) move each patch row sideways and down, ``col_scale`` (M,) spaces its
    columns (see :func:`sample_sheared_patches`)."""
    m = len(centres)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    du = np.arange(-half_w, half_w + 1, dtype=np.float32)
    dv = np.arange(-half_h, half_h + 1, dtype=np.float32)
    if col_scale is None:
        cols = du[None, None, :]
    else:
        cols = (col_scale[:, None, None] * du[None, None, :]).astype(np.float32)
    mx = (centres[:, 0, None, None].astype(np.float32) + cols).repeat(ph, axis=1)
    if row_shift is not None:
        mx += row_shift.astype(np.float32)[:, :, None]
    my = (centres[:, 1, None, None].astype(np.float32) + dv[None, :, None]).repeat(pw, axis=2)
    if row_rise is not None:
        my += row_rise.astype(np.float32)[:, :, None]
    mx = mx.reshape(m * ph, pw)
    my = my.reshape(m * ph, pw)
    out = np.empty((m * ph, pw), np.float32)
    step = 30000 // ph * ph  # cv2.remap maps must have < 32767 rows
    for r0 in range(0, m * ph, step):
        out[r0 : r0 + step] = cv2.remap(
            image,
            mx[r0 : r0 + step],
            my[r0 : r0 + step],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
    return out.reshape(m, ph, pw)


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
    patches : (M, 2*half_h+1, 2*half_w+1) float32 (zero outside the image)
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


def window_sums(image: F32, half_w: int, half_h: int) -> F32:
    """Sums over every (2*half_h+1, 2*half_w+1) window of an image, of its pixels and of the
    products of neighbouring pixels: what the mean and norm of a bilinear patch need.

    The bilinear patch at a sub-pixel position blends the four integer windows at the corners
    of its pixel cell; its sum and sum of squares follow from these sums at those corners
    (:func:`bilinear_patch_moments`) without sampling the patch.

    Parameters
    ----------
    image : (H, W) float32
    half_w, half_h : patch half sizes, px

    Returns
    -------
    sums : (H - 2*half_h, W - 2*half_w, 6) float32, indexed by the window's top-left pixel
        (y, x). With I the image and (j, i) over the window: ``sum`` = sum I[y+j, x+i],
        ``sum_sq`` = sum I^2, ``right`` = sum I[y+j, x+i] I[y+j, x+i+1], ``down`` = sum
        I[y+j, x+i] I[y+j+1, x+i], ``down_right`` = sum I[y+j, x+i] I[y+j+1, x+i+1],
        ``down_left`` = sum I[y+j, x+i+1] I[y+j+1, x+i]. Sums that would reach past the last
        row or column are 0 (they are never used: a bilinear patch's cell stays inside).
    """
    im = np.asarray(image, dtype=np.float64)
    h, w = im.shape
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    if h <= ph or w <= pw:
        raise ValueError(f"image {w}x{h} px is not larger than a {pw}x{ph} px window")
    nh, nw = h - ph + 1, w - pw + 1
    prods = [
        im,
        im * im,
        im[:, :-1] * im[:, 1:],
        im[:-1, :] * im[1:, :],
        im[:-1, :-1] * im[1:, 1:],
        im[:-1, 1:] * im[1:, :-1],
    ]
    out = np.zeros((nh, nw, len(prods)), np.float32)
    for c, q in enumerate(prods):
        ii = cv2.integral(q, sdepth=cv2.CV_64F)  # (h'+1, w'+1)
        box = ii[ph:, pw:] - ii[:-ph, pw:] - ii[ph:, :-pw] + ii[:-ph, :-pw]
        out[: box.shape[0], : box.shape[1], c] = box
    return out


def _cell(x: F64, n: int) -> NDArray[np.intp]:
    """Left end of the interpolation cell of ``x`` in 0..n-1: floor(x), but n-2 at x = n-1."""
    return np.minimum(np.floor(x), n - 2).astype(np.intp)


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
    s1, s2 : (...) float64, sum of the patch's values and of their squares (computed in float32:
        relative error ~1e-6)
    """
    n_slow, n_fast = sums.shape[-3], sums.shape[-2]
    hs, ws = (n_fast, n_slow) if x_major else (n_slow, n_fast)
    x0, y0 = _cell(x, ws), _cell(y, hs)
    fx = (x - x0).astype(np.float32)
    fy = (y - y0).astype(np.float32)
    slow, fast = (x0, y0) if x_major else (y0, x0)
    i00 = (slow if image is None else image * n_slow + slow) * n_fast + fast
    # the cell's four corners (00, 10, 01, 11 as x, y offsets) and their weights
    dx, dy = (n_fast, 1) if x_major else (1, n_fast)
    q = sums.reshape(-1, sums.shape[-1])[i00[..., None] + np.array([0, dx, dy, dx + dy])]
    w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1)
    s1 = np.einsum("...c,...c->...", w, q[..., 0])
    s2 = np.einsum("...c,...c->...", w * w, q[..., 1]) + 2 * (
        w[..., 0] * (w[..., 1] * q[..., 0, 2] + w[..., 2] * q[..., 0, 3])
        + w[..., 3] * (w[..., 2] * q[..., 2, 2] + w[..., 1] * q[..., 1, 3])
        + w[..., 0] * w[..., 3] * q[..., 0, 4]
        + w[..., 1] * w[..., 2] * q[..., 0, 5]
    )
    return s1.astype(np.float64), s2.astype(np.float64)


def compile_kernels() -> None:
    """Compile the patch sampler's Numba kernel (:func:`sample_patch_columns`) now.

    Numba compiles it on first use (a few seconds) and caches the machine code on disk beside
    the package, so only the first reference preparation after an install pays it.
    """
    img = np.zeros((16, 16), np.float32)
    sample_patch_columns(img, np.array([[8.0, 8.0]]), 2, 3)
