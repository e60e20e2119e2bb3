"""Separate slits from dots and extract the slit centre lines (paper, section 4.1, Fig. 11).

For one camera image with many roughly vertical laser stripes (slits) and the random dots
scattered along them, by stage:

1. :func:`separate` (:mod:`~multislit.stripes.separation`): a grey opening along each row,
   wider than a stripe, estimates the background (ambient light, albedo, texture); subtracting
   it (clipped at 0) leaves the stripes and dots on a flat background (Fig. 11 c). A
   morphological opening with a vertical line longer than a dot finds the dots (a line along
   the stripe where it leans: :mod:`~multislit.stripes.openings`), which are refilled by
   interpolation along the stripe's lean (d; :mod:`~multislit.stripes.slope`); the dots are the
   difference (e). The stripe and dot sizes that set the filters are estimated from the image
   (:mod:`~multislit.stripes.sizes`).
2. The centres (:mod:`~multislit.stripes.centres`): in every row, the maxima of the ridge
   response (:mod:`~multislit.stripes.response`: a matched filter across the stripe at its
   width, integrated along the stripe's lean over a few rows, so that a stripe a few noise
   sigmas above its background per pixel still stands out), each refined to sub-pixel by a
   3-point fit (Gaussian by default) on the slit image averaged along the stripe; saturated
   (flat-top) stripes are centred from a Gaussian fit to the unsaturated flanks.
   :func:`find_stripe_centres` takes the slit image's own maxima above a noise threshold
   (the photo mode's centres).
3. :func:`link_segments` (:mod:`~multislit.stripes.chains`): centre points in consecutive rows
   are chained into segments along the stripes' lean, broken at jumps, gaps and ambiguities;
   the centres only the ridge response shows are kept in long enough runs
   (:func:`~multislit.stripes.chains.settle_weak`).

:func:`extract_slits` runs the three steps. After identification, :func:`refine_centres`
(:mod:`~multislit.stripes.refine`) re-centres the points for triangulation. :func:`as_image`
is the package's check of an image argument; a colour (H, W, 3) image gives one plane, its
``channel``, in RGB or (``order="bgr"``, ``cv2.imread``'s arrays) BGR order.
:func:`extract_slits` takes the plane from the data unless ``channel`` is given
(:func:`choose_channel`: the plane in which the stripes stand out most, clipped planes
avoided).

Photos: the noise floor is one quantisation step of the data and the saturation level is
read from the data's flat tops (:func:`~multislit.stripes.separation.clip_level`).
``extract_slits(..., reject_texture=True)`` keeps only centres that look like a laser line
(:func:`stripe_like`, :func:`texture_sigma`, :func:`along_slits`, linked over rows): edges,
checker corners, texture and JPEG blocks go.

Pixel convention: (u, v), u right (column), v down (row), (0, 0) the centre of the top-left
pixel. Whole-image passes are OpenCV or NumPy, or compiled where one pass replaces several
whole-image temporaries (a float image's dot mask, the refinement's structure tensor
products); the loops NumPy cannot vectorise (the dots' refill and the stripe slope it needs,
the opening along leaning stripes, the row maxima, the linking) are compiled with Numba
(:func:`compile_kernels`).
"""

import numpy as np

from multislit.stripes.centres import (
    CENTRE_METHODS,
    DEFAULT_K_SIGMA,
    DEFAULT_V_SMOOTH,
    StripeCentres,
    along_slits,
    estimate_noise,
    find_stripe_centres,
    stripe_like,
    texture_sigma,
)
from multislit.stripes.chains import DEFAULT_MIN_LENGTH, link_segments
from multislit.stripes.channels import choose_channel, resolve_channel
from multislit.stripes.dots import centre_dots, find_dots
from multislit.stripes.linking import SlitExtraction, extract_slits
from multislit.stripes.openings import (
    STREAK_ANGLES_DEG,
    follow_stripe_opening,
    line_kernel,
    remove_streaks,
    vertical_opening,
)
from multislit.stripes.options import ExtractionOptions
from multislit.stripes.refine import (
    REFINE_STEGER_SCALE,
    refine_centres,
    refine_half_rows,
    refine_slit_image,
)
from multislit.stripes.refine import compile_kernels as _compile_refine_kernels
from multislit.stripes.response import lean_slopes, ridge_response, wide_centres
from multislit.stripes.separation import (
    BACKGROUNDS,
    Separation,
    fill_dots,
    lifted_opening_background,
    row_median_background,
    row_opening_background,
    separate,
)
from multislit.stripes.sizes import (
    FWHM_PER_SIGMA,
    estimate_dot_size,
    estimate_stripe_width,
    median_stride,
    opening_length,
    ridge_contrast,
)
from multislit.stripes.slope import slope_sigma, stripe_slope
from multislit.stripes.validation import (
    AUTO,
    CHANNEL_CHOICES,
    CHANNELS,
    ORDERS,
    SlitExtractionError,
    as_image,
)

__all__ = [
    "ExtractionOptions",
    "as_image",
    "CHANNELS",
    "CHANNEL_CHOICES",
    "AUTO",
    "ORDERS",
    "choose_channel",
    "resolve_channel",
    "BACKGROUNDS",
    "row_opening_background",
    "lifted_opening_background",
    "ridge_contrast",
    "stripe_like",
    "texture_sigma",
    "along_slits",
    "SlitExtractionError",
    "FWHM_PER_SIGMA",
    "CENTRE_METHODS",
    "DEFAULT_K_SIGMA",
    "DEFAULT_MIN_LENGTH",
    "DEFAULT_V_SMOOTH",
    "Separation",
    "StripeCentres",
    "SlitExtraction",
    "median_stride",
    "opening_length",
    "estimate_stripe_width",
    "estimate_dot_size",
    "row_median_background",
    "vertical_opening",
    "STREAK_ANGLES_DEG",
    "line_kernel",
    "remove_streaks",
    "slope_sigma",
    "stripe_slope",
    "separate",
    "estimate_noise",
    "find_stripe_centres",
    "link_segments",
    "extract_slits",
    "REFINE_STEGER_SCALE",
    "refine_slit_image",
    "refine_half_rows",
    "refine_centres",
    "compile_kernels",
]


def compile_kernels() -> None:
    """Compile the package's Numba kernels now: the extraction's (every centre method), the
    refinement's and the dots' (found, centred as spots).

    Numba compiles each kernel on first use and caches the machine code on disk beside the
    package, so only the first run after an install pays it; :func:`multislit.compile_kernels`
    calls this with the other stages' warm-ups. The extraction is run on small uint8, uint16
    and float32 images (each pixel type has its own machine code).
    """
    _compile_refine_kernels()
    img = np.zeros((48, 48), np.uint8)
    img[:, 22:26] = 200
    img[10:12, 30:32] = 120  # a dot beside the stripe
    img[30:32, 23:25] = 255
    for x in (img, img.astype(np.uint16) << 4, img.astype(np.float32) / 255.0):
        extract_slits(x, 4.0, 2.0)
        extract_slits(x)
        extract_slits(x, 4.0, 2.0, reject_texture=True)
        for method in CENTRE_METHODS:
            extract_slits(x, 4.0, 2.0, method=method, leaning=False)
        fill_dots(x, vertical_opening(x, 5), 1.0, 5)
        fill_dots(x, vertical_opening(x, 5), 1.0, 5, stripe_slope(x, 2.5))
        follow_stripe_opening(x, vertical_opening(x, 5), 5, np.full((12, 12), 30.0), 4, 0.0)
        ridge_response(x, 4.0, np.full((12, 12), 0.5, np.float32))  # along a leaning stripe
        lean_slopes(x, 4.0)
        wide_centres(x, 2.0, np.array([20]), np.array([23]), np.zeros(1))
    _compile_dot_kernels()


def _compile_dot_kernels() -> None:
    """The dots' kernels: a stripe with dots beside it, its dots found and centred as spots
    (:func:`~multislit.stripes.dots.centre_dots`, with a fitted and a given spot sigma)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float64)
    img = 10.0 + 180.0 * np.exp(-0.5 * ((xx - 47.5) / 1.5) ** 2)
    for cu, cv in rng.uniform(8.0, 88.0, size=(40, 2)):
        img += 90.0 * np.exp(-0.5 * ((xx - cu) ** 2 + (yy - cv) ** 2) / 1.1**2)
    img += rng.normal(0.0, 1.0, img.shape)
    ex = extract_slits(np.clip(img, 0, 255).astype(np.uint8), 4.0, 2.6)
    found = find_dots(ex.dots, ex.noise_sigma, ex.dot_size_px)
    for spot_sigma in (None, 1.1):
        centre_dots(ex, found.u, found.v, np.zeros(len(found.u)), spot_sigma)
