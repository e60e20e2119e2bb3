"""multislit.calibrate: camera and projector calibration from a capture folder.

:func:`calibrate_capture` turns a capture folder into a :class:`CalibrationResult`, whose
``calibration`` (:class:`Calibration`) the scans use; :func:`write_calibration` saves it with
its report. The building blocks live in the modules: ``camera`` (DLT and refinement),
``markers`` (checker corners), ``capture_camera`` (the camera of a capture), ``slit_points``
and ``slit_labels`` (points on the slits), ``slit_planes`` and ``projector`` (the projector
models and fits), ``boards`` (points on the slits from the reference boards), ``model`` (the
calibration file).
"""

from multislit.calibrate.camera import calibrate_dlt
from multislit.calibrate.model import Calibration
from multislit.calibrate.pipeline import (
    CalibrationResult,
    calibrate_capture,
    format_report,
    write_calibration,
)
from multislit.calibrate.projector import ProjectorMatrix
from multislit.calibrate.slit_planes import SlitPlanes, fit_slit_planes

__all__ = [
    "Calibration",
    "CalibrationResult",
    "ProjectorMatrix",
    "SlitPlanes",
    "calibrate_capture",
    "calibrate_dlt",
    "fit_slit_planes",
    "format_report",
    "write_calibration",
]
