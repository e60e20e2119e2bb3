"""multislit.identify."""

from multislit.identify.labelling import (
    Identification,
    IdentifyParams,
    identify,
    split_at_brightness_steps,
    template_size,
)
from multislit.identify.order import (
    OrderParams,
)
from multislit.identify.reference import (
    CURVE_DEGREE,
    WINDOW_SUMS,
    ReferenceSet,
    bilinear_patch_moments,
    curve_du,
    curve_u,
    estimate_epipole,
    intersect_line_curves,
    normalise_patches,
    prepare_reference,
    sample_patches,
    sample_sheared_patches,
    window_sums,
)

__all__ = [
    "CURVE_DEGREE",
    "sample_patches",
    "sample_sheared_patches",
    "normalise_patches",
    "WINDOW_SUMS",
    "window_sums",
    "bilinear_patch_moments",
    "curve_u",
    "curve_du",
    "intersect_line_curves",
    "ReferenceSet",
    "estimate_epipole",
    "prepare_reference",
    "OrderParams",
    "IdentifyParams",
    "Identification",
    "template_size",
    "split_at_brightness_steps",
    "identify",
]
