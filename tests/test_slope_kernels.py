"""The slope's row-by-row Sobel gives cv2.Sobel's derivatives bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from multislit.stripes.slope import _sobel_row


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
