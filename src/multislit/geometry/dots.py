"""The dot projector as a geometric model: a point source and one ray per dot.

A random-dot projector (a laser and a diffraction plate) sends each dot along a fixed ray from
one source. :class:`DotProjector` holds the source and the rays; a dot lands where its ray
meets the surface. The rays are kept as two angles in the projector's own frame:

- ``z`` the mean direction of the dots (forward), ``y`` along the slits (the slit planes' common
  axis, made orthogonal to ``z``), ``x = y x z`` across the slits;
- ``phi = atan2(x, z)`` across the slits, ``psi = asin(y)`` along them.

In this frame a surface point's ``phi`` says which slit band lights it and ``psi`` where along
the slit it lies, whatever its range.

Units: mm in the world (target) frame, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import CalibrationError
from multislit.geometry.camera import F64, as_points


def dot_frame(directions: ArrayLike, along: ArrayLike) -> F64:
    """(3, 3) rotation world -> dot frame, rows (x across, y along, z forward).

    Parameters
    ----------
    directions : (D, 3) float64, unit ray directions, world frame (their mean is z)
    along : (3,) float64, the direction along the slits (y, made orthogonal to z)
    """
    d = np.asarray(directions, np.float64)
    z = d.mean(axis=0)
    z /= np.linalg.norm(z)
    y = np.asarray(along, np.float64) - (np.asarray(along, np.float64) @ z) * z
    ny = np.linalg.norm(y)
    if not np.isfinite(ny) or ny < 1e-6:
        raise CalibrationError("the direction along the slits is parallel to the dots' mean ray")
    y /= ny
    return np.stack([np.cross(y, z), y, z])


def angles_of(vectors: F64, frame: F64) -> tuple[F64, F64, F64]:
    """(phi, psi, r) of world vectors (M, 3) from the source: angles in ``frame`` (rad) and
    length (mm)."""
    p = vectors @ frame.T
    r = np.linalg.norm(p, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        psi = np.arcsin(np.clip(p[:, 1] / r, -1.0, 1.0))
    return np.arctan2(p[:, 0], p[:, 2]), psi, r


def directions_of(phi: F64, psi: F64, frame: F64) -> F64:
    """(M, 3) unit world directions of the angles ``phi``, ``psi`` (M,) rad in ``frame``."""
    c = np.cos(psi)
    local = np.stack([np.sin(phi) * c, np.sin(psi), np.cos(phi) * c], axis=1)
    return local @ frame


@dataclass(frozen=True, eq=False)
class DotProjector:
    """A calibrated dot projector: one source, one ray per dot.

    Attributes
    ----------
    source : (3,) float64, mm, world frame, the point all rays start from
    frame : (3, 3) float64, rotation world -> dot frame (rows x across the slits, y along them,
        z forward; :func:`dot_frame`)
    phi, psi : (D,) float64, rad, each dot's ray: across and along the slits in ``frame``
    seen : (D,) int, on how many reference boards each dot was found
    residual_px : (D,) float64, px, RMS distance of each dot's images on the boards from where
        its ray puts them (NaN: seen on one board)
    reference_depths : (R,) float64, mm, the depths (along the camera's optical axis, at the
        image centre) of the reference boards the rays were found on: the depths the model was
        calibrated over
    brightness : (D,) float64, each dot's brightness: its dots' response (the image smoothed by
        the dot's Gaussian less its mean along the stripe) divided by the peak of the stripe
        nearest it, the median over the boards that show it (NaN: unknown)
    spot_sigma_px : px, the sigma of the Gaussian spot the boards' dots were fitted as on their
        sharp response (:func:`~multislit.stripes.dots.fit_dot_spots`), the median over the
        boards: a scan centres its dots with it (NaN: unknown)
    """

    source: F64
    frame: F64
    phi: F64
    psi: F64
    seen: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, int))
    residual_px: F64 = field(default_factory=lambda: np.zeros(0))
    reference_depths: F64 = field(default_factory=lambda: np.zeros(0))
    brightness: F64 = field(default_factory=lambda: np.zeros(0))
    spot_sigma_px: float = float("nan")

    def __post_init__(self) -> None:
        src = np.asarray(self.source, np.float64).reshape(-1)
        fr = np.asarray(self.frame, np.float64)
        phi = np.asarray(self.phi, np.float64).reshape(-1)
        psi = np.asarray(self.psi, np.float64).reshape(-1)
        if src.shape != (3,) or not np.all(np.isfinite(src)):
            raise CalibrationError(f"dot projector: source must be 3 finite numbers, got {src}")
        if fr.shape != (3, 3) or not np.allclose(fr @ fr.T, np.eye(3), atol=1e-6):
            raise CalibrationError("dot projector: frame must be a 3x3 rotation")
        if phi.shape != psi.shape or not (np.all(np.isfinite(phi)) and np.all(np.isfinite(psi))):
            raise CalibrationError("dot projector: phi and psi must be finite and of one length")
        seen = np.asarray(self.seen, int).reshape(-1)
        res = np.asarray(self.residual_px, np.float64).reshape(-1)
        if seen.size == 0:
            seen = np.ones(phi.size, int)
        if res.size == 0:
            res = np.full(phi.size, np.nan)
        if seen.shape != phi.shape or res.shape != phi.shape:
            raise CalibrationError("dot projector: seen and residual_px need one value per dot")
        object.__setattr__(self, "source", src)
        object.__setattr__(self, "frame", fr)
        object.__setattr__(self, "phi", phi)
        object.__setattr__(self, "psi", psi)
        object.__setattr__(self, "seen", seen)
        object.__setattr__(self, "residual_px", res)
        depths = np.asarray(self.reference_depths, np.float64).reshape(-1)
        if not np.all(np.isfinite(depths) & (depths > 0)):
            raise CalibrationError("dot projector: reference_depths must be positive depths (mm)")
        object.__setattr__(self, "reference_depths", depths)
        beta = np.asarray(self.brightness, np.float64).reshape(-1)
        if beta.size == 0:
            beta = np.full(phi.size, np.nan)
        if beta.shape != phi.shape:
            raise CalibrationError("dot projector: brightness needs one value per dot")
        if np.any(np.isfinite(beta) & (beta <= 0)) or np.any(np.isinf(beta)):
            raise CalibrationError("dot projector: brightness must be positive (or unknown)")
        object.__setattr__(self, "brightness", beta)
        sg = float(self.spot_sigma_px)
        if not (math.isnan(sg) or (math.isfinite(sg) and sg > 0)):
            raise CalibrationError("dot projector: spot_sigma_px must be positive (or unknown)")
        object.__setattr__(self, "spot_sigma_px", sg)

    @property
    def num_dots(self) -> int:
        """D, the dots with a ray."""
        return int(self.phi.size)

    @property
    def directions(self) -> F64:
        """(D, 3) float64, unit ray directions, world frame."""
        return directions_of(self.phi, self.psi, self.frame)

    def local(self, points: ArrayLike) -> tuple[F64, F64, F64]:
        """World points (M, 3) mm -> (phi, psi, r): their angles seen from the source (rad) and
        their distance from it (mm)."""
        return angles_of(as_points(points, 3, "points") - self.source, self.frame)

    def points(self, index: ArrayLike, r: ArrayLike) -> F64:
        """(M, 3) float64, mm, world: the points at distance ``r`` (M,) mm along the rays of
        the dots ``index`` (M,)."""
        i = np.asarray(index, np.intp)
        d = directions_of(self.phi[i], self.psi[i], self.frame)
        return self.source + np.asarray(r, np.float64)[:, None] * d

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "point source",
            "source": self.source.tolist(),
            "frame": self.frame.tolist(),
            "num_dots": self.num_dots,
            "phi": np.round(self.phi, 9).tolist(),
            "psi": np.round(self.psi, 9).tolist(),
            "seen": self.seen.tolist(),
            "residual_px": np.round(np.nan_to_num(self.residual_px, nan=-1.0), 4).tolist(),
            "reference_depths": self.reference_depths.tolist(),
            "brightness": np.round(np.nan_to_num(self.brightness, nan=-1.0), 5).tolist(),
            "spot_sigma_px": round(self.spot_sigma_px, 6) if self.spot_sigma_px > 0 else -1.0,
        }

    @classmethod
    def from_dict(cls, d: Any) -> DotProjector:
        """The model of :meth:`to_dict`; :class:`~multislit.errors.CalibrationError` naming
        what is malformed."""
        if not isinstance(d, dict):
            raise CalibrationError("calibration JSON: dot_projector must be an object")
        missing = [k for k in ("source", "frame", "phi", "psi") if k not in d]
        if missing:
            raise CalibrationError(f"calibration JSON: dot_projector has no {', '.join(missing)}")
        try:
            res = np.asarray(d.get("residual_px", []), np.float64)
            beta = np.asarray(d.get("brightness", []), np.float64)
            sg = float(d.get("spot_sigma_px", -1.0))
            return cls(
                source=np.asarray(d["source"], np.float64),
                frame=np.asarray(d["frame"], np.float64),
                phi=np.asarray(d["phi"], np.float64),
                psi=np.asarray(d["psi"], np.float64),
                seen=np.asarray(d.get("seen", []), int),
                residual_px=np.where(res < 0, np.nan, res),
                reference_depths=np.asarray(d.get("reference_depths", []), np.float64),
                brightness=np.where(beta < 0, np.nan, beta),
                spot_sigma_px=sg if sg > 0 else float("nan"),
            )
        except (TypeError, ValueError) as exc:
            if isinstance(exc, CalibrationError):
                raise
            raise CalibrationError(f"calibration JSON: dot_projector is malformed: {exc}") from None
