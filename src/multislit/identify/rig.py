"""The rig as the dots' geometry sees it: camera, slit planes and dot rays, prepared once.

:class:`RigGeometry` gathers what identification by the dots' geometry needs from a calibrated
rig -- the camera, one plane per slit and the dot projector's rays -- and the derived data it
reads at every frame: the dots ordered for range look-ups, each slit's band of dots, and the
measuring volume (the camera depths a surface may have). It is built once per rig
(:func:`rig_geometry`) and reused for every frame.

Units: mm in the world (target) frame, px in the image, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from multislit.errors import IdentificationError
from multislit.geometry import PinholeCamera
from multislit.geometry.camera import F64
from multislit.geometry.dots import DotProjector

#: The measuring volume's default depths, as fractions of the nearest and the farthest
#: reference board's depth (camera axis): a slit hypothesis putting a piece outside is ruled out.
#: The dot projector's rays were fitted over the boards' depths; the volume reaches a third
#: beyond them (a backdrop behind the objects), not more: every slit a volume admits is one more
#: hypothesis for every stripe piece.
DEFAULT_VOLUME = (0.7, 1.35)


@dataclass(frozen=True, eq=False)
class RigGeometry:
    """A calibrated rig, prepared for identification by the dots' geometry.

    Attributes
    ----------
    camera : PinholeCamera, the calibrated camera (with lens distortion)
    planes : (N, 4) float64, slit planes, unit normal n.X + d = 0 (mm); NaN rows: no plane
    dots : DotProjector, the dot source and one ray per dot
    depth_range : (2,) float64, mm, the camera depths (along its optical axis) a measured
        surface may have: the measuring volume
    half_band : (N,) float64, rad, half the angle between each slit and its neighbours, seen
        from the dot source (the band of dots that lies beside the slit's stripe)
    phi_sign : +1 or -1, the sign of the change of ``phi`` from a slit to the next (slits are
        numbered from left to right in the image)
    """

    camera: PinholeCamera
    planes: F64
    dots: DotProjector
    depth_range: F64
    half_band: F64
    phi_sign: float = 1.0
    _index: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def num_slits(self) -> int:
        return int(len(self.planes))

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(N,) bool, slits with a plane."""
        return np.all(np.isfinite(self.planes), axis=1)

    def with_depth_range(self, depth_range: tuple[float, float]) -> RigGeometry:
        """The same rig with another measuring volume (near, far) mm (camera depths)."""
        return rig_geometry(self.camera, self.planes, self.dots, depth_range)

    def camera_arrays(self) -> tuple[F64, F64, F64, F64]:
        """(fx, fy, cx, cy), R (3, 3) world -> camera, t (3,), dist (5,) k1 k2 p1 p2 k3: the
        camera as the compiled kernels read it."""
        c = self.camera
        d = np.zeros(5)
        d[: len(c.dist)] = c.dist
        return np.array([c.fx, c.fy, c.cx, c.cy]), c.R, c.t, d

    def dot_rays(self) -> tuple[F64, F64, F64, F64]:
        """The dots' rays as the kernels read them (kept with the rig): unit directions (D, 3)
        in the world frame, the cosine and the sine of their angle across the slits (D,) and
        the sine of their angle along them (D,)."""
        if "rays" not in self._index:
            phi, psi = self.dots.phi, self.dots.psi
            cs = np.cos(psi)
            local = np.stack([np.sin(phi) * cs, np.sin(psi), np.cos(phi) * cs], axis=1)
            self._index["rays"] = (
                np.ascontiguousarray(local @ self.dots.frame),
                np.cos(phi),
                np.sin(phi),
                np.sin(psi),
            )
        return self._index["rays"]

    def dot_index(self) -> tuple[NDArray[np.intp], NDArray[np.intp], float, float]:
        """The dots ordered for look-ups by angle (kept with the rig): (order (D,), bin_start
        (B+1,), phi0, bin_width): the dots of bin b (``phi`` in [phi0 + b w, phi0 + (b+1) w))
        are ``order[bin_start[b]:bin_start[b+1]]``, sorted by ``psi``."""
        if "dots" not in self._index:
            phi, psi = self.dots.phi, self.dots.psi
            hb = self.half_band[np.isfinite(self.half_band)]
            w = float(np.median(hb)) if hb.size else 0.01
            phi0 = float(phi.min()) if phi.size else 0.0
            b = np.floor((phi - phi0) / w).astype(np.intp) if phi.size else np.zeros(0, np.intp)
            nb = int(b.max()) + 1 if b.size else 1
            order = np.lexsort((psi, b)).astype(np.intp)
            start = np.searchsorted(b[order], np.arange(nb + 1)).astype(np.intp)
            self._index["dots"] = (order, start, phi0, w)
        return self._index["dots"]


def _half_bands(planes: F64, dots: DotProjector, depth: float) -> tuple[F64, float]:
    """(N,) rad: half the angle between each slit plane and its neighbours as seen from the
    dot source, at ``depth`` mm along the dots' mean ray (NaN for a slit without a plane); and
    the sign of the change of that angle from one slit to the next."""
    x0 = dots.source + dots.frame[2] * depth
    ok = np.all(np.isfinite(planes), axis=1)
    phi = np.full(len(planes), np.nan)
    n, d = planes[ok, :3], planes[ok, 3]
    foot = x0 - (n @ x0 + d)[:, None] * n  # the point of each plane nearest x0
    phi[ok], _, _ = dots.local(foot)
    k = np.flatnonzero(ok)
    out = np.full(len(planes), np.nan)
    sign = 1.0
    if k.size >= 2:
        g = np.gradient(phi[k], k.astype(float))
        out[k] = 0.5 * np.abs(g)
        sign = 1.0 if np.median(g) > 0 else -1.0
    elif k.size == 1:
        out[k] = 0.01
    return out, sign


def rig_geometry(
    camera: PinholeCamera,
    planes: F64,
    dots: DotProjector,
    depth_range: tuple[float, float] | None = None,
) -> RigGeometry:
    """Prepare a calibrated rig for identification by the dots' geometry.

    Parameters
    ----------
    camera : the calibrated PinholeCamera
    planes : (N, 4) float64, the slit planes (NaN rows: slits without a plane)
    dots : the calibrated DotProjector
    depth_range : (near, far) mm, camera depths of the measuring volume; default
        :data:`DEFAULT_VOLUME` times the nearest and farthest depth of the reference boards the
        dot projector was calibrated on

    Raises
    ------
    IdentificationError
        A camera that is not a PinholeCamera, no dots, or no measuring volume.
    """
    if not isinstance(camera, PinholeCamera):
        raise IdentificationError(
            f"identification by the dots' geometry needs a calibrated pinhole camera, got "
            f"{type(camera).__name__}"
        )
    if not isinstance(dots, DotProjector) or dots.num_dots == 0:
        raise IdentificationError(
            "identification by the dots' geometry needs the calibrated dot projector; "
            "recalibrate with the reference images (multislit calibrate)"
        )
    pl = np.asarray(planes, np.float64)
    if depth_range is None:
        boards = dots.reference_depths
        if boards.size == 0:
            raise IdentificationError(
                "no measuring volume: the dot projector has no reference board depths; give "
                "depth_range"
            )
        depth_range = (DEFAULT_VOLUME[0] * boards.min(), DEFAULT_VOLUME[1] * boards.max())
    near, far = (float(x) for x in depth_range)
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        raise IdentificationError(
            f"depth_range must be two depths 0 < near < far (mm), got {depth_range}"
        )
    half_band, sign = _half_bands(pl, dots, 0.5 * (near + far))
    return RigGeometry(camera, pl, dots, np.array([near, far]), half_band, sign)
