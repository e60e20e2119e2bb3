"""multislit.reconstruct."""

from multislit.reconstruct.scan import (
    CALIBRATION_FILE,
    HOLE_SCAN_PARAMS,
    HoleEdges,
    HoleMeasurement,
    ScanParams,
    ScanResult,
    capture_reference,
    load_capture_calibration,
    locate_edge_subpixel,
    measure_holes_in_scan,
    scan_capture,
    scan_image,
)
from multislit.reconstruct.triangulation import (
    triangulate,
    triangulate_matrix,
)

__all__ = [
    "triangulate_matrix",
    "triangulate",
    "CALIBRATION_FILE",
    "ScanParams",
    "HOLE_SCAN_PARAMS",
    "ScanResult",
    "scan_image",
    "load_capture_calibration",
    "capture_reference",
    "scan_capture",
    "HoleEdges",
    "HoleMeasurement",
    "locate_edge_subpixel",
    "measure_holes_in_scan",
]
