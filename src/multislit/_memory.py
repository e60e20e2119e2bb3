"""The process's memory allocator, set for frames that come one after another.

A frame's stages make and free arrays of the image's size (megabytes each). glibc's allocator
maps such a block from the system afresh on each request and hands it back when it is freed,
and trims the free memory at the top of its heap, so every frame pays for touching its
buffers' pages again (thousands of page faults, several ms a stage at 1280x1024). Raising the
size up to which blocks come from the heap, and the free memory the heap keeps, makes a frame
reuse the last one's memory instead.
"""

from __future__ import annotations

import ctypes
import os
import sys
import warnings

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap (glibc's largest on 64-bit systems: 32 MiB; a
#: 1920x1080 float64 image is 16 MiB) ...
MMAP_THRESHOLD = 32 * 2**20
#: ... and the heap keeps up to this much free memory rather than hand it back.
TRIM_THRESHOLD = 256 * 2**20
#: The environment variables by which a user sets these; a user's own setting stands.
_USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
#: ``MULTISLIT_ALLOCATOR``: ``frames`` (the default) sets the allocator, ``system`` leaves it as
#: it is.
_CHOICE = "MULTISLIT_ALLOCATOR"
_CHOICES = ("frames", "system")


def keep_freed_buffers() -> bool:
    """Set glibc's allocator to keep frame-sized blocks in the heap (:data:`MMAP_THRESHOLD`,
    :data:`TRIM_THRESHOLD`); nothing on another C library, where the user set either in the
    environment (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``), or with
    ``MULTISLIT_ALLOCATOR=system``. Another value of ``MULTISLIT_ALLOCATOR`` is named in a
    warning and taken as ``frames``. Returns whether it was set."""
    choice = os.environ.get(_CHOICE, _CHOICES[0])
    if choice not in _CHOICES:
        # one line, placed at the variable (no source line under it)
        warnings.warn_explicit(
            f"{_CHOICE} must be one of {', '.join(_CHOICES)}, got {choice!r}: taken as "
            f"{_CHOICES[0]!r} (set it to 'system' to leave the memory allocator as it is)",
            UserWarning,
            f"environment {_CHOICE}",
            0,
        )
        choice = _CHOICES[0]
    if (
        choice == "system"
        or not sys.platform.startswith("linux")
        or any(k in os.environ for k in _USER_SETTINGS)
    ):
        return False
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return False
    # glibc's (musl and others have no such mallopt parameters)
    if not (hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt")):
        return False
    mallopt = libc.mallopt
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )
