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
"""

__version__ = "0.1.0"

from multislit.calibrate import Calibration, calibrate_capture, write_calibration
from multislit.errors import MultislitError
from multislit.identify import capture_reference, prepare_reference
from multislit.io import Capture, read_ply, write_ply
from multislit.measure import measure_holes
from multislit.reconstruct import ScanOptions, scan_capture, scan_image
from multislit.sim import RigSpec, simulate_capture

__all__ = [
    "Calibration",
    "Capture",
    "MultislitError",
    "RigSpec",
    "ScanOptions",
    "calibrate_capture",
    "capture_reference",
    "measure_holes",
    "prepare_reference",
    "read_ply",
    "scan_capture",
    "scan_image",
    "simulate_capture",
    "write_calibration",
    "write_ply",
]
