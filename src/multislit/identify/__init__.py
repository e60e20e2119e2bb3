"""Slit identification: which slit each stripe of a scan is (paper, section 4.2).

- :mod:`~multislit.identify.reference`: the reference images of a flat board prepared once
  per rig (:func:`prepare_reference` -> :class:`ReferenceSet`: a curve per slit, the dot
  images, the dot projector's epipole);
- :mod:`~multislit.identify.patches`: bilinear patches and the window sums for their moments;
- :mod:`~multislit.identify.matching`: scan dot templates matched with the references along
  the epipolar lines (normalised cross-correlation);
- :mod:`~multislit.identify.segments`: the stripe segments' points, samples, ends and splits;
- :mod:`~multislit.identify.rig`, :mod:`~multislit.identify.evidence`,
  :mod:`~multislit.identify.pieces`, :mod:`~multislit.identify.graph`,
  :mod:`~multislit.identify.geometric`: identification by the dots' geometry (the default):
  the calibrated dot rays predict the dots beside each piece of stripe under each slit; one
  labelling of all pieces;
- :mod:`~multislit.identify.labelling`, :mod:`~multislit.identify.votes`,
  :mod:`~multislit.identify.prior`: the paper's template matching (``method="template"``): the
  samples of each segment vote, with a confidence from the vote's margin; in a sequence the
  previous frame's labels are checked first;
- :mod:`~multislit.identify.frame`: :func:`identify`, either method on one frame.
"""

from multislit.identify.frame import compile_kernels, identify
from multislit.identify.labelling import identify_template
from multislit.identify.matching import prepare_scoring, template_size
from multislit.identify.options import METHODS, IdentifyOptions
from multislit.identify.patches import (
    WINDOW_SUMS,
    bilinear_ncc,
    bilinear_patch_moments,
    normalise_patches,
    sample_patches,
    sample_sheared_patches,
    window_sums,
)
from multislit.identify.reference import (
    CURVE_DEGREE,
    TEMPLATE_BACKGROUND,
    ReferenceSet,
    capture_reference,
    curve_du,
    curve_u,
    estimate_epipole,
    intersect_line_curves,
    prepare_reference,
)
from multislit.identify.result import SOURCES, DotMatches, Identification, PieceLabels
from multislit.identify.rig import RigGeometry, rig_geometry
from multislit.identify.segments import split_at_brightness_steps

__all__ = [
    "TEMPLATE_BACKGROUND",
    "IdentifyOptions",
    "METHODS",
    "PieceLabels",
    "DotMatches",
    "SOURCES",
    "RigGeometry",
    "rig_geometry",
    "identify_template",
    "identify",
    "Identification",
    "prepare_reference",
    "capture_reference",
    "ReferenceSet",
    "template_size",
    "prepare_scoring",
    "split_at_brightness_steps",
    "CURVE_DEGREE",
    "curve_u",
    "curve_du",
    "intersect_line_curves",
    "estimate_epipole",
    "sample_patches",
    "sample_sheared_patches",
    "normalise_patches",
    "compile_kernels",
    "WINDOW_SUMS",
    "window_sums",
    "bilinear_patch_moments",
    "bilinear_ncc",
]
