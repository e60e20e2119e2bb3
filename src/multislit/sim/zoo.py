"""A zoo of rigs and scenes drawn at random, across the range real builders use.

:func:`random_rig` draws a :class:`RigSpec`: a 0.3-5 MP camera with lens distortion up to
|k1| = 0.15, a 200-500 mm baseline, a 0.5-1.5 m standoff, 15-61 slits whose fan fits the
camera's view on every reference board, dots in bands or uniform from a source 20-80 mm along
and up to 10 mm across the slit axis, and a sensor from clean to poor (noise, speckle, ambient
light). :func:`random_scene` draws objects in front of a backdrop wall: small spheres, a ball
bar, rods, boxes showing side faces, a staircase, a free-form body, a textured plate; some are
dark. :func:`simulate_zoo_capture` writes a capture folder for one seed.

Every draw goes through the ``numpy.random.Generator`` passed in: the same seed gives the same
rig and scenes. The rig looks along -Z from Z = 1000 mm (as the default rig), so the reference
boards of :func:`multislit.sim.simulate_capture` stand at the drawn distances.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from multislit.errors import MultislitError
from multislit.sim.primitives import (
    F64,
    Box,
    Cylinder,
    HeightField,
    Polygon,
    Primitive,
    Scene,
    Sphere,
    noise_texture,
)
from multislit.sim.rig import (
    CameraSpec,
    DotProjectorSpec,
    RigSpec,
    SensorSpec,
    SimulatedRig,
    SlitProjectorSpec,
)
from multislit.sim.scene import TargetDesign, backdrop_wall
from multislit.sim.simulate import Progress, simulate_capture

#: World Z of the rig (camera and projector centres), mm, as the default rig.
RIG_Z = 1000.0
#: Reference board distances as fractions of the standoff.
REFERENCE_FRACTIONS = (0.85, 1.0, 1.15)
#: The nearest an object may come to the rig, as a fraction of the standoff.
NEAR_FRACTION = 0.85

_MIN_SPACING_PX = 8.0  # stripes at least this far apart at the standoff (full-size camera)
_DOT_DENSITY = 0.0098  # dots per px^2 of the fan's image, as the default rig
_MARGIN = 0.03  # fraction of the image width every slit keeps from the image's sides
_TRIES = 200


def _standoff(spec: RigSpec) -> float:
    """Camera-to-aim-point distance along Z, mm."""
    return float(spec.camera.position[2] - spec.camera.look_at[2])


def _half_fov(spec: RigSpec) -> float:
    """The camera's horizontal half field of view, rad."""
    return float(np.arctan(0.5 * spec.camera.image_size[0] / spec.camera.focal_px))


def _slits_fit(spec: RigSpec) -> bool:
    """Every slit's line on every reference board projects inside the image (with a margin)."""
    rig = SimulatedRig.build(spec)
    p = rig.projector
    w, h = spec.camera.image_size
    psi = np.linspace(-0.3, 0.3, 5) * p.fan_half
    a, s = np.meshgrid(p.angles, psi)
    dirs = np.stack([np.sin(a) * np.cos(s), np.sin(s), np.cos(a) * np.cos(s)], -1).reshape(-1, 3)
    dirs = dirs @ p.R
    for dist in spec.reference_distances:
        t = (RIG_Z - dist - p.origin[2]) / dirs[:, 2]
        uv = rig.camera.project(p.origin + t[:, None] * dirs)
        m = _MARGIN * w
        if not (np.isfinite(uv).all() and np.all((uv[:, 0] > m) & (uv[:, 0] < w - 1 - m))):
            return False
        if not np.all((uv[:, 1] > 0) & (uv[:, 1] < h - 1)):
            return False
    return True


def _camera(rng: np.random.Generator, standoff: float, cam_x: float) -> CameraSpec:
    mp = float(np.exp(rng.uniform(np.log(0.3), np.log(5.0))))
    aspect = float(rng.choice([4 / 3, 5 / 4, 16 / 9]))
    w = int(round(np.sqrt(mp * 1e6 * aspect) / 16) * 16)
    h = int(round(w / aspect / 8) * 8)
    half_fov = np.radians(rng.uniform(16.0, 28.0))
    k1 = rng.uniform(-0.15, 0.15)
    return CameraSpec(
        image_size=(w, h),
        focal_px=float(0.5 * w / np.tan(half_fov)),
        principal_offset_px=tuple(float(x) for x in rng.uniform(-0.01, 0.01, 2) * w),
        dist=(
            float(k1),
            float(rng.uniform(-0.05, 0.05)),
            float(rng.uniform(-5e-4, 5e-4)),
            float(rng.uniform(-5e-4, 5e-4)),
        ),
        position=(cam_x, float(rng.uniform(-20.0, 20.0)), RIG_Z),
        look_at=(0.0, 0.0, RIG_Z - standoff),
    )


def _slits(
    rng: np.random.Generator, cam: CameraSpec, standoff: float, proj_x: float, fill: float
) -> SlitProjectorSpec:
    """A slit projector whose fan spans ``fill`` of the camera's field at the standoff."""
    w, h = cam.image_size
    f = cam.focal_px
    tan_max = fill * 0.5 * w / f
    fan_px = 2 * tan_max * f
    n_max = int(min(61, fan_px / _MIN_SPACING_PX + 1))
    n = int(rng.integers(15, max(n_max, 15) + 1)) | 1  # odd: a central order
    n = min(n, 61)
    wavelength = float(rng.choice([520.0, 635.0, 650.0, 660.0]))
    pitch = (n - 1) / 2 * wavelength * 1e-3 / np.sin(np.arctan(tan_max))
    spacing_px = fan_px / (n - 1)
    sigma_px = min(rng.uniform(1.0, 1.5), spacing_px / 6)
    fan_half = np.degrees(np.arctan(0.5 * h / f * rng.uniform(1.2, 1.45)))
    return SlitProjectorSpec(
        num_slits=n,
        wavelength_nm=wavelength,
        pitch_um=float(pitch),
        stripe_sigma_mrad=float(sigma_px / f * 1e3),
        fan_half_deg=float(fan_half),
        power=float(0.85 * (standoff / 900.0) ** 2 * rng.uniform(0.7, 1.1)),
        position=(proj_x, 0.0, RIG_Z),
        look_at=(0.0, 0.0, RIG_Z - standoff),
    )


def _dots(
    rng: np.random.Generator, cam: CameraSpec, slits: SlitProjectorSpec, standoff: float
) -> DotProjectorSpec:
    f = cam.focal_px
    spread = (slits.num_slits - 1) / 2 * slits.wavelength_nm * 1e-3 / slits.pitch_um
    fan_w = 2 * np.tan(np.arcsin(spread)) * f
    fan_h = 2 * np.tan(np.radians(slits.fan_half_deg)) * f
    along = rng.uniform(20.0, 80.0) * rng.choice([-1.0, 1.0])
    return DotProjectorSpec(
        offset=(float(rng.uniform(-10.0, 10.0)), float(along), 0.0),
        num_dots=int(_DOT_DENSITY * rng.uniform(0.7, 1.4) * fan_w * fan_h),
        pattern=str(rng.choice(["bands", "uniform"])),
        band_halfwidth=float(rng.uniform(0.3, 0.45)),
        dot_sigma_mrad=float(rng.uniform(0.7, 1.0) / f * 1e3),
        power=float(0.7 * (standoff / 900.0) ** 2 * rng.uniform(0.7, 1.1)),
        seed=int(rng.integers(0, 2**31 - 1)),
    )


def _sensor(rng: np.random.Generator) -> SensorSpec:
    q = rng.uniform()  # 0: clean, 1: poor
    return SensorSpec(
        full_well_e=float(rng.uniform(6000.0, 15000.0)),
        read_noise_e=float(4.0 + 16.0 * q * rng.uniform(0.7, 1.0)),
        blur_sigma_px=float(rng.uniform(0.5, 0.9)),
        ambient=float(0.03 + 0.25 * q * rng.uniform(0.5, 1.0)),
        speckle_contrast=float(0.05 + 0.2 * q * rng.uniform(0.5, 1.0)),
    )


def random_rig(rng: np.random.Generator) -> RigSpec:
    """A rig drawn across the range real builders use.

    Camera 0.3-5 MP (aspect 4:3, 5:4 or 16:9), horizontal half field 16-28 degrees, k1 within
    +-0.15; standoff 0.5-1.5 m; baseline 200-500 mm and 0.2-0.7 of the standoff, the camera on
    the left; 15-61 slits (odd), at least 8 px apart, whose fan fills 45-75 % of the field;
    dots in bands or uniform, 20-80 mm along and up to 10 mm across the slit axis; reference
    boards at 0.85, 1.0 and 1.15 of the standoff. The fan is narrowed until every slit is in
    the image on every reference board.

    Parameters
    ----------
    rng : the only source of randomness

    Returns
    -------
    RigSpec (validated)
    """
    standoff = float(rng.uniform(500.0, 1500.0))
    baseline = float(rng.uniform(max(200.0, 0.2 * standoff), min(500.0, 0.7 * standoff)))
    frac = rng.uniform(0.4, 0.6)
    cam = _camera(rng, standoff, float(-baseline * frac))
    fill = rng.uniform(0.45, 0.75)
    slits = _slits(rng, cam, standoff, float(baseline * (1 - frac)), fill)
    dots = _dots(rng, cam, slits, standoff)
    spec = RigSpec(
        camera=cam,
        slits=slits,
        dots=dots,
        sensor=_sensor(rng),
        reference_distances=tuple(round(standoff * x, 1) for x in REFERENCE_FRACTIONS),
    )
    for _ in range(20):
        spec.validate()
        if _slits_fit(spec):
            return spec
        s = spec.slits
        spec = replace(spec, slits=replace(s, pitch_um=s.pitch_um * 1.08))
        spec = replace(spec, dots=_dots(rng, cam, spec.slits, standoff))
    raise MultislitError("random_rig: could not fit the slit fan into the camera's view")


def zoo_target(spec: RigSpec) -> TargetDesign:
    """The calibration target scaled to the rig's field of view and placed at its standoff.

    The default target suits a 640 mm wide field at 900 mm; every length scales with 0.85 of the
    field's width at the standoff and the corner sits as far behind the aim point as the
    default's, scaled.
    """
    standoff = _standoff(spec)
    k = 0.85 * standoff * np.tan(_half_fov(spec)) / (900.0 * 640.0 / 1800.0)
    d = TargetDesign()
    return TargetDesign(
        depth=d.depth * k,
        height=d.height * k,
        ramp_depth=d.ramp_depth * k,
        ramp_slope=d.ramp_slope,
        marker_size=d.marker_size * k,
        marker_pitch=d.marker_pitch * k,
        corner_z=(RIG_Z - standoff) - (RIG_Z - 900.0 - d.corner_z) * k,
    )


# --------------------------------------------------------------------------- scenes
class _Stage:
    """Where objects may go: in the camera's view, in the slit fan, between ``near`` and the wall."""

    def __init__(self, rng: np.random.Generator, spec: RigSpec, wall_d: float) -> None:
        self.rng = rng
        self.rig = SimulatedRig.build(spec)
        self.standoff = _standoff(spec)
        self.near = NEAR_FRACTION * self.standoff
        self.wall_d = wall_d
        self.wall_z = RIG_Z - wall_d
        w = spec.camera.image_size[0]
        self.field = 2 * self.standoff * w / (2 * spec.camera.focal_px)  # mm across at standoff

    def point(self, front: float, back: float, inner: float = 0.7) -> F64:
        """A point whose distance from the rig is in [front, back] mm, inside the slit fan and
        the central ``inner`` of the image."""
        rig, rng = self.rig, self.rng
        w, h = rig.camera.image_size
        ang, fan = rig.projector.angles, rig.projector.fan_half
        front, back = max(front, self.near), min(back, self.wall_d - 1.0)
        back = max(back, front)
        for _ in range(_TRIES):
            uv = np.array(
                [
                    [
                        w * rng.uniform(0.5 - inner / 2, 0.5 + inner / 2),
                        h * rng.uniform(0.5 - inner / 2, 0.5 + inner / 2),
                    ]
                ]
            )
            o, d = rig.camera.rays(uv)
            dist = rng.uniform(front, back)
            x = o[0] + (RIG_Z - dist - o[0, 2]) / d[0, 2] * d[0]
            phi, psi, _ = rig.projector.local(x[None])
            if ang[0] < phi[0] < ang[-1] and abs(psi[0]) < 0.7 * fan:
                return x
        raise MultislitError("random_scene: no place for an object in the fan")

    def albedo(self) -> float:
        """A surface albedo; one surface in five is dark."""
        rng = self.rng
        return float(rng.uniform(0.05, 0.15) if rng.uniform() < 0.2 else rng.uniform(0.4, 0.9))


def _rotation(axis: F64, angle: float) -> F64:
    """Rotation matrix (Rodrigues) about a unit ``axis`` by ``angle`` rad."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _sphere(st: _Stage, i: int, info: dict) -> list[Primitive]:
    r = st.rng.uniform(15.0, 75.0)
    c = st.point(st.near + r, st.wall_d - r - 5.0)
    info.setdefault("spheres", []).append({"centre": c.tolist(), "radius": r})
    return [Sphere(c, r, texture_albedo=st.albedo(), name=f"sphere{i}")]


def _ball_bar(st: _Stage, i: int, info: dict) -> list[Primitive]:
    rng = st.rng
    r = rng.uniform(15.0, 30.0)
    length = rng.uniform(0.25, 0.5) * st.field
    a = rng.uniform(-0.6, 0.6)
    half = 0.5 * length * np.array([np.cos(a), np.sin(a), rng.uniform(-0.15, 0.15)])
    reach = r + abs(half[2])  # how far the bar reaches towards the rig from its middle
    mid = st.point(st.near + reach, st.wall_d - reach - 40.0, inner=0.4)
    c1, c2 = mid - half, mid + half
    rod_r = rng.uniform(2.5, 6.0)
    info.setdefault("spheres", []).extend([{"centre": c.tolist(), "radius": r} for c in (c1, c2)])
    info.setdefault("ball_bars", []).append({"length": float(np.linalg.norm(c2 - c1))})
    alb = st.albedo()
    return [
        Sphere(c1, r, texture_albedo=alb, name=f"ballbar{i}_ball1"),
        Sphere(c2, r, texture_albedo=alb, name=f"ballbar{i}_ball2"),
        Cylinder(c1, c2 - c1, float(np.linalg.norm(c2 - c1)), rod_r, 0.6, f"ballbar{i}_rod"),
        Cylinder(
            mid, (0.0, -1.0, 0.0), 0.6 * st.field, rng.uniform(5.0, 10.0), 0.5, f"ballbar{i}_stem"
        ),
    ]


def _rod(st: _Stage, i: int, info: dict) -> list[Primitive]:
    rng = st.rng
    r = rng.uniform(2.5, 20.0)
    length = rng.uniform(0.2, 0.5) * st.field
    tilt = rng.uniform(-0.7, 0.7)
    axis = np.array([np.sin(tilt), np.cos(tilt), rng.uniform(-0.3, 0.3)])
    axis /= np.linalg.norm(axis)
    if rng.uniform() < 0.3:  # lying rather than standing
        axis = axis[[1, 0, 2]]
    reach = r + 0.5 * length * abs(axis[2])
    mid = st.point(st.near + reach, st.wall_d - reach - 10.0)
    base = mid - 0.5 * length * axis
    return [Cylinder(base, axis, length, r, st.albedo(), f"rod{i}")]


def _box(st: _Stage, i: int, info: dict) -> list[Primitive]:
    rng = st.rng
    half = rng.uniform(20.0, 100.0, 3)
    reach = float(np.linalg.norm(half))
    c = st.point(st.near + reach, st.wall_d - reach - 5.0)
    yaw = rng.uniform(0.35, 1.05) * rng.choice([-1.0, 1.0])  # side faces towards the camera
    pitch = rng.uniform(-0.35, 0.35)
    R = _rotation(np.array([1.0, 0, 0]), pitch) @ _rotation(np.array([0, 1.0, 0]), yaw)
    return [Box(c, half, R.T, st.albedo(), f"box{i}")]


def _staircase(st: _Stage, i: int, info: dict) -> list[Primitive]:
    """Steps from the wall towards the rig, tilted back so the treads face the camera."""
    rng = st.rng
    n = int(rng.integers(3, 6))
    room = 0.9 * (st.wall_d - st.near)  # depth the steps may take up
    rise = min(rng.uniform(20.0, 50.0), 0.3 * room / n)
    tread = min(rng.uniform(20.0, 60.0), (room - 0.6 * n * rise) / n)
    width = rng.uniform(0.15, 0.35) * st.field
    top = st.point(st.wall_d - 5.0, st.wall_d - 1.0, inner=0.5)
    tilt = rng.uniform(0.2, 0.6)
    R = _rotation(np.array([1.0, 0, 0]), -tilt)
    alb = st.albedo()
    prims: list[Primitive] = []
    for k in range(n):
        depth = tread * (k + 1)  # the lower steps reach further towards the rig
        local = np.array([0.0, -(k + 0.5) * rise, 0.5 * depth])
        c = top + R @ local
        half = (0.5 * width, 0.5 * rise, 0.5 * depth)
        prims.append(Box(c, half, R.T, alb, f"stairs{i}_step{k}"))
    return prims


def _freeform(st: _Stage, i: int, info: dict) -> list[Primitive]:
    rng = st.rng
    nb = int(rng.integers(2, 5))
    sig = rng.uniform(20.0, 70.0, (nb, 2))
    ab = rng.uniform(-1.0, 1.0, (nb, 2)) * sig
    room = st.wall_d - st.near
    amp = rng.uniform(30.0, 120.0, nb)
    amp *= min(1.0, 0.6 * room / amp.sum())  # overlapping bumps add up
    bumps = np.column_stack([ab, sig, amp])
    half_a = float(np.max(np.abs(ab[:, 0]) + 2.0 * sig[:, 0]))
    half_b = float(np.max(np.abs(ab[:, 1]) + 2.0 * sig[:, 1]))
    normal = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 1.0])
    lean = float(np.hypot(normal[0] * half_a, normal[1] * half_b))  # the tilted plate's reach
    gap = rng.uniform(0.0, 0.5) * max(0.0, room - amp.sum() - lean)
    base = st.point(st.wall_d - gap - 1.0, st.wall_d - gap, inner=0.5)
    return [HeightField(base, normal, bumps, half_a, half_b, st.albedo(), name=f"freeform{i}")]


def _plate(st: _Stage, i: int, info: dict) -> list[Primitive]:
    """A tilted plate with a printed texture (albedo 0.05-0.9)."""
    rng = st.rng
    ha, hb = rng.uniform(40.0, 120.0, 2)
    normal = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.4, 0.4), 1.0])
    reach = float(np.hypot(ha, hb)) * np.linalg.norm(normal[:2]) / np.linalg.norm(normal)
    c = st.point(st.near + reach, st.wall_d - reach)
    outline = np.array([[-ha, -hb], [ha, -hb], [ha, hb], [-ha, hb]])
    tex = noise_texture(rng, rng.uniform(3.0, 10.0), 0.05, 0.9)
    return [Polygon(c, normal, outline=outline, texture=tex, name=f"plate{i}")]


_KINDS: dict[str, Callable[[_Stage, int, dict], list[Primitive]]] = {
    "sphere": _sphere,
    "ballbar": _ball_bar,
    "rod": _rod,
    "box": _box,
    "staircase": _staircase,
    "freeform": _freeform,
    "plate": _plate,
}


def random_scene(
    rng: np.random.Generator, spec: RigSpec, *, name: str = "zoo", objects: int | None = None
) -> Scene:
    """Objects drawn at random in front of a backdrop wall, in the rig's view and slit fan.

    The wall stands 1.08-1.18 times the standoff from the rig; objects lie between 0.85 times
    the standoff and the wall: spheres of 30-150 mm, a ball bar (two 30-60 mm balls, a rod and
    a stem), rods and cylinders of 5-40 mm, boxes turned to show side faces, a staircase tilted
    back, a free-form body, a textured plate. One surface in five is dark (albedo 0.05-0.15).
    Objects may occlude each other and cast shadows on the wall.

    Parameters
    ----------
    rng : the only source of randomness
    spec : the rig the scene is for (its view, fan and standoff)
    name : the scene's name (the scan image's name)
    objects : how many objects; default 3-6 drawn

    Returns
    -------
    Scene with ``backdrop = ("wall",)``; ``info`` lists the spheres and ball bars
    """
    standoff = _standoff(spec)
    st = _Stage(rng, spec, standoff * rng.uniform(1.08, 1.18))
    n = int(rng.integers(3, 7)) if objects is None else int(objects)
    kinds = rng.choice(list(_KINDS), size=n)
    info: dict = {"kinds": [str(k) for k in kinds]}
    prims: list[Primitive] = []
    for i, kind in enumerate(kinds):
        prims += _KINDS[str(kind)](st, i, info)
    prims.append(backdrop_wall(st.wall_z, float(rng.uniform(0.3, 0.7))))
    return Scene(name, prims, info, backdrop=("wall",))


def simulate_zoo_capture(
    outdir: str | Path,
    seed: int,
    *,
    scenes: int = 2,
    max_size: tuple[int, int] = (1920, 1080),
    progress: Progress | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a capture folder of a zoo rig and zoo scenes drawn from ``seed``.

    The rig and scenes are drawn at full size; the camera is then scaled down (stripe and dot
    pixel widths kept, :meth:`RigSpec.scaled`) to fit ``max_size``. The folder holds what
    :func:`multislit.sim.simulate_capture` writes, with the target scaled to the rig
    (:func:`zoo_target`) and scans ``zoo0``, ``zoo1``, ...

    Parameters
    ----------
    outdir : folder to create (must be empty or absent unless ``overwrite``)
    seed : draws the rig, the scenes and the images' noise
    scenes : how many scenes (one scan each)
    max_size : (W, H) px, the largest camera image; default full HD
    progress : called as ``progress(i, n, name)`` before each image
    overwrite : allow writing into a folder that is not empty

    Returns
    -------
    The capture folder's path.
    """
    if scenes < 1:
        raise MultislitError(f"scenes must be >= 1, got {scenes}")
    rng = np.random.default_rng(seed)
    spec = random_rig(rng)
    scene_objs = [random_scene(rng, spec, name=f"zoo{j}") for j in range(scenes)]
    w, h = spec.camera.image_size
    factor = min(1.0, max_size[0] / w, max_size[1] / h)
    if factor < 1.0:
        spec = spec.scaled(factor)
    return simulate_capture(
        outdir,
        scene_objs,
        spec,
        seed=seed,
        progress=progress,
        overwrite=overwrite,
        target=zoo_target(spec),
    )
