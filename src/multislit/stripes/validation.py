"""Checks of the image and parameter arguments of the stripe extraction."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import IdentificationError


class SlitExtractionError(IdentificationError):
    """Slit extraction cannot run on the given input (bad image or parameters)."""


#: Colour channels :func:`as_image` can take from an (H, W, 3) colour image; the first is
#: its default (a red laser). ``"luma"`` is Rec. 601 luma, 0.299 R + 0.587 G + 0.114 B.
CHANNELS = ("red", "green", "blue", "luma")
#: The channel chosen from the data (:func:`~multislit.stripes.channels.choose_channel`): the
#: plane whose stripes stand out most above their background, clipped planes avoided.
AUTO = "auto"
#: Every ``channel`` value of the extraction and the readers: :data:`AUTO` and the planes.
CHANNEL_CHOICES = (AUTO, *CHANNELS)
#: Orders of the planes of a colour array: RGB (the package's), BGR (``cv2.imread``'s).
ORDERS = ("rgb", "bgr")
_LUMA = (0.299, 0.587, 0.114)


def check_order(order: object) -> str:
    """``order`` if it is one of :data:`ORDERS`."""
    if order not in ORDERS:
        raise SlitExtractionError(
            f"order must be 'rgb' or 'bgr' (cv2.imread's arrays are BGR), got {order!r}"
        )
    return str(order)


def plane_index(channel: str, order: str = "rgb") -> int:
    """The index of colour plane ``channel`` (red, green or blue) in an array of ``order``."""
    i = CHANNELS.index(channel)
    return 2 - i if order == "bgr" else i


def _one_channel(arr: NDArray, channel: str, name: str, order: str) -> NDArray:
    """The (H, W) plane ``channel`` of an (H, W, C) RGB(A) or BGR(A) array, dtype kept."""
    if arr.shape[2] == 1:
        return arr[:, :, 0]
    if arr.shape[2] not in (3, 4):
        raise SlitExtractionError(
            f"{name} must be a 2-D (H, W) grayscale or (H, W, 3) RGB array, got shape {arr.shape}"
        )
    if channel == AUTO:
        raise SlitExtractionError(
            "channel 'auto' is chosen from the image first (multislit.stripes.choose_channel); "
            f"as_image takes one of {CHANNELS}"
        )
    if channel not in CHANNELS:
        raise SlitExtractionError(f"channel must be one of {CHANNEL_CHOICES}, got {channel!r}")
    check_order(order)
    if channel != "luma":
        return arr[:, :, plane_index(channel, order)]
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.number):
        return arr[:, :, 0]  # the dtype check below names the problem
    r, g, b = (arr[:, :, plane_index(c, order)] for c in ("red", "green", "blue"))
    y = r * _LUMA[0] + g * _LUMA[1] + b * _LUMA[2]
    if np.issubdtype(arr.dtype, np.integer):
        info = np.iinfo(arr.dtype)
        return np.clip(np.rint(y), info.min, info.max).astype(arr.dtype)
    return y


def as_image(
    image: ArrayLike, *, name: str = "image", channel: str = "red", order: str = "rgb"
) -> NDArray:
    """Check an image argument and return it as one plane in a dtype the pipeline works in.

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) colour array (an (H, W, 4) array's alpha is
        ignored), uint8, uint16, any other integer or float dtype
    name : the argument's name, used in error messages; default ``"image"``
    channel : the plane of a colour image, one of :data:`CHANNELS`; default ``"red"``; ignored
        for a grayscale image. (The extraction's ``channel="auto"`` is resolved before, by
        :func:`~multislit.stripes.channels.choose_channel`.)
    order : {'rgb', 'bgr'}
        The order of a colour image's planes: ``"bgr"`` for arrays from ``cv2.imread``.
        Default ``"rgb"``.

    Returns
    -------
    (H, W) array: the plane itself if uint8 or uint16 (``image`` itself for a grayscale
    image), else a float32 copy

    Raises
    ------
    SlitExtractionError
        (a ``ValueError``) if ``image`` is neither (H, W) nor (H, W, 3|4), is empty, is boolean
        or not numeric, or holds NaN or infinite values, or ``channel`` or ``order`` is
        unknown.
    """
    arr = np.asarray(image)
    if arr.ndim == 3:
        arr = _one_channel(arr, channel, name, order)
    if arr.ndim != 2:
        raise SlitExtractionError(
            f"{name} must be a 2-D (H, W) grayscale or (H, W, 3) RGB array, got shape {arr.shape}"
        )
    if arr.size == 0:
        raise SlitExtractionError(f"{name} is empty (shape {arr.shape})")
    if arr.dtype == np.uint8 or arr.dtype == np.uint16:
        return arr
    if arr.dtype == np.bool_ or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise SlitExtractionError(f"{name} must be uint8, uint16 or float, got dtype {arr.dtype}")
    out = arr.astype(np.float32)
    if not np.isfinite(out).all():
        raise SlitExtractionError(f"{name} contains NaN or infinite values")
    return out


def positive_px(x: float | None, name: str) -> float | None:
    """``x`` as a float if it is a finite positive number of pixels, None if None."""
    if x is None:
        return None
    x = float(x)
    if not math.isfinite(x) or x <= 0:
        raise SlitExtractionError(f"{name} must be a positive number of pixels, got {x}")
    return x


def int_at_least(x: object, name: str, lo: int) -> int:
    """``x`` as an int if it is an integer (not a bool) >= ``lo``."""
    if isinstance(x, bool) or not isinstance(x, int | np.integer) or int(x) < lo:
        raise SlitExtractionError(f"{name} must be an integer >= {lo}, got {x!r}")
    return int(x)


def smoothing_taps(v_smooth: int) -> int:
    """Rows averaged along the stripe: ``v_smooth`` if it is an odd integer >= 1."""
    if int(v_smooth) != v_smooth or v_smooth < 1 or v_smooth % 2 == 0:
        raise SlitExtractionError(f"v_smooth must be an odd integer >= 1, got {v_smooth}")
    return int(v_smooth)
