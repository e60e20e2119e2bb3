"""Peer method for the benchmarks, in the simulator: Gray-code structured light.

Gray codes (a multi-image method)
    :class:`PatternProjector` is a 2-D pinhole projector placed where the slit projector is
    (same origin and rotation) whose image covers the slit fan. :func:`prepare_patterns` casts
    the camera's rays into a scene once (supersampled), finds where each sample lands in the
    projector image and how much light it gets (Lambertian cos, 1/r^2, albedo, shadow test from
    the projector); :func:`render_pattern` then renders any projector image cheaply (no speckle:
    the projector is incoherent; the rig's blur and sensor model). :func:`gray_code_patterns`
    makes the column sequence in OpenCV's ``structured_light.GrayCodePattern`` order (white,
    black, then each bit MSB first followed by its inverse), :func:`decode_gray_code` reads the
    column of each camera pixel from the pattern/inverse pairs, and :func:`triangulate_columns`
    intersects the camera's lines of sight with the projector's column planes.

Units: mm and px; camera pixels (u, v), (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry import PinholeCamera, as_points, intersect_rays_planes
from multislit.sim import Scene, SimulatedRig
from multislit.sim.render import R0, SHADOW_EPS, camera_rays, expose
from multislit.sim.rig import SensorSpec

F64 = NDArray[np.float64]

__all__ = [
    "GrayDecode",
    "PatternGeometry",
    "PatternProjector",
    "decode_gray_code",
    "gray_code_patterns",
    "n_gray_bits",
    "prepare_patterns",
    "render_pattern",
    "render_patterns",
    "triangulate_columns",
]


# --------------------------------------------------------------------------- projector
@dataclass(frozen=True, eq=False)
class PatternProjector:
    """A pinhole projector of 2-D images (square pixels, no distortion).

    Parameters
    ----------
    origin : (3,) float64, mm, world: the centre of projection
    R : (3, 3) float64, world -> projector rotation (x right, y down, z forward)
    f : float, px, focal length
    size : (W, H) int, px, projector resolution
    power : float
        Radiance of a white pixel on a white (albedo 1) surface facing it at 900 mm, in the
        camera's full-scale units.
    black_level : float
        Fraction of ``power`` a black pixel still emits (finite contrast).
    """

    origin: F64
    R: F64
    f: float
    size: tuple[int, int] = (1024, 768)
    power: float = 0.85
    black_level: float = 0.005

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", np.asarray(self.origin, float).reshape(3))
        object.__setattr__(self, "R", np.asarray(self.R, float).reshape(3, 3))
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))
        if not (self.f > 0 and self.size[0] >= 2 and self.size[1] >= 2):
            raise MultislitError(f"bad projector: f={self.f}, size={self.size}")
        if not (0 <= self.black_level < 1 and self.power >= 0):
            raise MultislitError("projector power must be >= 0 and black_level in [0, 1)")

    @classmethod
    def from_rig(
        cls,
        rig: SimulatedRig,
        size: tuple[int, int] = (1024, 768),
        power: float | None = None,
        black_level: float = 0.005,
    ) -> PatternProjector:
        """The projector at the slit projector's place, its image covering the slit fan.

        The focal length is the largest with which the image still spans the slits' angles
        (plus half a spacing) across and the sheets' fan (``fan_half``) along them.
        ``power`` defaults to the slit projector's.
        """
        p = rig.projector
        ang = np.asarray(p.angles)
        spacing = float(np.median(np.diff(ang))) if len(ang) > 1 else 0.02
        half_x = float(np.abs(ang).max()) + 0.5 * spacing
        half_y = float(p.fan_half)
        w, h = int(size[0]), int(size[1])
        f = min(0.5 * w / np.tan(half_x), 0.5 * h / np.tan(half_y))
        pw = rig.spec.slits.power if power is None else float(power)
        return cls(p.origin.copy(), p.R.copy(), float(f), (w, h), pw, black_level)

    @property
    def cx(self) -> float:
        return (self.size[0] - 1) / 2

    @property
    def cy(self) -> float:
        return (self.size[1] - 1) / 2

    def project(self, points: ArrayLike) -> F64:
        """World points (N, 3) mm -> projector pixels (N, 2) px (NaN at or behind it)."""
        q = (as_points(points, 3, "points") - self.origin) @ self.R.T
        z = q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = self.f * q[:, :2] / z[:, None] + np.array([self.cx, self.cy])
        uv[~(z > 1e-9)] = np.nan
        return uv

    def column_planes(self, columns: ArrayLike) -> F64:
        """Planes (N, 4), unit normals, world, of projector columns (continuous, px).

        The plane of column ``u`` holds the projector's centre and its pixels with that u.
        """
        x = (np.asarray(columns, float).reshape(-1) - self.cx) / self.f
        n_p = np.stack([np.ones_like(x), np.zeros_like(x), -x], axis=1)
        n_p /= np.linalg.norm(n_p, axis=1, keepdims=True)
        n_w = n_p @ self.R
        return np.concatenate([n_w, -(n_w @ self.origin)[:, None]], axis=1)


# --------------------------------------------------------------------------- rendering
@dataclass(eq=False)
class PatternGeometry:
    """What :func:`render_pattern` needs of a scene: computed once, reused for every pattern.

    Attributes
    ----------
    shape : (H, W) of the camera image
    supersample : int, s x s samples per camera pixel
    proj_uv : (H*W*s*s, 2) float32, px: projector pixel of each sample (NaN: none)
    gain : (H*W*s*s,) float32: radiance of the sample under a white pixel (0 in the projector's
        shadow or outside its image)
    ambient : (H, W) float32: ambient radiance (pixel mean)
    xyz : (H, W, 3) float32, mm, world: the true point at each pixel centre (NaN: nothing)
    sensor : the rig's sensor
    projector : the projector
    """

    shape: tuple[int, int]
    supersample: int
    proj_uv: NDArray[np.float32]
    gain: NDArray[np.float32]
    ambient: NDArray[np.float32]
    xyz: NDArray[np.float32]
    sensor: SensorSpec
    projector: PatternProjector


def prepare_patterns(
    rig: SimulatedRig,
    scene: Scene,
    projector: PatternProjector | None = None,
    supersample: int = 2,
    ambient: bool = True,
) -> PatternGeometry:
    """Cast the camera's rays into ``scene`` and light the hits from ``projector``.

    Parameters
    ----------
    rig : the camera and sensor (and, by default, the projector's place)
    scene : what is in front of the rig
    projector : default ``PatternProjector.from_rig(rig)``
    supersample : s, s x s samples per pixel (a camera pixel integrates several projector
        pixels where these are smaller)
    ambient : add the rig's ambient light

    Returns
    -------
    PatternGeometry
    """
    if supersample < 1:
        raise MultislitError(f"supersample must be >= 1, got {supersample}")
    proj = PatternProjector.from_rig(rig) if projector is None else projector
    cam = rig.camera
    w, h = cam.image_size
    o, d = camera_rays(rig)
    xyz = scene.cast(o, d).point.reshape(h, w, 3).astype(np.float32)
    s = int(supersample)
    if s == 1:
        so, sd = o, d
    else:
        offs = (np.arange(s) + 0.5) / s - 0.5
        ou, ov = np.meshgrid(offs, offs)
        uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        sub = np.stack(
            [
                (uu.ravel()[:, None] + ou.ravel()[None, :]).ravel(),
                (vv.ravel()[:, None] + ov.ravel()[None, :]).ravel(),
            ],
            axis=1,
        )
        so, sd = cam.rays(sub)
    hit = scene.cast(so, sd)
    ok = np.isfinite(hit.t)
    n_s = len(so)
    amb = np.zeros(n_s)
    if ambient:
        cos_v = np.clip(-np.einsum("ij,ij->i", hit.normal[ok], sd[ok]), 0, None)
        amb[ok] = rig.spec.sensor.ambient * hit.albedo[ok] * (0.5 + 0.5 * cos_v)
    gain = np.zeros(n_s)
    uv = np.full((n_s, 2), np.nan)
    idx = np.flatnonzero(ok)
    if idx.size:
        x = hit.point[idx]
        v = x - proj.origin
        r = np.linalg.norm(v, axis=1)
        dirs = v / r[:, None]
        cos_i = np.clip(-np.einsum("ij,ij->i", hit.normal[idx], dirs), 0, None)
        puv = proj.project(x)
        pw, ph = proj.size
        inside = (
            np.isfinite(puv).all(axis=1)
            & (puv[:, 0] >= -0.5)
            & (puv[:, 0] < pw - 0.5)
            & (puv[:, 1] >= -0.5)
            & (puv[:, 1] < ph - 0.5)
            & (cos_i > 0)
        )
        t, _ = scene.first_hit_t(np.broadcast_to(proj.origin, dirs.shape).copy(), dirs)
        inside &= ~(t < r - SHADOW_EPS)
        g = proj.power * hit.albedo[idx] * cos_i * (R0 / r) ** 2
        gain[idx[inside]] = g[inside]
        uv[idx[inside]] = puv[inside]
    amb_px = amb.reshape(h * w, s * s).mean(axis=1).reshape(h, w)
    return PatternGeometry(
        (h, w),
        s,
        uv.astype(np.float32),
        gain.astype(np.float32),
        amb_px.astype(np.float32),
        xyz,
        rig.spec.sensor,
        proj,
    )


def render_pattern(
    geom: PatternGeometry, pattern: ArrayLike, rng: np.random.Generator
) -> NDArray[np.integer]:
    """Camera image of the scene lit by one projector image.

    Parameters
    ----------
    geom : from :func:`prepare_patterns`
    pattern : (H_p, W_p) projector image, uint8 (0-255) or float in [0, 1], nearest pixel
    rng : the noise source

    Returns
    -------
    image : (H, W) uint8 or uint16, as the rig's sensor gives it
    """
    proj = geom.projector
    pat = np.asarray(pattern)
    if pat.shape != (proj.size[1], proj.size[0]):
        raise MultislitError(
            f"pattern must be (H, W) = {(proj.size[1], proj.size[0])}, got {pat.shape}"
        )
    val = pat.astype(np.float32) / (255.0 if pat.dtype == np.uint8 else 1.0)
    val = proj.black_level + (1.0 - proj.black_level) * np.clip(val, 0, 1)
    ok = np.isfinite(geom.proj_uv[:, 0])
    iu = np.zeros(len(ok), np.int64)
    iv = np.zeros(len(ok), np.int64)
    iu[ok] = np.floor(geom.proj_uv[ok, 0] + 0.5).astype(np.int64)
    iv[ok] = np.floor(geom.proj_uv[ok, 1] + 0.5).astype(np.int64)
    np.clip(iu, 0, proj.size[0] - 1, out=iu)
    np.clip(iv, 0, proj.size[1] - 1, out=iv)
    light = np.where(ok, geom.gain * val[iv, iu], 0.0).astype(np.float32)
    h, w = geom.shape
    s2 = geom.supersample**2
    radiance = geom.ambient + light.reshape(h * w, s2).mean(axis=1).reshape(h, w)
    radiance = cv2.GaussianBlur(radiance, (0, 0), geom.sensor.blur_sigma_px)
    return expose(radiance, geom.sensor, rng)


def render_patterns(
    geom: PatternGeometry, patterns: ArrayLike, rng: np.random.Generator
) -> NDArray[np.integer]:
    """:func:`render_pattern` for each of ``patterns`` (K, H_p, W_p) -> images (K, H, W)."""
    return np.stack([render_pattern(geom, p, rng) for p in patterns])


# --------------------------------------------------------------------------- Gray codes
def n_gray_bits(width: int) -> int:
    """Bits needed to code ``width`` columns: ceil(log2(width))."""
    if width < 2:
        raise MultislitError(f"width must be >= 2, got {width}")
    return int(np.ceil(np.log2(width)))


def gray_code_patterns(width: int, height: int) -> NDArray[np.uint8]:
    """Column Gray-code sequence for a ``width`` x ``height`` projector.

    The order is OpenCV's ``structured_light.GrayCodePattern`` column images, preceded by its
    shadow-mask images: white, black, then for each bit (most significant first) the bit
    pattern and its inverse; ``2 + 2 * n_gray_bits(width)`` images in all. Column c shows bit k
    of ``c ^ (c >> 1)``.

    Returns
    -------
    patterns : (2 + 2 n, height, width) uint8, 0 or 255
    """
    n = n_gray_bits(width)
    c = np.arange(width)
    g = c ^ (c >> 1)
    rows = [np.ones(width, bool), np.zeros(width, bool)]
    for k in range(n):
        b = ((g >> (n - 1 - k)) & 1).astype(bool)
        rows += [b, ~b]
    out = np.stack(rows).astype(np.uint8) * 255
    return np.ascontiguousarray(np.broadcast_to(out[:, None, :], (len(rows), height, width)))


@dataclass(frozen=True, eq=False)
class GrayDecode:
    """Decoded columns.

    columns : (H, W) float64, projector column (px, pixel-centre convention) or NaN
    valid : (H, W) bool
    contrast : (H, W) float64, white minus black, DN
    """

    columns: F64
    valid: NDArray[np.bool_]
    contrast: F64


def decode_gray_code(
    images: ArrayLike,
    width: int,
    min_contrast: float = 0.03,
    min_bit_contrast: float = 0.0,
    full_scale: float | None = None,
) -> GrayDecode:
    """Projector column of each camera pixel from a :func:`gray_code_patterns` capture.

    Parameters
    ----------
    images : (2 + 2 n, H, W) camera images in :func:`gray_code_patterns` order
    width : projector width the patterns were made for (n = ``n_gray_bits(width)``)
    min_contrast : pixels whose white minus black is below this fraction of full scale are
        invalid (shadow, dark or unlit)
    min_bit_contrast : pixels where any pattern/inverse pair differs by less than this fraction
        of full scale are invalid (0: decide every bit by the sign alone)
    full_scale : the sensor's full scale, DN; default from the images' dtype (255 for uint8)

    Returns
    -------
    GrayDecode
    """
    im = np.asarray(images)
    n = n_gray_bits(width)
    if im.ndim != 3 or im.shape[0] != 2 + 2 * n:
        raise MeasurementError(
            f"images must be (2 + 2 * {n}, H, W) for a {width}-column projector, got {im.shape}"
        )
    if full_scale is None:
        full_scale = float(np.iinfo(im.dtype).max) if im.dtype.kind in "ui" else 1.0
    f = im.astype(np.float32)
    contrast = f[0] - f[1]
    valid = contrast > min_contrast * full_scale
    binary = np.zeros(im.shape[1:], np.int64)
    bit = np.zeros(im.shape[1:], bool)
    for k in range(n):
        diff = f[2 + 2 * k] - f[3 + 2 * k]
        if min_bit_contrast > 0:
            valid &= np.abs(diff) >= min_bit_contrast * full_scale
        bit ^= diff > 0  # Gray -> binary: running XOR from the most significant bit
        binary = (binary << 1) | bit
    valid &= binary < width
    cols = np.where(valid, binary.astype(float), np.nan)
    return GrayDecode(cols, valid, contrast.astype(float))


def triangulate_columns(
    camera: PinholeCamera, projector: PatternProjector, columns: ArrayLike
) -> F64:
    """3D points where camera pixels' lines of sight meet their projector column planes.

    Parameters
    ----------
    camera : the camera the columns image is in
    projector : the projector
    columns : (H, W) float, projector column per camera pixel (NaN: none)

    Returns
    -------
    xyz : (H, W, 3) float64, mm, world (NaN where no column or no intersection)
    """
    c = np.asarray(columns, float)
    h, w = c.shape
    out = np.full((h * w, 3), np.nan)
    idx = np.flatnonzero(np.isfinite(c.ravel()))
    if idx.size:
        uv = np.stack([idx % w, idx // w], axis=1).astype(float)
        o, d = camera.rays(uv)
        out[idx], _ = intersect_rays_planes(
            o, d, projector.column_planes(c.ravel()[idx]), min_cos=1e-3
        )
    return out.reshape(h, w, 3)
