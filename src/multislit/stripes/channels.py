"""The colour plane in which the laser's stripes show best (``channel="auto"``).

A red laser is clearest in the red plane, until it is over-exposed: then the red plane is
clipped flat over the line and its halo (a JPEG's 250-255), the line's centre is lost in the
flat top, and the green or blue plane, which sees the laser through the sensor's crosstalk,
shows an unclipped line. :func:`choose_channel` reads that from the data: on a sample of
rows of each plane it measures how far the strongest ridge stands out of the row's
background (the row opening), in noise sigmas of the plane, over the rows where the ridge
does not reach the plane's clip level. A line clipped only where it crosses bright squares
keeps the rows where it is not (a red line on a checkerboard stays in the red plane); a
plane clipped in most rows is avoided.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.stripes.separation import (
    clip_level,
    noise_from_difference,
    quantisation_step,
    row_opening_background,
)
from multislit.stripes.sizes import estimate_stripe_width, sample_rows
from multislit.stripes.validation import (
    AUTO,
    CHANNEL_CHOICES,
    SlitExtractionError,
    as_image,
    check_order,
)

__all__ = ["choose_channel", "resolve_channel", "channel_scores"]

#: The colour planes :func:`choose_channel` chooses from.
_PLANES = ("red", "green", "blue")
#: Rows of each plane sampled.
_SAMPLE_ROWS = 48
#: A row's ridge counts as clipped when its peak pixel or a neighbour reaches the clip level.
_CLIP_REACH_PX = 1
#: A plane whose ridges are clipped in more of the sampled rows than this is avoided: an
#: over-exposed line, flat over its width and halo, has lost its centre. (A red line on a
#: checkerboard clips where it crosses the white squares, about half of its rows.)
_MAX_CLIPPED_ROWS = 0.75


def _clip(plane: NDArray) -> float | None:
    """The level at which ``plane`` clips: the data's pile-up, else an integer type's top."""
    level = clip_level(plane, quantisation_step(plane))
    if np.issubdtype(plane.dtype, np.integer):
        top = float(np.iinfo(plane.dtype).max)
        return top if level is None else min(level, top)
    return level


def _plane_score(plane: NDArray) -> tuple[float, float]:
    """(score, clipped fraction) of one (H, W) plane: the mean over the sampled rows whose
    strongest ridge is not clipped of its height above the row opening in noise sigmas (0
    when more than ``_MAX_CLIPPED_ROWS`` of the rows clip), and the fraction of rows whose
    ridge is clipped."""
    try:
        width = estimate_stripe_width(plane)
    except SlitExtractionError:
        return 0.0, 0.0  # no ridge at all
    idx = sample_rows(plane.shape[0], _SAMPLE_ROWS)
    rows = np.ascontiguousarray(plane[idx], dtype=np.float32)
    hp = rows - row_opening_background(rows, width)
    r = np.arange(len(idx))
    k = np.argmax(hp, axis=1)
    peak = hp[r, k].astype(np.float64)
    spread = noise_from_difference(plane)
    level = _clip(plane)
    clipped = np.zeros(len(idx), bool)
    if level is not None:
        w = plane.shape[1]
        for d in range(-_CLIP_REACH_PX, _CLIP_REACH_PX + 1):
            clipped |= plane[idx, np.clip(k + d, 0, w - 1)] >= level
    frac = float(clipped.mean())
    if frac > _MAX_CLIPPED_ROWS:
        return 0.0, frac
    return float(np.mean(peak[~clipped])) / spread, frac


def channel_scores(image: ArrayLike, *, order: str = "rgb") -> dict[str, tuple[float, float]]:
    """Plane name -> (score, clipped fraction) for the red, green and blue planes of a colour
    image (see :func:`choose_channel`)."""
    arr = np.asarray(image)
    check_order(order)
    return {ch: _plane_score(as_image(arr, channel=ch, order=order)) for ch in _PLANES}


def choose_channel(image: ArrayLike, *, order: str = "rgb") -> str:
    """The colour plane whose stripes stand out most above their background, clipped planes
    avoided.

    Parameters
    ----------
    image : (H, W, 3) or (H, W, 4) colour array (uint8, uint16 or float); a grayscale image
        has one plane: ``"red"`` is returned, which :func:`~multislit.stripes.as_image`
        ignores for it
    order : {'rgb', 'bgr'}
        The order of the planes (``"bgr"`` for ``cv2.imread``'s arrays). Default ``"rgb"``.

    Returns
    -------
    ``"red"``, ``"green"`` or ``"blue"``: the plane with the highest score, the mean over the
    48 sampled rows whose strongest ridge is not clipped of that ridge's height above the
    row's opening background in noise sigmas
    (:func:`~multislit.stripes.separation.noise_from_difference`); a plane whose ridges clip
    in more than 3/4 of the rows scores 0. When every plane scores 0 (clipped, or no ridge),
    the plane whose ridges clip least.

    Raises
    ------
    SlitExtractionError
        A bad image or ``order``.
    """
    arr = np.asarray(image)
    if arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 1):
        as_image(arr)  # the checks of a grayscale image
        return _PLANES[0]
    scores = channel_scores(arr, order=order)
    best = max(_PLANES, key=lambda ch: scores[ch][0])  # the first of equal ones
    if scores[best][0] > 0:
        return best
    return min(_PLANES, key=lambda ch: scores[ch][1])


def resolve_channel(image: ArrayLike, channel: str | None, *, order: str = "rgb") -> str:
    """``channel``, or the plane :func:`choose_channel` finds when it is ``"auto"`` or None."""
    if channel is None or channel == AUTO:
        return choose_channel(image, order=order)
    if channel not in CHANNEL_CHOICES:
        raise SlitExtractionError(f"channel must be one of {CHANNEL_CHOICES}, got {channel!r}")
    return channel
