"""The dots' centres: where each projected dot lies in a dot image, to a fraction of a pixel.

The separation leaves the dots on a flat background (:class:`~multislit.stripes.SlitExtraction`'s
``dots``). A dot is a small blob about ``dot_size_px`` across; :func:`find_dots` smooths the
dot image with a Gaussian of the dot's own size (the matched filter for a Gaussian spot), takes
every local maximum that stands ``k_sigma`` noise sigmas of the smoothed image above zero, and
centres it to sub-pixel by a parabola through the logarithms of the three samples along each
axis (exact for a Gaussian spot).

Units: px, (u, v) = (column, row), (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.sizes import FWHM_PER_SIGMA
from multislit.stripes.validation import SlitExtractionError

F64 = NDArray[np.float64]

#: Default detection threshold of :func:`find_dots`, in noise sigmas of the smoothed dot image.
DEFAULT_DOT_K_SIGMA = 4.0
#: Places closer than this many stripe widths (FWHM) to a stripe centre are near it: speckle on
#: the stripe leaves dot-like peaks there ...
STRIPE_CLEARANCE = 0.9
#: ... so a dot near a stripe counts only when its peak reaches this share of the stripe's.
MIN_DOT_RATIO = 0.2
#: Smallest smoothing sigma, px (a dot is never sharper than the pixel).
_MIN_SIGMA = 0.5


@dataclass(frozen=True, eq=False)
class DotCentres:
    """The dots found in one dot image.

    Attributes
    ----------
    u, v : (M,) float64, px, sub-pixel dot centres, sorted by (row, column) of their peaks
    peak : (M,) float64, the smoothed dot image at the peak pixel (intensity units)
    """

    u: F64
    v: F64
    peak: F64

    def __len__(self) -> int:
        return len(self.u)

    @property
    def uv(self) -> F64:
        """(M, 2) float64, px, the centres."""
        return np.stack([self.u, self.v], axis=1)

    def subset(self, keep: NDArray[np.bool_]) -> DotCentres:
        """The dots where ``keep`` (M,) bool is True."""
        return DotCentres(self.u[keep], self.v[keep], self.peak[keep])


def smoothed_noise(noise_sigma: float, sigma_px: float) -> float:
    """Noise sigma of white noise of ``noise_sigma`` after a 2-D Gaussian blur of ``sigma_px``
    (px): the blur's kernel has a squared sum of 1 / (4 pi sigma^2)."""
    return float(noise_sigma) / (2.0 * math.sqrt(math.pi) * max(float(sigma_px), _MIN_SIGMA))


def find_dots(
    dot_image: ArrayLike,
    noise_sigma: float,
    dot_size_px: float,
    *,
    k_sigma: float = DEFAULT_DOT_K_SIGMA,
) -> DotCentres:
    """The centres of the dots of a dot image.

    Parameters
    ----------
    dot_image : (H, W) float, the dots on a zero background (e.g. ``extract_slits(img).dots``)
    noise_sigma : float, intensity units, the noise sigma of the unsmoothed image (e.g.
        ``SlitExtraction.noise_sigma``)
    dot_size_px : float, px, the dots' FWHM
    k_sigma : float, the threshold in noise sigmas of the smoothed image; default 4

    Returns
    -------
    DotCentres (empty when there are none)

    Raises
    ------
    SlitExtractionError
        ``dot_image`` is not a 2-D array, or a parameter is not a positive finite number.
    """
    d = np.asarray(dot_image)
    if d.ndim != 2 or d.size == 0:
        raise SlitExtractionError(f"dot_image must be a non-empty 2-D array, got shape {d.shape}")
    for name, x in (("noise_sigma", noise_sigma), ("dot_size_px", dot_size_px)):
        if not (isinstance(x, int | float | np.floating) and math.isfinite(x) and x > 0):
            raise SlitExtractionError(f"{name} must be a positive number, got {x!r}")
    if not (math.isfinite(k_sigma) and k_sigma >= 0):
        raise SlitExtractionError(f"k_sigma must be >= 0, got {k_sigma!r}")
    sigma = max(_MIN_SIGMA, float(dot_size_px) / FWHM_PER_SIGMA)
    s = cv2.GaussianBlur(d.astype(np.float32, copy=False), (0, 0), sigma)
    thr = k_sigma * smoothed_noise(noise_sigma, sigma)
    peak = (s >= cv2.dilate(s, np.ones((3, 3), np.uint8))) & (s > thr)
    peak[0, :] = peak[-1, :] = False
    peak[:, 0] = peak[:, -1] = False
    r, c = np.nonzero(peak)
    if r.size == 0:
        e = np.zeros(0)
        return DotCentres(e, e.copy(), e.copy())
    floor = 1e-3 * float(thr) if thr > 0 else 1e-6
    lc = np.log(np.maximum(s[r, c], floor))
    du = _log_parabola(
        np.log(np.maximum(s[r, c - 1], floor)), lc, np.log(np.maximum(s[r, c + 1], floor))
    )
    dv = _log_parabola(
        np.log(np.maximum(s[r - 1, c], floor)), lc, np.log(np.maximum(s[r + 1, c], floor))
    )
    return DotCentres(c + du, r + dv, s[r, c].astype(np.float64))


def _log_parabola(a: F64, b: F64, c: F64) -> F64:
    """Offset (-0.5..0.5) of the vertex of the parabola through (-1, a), (0, b), (1, c)."""
    den = a - 2.0 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (a - c) / den, 0.0)
    return np.clip(off, -0.5, 0.5)


def stripe_maps(
    u: F64, v: F64, peak: F64, shape: tuple[int, int], radius_px: float
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Where the stripes are, for judging dots near them.

    Parameters
    ----------
    u, v : (K,) float64, px, stripe centres
    peak : (K,) float64, the stripes' peak heights at the centres (intensity units)
    shape : (H, W)
    radius_px : px, how far from a centre the peak map reaches

    Returns
    -------
    distance : (H, W) float32, px, from each pixel to the nearest stripe centre (rounded to
        pixels; large where there are none)
    stripe_peak : (H, W) float32, the largest stripe peak within ``radius_px`` of each pixel
        (0 farther from every stripe)
    """
    h, w = shape
    r = np.clip(np.rint(v).astype(np.intp), 0, h - 1)
    c = np.clip(np.rint(u).astype(np.intp), 0, w - 1)
    marks = np.full((h, w), 255, np.uint8)
    marks[r, c] = 0
    dist = cv2.distanceTransform(marks, cv2.DIST_L2, 3)
    pk = np.zeros((h, w), np.float32)
    np.maximum.at(pk, (r, c), np.asarray(peak, np.float32))
    rad = max(1, int(math.ceil(radius_px)))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
    return dist, cv2.dilate(pk, k)


def dots_clear_of_stripes(
    dots: DotCentres,
    distance: NDArray[np.float32],
    stripe_peak: NDArray[np.float32],
    clearance_px: float,
    min_ratio: float,
) -> tuple[DotCentres, NDArray[np.bool_]]:
    """The dots that are not speckle on a stripe, and which of them lie near one.

    Speckle on a stripe leaves dot-like peaks in the dot image, weaker than a dot: a dot closer
    than ``clearance_px`` to a stripe centre is kept only when its peak is at least
    ``min_ratio`` times the stripe's peak there.

    Returns
    -------
    kept : DotCentres
    near : (M',) bool, the kept dots closer than ``clearance_px`` to a stripe centre
    """
    h, w = distance.shape
    r = np.clip(np.rint(dots.v).astype(np.intp), 0, h - 1)
    c = np.clip(np.rint(dots.u).astype(np.intp), 0, w - 1)
    near = distance[r, c] < clearance_px
    keep = ~near | (dots.peak >= min_ratio * stripe_peak[r, c])
    return dots.subset(keep), near[keep]
