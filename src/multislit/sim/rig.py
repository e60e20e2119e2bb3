"""The simulated rig: a description users edit (``RigSpec``, JSON) and the truth models built from it.

Defaults follow the paper: a 1280x1024 camera, 450 mm camera-to-projector baseline, both aimed at
a point about 0.9 m away, 25 slits from a diffraction grating (sin(theta_m) = m lambda / pitch),
and a random-dot projector mounted a few tens of mm above the slit projector (along the slits).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from multislit.errors import MultislitError
from multislit.geometry import PinholeCamera, look_at, rvec_from_rotation
from multislit.geometry.dots import DotProjector as GeometricDotProjector
from multislit.geometry.dots import dot_frame

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CameraSpec:
    image_size: tuple[int, int] = (1280, 1024)
    focal_px: float = 1800.0  # ~8.6 mm lens on 4.8 um pixels (Basler acA1300-60)
    principal_offset_px: tuple[float, float] = (6.0, -4.0)  # principal point minus image centre
    dist: tuple[float, float, float, float] = (-0.08, 0.05, 0.0004, -0.0003)  # k1 k2 p1 p2
    position: tuple[float, float, float] = (-225.0, 0.0, 1000.0)  # mm, world
    look_at: tuple[float, float, float] = (0.0, 0.0, 100.0)


@dataclass(frozen=True)
class SlitProjectorSpec:
    num_slits: int = 25
    wavelength_nm: float = 650.0
    pitch_um: float = 34.0  # grating period: orders m spaced by ~lambda/pitch rad
    stripe_sigma_mrad: float = 0.8  # Gaussian sheet profile across the slit
    fan_half_deg: float = 22.0  # half opening of each sheet along the slit
    power: float = 0.85  # peak radiance on a white surface at 900 mm, in full-scale units
    position: tuple[float, float, float] = (225.0, 0.0, 1000.0)
    look_at: tuple[float, float, float] = (0.0, 0.0, 100.0)


@dataclass(frozen=True)
class DotProjectorSpec:
    offset: tuple[float, float, float] = (0.0, -40.0, 0.0)  # mm, slit-projector frame (y down)
    num_dots: int = 12000
    pattern: str = "bands"  # "bands" (dots along the slits, paper Fig. 8) or "uniform"
    band_halfwidth: float = 0.42  # half width of a band, as a fraction of the slit spacing
    dot_sigma_mrad: float = 0.45
    power: float = 0.7
    seed: int = 20160101  # the pattern is a property of the diffraction plate: fixed


@dataclass(frozen=True)
class SensorSpec:
    full_well_e: float = 10000.0  # electrons at full scale
    read_noise_e: float = 8.0
    bit_depth: int = 8
    blur_sigma_px: float = 0.6  # optical blur (Gaussian PSF)
    ambient: float = 0.10  # ambient radiance on a white surface, full-scale units
    speckle_contrast: float = 0.12
    speckle_grain_px: float = 0.8
    supersample: int = 3  # n x n samples in pixels at depth/object edges
    markers_exposure: float = 6.0  # the lasers-off markers image is exposed this much longer
    noise: bool = True


@dataclass(frozen=True)
class RigSpec:
    """Everything the simulator needs to know about a rig. Units mm, px, mrad as named."""

    camera: CameraSpec = field(default_factory=CameraSpec)
    slits: SlitProjectorSpec = field(default_factory=SlitProjectorSpec)
    dots: DotProjectorSpec = field(default_factory=DotProjectorSpec)
    sensor: SensorSpec = field(default_factory=SensorSpec)
    reference_distances: tuple[float, ...] = (780.0, 900.0, 1020.0)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RigSpec:
        if not isinstance(d, dict):
            raise MultislitError("rig description must be a JSON object")
        parts: dict[str, Any] = {}
        sub = {
            "camera": CameraSpec,
            "slits": SlitProjectorSpec,
            "dots": DotProjectorSpec,
            "sensor": SensorSpec,
        }
        unknown = set(d) - set(sub) - {"reference_distances"}
        if unknown:
            raise MultislitError(
                f"rig description: unknown section(s) {sorted(unknown)}; known: {sorted(sub)}"
            )
        for key, klass in sub.items():
            if key in d:
                vals = d[key]
                names = {f.name for f in fields(klass)}
                bad = set(vals) - names
                if bad:
                    raise MultislitError(
                        f"rig description [{key}]: unknown key(s) {sorted(bad)}; known: {sorted(names)}"
                    )
                conv = {k: tuple(v) if isinstance(v, list) else v for k, v in vals.items()}
                parts[key] = klass(**conv)
        if "reference_distances" in d:
            parts["reference_distances"] = tuple(float(x) for x in d["reference_distances"])
        spec = cls(**parts)
        spec.validate()
        return spec

    @classmethod
    def from_json(cls, s: str) -> RigSpec:
        try:
            return cls.from_dict(json.loads(s))
        except json.JSONDecodeError as exc:
            raise MultislitError(f"rig description is not valid JSON: {exc}") from None

    @classmethod
    def load(cls, path: str | Path) -> RigSpec:
        p = Path(path)
        if not p.is_file():
            raise MultislitError(f"rig file not found: {p}")
        return cls.from_json(p.read_text())

    def validate(self) -> None:
        w, h = self.camera.image_size
        if w < 32 or h < 32:
            raise MultislitError(f"camera.image_size must be at least 32x32 px, got {w}x{h}")
        if self.slits.num_slits < 1:
            raise MultislitError("slits.num_slits must be >= 1")
        m = (self.slits.num_slits - 1) / 2
        if m * self.slits.wavelength_nm * 1e-3 / self.slits.pitch_um >= 0.9:
            raise MultislitError(
                "slits: the outer diffraction orders exceed 64 degrees; increase pitch_um"
            )
        if self.dots.pattern not in ("bands", "uniform"):
            raise MultislitError(
                f"dots.pattern must be 'bands' or 'uniform', got {self.dots.pattern!r}"
            )
        if len(self.reference_distances) < 2:
            raise MultislitError("reference_distances needs >= 2 board distances")
        if self.sensor.bit_depth not in (8, 16):
            raise MultislitError("sensor.bit_depth must be 8 or 16")

    def scaled(self, factor: float) -> RigSpec:
        """The same rig with a camera of ``factor`` x the resolution (stripe and dot pixel widths kept).

        Used for fast tests: ``RigSpec().scaled(0.5)`` renders 640x512 images whose stripes and dots
        are as many pixels wide as the full-size rig's.
        """
        if not (isinstance(factor, int | float) and factor > 0):
            raise MultislitError(
                f"scale factor must be a positive number (0.5: half size), got {factor!r}"
            )
        cam = replace(
            self.camera,
            image_size=(
                round(self.camera.image_size[0] * factor),
                round(self.camera.image_size[1] * factor),
            ),
            focal_px=self.camera.focal_px * factor,
            principal_offset_px=(
                self.camera.principal_offset_px[0] * factor,
                self.camera.principal_offset_px[1] * factor,
            ),
        )
        slits = replace(self.slits, stripe_sigma_mrad=self.slits.stripe_sigma_mrad / factor)
        dots = replace(
            self.dots,
            dot_sigma_mrad=self.dots.dot_sigma_mrad / factor,
            num_dots=max(1, round(self.dots.num_dots * factor * factor)),
        )
        return replace(self, camera=cam, slits=slits, dots=dots)


def dense_rig() -> RigSpec:
    """The default rig with a grating of twice the pitch: 49 slits over the same field.

    Pitch 68 um (default 34 um, 25 slits) and a thinner sheet (stripe sigma 0.6 mrad, default
    0.8): about 17 px between stripes at full size. The identification and centre benchmarks'
    second rig, and the tests' 49-slit scenes. Its ``scaled(0.5)`` puts the stripes ~8.6 px
    apart at the same stripe width, as dense as a 98-slit grating at full size.
    """
    base = RigSpec()
    return replace(
        base, slits=replace(base.slits, num_slits=49, pitch_um=68.0, stripe_sigma_mrad=0.6)
    )


# --------------------------------------------------------------------------- truth models
@dataclass(frozen=True, eq=False)
class SlitProjector:
    """True slit projector: sheets through a common axis (the projector's y axis).

    ``angles[k]`` is the angle (rad) of slit k's sheet from the projector's optical axis, in
    its x-z plane; slits are numbered left to right as seen by the camera.
    """

    origin: F64
    R: F64  # world -> projector
    angles: F64
    sigma: float  # rad
    fan_half: float  # rad
    powers: F64

    @property
    def num_slits(self) -> int:
        return len(self.angles)

    def planes(self) -> F64:
        """(N, 4) slit planes in the world frame, unit normals, n.X + d = 0."""
        n_p = np.stack(
            [np.cos(self.angles), np.zeros_like(self.angles), -np.sin(self.angles)], axis=1
        )
        n_w = n_p @ self.R
        return np.concatenate([n_w, -(n_w @ self.origin)[:, None]], axis=1)

    @property
    def axis(self) -> tuple[F64, F64]:
        """The common axis of the sheets: a point (3,) and a unit direction (3,), world frame."""
        return self.origin.copy(), self.R[1].copy()

    def local(self, x: F64) -> tuple[F64, F64, F64]:
        """World points (N, 3) -> (phi, psi, r): angle across the slits, along the slits, range."""
        p = (x - self.origin) @ self.R.T
        phi = np.arctan2(p[:, 0], p[:, 2])
        psi = np.arctan2(p[:, 1], np.hypot(p[:, 0], p[:, 2]))
        return phi, psi, np.linalg.norm(p, axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "origin": self.origin.tolist(),
            "R": self.R.tolist(),
            "angles": self.angles.tolist(),
            "sigma": self.sigma,
            "fan_half": self.fan_half,
            "powers": self.powers.tolist(),
            "planes": self.planes().tolist(),
        }


@dataclass(frozen=True, eq=False)
class DotProjector:
    """True dot projector: fixed unit directions in the world frame from ``origin``."""

    origin: F64
    directions: F64  # (D, 3)
    brightness: F64  # (D,)
    sigma: float  # rad

    def to_dict(self) -> dict[str, Any]:
        return {
            "origin": self.origin.tolist(),
            "num_dots": len(self.directions),
            "sigma": self.sigma,
        }


@dataclass(frozen=True, eq=False)
class SimulatedRig:
    """The truth models built from a :class:`RigSpec`."""

    spec: RigSpec
    camera: PinholeCamera
    projector: SlitProjector
    dots: DotProjector

    @classmethod
    def build(cls, spec: RigSpec | None = None) -> SimulatedRig:
        spec = spec or RigSpec()
        spec.validate()
        c = spec.camera
        Rc = look_at(c.position, c.look_at)
        t = -Rc @ np.asarray(c.position, float)
        w, h = c.image_size
        cam = PinholeCamera(
            fx=c.focal_px,
            fy=c.focal_px,
            cx=(w - 1) / 2 + c.principal_offset_px[0],
            cy=(h - 1) / 2 + c.principal_offset_px[1],
            rvec=tuple(rvec_from_rotation(Rc)),
            tvec=tuple(t),
            dist=c.dist,
            image_size=(w, h),
        )
        s = spec.slits
        Rp = look_at(s.position, s.look_at)
        n = s.num_slits
        orders = np.arange(n) - (n - 1) // 2
        sin_t = orders * s.wavelength_nm * 1e-9 / (s.pitch_um * 1e-6)
        angles = np.arcsin(sin_t)
        # diffraction envelope: outer orders a little weaker
        powers = s.power * (1.0 - 0.25 * (orders / max(1, np.abs(orders).max())) ** 2)
        proj = SlitProjector(
            origin=np.asarray(s.position, float),
            R=Rp,
            angles=angles,
            sigma=s.stripe_sigma_mrad * 1e-3,
            fan_half=np.radians(s.fan_half_deg),
            powers=powers,
        )
        dots = _make_dots(spec, proj)
        return cls(spec, cam, proj, dots)


def _make_dots(spec: RigSpec, proj: SlitProjector) -> DotProjector:
    d = spec.dots
    rng = np.random.default_rng(d.seed)
    origin = proj.origin + np.asarray(d.offset, float) @ proj.R
    n = d.num_dots
    ang = proj.angles
    spacing = np.median(np.diff(ang)) if len(ang) > 1 else 0.02
    if d.pattern == "bands":
        k = rng.integers(0, len(ang), n)
        phi = ang[k] + rng.uniform(-1, 1, n) * d.band_halfwidth * spacing
    else:
        phi = rng.uniform(ang[0] - 0.5 * spacing, ang[-1] + 0.5 * spacing, n)
    psi = rng.uniform(-proj.fan_half, proj.fan_half, n)
    # direction in the (parallel) dot projector frame: angle phi in x-z, elevation psi
    dp = np.stack([np.sin(phi) * np.cos(psi), np.sin(psi), np.cos(phi) * np.cos(psi)], axis=1)
    dw = dp @ proj.R
    bright = rng.uniform(0.55, 1.0, n)
    return DotProjector(origin, dw, bright, d.dot_sigma_mrad * 1e-3)


def true_dot_projector(rig: SimulatedRig) -> GeometricDotProjector:
    """The simulated rig's dot projector as the calibration's model
    (:class:`~multislit.geometry.dots.DotProjector`): the true source and rays, the frame's y along
    the slit projector's axis, and the reference boards' depths along the camera's axis."""
    d = rig.dots.directions
    frame = dot_frame(d, rig.projector.axis[1])
    p = d @ frame.T
    w, h = rig.camera.image_size
    o, ray = rig.camera.rays(np.array([[(w - 1) / 2.0, (h - 1) / 2.0]]))
    depths = []
    for dist in rig.spec.reference_distances:
        z = float(rig.spec.camera.position[2]) - float(dist)  # the board's plane Z = z
        t = (z - o[0, 2]) / ray[0, 2]
        depths.append(float(rig.camera.to_camera(o + t * ray)[0, 2]))
    return GeometricDotProjector(
        rig.dots.origin,
        frame,
        np.arctan2(p[:, 0], p[:, 2]),
        np.arcsin(np.clip(p[:, 1], -1.0, 1.0)),
        reference_depths=np.array(depths),
    )
