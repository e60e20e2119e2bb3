"""multislit: single-shot 3D measurement with multiple laser slits identified by random dots.

A projector casts many parallel laser slits at once and a second laser scatters random dots
along them; the dot texture around each piece of stripe tells which slit it is, so one camera
image gives a full set of 3D profiles.

>>> import multislit as ms
>>> cap = ms.Capture.open("mycapture")                 # doctest: +SKIP
>>> cal = ms.calibrate_capture(cap).calibration                # once per rig
>>> ref = ms.capture_reference(cap)                    # once per rig
>>> scan = ms.scan_image(cap.image(cap.scans[0]), ref, cal)
>>> scan.points                                        # (K, 3) mm

The subpackages follow the data: :mod:`multislit.io` (capture folders, PLY),
:mod:`multislit.stripes` (separation, stripe centres), :mod:`multislit.identify` (reference
lines, slit addresses by the dots), :mod:`multislit.reconstruct` (triangulation, scans),
:mod:`multislit.measure` (holes, VDI/VDE 2634 figures); :mod:`multislit.calibrate`,
:mod:`multislit.geometry` and :mod:`multislit.sim` (the rig simulator) beside them.
:func:`compile_kernels` compiles every compiled (Numba) kernel of the package before the first
frame; :func:`set_threads` sets how many threads a frame may use.
"""

__version__ = "0.1.0"

import numbers
import os

# The compiled kernels spread their windows over Numba's threads (OpenMP); between those runs
# the threads sleep rather than spin, or a spinning thread takes its core from the OpenCV calls
# and the serial work of the frame. Set before the OpenMP runtime starts; a user's own setting
# stands.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import cv2  # noqa: E402
import numba  # noqa: E402

from multislit import calibrate, identify, reconstruct, stripes
from multislit._memory import keep_freed_buffers
from multislit.calibrate import Calibration, calibrate_capture, write_calibration
from multislit.errors import MultislitError
from multislit.identify import capture_reference, prepare_reference
from multislit.io import Capture, read_ply, write_ply
from multislit.measure import measure_holes
from multislit.reconstruct import ScanOptions, scan_capture, scan_image
from multislit.sim import RigSpec, simulate_capture

# A frame's image-sized buffers are kept in the heap when freed, so the next frame reuses them
# rather than faulting their pages in again (:mod:`multislit._memory`; MULTISLIT_ALLOCATOR=system
# or a user's own MALLOC_MMAP_THRESHOLD_ or MALLOC_TRIM_THRESHOLD_ leaves the allocator alone).
keep_freed_buffers()

__all__ = [
    "Calibration",
    "Capture",
    "MultislitError",
    "RigSpec",
    "ScanOptions",
    "calibrate_capture",
    "capture_reference",
    "compile_kernels",
    "measure_holes",
    "prepare_reference",
    "read_ply",
    "scan_capture",
    "scan_image",
    "set_threads",
    "simulate_capture",
    "write_calibration",
    "write_ply",
]


def compile_kernels() -> None:
    """Compile every Numba kernel of the package now, or load it from Numba's disk cache.

    Numba compiles a kernel on its first call (seconds for the package's pipeline) and caches
    the machine code beside the package, so only the first run after an install pays that;
    after this call the first frame costs what the others do. It runs each stage package's
    warm-up (:mod:`~multislit.stripes`: the extraction, the dots and the refinement;
    :mod:`~multislit.identify`: both identification methods and the reference;
    :mod:`~multislit.reconstruct`: the triangulation; :mod:`~multislit.calibrate`: the
    reference boards' dots and the slits' order), each on small synthetic images. A second
    call is quick: the warm-ups run again on their small images, nothing is compiled.
    """
    for stage in (stripes, identify, reconstruct, calibrate):
        stage.compile_kernels()


def set_threads(threads: int) -> None:
    """Set how many threads the work on one frame may use: OpenCV's and Numba's.

    By default both use every core. The identification's compiled kernels spread their windows
    over Numba's threads, OpenCV its whole-image calls over its own; the result does not depend
    on the number. Worker processes that are themselves the parallelism (``stream --workers``,
    ``batch``) set 1.

    Parameters
    ----------
    threads : int, >= 1, at most Numba's ``NUMBA_NUM_THREADS`` (the cores, by default)
    """
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 1:
        raise MultislitError(f"threads must be a whole number >= 1, got {threads!r}")
    threads = int(threads)
    if threads > numba.config.NUMBA_NUM_THREADS:
        raise MultislitError(
            f"threads must be at most {numba.config.NUMBA_NUM_THREADS} (NUMBA_NUM_THREADS: the "
            f"cores), got {threads}"
        )
    cv2.setNumThreads(threads)
    numba.set_num_threads(threads)
