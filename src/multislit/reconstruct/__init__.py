"""multislit.reconstruct: identified stripe points -> 3D points (triangulation and scans)."""

from multislit.reconstruct.options import RefineOptions, ScanOptions
from multislit.reconstruct.scan import (
    CALIBRATION_FILE,
    ScanResult,
    compile_kernels,
    faded_ends,
    load_capture_calibration,
    rig_of,
    scan_capture,
    scan_image,
    scan_image_for_holes,
)
from multislit.reconstruct.triangulation import (
    triangulate,
    triangulate_matrix,
)

__all__ = [
    "ScanOptions",
    "RefineOptions",
    "triangulate_matrix",
    "triangulate",
    "CALIBRATION_FILE",
    "ScanResult",
    "scan_image",
    "scan_image_for_holes",
    "faded_ends",
    "load_capture_calibration",
    "scan_capture",
    "rig_of",
    "compile_kernels",
]
