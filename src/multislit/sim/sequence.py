"""A sequence of frames of objects moving in front of the rig, with the truth of every frame.

:func:`simulate_sequence` renders the rig's reference images once and then ``frames`` scans of
a sphere and a box that translate together a few mm per frame across the field, in front of a
wall, as a camera running at its frame rate sees a part passing on a conveyor. The images and
the per-pixel truth come back as arrays (no folder is written): the references go to
:func:`multislit.identify.prepare_reference`, each frame to
:func:`multislit.identify.identify`, and :func:`multislit.sim.object_metrics` scores a frame
against its truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MultislitError
from multislit.sim.primitives import Box, Primitive, Scene, Sphere
from multislit.sim.render import render
from multislit.sim.rig import RigSpec, SimulatedRig
from multislit.sim.scene import backdrop_wall, reference_board
from multislit.sim.simulate import _check_reference

#: World Z of the rig (camera and projector centres), mm, as the default rig.
_RIG_Z = 1000.0


@dataclass(frozen=True, eq=False)
class SimulatedSequence:
    """Frames of a moving scene rendered by :func:`simulate_sequence`, with their truth.

    Attributes
    ----------
    spec : the rig the images were rendered with
    references : list of (H, W) uint8/uint16, the reference board images, nearest board first
    reference_names : their names (``ref_0780``, ...), as a capture folder's reference images
    images : list of (H, W) uint8/uint16, the scans, one per frame, in order
    truth_slit : list of (H, W) int16, per frame the slit lighting each pixel (-1: none)
    truth_object : list of (H, W) bool, per frame True where the pixel sees a moving object
        (False: the wall behind, or nothing)
    offsets : (F, 3) float64, mm, world: the objects' displacement in each frame from their
        place in the first
    """

    spec: RigSpec
    references: list[NDArray]
    reference_names: list[str]
    images: list[NDArray]
    truth_slit: list[NDArray[np.int16]]
    truth_object: list[NDArray[np.bool_]]
    offsets: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.images)


def moving_scene(offset: ArrayLike, *, name: str = "moving") -> Scene:
    """The sequence's scene with its objects displaced by ``offset``.

    A sphere (radius 60 mm) and a box (60 x 90 x 50 mm) side by side, 850-900 mm from the rig,
    in front of a wall 1100 mm away (mid grey). At zero offset the pair stands left of the
    field's centre, so a displacement along +X carries it across the field.

    Parameters
    ----------
    offset : (3,) float, mm, world: the objects' displacement (X right, Y up, Z towards the rig)
    name : the scene's name; default "moving"
    """
    d = np.asarray(offset, float)
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        raise MultislitError(f"offset must be 3 finite numbers (mm), got {offset!r}")
    prims: list[Primitive] = [
        Sphere(np.array([-150.0, 20.0, _RIG_Z - 910.0]) + d, 60.0, name="sphere"),
        Box(
            np.array([-40.0, -40.0, _RIG_Z - 875.0]) + d,
            (30.0, 45.0, 25.0),
            texture_albedo=0.65,
            name="box",
        ),
        backdrop_wall(_RIG_Z - 1100.0, 0.55),
    ]
    return Scene(name, prims, {"offset": d.tolist()}, backdrop=("wall",))


def simulate_sequence(
    spec: RigSpec | None = None,
    *,
    frames: int = 30,
    step_mm: ArrayLike = (4.0, 0.0, 0.0),
    seed: int = 0,
) -> SimulatedSequence:
    """Render the references and ``frames`` scans of objects moving across the field.

    The objects (:func:`moving_scene`) move by ``step_mm`` from one frame to the next. Every
    image gets its own noise and speckle from one seeded ``numpy.random.Generator`` stream:
    the same arguments give the same images.

    Parameters
    ----------
    spec : the rig; default ``RigSpec()`` (1280x1024 px, 25 slits). ``RigSpec().scaled(0.5)``
        gives 640x512 images for quick tests
    frames : number of scans, >= 1; default 30
    step_mm : (3,) float, mm, world: the displacement per frame (X right, Y up, Z towards the
        rig), or one number for a move along +X; default 4 mm along X (at 60 frames a second,
        a conveyor at 0.24 m/s)
    seed : seeds the images' noise; default 0

    Returns
    -------
    SimulatedSequence with the reference images, the scans and each scan's truth.

    Raises
    ------
    MultislitError
        (a ``ValueError``) if ``frames`` is not a positive integer or ``step_mm`` is not one or
        three finite numbers, or a reference board does not show every slit.
    """
    if isinstance(frames, bool) or not isinstance(frames, int | np.integer) or frames < 1:
        raise MultislitError(f"frames must be a positive integer, got {frames!r}")
    step = np.asarray(step_mm, float)
    if step.shape == ():
        step = np.array([float(step), 0.0, 0.0])
    if step.shape != (3,) or not np.all(np.isfinite(step)):
        raise MultislitError(f"step_mm must be one or three finite numbers (mm), got {step_mm!r}")
    spec = spec or RigSpec()
    rig = SimulatedRig.build(spec)
    n_ref = len(spec.reference_distances)
    seeds = np.random.SeedSequence(seed).spawn(n_ref + int(frames))
    references, names = [], []
    for i, dist in enumerate(spec.reference_distances):
        name = f"ref_{dist:04.0f}"
        r = render(rig, reference_board(dist), np.random.default_rng(seeds[i]))
        _check_reference(rig, r, f"reference/{name}")
        references.append(r.image)
        names.append(name)
    offsets = np.arange(int(frames))[:, None] * step[None, :]
    images, truth_slit, truth_object = [], [], []
    for f, d in enumerate(offsets):
        scene = moving_scene(d, name=f"frame_{f:04d}")
        r = render(rig, scene, np.random.default_rng(seeds[n_ref + f]))
        images.append(r.image)
        truth_slit.append(r.slit)
        truth_object.append(scene.is_object(r.obj))
    return SimulatedSequence(spec, references, names, images, truth_slit, truth_object, offsets)
