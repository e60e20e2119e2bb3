"""The separation's run finder gives the vertical runs a column-by-column NumPy scan gives."""

from __future__ import annotations

import numpy as np
import pytest

from multislit.stripes.separation import _mask_runs_v, mask_runs


def _runs_ref(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertical runs of nonzero pixels (column, start, stop), in the order of a row-major scan
    of their ends (stop row, then column)."""
    h, w = mask.shape
    mt = np.zeros((w, h + 2), np.int8)
    mt[:, 1:-1] = mask.T != 0
    col, start, stop = mask_runs(np.diff(mt, axis=1))
    order = np.lexsort((col, stop))
    return col[order], start[order], stop[order]


@pytest.mark.parametrize("width", [1, 7, 8, 13, 24, 40])
def test_mask_runs_v_matches_column_scan(width):
    rng = np.random.default_rng(width)
    for h in (1, 2, 9, 33):
        for density in (0.0, 0.1, 0.5, 0.9, 1.0):
            # any nonzero byte is a mask pixel (dot_mask writes 255; a bare uint8 mask may not)
            values = rng.integers(1, 256, (h, width))
            mask = np.where(rng.random((h, width)) < density, values, 0).astype(np.uint8)
            words = mask.view(np.uint64) if width % 8 == 0 else np.zeros((h, 0), np.uint64)
            cap = max(int(np.count_nonzero(mask)), 1)
            got = _mask_runs_v(mask, words, cap)
            for g, e in zip(got, _runs_ref(mask), strict=True):
                np.testing.assert_array_equal(g, e)
