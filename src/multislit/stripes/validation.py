"""Checks of the image and parameter arguments of the stripe extraction."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import IdentificationError


class SlitExtractionError(IdentificationError):
    """Slit extraction cannot run on the given input (bad image or parameters)."""


def as_image(image: ArrayLike, *, name: str = "image") -> NDArray:
    """Check a grayscale image argument and return it in a dtype the pipeline works in.

    Parameters
    ----------
    image : (H, W) array, uint8, uint16, any other integer or float dtype
    name : the argument's name, used in error messages; default ``"image"``

    Returns
    -------
    (H, W) array: ``image`` itself if uint8 or uint16, else a float32 copy

    Raises
    ------
    SlitExtractionError
        (a ``ValueError``) if ``image`` is not 2-D, is empty, is boolean or not numeric, or
        holds NaN or infinite values.
    """
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise SlitExtractionError(
            f"{name} must be a 2-D (H, W) grayscale array, got shape {arr.shape}"
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
