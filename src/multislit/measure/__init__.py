"""multislit.measure."""

from multislit.measure.holes import (
    CircleFit,
    EdgePoints,
    HoleResult,
    fit_circle,
    fit_plane_robust,
    from_plane_coords,
    hole_edges_from_profiles,
    measure_holes,
    plane_basis,
    project_to_plane,
)
from multislit.measure.vdi2634 import (
    MAX_EXCLUDE,
    AcceptanceRow,
    SphereFit,
    acceptance_table,
    fit_sphere,
    flatness_error,
    markdown_table,
    probing_error_form,
    probing_error_size,
    sphere_spacing_error,
)

__all__ = [
    "fit_plane_robust",
    "plane_basis",
    "project_to_plane",
    "from_plane_coords",
    "CircleFit",
    "fit_circle",
    "HoleResult",
    "measure_holes",
    "EdgePoints",
    "hole_edges_from_profiles",
    "MAX_EXCLUDE",
    "SphereFit",
    "fit_sphere",
    "probing_error_form",
    "probing_error_size",
    "sphere_spacing_error",
    "flatness_error",
    "markdown_table",
    "AcceptanceRow",
    "acceptance_table",
]
