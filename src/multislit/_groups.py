"""Statistics per group of values, shared by the stages."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def group_medians(x: F64, group: I64, num_groups: int) -> F64:
    """(num_groups,) the median of the finite ``x`` of each group (NaN: none)."""
    f = np.isfinite(x)
    x, group = x[f], group[f]
    # by value, then stably by group (a radix sort where the groups fit in 16 bits)
    o = np.argsort(x)
    key = group[o]
    o = o[np.argsort(key.astype(np.uint16) if num_groups <= 1 << 16 else key, kind="stable")]
    x = x[o]
    n = np.bincount(group, minlength=num_groups)
    start = np.r_[0, np.cumsum(n)[:-1]]
    out = np.full(num_groups, np.nan)
    g = np.flatnonzero(n)
    lo = start[g] + (n[g] - 1) // 2
    hi = start[g] + n[g] // 2
    out[g] = 0.5 * (x[lo] + x[hi])
    return out
