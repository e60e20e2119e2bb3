"""Calls of the identification's parallel (Numba ``parallel=True``) kernels.

Numba spreads a parallel kernel over its threading layer: OpenMP or TBB where the machine has
them, else its own work queue, which must not be entered by two threads at once (the process
aborts). A frame may be identified on several threads of one process (``batch`` on a Dask
cluster of threads, a user's thread pool), so on the work queue the kernels are called one at
a time; on OpenMP and TBB, side by side.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numba

_ONE_AT_A_TIME = threading.Lock()
#: Numba's threading layers that parallel kernels may enter from several threads at once.
_THREAD_SAFE = ("omp", "tbb")


def launch(kernel: Callable[..., Any], *args: Any) -> Any:
    """``kernel(*args)``: one call at a time unless Numba's threading layer is known to take
    calls from several threads (it is known after the process's first parallel call)."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet: the layer is not chosen
        layer = None
    if layer in _THREAD_SAFE:
        return kernel(*args)
    with _ONE_AT_A_TIME:
        return kernel(*args)
