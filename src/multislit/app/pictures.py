"""A picture of a scanned frame: where the scan saw the stripes and where it is blind.

:func:`scan_picture` draws the frame, dimmed, with every stripe point of the scan in its
slit's colour and every stripe centre the scan left out (unidentified, dropped by the
identification, or not triangulated) in magenta; ``multislit scan --pictures`` and
``multislit stream --pictures`` write it beside each PLY (``NAME.png``, ``frame_000000.png``),
and ``multislit view`` shows it next to the 3D plot.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MeasurementError
from multislit.reconstruct import ScanResult
from multislit.stripes import as_image

__all__ = ["scan_picture", "encode_png", "LEFT_OUT_BGR"]

#: The colour of the stripe centres left out (BGR): magenta, outside the slits' colour map.
LEFT_OUT_BGR = (255, 0, 255)
#: How bright the frame is drawn under the points (the points stand out).
_DIM = 0.6
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _grey8(image: ArrayLike) -> NDArray[np.uint8]:
    """The frame as 8-bit grey, scaled to its own range (16-bit or float data)."""
    img = as_image(image)
    if img.dtype == np.uint8:
        return img
    x = img.astype(np.float32)
    lo, hi = float(x.min()), float(x.max())
    return np.clip((x - lo) * (255.0 / max(hi - lo, 1e-12)), 0, 255).astype(np.uint8)


def _slit_colours(slit: NDArray[np.int64], num_slits: int) -> NDArray[np.uint8]:
    """(K, 3) BGR colours of slit numbers on the turbo colour map, over 0..num_slits-1."""
    scale = 255.0 / max(num_slits - 1, 1)
    index = np.clip(np.rint(slit * scale), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(index.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)


def _dots(canvas: NDArray[np.uint8], u: NDArray, v: NDArray, colours: NDArray) -> None:
    """Paint 2x2-pixel dots at the points (u, v) px, clipped to the canvas."""
    h, w = canvas.shape[:2]
    c = np.clip(np.rint(u).astype(np.intp), 0, w - 1)
    r = np.clip(np.rint(v).astype(np.intp), 0, h - 1)
    for dr in (0, 1):
        for dc in (0, 1):
            canvas[np.minimum(r + dr, h - 1), np.minimum(c + dc, w - 1)] = colours


def scan_picture(image: ArrayLike, result: ScanResult, *, num_slits: int | None = None) -> NDArray:
    """The frame with the scan's stripe points coloured by slit and those left out marked.

    Parameters
    ----------
    image : (H, W) the scanned frame (the plane the scan read), any dtype the scan takes
    result : the frame's :class:`~multislit.reconstruct.ScanResult`
    num_slits : int, optional
        The rig's slits (the colour scale's range). Default: the highest slit in the result.

    Returns
    -------
    (H, W, 3) uint8 BGR picture: the frame dimmed, the points on the slits' turbo colours,
    the stripe centres left out in magenta (:data:`LEFT_OUT_BGR`), and a line of counts.

    Raises
    ------
    MeasurementError
        ``result`` is not a ScanResult or was made from an image of another size.
    """
    if not isinstance(result, ScanResult):
        raise MeasurementError(f"result must be a ScanResult, got {type(result).__name__}")
    grey = _grey8(image)
    h, w = grey.shape
    if tuple(result.image_size) not in ((w, h), (0, 0)):
        raise MeasurementError(
            f"the scan is of a {result.image_size[0]}x{result.image_size[1]} px image, the "
            f"picture's frame {w}x{h} px"
        )
    canvas = cv2.cvtColor((grey * _DIM).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    ident = result.identification
    left = np.ones(len(ident.u), bool)
    left[result.index] = False
    _dots(canvas, ident.u[left], ident.v[left], np.array(LEFT_OUT_BGR, np.uint8))
    n = num_slits if num_slits is not None else int(result.slit.max(initial=0)) + 1
    _dots(canvas, result.u, result.v, _slit_colours(result.slit, n))
    text = (
        f"{result.name or 'frame'}: {result.num_points} points by slit, "
        f"{int(left.sum())} stripe centres left out (magenta)"
    )
    scale = max(0.4, w / 1600)
    org = (8, int(24 * scale) + 4)
    cv2.putText(canvas, text, org, _FONT, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(canvas, text, org, _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def encode_png(picture: NDArray) -> bytes:
    """The picture as PNG bytes."""
    ok, buf = cv2.imencode(".png", picture)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 array
        raise MeasurementError("cannot encode the picture as PNG")
    return buf.tobytes()
