"""The compiled structure-tensor kernels of :mod:`multislit.stripes.slope` against their
definitions through OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from multislit.stripes.slope import _sobel_row, cell_tensor


def _cell_tensor_reference(img: np.ndarray, ch: int, cw: int, f: int) -> np.ndarray:
    """Per cell, the means of gu^2, gv^2 and 2 gu gv of cv2.Sobel's 3 x 3 derivatives over
    its pixels clear of the image's border (the last cells take the remainder)."""
    h, w = img.shape
    gu = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3)
    gv = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3)
    out = np.zeros((ch, cw, 3))
    count = np.zeros((ch, cw))
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            ci, cj = min(i // f, ch - 1), min(j // f, cw - 1)
            out[ci, cj] += gu[i, j] ** 2, gv[i, j] ** 2, 2 * gu[i, j] * gv[i, j]
            count[ci, cj] += 1
    return out / np.maximum(count, 1)[..., None]


@pytest.mark.parametrize("dtype", (np.uint8, np.uint16, np.float32))
def test_cell_tensor_is_the_mean_of_sobels_products_per_cell(dtype):
    rng = np.random.default_rng(7)
    top = 255 if dtype == np.float32 else np.iinfo(dtype).max
    for (h, w), f in (((17, 29), 4), ((33, 20), 8), ((9, 9), 2)):
        img = rng.integers(0, top + 1, (h, w)).astype(dtype)
        img[0, :] = top  # the largest sums
        got = cell_tensor(img, h // f, w // f, f)
        want = _cell_tensor_reference(img, h // f, w // f, f)
        np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-3 * top)


@pytest.mark.parametrize("dtype", (np.uint8, np.uint16))
def test_sobel_row_matches_opencv(dtype):
    rng = np.random.default_rng(7)
    top = np.iinfo(dtype).max
    for h, w in ((1, 1), (2, 3), (3, 2), (17, 29)):
        img = rng.integers(0, top + 1, (h, w)).astype(dtype)
        img[0, :] = top  # the largest sums
        gu = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
        gv = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
        ou = np.empty(w, np.float32)
        ov = np.empty(w, np.float32)
        for r in range(h):
            _sobel_row(img, r, ou, ov)
            np.testing.assert_array_equal(ou, gu[r])
            np.testing.assert_array_equal(ov, gv[r])
