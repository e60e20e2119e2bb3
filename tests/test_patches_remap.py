"""The sheared-patch sampler's compiled kernel (multislit.identify.patches._remap_patches)
against a straightforward NumPy computation of the same float32 operations."""

import numpy as np
import pytest

from multislit.identify.patches import _remap_patches


def _fma32(a, t, d):
    """float32 a + t d rounded once (the float64 sum is exact to far below a float32 ulp)."""
    return (a.astype(np.float64) + t.astype(np.float64) * d.astype(np.float64)).astype(np.float32)


def _lerp32(a, b, t):
    return _fma32(a, t, (b - a).astype(np.float32))


def _remap_numpy(img, centres, hw, hh, shift, rise, scale):
    """Each pixel's position as float32 sums, then ``cv2.remap``'s bilinear blends (along x,
    then y, each a fused multiply-add), 0 outside the image and at non-finite positions."""
    h, w = img.shape
    du = np.arange(-hw, hw + 1, dtype=np.float32)
    dv = np.arange(-hh, hh + 1, dtype=np.float32)
    cols = (scale[:, None] * du[None, :]).astype(np.float32)  # (M, pw)
    x = (centres[:, 0, None, None].astype(np.float32) + cols[:, None, :]) + shift.astype(
        np.float32
    )[:, :, None]
    y = (centres[:, 1, None].astype(np.float32) + dv[None, :]) + rise.astype(np.float32)
    y = np.broadcast_to(y[:, :, None], x.shape)
    ok = np.isfinite(x) & np.isfinite(y)
    xf = np.floor(np.where(ok, x, 0)).astype(np.float32)
    yf = np.floor(np.where(ok, y, 0)).astype(np.float32)
    ax, ay = x - xf, y - yf
    x0, y0 = xf.astype(np.int64), yf.astype(np.int64)

    def at(r, c):
        inside = ok & (r >= 0) & (r < h) & (c >= 0) & (c < w)
        return np.where(inside, img[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], 0).astype(
            np.float32
        )

    top = _lerp32(at(y0, x0), at(y0, x0 + 1), ax)
    bottom = _lerp32(at(y0 + 1, x0), at(y0 + 1, x0 + 1), ax)
    return np.where(ok, _lerp32(top, bottom, ay), 0).astype(np.float32)


@pytest.mark.parametrize(("hw", "hh"), [(3, 5), (5, 2), (2, 2)])
def test_remap_kernel_equals_numpy_bitwise(rng, hw, hh):
    m, h, w = 60, 40, 50
    ph = 2 * hh + 1
    img = rng.uniform(0, 255, (h, w)).astype(np.float32)
    centres = np.column_stack([rng.uniform(-6, w + 6, m), rng.uniform(-6, h + 6, m)])
    centres[:4] = [[25.3, 20.7], [0.0, 0.0], [w - 1.0, h - 1.0], [w - 1 - hw, h - 1 - hh]]
    shift = rng.normal(0, 2, (m, ph))
    rise = rng.normal(0, 1, (m, ph))
    scale = rng.uniform(0.5, 1.5, m)
    shift[4, 1], rise[5, 2], rise[6, 0], shift[7, 3] = np.nan, np.inf, -np.inf, 1e12
    centres[8] = [np.nan, 20.0]
    got = _remap_patches(img, centres, hw, hh, shift, rise, scale)
    with np.errstate(invalid="ignore"):
        want = _remap_numpy(img, centres, hw, hh, shift, rise, scale)
    assert got.shape == want.shape == (m, ph, 2 * hw + 1)
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32))
    assert np.all(got[4, 1] == 0) and np.all(got[8] == 0) and np.any(got[0] != 0)
    if hh > hw:  # tall patches: a transposed view of column-by-column memory
        assert got.transpose(0, 2, 1).flags.c_contiguous
    else:
        assert got.flags.c_contiguous
