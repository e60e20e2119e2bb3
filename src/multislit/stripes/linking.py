"""Chain stripe centres into segments; the whole extraction of one image."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.centres import (
    CENTRE_METHODS,
    DEFAULT_K_SIGMA,
    DEFAULT_V_SMOOTH,
    TEXTURE_FRACTION,
    StripeCentres,
    along_slits,
    estimate_noise,
    find_centres_validated,
    find_ridge_centres_validated,
    texture_sigma,
)
from multislit.stripes.chains import DEFAULT_MIN_LENGTH, link_weak
from multislit.stripes.channels import resolve_channel
from multislit.stripes.openings import remove_streaks
from multislit.stripes.response import ridge_threshold
from multislit.stripes.ridges import column_pass, merge_dots, merge_passes
from multislit.stripes.separation import (
    BACKGROUNDS,
    PHOTO_OPENING_WIDTHS,
    background_validated,
    dot_size_validated,
    noise_by_level,
    noise_from_difference,
    saturation_level_of,
    separate_validated,
    shows_jpeg_blocks,
)
from multislit.stripes.sizes import (
    estimate_stripe_width,
    opening_length,
)
from multislit.stripes.validation import (
    SlitExtractionError,
    as_image,
    positive_px,
    smoothing_taps,
)
from multislit.summaries import Summarised

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, eq=False, repr=False)
class SlitExtraction(Summarised):
    """Result of :func:`extract_slits`.

    Two kinds of points: those of stripes nearer the vertical, found along the image's rows
    (``by_column`` False: ``v`` a whole row, ``u`` sub-pixel, linked row to row), and those of
    stripes leaning towards the horizontal, found along its columns by the column pass
    (:mod:`~multislit.stripes.ridges`; ``by_column`` True: ``u`` a whole column, ``v``
    sub-pixel, linked column to column). Each segment holds points of one kind.

    Attributes
    ----------
    u, v : (K,) float64, sub-pixel stripe centres (px), sorted by (row, u), row = rint(v)
    peak : (K,) float64, slit intensity at the centre (intensity units above background)
    width : (K,) float64, stripe FWHM along the row, or along the column where ``by_column``
        (px), NaN where unknown
    segment : (K,) int64, segment id (0..S-1, ordered by mean u), -1 for points in segments
        shorter than ``min_length`` (the column pass keeps only linked points)
    dots : (H, W) float32, the dot image (Fig. 11 e) less its streaks (:func:`~multislit.stripes.openings.remove_streaks`:
        pieces of stripes that lean too far for the vertical opening, on curved surfaces); near
        the column pass's points, the column pass's dot image
    noise_sigma : noise sigma of the highpass image (intensity units)
    stripe_width_px : stripe FWHM used (px); NaN if no stripe could be found to estimate it
    dot_size_px : dot FWHM used (px); NaN if not estimated (no stripes)
    angle : (K,) float64, rad, the stripe's direction at the point from the image's vertical,
        positive leaning right going down, in (-pi/2, pi/2]: from a line fitted to its
        segment's points around it (:func:`~multislit.stripes.ridges.chain_angles`); NaN for
        unlinked points
    by_column : (K,) bool, the point was found along its column (a stripe leaning more than
        about 45 degrees from the vertical)
    plane : (H, W) the image plane the extraction ran on (a colour image's laser plane), as
        given (uint8, uint16 or float): where the dots' response is read
        (:func:`~multislit.stripes.dots.dot_response`)
    """

    u: F64
    v: F64
    peak: F64
    width: F64
    segment: I64
    dots: F32
    noise_sigma: float
    stripe_width_px: float
    dot_size_px: float
    angle: F64
    by_column: NDArray[np.bool_]
    plane: NDArray

    @property
    def num_segments(self) -> int:
        """Number of kept segments S."""
        return int(self.segment.max()) + 1 if self.segment.size else 0

    def summary(self) -> str:
        """One line: centres, segments, sizes and noise."""
        linked = int(np.count_nonzero(self.segment >= 0))
        h, w = self.dots.shape
        return (
            f"{self.u.size} stripe centres ({linked} in {self.num_segments} segments) in a "
            f"{w}x{h} px image; stripe width {self.stripe_width_px:.2f} px, dot size "
            f"{self.dot_size_px:.2f} px, noise {self.noise_sigma:.3g}"
        )


def _empty_extraction(img: NDArray, noise: float, sw: float, ds: float) -> SlitExtraction:
    e = np.empty(0)
    shape = img.shape
    return SlitExtraction(
        u=e,
        v=e.copy(),
        peak=e.copy(),
        width=e.copy(),
        segment=np.empty(0, np.int64),
        dots=np.zeros(shape, np.float32),
        noise_sigma=noise,
        stripe_width_px=sw,
        dot_size_px=ds,
        angle=e.copy(),
        by_column=np.zeros(0, bool),
        plane=img,
    )


def _levels(img: NDArray, bg: NDArray, noise: float) -> tuple[NDArray, F64, F64] | None:
    """The frame's noise by background level for the thresholds (:func:`noise_by_level`,
    with the row background ``bg``), or None where the image shows a JPEG's blocks
    (:func:`shows_jpeg_blocks`: its errors do not show as noise; the frame's noise, at least
    a quantisation step, holds everywhere)."""
    if shows_jpeg_blocks(img):
        return None
    lv, sc = noise_by_level(img, bg, noise)
    return bg, lv, sc


def extract_slits(
    image: ArrayLike,
    stripe_width_px: float | None = None,
    dot_size_px: float | None = None,
    *,
    method: str = "gaussian",
    k_sigma: float = DEFAULT_K_SIGMA,
    saturation_level: float | None = None,
    v_smooth: int = DEFAULT_V_SMOOTH,
    max_du: float = 1.5,
    max_gap: int = 2,
    min_length: int = DEFAULT_MIN_LENGTH,
    reject_texture: bool = False,
    channel: str | None = None,
    order: str = "rgb",
    leaning: bool = True,
    background: str = "opening",
) -> SlitExtraction:
    """Stripe centre points, their segments and the dot image of one camera image.

    :func:`separate` -> the centres where the ridge response stands out
    (:func:`~multislit.stripes.centres.find_ridge_centres_validated`: the slit image filtered
    across the stripe at its width and integrated along it, above
    :data:`~multislit.stripes.response.RIDGE_K_FRACTION` times ``k_sigma`` of the response's
    noise; a centre is strong where a single pixel exceeds ``k_sigma`` times the highpass
    noise, weak where the response alone shows it; both noises scaled at each peak by the noise
    at its background's level, :func:`~multislit.stripes.separation.noise_by_level`, unless the
    image shows a JPEG's blocks; saturated runs from the image) ->
    :func:`~multislit.stripes.chains.link_segments` along the stripes' lean, the weak centres
    settled by :func:`~multislit.stripes.chains.settle_weak` (weak runs at a segment's ends
    are kept where :data:`~multislit.stripes.chains.WEAK_TAIL_FACTOR` times ``min_length``
    long, segments of weak centres only where
    :data:`~multislit.stripes.chains.WEAK_LENGTH_FACTOR` times; a weak centre in no segment is
    dropped); the dot image is cleaned of streaks by
    :func:`~multislit.stripes.openings.remove_streaks`. The same steps on the transposed
    image find the stripes that lean towards the horizontal, column by column
    (:func:`~multislit.stripes.ridges.column_pass`, where a quick look along the columns finds
    them: linked column to column, pieces that continue one another along the stripe joined,
    kept where at least :data:`~multislit.stripes.ridges.MIN_LENGTH_FACTOR` times
    ``min_length`` columns long, strong somewhere and running through no stripes of the row
    pass); a stripe both passes found goes to the one along whose direction it leans less
    (:func:`~multislit.stripes.ridges.merge_passes`). An image without slits gives an empty
    result (zero-length arrays), not an error.

    ``reject_texture`` is for photos (a board, a turntable, a textured object; JPEG): the
    row opening has a shorter line
    (:data:`~multislit.stripes.separation.PHOTO_OPENING_WIDTHS`, to follow checker squares)
    and is not lifted, and only centres
    that look like a laser line are kept: darker on both sides in the slit image
    (:func:`~multislit.stripes.centres.stripe_like`: not an edge or a plateau), standing
    out of the texture beside it (``TEXTURE_FRACTION * k_sigma`` times
    :func:`~multislit.stripes.centres.texture_sigma`), on structure that runs along the
    slits (:func:`~multislit.stripes.centres.along_slits`: not a horizontal edge or a corner)
    and linked into a segment (continuing over rows). The simulator's images keep most of
    their linked centres in this mode. The photo
    mode keeps the row pass only: along the columns, a checkerboard's horizontal edges and
    its squares' rows would pass for stripes; and it takes the slit image's row maxima above
    the threshold (:func:`~multislit.stripes.centres.find_stripe_centres`), not the ridge
    response's, whose integration along a line would make stripes of texture.

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) RGB image, uint8, uint16 or float
    stripe_width_px, dot_size_px : FWHMs (px); estimated from the image if None
    method : sub-pixel method, one of :data:`CENTRE_METHODS`
    k_sigma : detection threshold in noise sigmas (the frame's noise, at least one
        quantisation step of the data, scaled down where the background's level is quieter): a
        single pixel's, and (times :data:`~multislit.stripes.response.RIDGE_K_FRACTION`, in
        sigmas of its own noise) the ridge response's
    saturation_level : camera saturation value; default read from the data (flat tops piling
        up at the top of the histogram), else the dtype maximum for integer images
    v_smooth : rows (odd) averaged along the stripe for the sub-pixel fit
    max_du, max_gap, min_length : see :func:`link_segments`
    reject_texture : the photo mode described above; default False
    channel : {'auto', 'red', 'green', 'blue', 'luma'} or None
        The plane of a colour image; ``"auto"`` or None (default): the plane whose stripes
        stand out most above their background, clipped planes avoided
        (:func:`~multislit.stripes.channels.choose_channel`: the red plane of a red laser,
        the green or blue one where the red is clipped over the line). Ignored for a
        grayscale image.
    order : {'rgb', 'bgr'}
        The order of a colour image's planes: ``"bgr"`` for arrays from ``cv2.imread``.
        Default ``"rgb"``.
    leaning : bool
        Find the stripes that lean towards the horizontal too (the column pass). Default
        True; False: the row pass only (stripes up to about 56 degrees from the vertical), for
        images known to hold no others (the calibration's target and reference boards) or
        where time counts more.
    background : {'opening', 'median'}
        The row background (:data:`~multislit.stripes.separation.BACKGROUNDS` of
        :func:`separate`): ``"opening"`` (default), the row's grey opening lifted to the
        background's level (:func:`~multislit.stripes.separation.lifted_opening_background`),
        which passes under the stripes however close they lie and follows every edge;
        ``"median"``, the paper's running median (where stripes cover half the row it sits on
        their flanks), which the calibration's boards and the template method's frames take
        (:data:`~multislit.identify.reference.TEMPLATE_BACKGROUND`).

    Returns
    -------
    SlitExtraction

    Raises
    ------
    SlitExtractionError
        invalid image (not 2-D, empty, NaN/inf, bad dtype) or parameters.
    """
    # one contiguous plane: OpenCV and the compiled kernels read rows (a colour image's plane
    # is a strided view)
    plane = resolve_channel(image, channel, order=order)
    img = np.ascontiguousarray(as_image(image, channel=plane, order=order))
    if background not in BACKGROUNDS:
        raise SlitExtractionError(f"background must be one of {BACKGROUNDS}, got {background!r}")
    if not isinstance(leaning, bool | np.bool_):
        raise SlitExtractionError(f"leaning must be True or False, got {leaning!r}")
    if method not in CENTRE_METHODS:
        raise SlitExtractionError(f"method must be one of {CENTRE_METHODS}, got {method!r}")
    if not math.isfinite(k_sigma) or k_sigma < 0:
        raise SlitExtractionError(f"k_sigma must be >= 0, got {k_sigma}")
    sw = positive_px(stripe_width_px, "stripe_width_px")
    ds = positive_px(dot_size_px, "dot_size_px")
    if sw is None:
        try:
            est = estimate_stripe_width(img)
        except SlitExtractionError:
            est = None
        if est is None:  # nothing stripe-like: no slits
            return _empty_extraction(
                img, estimate_noise(img), math.nan, ds if ds is not None else math.nan
            )
        sw = est
    # the whole image's noise and saturation level, read once for every step that needs them
    noise0 = noise_from_difference(img)
    level = saturation_level_of(img) if saturation_level is None else saturation_level
    if reject_texture:
        bg = background_validated(img, sw, background, PHOTO_OPENING_WIDTHS)
    else:
        bg = background_validated(img, sw, background, noise=noise0)
    if ds is None:
        # the dots' size on the image less its row median (the photo mode's: less its opening)
        ds = dot_size_validated(img, sw, bg if reject_texture or background == "median" else None)
    hp, slits, sat, noise = separate_validated(
        img, sw, ds, level, background, bg, keep_ends=not reject_texture, noise=noise0
    )
    dots = remove_streaks(cv2.subtract(hp, slits), opening_length(ds)).astype(
        np.float32, copy=False
    )
    taps = smoothing_taps(v_smooth)
    if reject_texture:
        centres = find_centres_validated(slits, k_sigma * noise, method, sat, sw, taps, True)
        strong = np.ones(centres.u.size, bool)
        slope = np.zeros(centres.u.size)
    else:
        levels = _levels(img, bg, noise)
        centres, strong, slope = find_ridge_centres_validated(
            slits,
            k_sigma * noise,
            ridge_threshold(k_sigma * noise, sw),
            method,
            sat,
            sw,
            taps,
            image=img,
            levels=levels,
        )
    if reject_texture:
        r = np.rint(centres.v).astype(np.intp)
        c = np.clip(np.rint(centres.u).astype(np.intp), 0, img.shape[1] - 1)
        keep = centres.peak >= TEXTURE_FRACTION * k_sigma * texture_sigma(slits, sw)[r, c]
        keep &= along_slits(slits, centres.u, centres.v, sw)
        centres = StripeCentres(*(a[keep] for a in centres))
        strong, slope = strong[keep], slope[keep]
    link = {"max_du": max_du, "max_gap": max_gap, "min_length": min_length}
    segment = link_weak(centres.u, centres.v, strong, slope, centres.peak, **link)
    # a laser line continues over rows (the photo mode); a weak centre counts in a segment only
    linked = segment >= 0 if reject_texture else (segment >= 0) | strong
    if not linked.all():
        centres = StripeCentres(*(a[linked] for a in centres))
        segment, strong, slope = segment[linked], strong[linked], slope[linked]
    if reject_texture or not leaning:
        none = np.zeros(0, np.int64)
        merged = merge_passes(
            centres, segment, _no_centres(), none, link, 0.0, (none, none), (strong, slope)
        )
    else:
        thr = k_sigma * noise
        lk = segment >= 0
        rows = (centres.v[lk], centres.u[lk])  # the row pass's stripes, in the columns' frame
        cols = column_pass(
            img,
            sw,
            ds,
            thr,
            method,
            level,
            taps,
            link,
            rows,
            None if levels is None else levels[1:],
        )
        merged = merge_passes(
            centres,
            segment,
            cols.centres,
            cols.segment,
            link,
            thr,
            rows,
            (strong, slope),
            (cols.strong, cols.slope),
        )
        c = merged.by_column
        dots = merge_dots(dots, cols.dots, merged.centres.u[c], merged.centres.v[c], sw)
    centres = merged.centres
    return SlitExtraction(
        u=centres.u,
        v=centres.v,
        peak=centres.peak,
        width=centres.width,
        segment=merged.segment,
        dots=dots,
        noise_sigma=noise,
        stripe_width_px=sw,
        dot_size_px=ds,
        angle=merged.angle,
        by_column=merged.by_column,
        plane=img,
    )


def _no_centres() -> StripeCentres:
    e = np.empty(0)
    return StripeCentres(e, e.copy(), e.copy(), e.copy())
