"""multislit.measure: holes in a flat plate and the VDI/VDE 2634 acceptance metrics."""

from multislit.measure.edges import (
    EdgePoints,
    HoleEdges,
    hole_edges_from_profiles,
    locate_edge_subpixel,
    subpixel_edges,
)
from multislit.measure.hole_fit import HoleResult, fit_holes
from multislit.measure.holes import HoleMeasurement, measure_holes, measure_holes_from_points
from multislit.measure.vdi2634 import (
    MAX_EXCLUDE,
    AcceptanceRow,
    acceptance_table,
    flatness_error,
    markdown_table,
    probing_error_form,
    probing_error_size,
    sphere_spacing_error,
)

__all__ = [
    "measure_holes",
    "measure_holes_from_points",
    "HoleMeasurement",
    "HoleResult",
    "fit_holes",
    "EdgePoints",
    "HoleEdges",
    "hole_edges_from_profiles",
    "locate_edge_subpixel",
    "subpixel_edges",
    "MAX_EXCLUDE",
    "probing_error_form",
    "probing_error_size",
    "sphere_spacing_error",
    "flatness_error",
    "markdown_table",
    "AcceptanceRow",
    "acceptance_table",
]
