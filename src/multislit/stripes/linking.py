"""Chain stripe centres into segments; the whole extraction of one image."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit
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
    texture_sigma,
)
from multislit.stripes.channels import resolve_channel
from multislit.stripes.openings import remove_streaks
from multislit.stripes.separation import background_validated, separate_validated
from multislit.stripes.sizes import (
    estimate_dot_size,
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

#: Default minimum number of centre points of a kept segment: shorter runs are noise or residues
#: of dots, and a segment must be long enough to carry a dot template for identification.
DEFAULT_MIN_LENGTH = 10


@dataclass(frozen=True, eq=False, repr=False)
class SlitExtraction(Summarised):
    """Result of :func:`extract_slits`.

    Attributes
    ----------
    u, v : (K,) float64, sub-pixel stripe centres (px), sorted by (v, u)
    peak : (K,) float64, slit intensity at the centre (intensity units above background)
    width : (K,) float64, stripe FWHM along the row (px), NaN where unknown
    segment : (K,) int64, segment id from :func:`link_segments` (0..S-1, ordered by mean u),
        -1 for points in segments shorter than ``min_length``
    dots : (H, W) float32, the dot image (Fig. 11 e) less its streaks (:func:`~multislit.stripes.openings.remove_streaks`:
        pieces of stripes that lean too far for the vertical opening, on curved surfaces)
    noise_sigma : noise sigma of the highpass image (intensity units)
    stripe_width_px : stripe FWHM used (px); NaN if no stripe could be found to estimate it
    dot_size_px : dot FWHM used (px); NaN if not estimated (no stripes)
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


def link_segments(
    u: ArrayLike,
    v: ArrayLike,
    max_du: float = 1.5,
    max_gap: int = 2,
    min_length: int = DEFAULT_MIN_LENGTH,
) -> I64:
    """Chain centre points of consecutive rows into segments continuous along v.

    A point p in row v is linked to a point q in the first row v + g (g = 1 .. max_gap + 1)
    that has any point within ``max_du * g`` px of p's column, if q is the only such point
    there and p is likewise the only candidate in q's first non-empty row above. Ambiguities
    (two candidates), jumps and longer gaps break the chain. One sort and a compiled linear
    pass (the windows move monotonically along the sorted points).

    Parameters
    ----------
    u, v : (K,) centre columns and rows (px); v is rounded to integer rows
    max_du : largest column change per row (px) within a segment
    max_gap : largest number of missing rows bridged
    min_length : segments with fewer points get label -1

    Returns
    -------
    labels : (K,) int64, segment id per point (0..S-1, ordered by the segments' mean u), -1 for
        points of too-short segments
    """
    uu = np.asarray(u, dtype=np.float64)
    vv = np.asarray(v, dtype=np.float64)
    if uu.ndim != 1 or vv.shape != uu.shape:
        raise SlitExtractionError(
            f"u and v must be 1-D arrays of the same length, got {uu.shape} and {vv.shape}"
        )
    if not (np.isfinite(uu).all() and np.isfinite(vv).all()):
        raise SlitExtractionError("u and v must be finite")
    if not math.isfinite(max_du) or max_du < 0:
        raise SlitExtractionError(f"max_du must be >= 0, got {max_du}")
    if int(max_gap) != max_gap or max_gap < 0:
        raise SlitExtractionError(f"max_gap must be an integer >= 0, got {max_gap}")
    if int(min_length) != min_length or min_length < 1:
        raise SlitExtractionError(f"min_length must be an integer >= 1, got {min_length}")
    n = uu.size
    if n == 0:
        return np.empty(0, np.int64)
    rows = np.rint(vv)
    if n > 1 and bool(
        np.all((rows[1:] > rows[:-1]) | ((rows[1:] == rows[:-1]) & (uu[1:] >= uu[:-1])))
    ):
        order = np.arange(n)  # already sorted by (row, u), as the centres come
    else:
        order = np.lexsort((uu, rows))
    us = uu[order] - uu.min()
    rs = rows[order] - rows.min()
    max_g = int(max_gap) + 1
    # key = row * span + u is sorted; span exceeds the u range plus the search tolerance, so a
    # search window never spills into another row
    span = float(us.max()) + 2 * max_du * max_g + 2.0
    key = rs * span + us
    comp, size, sum_u = _chains(key, us, span, float(max_du), max_g)
    keep = size >= min_length
    mean_u = sum_u / size
    kept = np.flatnonzero(keep)
    new_id = np.full(size.size, -1, np.int64)
    new_id[kept[np.argsort(mean_u[kept], kind="stable")]] = np.arange(kept.size)
    labels = np.empty(n, np.int64)
    labels[order] = new_id[comp]
    return labels


@njit(cache=True)
def _first_neighbour(key, span, max_du, max_g, sign):
    """Per point of the sorted ``key`` (K,): index of the unique point within ``max_du * g``
    px of its column in the first row g = 1 .. ``max_g`` away (``sign`` +1 below, -1 above)
    that has any, -1 if none, -2 if ambiguous. The windows move monotonically with the key,
    so two pointers per g replace the binary searches (the same comparisons)."""
    n = key.size
    found = np.full(n, -1, np.int64)
    for g in range(1, max_g + 1):
        tol = max_du * g
        shift = float(sign * g) * span
        lo = 0
        hi = 0
        for i in range(n):
            centre = key[i] + shift
            a = centre - tol
            b = centre + tol
            while lo < n and key[lo] < a:  # searchsorted(key, a, "left")
                lo += 1
            if hi < lo:
                hi = lo
            while hi < n and key[hi] <= b:  # searchsorted(key, b, "right")
                hi += 1
            if found[i] == -1 and hi > lo:
                found[i] = lo if hi - lo == 1 else -2
    return found


@njit(cache=True)
def _chains(key, us, span, max_du, max_g):
    """Chain the points of the sorted ``key`` (K,): a point and the first candidate below it
    are linked where each is the other's unique candidate (:func:`link_segments`). Returns
    each point's chain (K,) int64, numbered in the order of the chains' first points, and
    each chain's size and sum of ``us`` (summed in point order)."""
    n = key.size
    nxt = _first_neighbour(key, span, max_du, max_g, 1)
    prv = _first_neighbour(key, span, max_du, max_g, -1)
    comp = np.empty(n, np.int64)
    m = 0
    for i in range(n):  # a link goes to a later row: the predecessor has a lower index
        p = prv[i]
        if p >= 0 and nxt[p] == i:
            comp[i] = comp[p]
        else:
            comp[i] = m
            m += 1
    size = np.zeros(m, np.int64)
    sum_u = np.zeros(m, np.float64)
    for i in range(n):
        size[comp[i]] += 1
        sum_u[comp[i]] += us[i]
    return comp, size, sum_u


def _empty_extraction(shape: tuple[int, int], noise: float, sw: float, ds: float) -> SlitExtraction:
    e = np.empty(0)
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
    )


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
) -> SlitExtraction:
    """Stripe centre points, their segments and the dot image of one camera image.

    :func:`separate` -> :func:`find_stripe_centres` (threshold ``k_sigma`` times the highpass
    noise, saturated runs from the image) -> :func:`link_segments`; the dot image is cleaned of
    streaks by :func:`~multislit.stripes.openings.remove_streaks`. An image without slits
    gives an empty result (zero-length arrays), not an error.

    ``reject_texture`` is for photos (a board, a turntable, a textured object; JPEG): the
    row background is the row opening (``background="opening"`` of :func:`separate`, which
    follows checker squares and edges where the row median leaves ripples), and only centres
    that look like a laser line are kept: darker on both sides in the slit image
    (:func:`~multislit.stripes.centres.stripe_like`: not an edge or a plateau), standing
    out of the texture beside it (``TEXTURE_FRACTION * k_sigma`` times
    :func:`~multislit.stripes.centres.texture_sigma`), on structure that runs along the
    slits (:func:`~multislit.stripes.centres.along_slits`: not a horizontal edge or a corner)
    and linked into a segment (continuing over rows). The simulator's images keep most of
    their linked centres in this mode; the default keeps the paper's row median.

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) RGB image, uint8, uint16 or float
    stripe_width_px, dot_size_px : FWHMs (px); estimated from the image if None
    method : sub-pixel method, one of :data:`CENTRE_METHODS`
    k_sigma : detection threshold in noise sigmas (the noise is at least one quantisation
        step of the data)
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
    background = "opening" if reject_texture else "median"
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
                img.shape, estimate_noise(img), math.nan, ds if ds is not None else math.nan
            )
        sw = est
    bg = None
    if ds is None:
        bg = background_validated(img, sw, background)
        # dots from the same optics: fall back to the stripe
        ds = estimate_dot_size(cv2.subtract(img, bg)) or sw
    hp, slits, sat, noise = separate_validated(img, sw, ds, saturation_level, background, bg)
    dots = remove_streaks(cv2.subtract(hp, slits), opening_length(ds)).astype(
        np.float32, copy=False
    )
    centres = find_centres_validated(
        slits, k_sigma * noise, method, sat, sw, smoothing_taps(v_smooth), reject_texture
    )
    if reject_texture:
        r = np.rint(centres.v).astype(np.intp)
        c = np.clip(np.rint(centres.u).astype(np.intp), 0, img.shape[1] - 1)
        keep = centres.peak >= TEXTURE_FRACTION * k_sigma * texture_sigma(slits, sw)[r, c]
        keep &= along_slits(slits, centres.u, centres.v, sw)
        centres = StripeCentres(*(a[keep] for a in centres))
    segment = link_segments(
        centres.u, centres.v, max_du=max_du, max_gap=max_gap, min_length=min_length
    )
    if reject_texture:  # a laser line continues over rows
        linked = segment >= 0
        centres = StripeCentres(*(a[linked] for a in centres))
        segment = segment[linked]
    return SlitExtraction(
        u=centres.u,
        v=centres.v,
        peak=centres.peak,
        width=centres.width,
        segment=segment,
        dots=dots,
        noise_sigma=noise,
        stripe_width_px=sw,
        dot_size_px=ds,
    )
