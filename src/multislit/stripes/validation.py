"""Checks of the image and parameter arguments of the stripe extraction."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import IdentificationError


class SlitExtractionError(IdentificationError):
    """Slit extraction cannot run on the given input (bad image or parameters)."""


#: Colour channels :func:`as_image` can take from an (H, W, 3) RGB image; the first is the
#: default (a red laser). ``"luma"`` is Rec. 601 luma, 0.299 R + 0.587 G + 0.114 B.
CHANNELS = ("red", "green", "blue", "luma")
_LUMA = (0.299, 0.587, 0.114)


def _one_channel(arr: NDArray, channel: str, name: str) -> NDArray:
    """The (H, W) plane ``channel`` of an (H, W, C) RGB or RGBA array, dtype kept."""
    if arr.shape[2] == 1:
        return arr[:, :, 0]
    if arr.shape[2] not in (3, 4):
        raise SlitExtractionError(
            f"{name} must be a 2-D (H, W) grayscale or (H, W, 3) RGB array, got shape {arr.shape}"
        )
    if channel not in CHANNELS:
        raise SlitExtractionError(f"channel must be one of {CHANNELS}, got {channel!r}")
    if channel != "luma":
        return arr[:, :, CHANNELS.index(channel)]
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.number):
        return arr[:, :, 0]  # the dtype check below names the problem
    y = arr[:, :, 0] * _LUMA[0] + arr[:, :, 1] * _LUMA[1] + arr[:, :, 2] * _LUMA[2]
    if np.issubdtype(arr.dtype, np.integer):
        info = np.iinfo(arr.dtype)
        return np.clip(np.rint(y), info.min, info.max).astype(arr.dtype)
    return y


def as_image(image: ArrayLike, *, name: str = "image", channel: str = "red") -> NDArray:
    """Check an image argument and return it as one plane in a dtype the pipeline works in.

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) colour array (RGB order; an (H, W, 4) RGBA array's
        alpha is ignored), uint8, uint16, any other integer or float dtype. Arrays from
        ``cv2.imread`` are BGR: pass ``img[..., ::-1]``.
    name : the argument's name, used in error messages; default ``"image"``
    channel : the plane of a colour image, one of :data:`CHANNELS`; default ``"red"`` (the
        laser's colour: on a red laser's line the red channel has the most contrast); ignored
        for a grayscale image

    Returns
    -------
    (H, W) array: the plane itself if uint8 or uint16 (``image`` itself for a grayscale
    image), else a float32 copy

    Raises
    ------
    SlitExtractionError
        (a ``ValueError``) if ``image`` is neither (H, W) nor (H, W, 3|4), is empty, is boolean
        or not numeric, or holds NaN or infinite values, or ``channel`` is unknown.
    """
    arr = np.asarray(image)
    if arr.ndim == 3:
        arr = _one_channel(arr, channel, name)
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
