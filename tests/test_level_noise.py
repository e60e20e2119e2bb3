"""The noise grows with the level (read noise plus shot noise): the extraction's thresholds follow
it, so dim stripes on a dark surface are found where the frame's one noise sigma (set by the
bright wall) would miss them, and a JPEG keeps the frame's noise (synthetic 8-bit images made
here)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from multislit.stripes import FWHM_PER_SIGMA, extract_slits
from multislit.stripes.separation import (
    LEVEL_NOISE_FLOOR,
    background_validated,
    noise_by_level,
    noise_from_difference,
    shows_jpeg_blocks,
)

from .test_slits import _pixel_gauss

SIGMA = 1.3
SW = SIGMA * FWHM_PER_SIGMA
#: The sensor: read noise (DN) and electrons per DN (shot noise).
READ_DN, GAIN = 0.3, 40.0


def _frame(seed, *, dark_amp=2.5, rows=(0, 150)):
    """(H, W) uint8: a wall (background 40 DN, stripes of 80 DN) on the left half and a dark
    surface (background 3 DN, stripes of ``dark_amp`` DN) on the right, vertical stripes every
    16 px, with read and shot noise; the dark surface's stripes run over ``rows`` only. Returns
    the image, the dark stripes' true columns and the dark surface's pixel noise (DN)."""
    rng = np.random.default_rng(seed)
    h, w = 200, 320
    u = np.arange(w, dtype=float)
    cols = np.arange(8.5, w, 16.0) + rng.uniform(-0.5, 0.5)
    wall = u < w / 2
    signal = np.where(wall, 40.0, 3.0)[None, :].repeat(h, 0)
    for c in cols:
        profile = _pixel_gauss(u, c, SIGMA)
        amp = 80.0 if c < w / 2 else dark_amp
        lit = (
            np.ones(h, bool) if c < w / 2 else (np.arange(h) >= rows[0]) & (np.arange(h) < rows[1])
        )
        signal[lit] += amp * profile[None, :]
    noisy = signal + rng.normal(0.0, 1.0, signal.shape) * np.sqrt(READ_DN**2 + signal / GAIN)
    img = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    dark_sigma = float(np.std(img[rows[1] :, w // 2 + 8 :].astype(float)))
    return img, cols[cols > w / 2], dark_sigma


def _dark_hits(ex, cols, rows):
    """The share of the dark stripes' rows in ``rows`` with a linked centre within 1 px, and
    the number of linked centres on the dark surface farther than 2 px from every stripe or
    below its stripes' rows."""
    lk = ex.segment >= 0
    u, v = ex.u[lk], ex.v[lk]
    on_dark = u > 160 + 4
    d = np.abs(u[:, None] - cols[None, :]).min(axis=1)
    hit = np.zeros((cols.size, 200), bool)
    k = np.abs(u[:, None] - cols[None, :]).argmin(axis=1)
    close = on_dark & (d <= 1.0)
    hit[k[close], np.rint(v[close]).astype(int)] = True
    false = on_dark & ((d > 2.0) | (v >= rows[1] + 3))
    return hit[:, rows[0] + 5 : rows[1] - 5].mean(), int(np.count_nonzero(false))


def test_the_noise_by_level_follows_the_shot_noise():
    img, _, dark_sigma = _frame(0)
    noise = noise_from_difference(img)
    bg = background_validated(img, SW, "opening", noise=noise)
    levels, scale = noise_by_level(img, bg, noise)
    # the frame's noise is the wall's (the median difference, a whole grey level): the dark
    # surface's is about half of it
    assert dark_sigma < 0.7 * noise
    at_dark = float(np.interp(3.0, levels, scale)) * noise
    assert at_dark == pytest.approx(dark_sigma, rel=0.2)
    assert np.all(np.diff(scale) >= 0) and np.all((scale >= LEVEL_NOISE_FLOOR) & (scale <= 1))
    assert float(np.interp(40.0, levels, scale)) == 1.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dim_stripes_on_a_dark_surface_beside_a_bright_wall_are_found(seed):
    # 2.5 DN stripes on a surface of 3 DN whose noise is 0.47 DN: far under the frame's
    # threshold (8 sigmas of the wall's 1 DN), 5 sigmas of their own surface's noise. Measured
    # on seeds 0, 1, 2: 100, 100, 99 % found, nothing else (with the frame's one noise sigma
    # for the whole image: 0 %)
    img, cols, _ = _frame(seed, dark_amp=2.5, rows=(0, 150))
    ex = extract_slits(img, stripe_width_px=SW, dot_size_px=1.9)
    found, false = _dark_hits(ex, cols, (0, 150))
    assert found >= 0.9
    assert false == 0


def test_a_jpeg_keeps_the_frames_noise():
    img, cols, _ = _frame(3)
    assert not shows_jpeg_blocks(img)
    for quality in (95, 90, 75):
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
        jpeg = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        assert shows_jpeg_blocks(jpeg), quality
        # the compression's errors (a grey level or so, shaped like the image) are not noise
        # the dark surface's differences show: no centre off the stripes
        ex = extract_slits(jpeg, stripe_width_px=SW, dot_size_px=1.9)
        assert _dark_hits(ex, cols, (0, 150))[1] == 0, quality


def test_noise_of_many_grey_levels_is_measured_too():
    # 16-bit data whose noise spans hundreds of steps: the differences are read in eighths of
    # the frame's noise, not in steps (which would cap them and take the noise for far less)
    rng = np.random.default_rng(4)
    level = np.where(np.arange(320) < 160, 20000.0, 2000.0)[None, :].repeat(200, 0)
    img = np.clip(np.rint(level + rng.normal(0.0, 1.0, level.shape) * np.sqrt(level)), 0, 65535)
    img = img.astype(np.uint16)
    noise = noise_from_difference(img)
    levels, scale = noise_by_level(img, level, noise)
    assert float(np.interp(20000.0, levels, scale)) == 1.0
    # sqrt(2000) / sqrt(20000) of the bright half's, the frame's about the mean of the two
    dark = float(np.interp(2000.0, levels, scale)) * noise
    assert dark == pytest.approx(np.sqrt(2000.0), rel=0.15)
