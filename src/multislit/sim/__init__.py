"""The simulator: rigs, scenes, physically based rendering, capture folders and scoring.

A rig is described by a :class:`RigSpec` (camera, slit projector, dot projector, sensor) and
built into truth models by :meth:`SimulatedRig.build`; a :class:`Scene` is a list of
primitives; :func:`render` makes one camera image with its per-pixel truth and
:func:`simulate_capture` writes a whole capture folder, :func:`simulate_sequence` renders frames
of objects moving across the field. :func:`random_rig` and
:func:`random_scene` draw rigs and scenes from the range real builders use;
:func:`identification_metrics`, :func:`object_metrics` and :func:`coverage_losses` score an
identification against the truth.
"""

from multislit.sim.evaluate import (
    LOSSES,
    RESOLVABLE_SNR,
    coverage_losses,
    identification_metrics,
    object_metrics,
)
from multislit.sim.primitives import (
    Box,
    Cylinder,
    HeightField,
    Polygon,
    Primitive,
    Scene,
    Sphere,
    constant,
    noise_texture,
)
from multislit.sim.render import Rendered, render, stripe_snr
from multislit.sim.rig import RigSpec, SimulatedRig, dense_rig, true_dot_projector
from multislit.sim.scene import SCENES, TargetDesign, make_scene, reference_board, standard_object
from multislit.sim.sequence import SimulatedSequence, moving_scene, simulate_sequence
from multislit.sim.simulate import Progress, simulate_capture
from multislit.sim.zoo import random_rig, random_scene, simulate_zoo_capture, zoo_target

__all__ = [
    "LOSSES",
    "RESOLVABLE_SNR",
    "SCENES",
    "Box",
    "Cylinder",
    "HeightField",
    "Polygon",
    "Primitive",
    "Progress",
    "Rendered",
    "RigSpec",
    "Scene",
    "SimulatedRig",
    "SimulatedSequence",
    "Sphere",
    "TargetDesign",
    "constant",
    "coverage_losses",
    "dense_rig",
    "identification_metrics",
    "make_scene",
    "moving_scene",
    "noise_texture",
    "object_metrics",
    "random_rig",
    "random_scene",
    "reference_board",
    "render",
    "simulate_capture",
    "simulate_sequence",
    "simulate_zoo_capture",
    "standard_object",
    "stripe_snr",
    "true_dot_projector",
    "zoo_target",
]
