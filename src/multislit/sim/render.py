"""Physically based rendering of one camera image of a scene under the rig's lasers.

Per pixel: a camera ray (with the lens distortion inverted) is cast into the scene; the hit point
gets ambient light (Lambertian, albedo), the slit sheets' light (Gaussian profile across each
sheet, fan along it, 1/r^2, cos of incidence, occlusion: a point the projector cannot see gets
none) and the random dots (cast from the dot projector, visible only where the camera sees the
lit point). Pixels at depth or object edges are supersampled. Laser light carries speckle; the
sensor adds optical blur, shot and read noise, saturation and quantisation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from multislit.sim.primitives import Scene
from multislit.sim.rig import SimulatedRig

F64 = NDArray[np.float64]
R0 = 900.0  # mm: range at which the laser powers are specified
SHADOW_EPS = 0.05  # mm: a hit this much before the lit point counts as an occluder


@dataclass
class Rendered:
    """A rendered image and its ground truth (all at pixel centres).

    image : (H, W) uint8 or uint16
    xyz : (H, W, 3) float32, mm, world: the surface point seen by each pixel (NaN: nothing)
    slit : (H, W) int16: the slit whose sheet lights the pixel's point (within 2 sigma), -1 none
    lit : (H, W) bool: the slit projector sees the point (not in its shadow)
    radiance : (H, W) float32: noise-free radiance before the sensor (full scale = 1)
    obj : (H, W) int16: index of the scene primitive seen by each pixel (-1: nothing), or None
    stripe_snr : (H, W) float32: the slits' light at the pixel over the pixel's noise
        (:func:`stripe_snr`; 0 where no slit lights it), or None
    """

    image: NDArray
    xyz: NDArray[np.float32]
    slit: NDArray[np.int16]
    lit: NDArray[np.bool_]
    radiance: NDArray[np.float32]
    obj: NDArray[np.int16] | None = None
    stripe_snr: NDArray[np.float32] | None = None


def _pixel_grid(w: int, h: int) -> F64:
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    return np.stack([u.ravel(), v.ravel()], axis=1)


_RAY_CACHE: dict[tuple, tuple[F64, F64]] = {}


def camera_rays(rig: SimulatedRig) -> tuple[F64, F64]:
    """Rays through every pixel centre, (H*W, 3) origins and unit directions (cached per camera)."""
    cam = rig.camera
    key = (cam.fx, cam.fy, cam.cx, cam.cy, cam.rvec, cam.tvec, cam.dist, cam.image_size)
    if key not in _RAY_CACHE:
        if len(_RAY_CACHE) >= 4:
            _RAY_CACHE.pop(next(iter(_RAY_CACHE)))
        w, h = cam.image_size
        _RAY_CACHE[key] = cam.rays(_pixel_grid(w, h))
    return _RAY_CACHE[key]


def _slit_light(
    rig: SimulatedRig, scene: Scene, x: F64, n: F64, albedo: F64
) -> tuple[F64, NDArray, NDArray]:
    """Slit radiance at surface points; also the nearest slit index and whether lit (unshadowed)."""
    p = rig.projector
    phi, psi, r = p.local(x)
    ang = p.angles
    k = (
        np.clip(np.searchsorted(ang, phi), 1, len(ang) - 1)
        if len(ang) > 1
        else np.zeros(len(x), int)
    )
    if len(ang) > 1:
        left = np.abs(phi - ang[k - 1]) < np.abs(phi - ang[k])
        k = np.where(left, k - 1, k)
    dphi = phi - ang[k]
    prof = np.exp(-0.5 * (dphi / p.sigma) ** 2)
    # also the second-nearest sheet can contribute where sheets are close
    fan = 1.0 / (1.0 + np.exp((np.abs(psi) - p.fan_half) / 0.01))
    to_src = (p.origin - x) / r[:, None]
    cos_i = np.einsum("ij,ij->i", n, to_src)
    e = p.powers[k] * prof * fan * np.clip(cos_i, 0, None) * (R0 / r) ** 2 * albedo
    e = np.nan_to_num(e)
    lit = np.isfinite(r) & (cos_i > 0)
    need = lit & (e > 1e-4)
    idx = np.flatnonzero(need)
    if idx.size:
        d = -to_src[idx]
        o = np.broadcast_to(p.origin, d.shape)
        t, _ = scene.first_hit_t(np.ascontiguousarray(o), d)
        shadow = t < r[idx] - SHADOW_EPS
        e[idx[shadow]] = 0.0
        lit[idx[shadow]] = False
    return e, np.where(np.abs(dphi) < 2 * p.sigma, k, -1), lit


def _ambient(hit_n: F64, d: F64, albedo: F64, level: float) -> F64:
    # a soft room light: half from a diffuse dome, half from a lamp near the camera
    cos_v = np.clip(-np.einsum("ij,ij->i", hit_n, d), 0, None)
    return np.nan_to_num(level * albedo * (0.5 + 0.5 * cos_v))


def _shade(rig: SimulatedRig, scene: Scene, o: F64, d: F64, lasers: bool, ambient: bool):
    hit = scene.cast(o, d)
    ok = np.isfinite(hit.t)
    rad = np.zeros(len(o))
    slit_e = np.zeros(len(o))
    slit_k = np.full(len(o), -1)
    lit = np.zeros(len(o), bool)
    if ambient:
        rad[ok] = _ambient(hit.normal[ok], d[ok], hit.albedo[ok], rig.spec.sensor.ambient)
    if lasers and np.any(ok):
        e, k, lt = _slit_light(rig, scene, hit.point[ok], hit.normal[ok], hit.albedo[ok])
        slit_e[ok] = e
        slit_k[ok] = np.where(lt, k, -1)
        lit[ok] = lt
    return hit, rad, slit_e, slit_k, lit


def _dots_image(rig: SimulatedRig, scene: Scene, shape: tuple[int, int]) -> F64:
    """Splat the visible random dots as Gaussian spots."""
    h, w = shape
    dp = rig.dots
    o = np.broadcast_to(dp.origin, dp.directions.shape).copy()
    hit = scene.cast(o, dp.directions)
    ok = np.isfinite(hit.t)
    x = hit.point[ok]
    nrm = hit.normal[ok]
    r = hit.t[ok]
    bright = dp.brightness[ok]
    alb = hit.albedo[ok]
    cos_i = np.clip(np.einsum("ij,ij->i", nrm, -dp.directions[ok]), 0, None)
    # visibility from the camera: the camera's first hit along the line of sight is this point
    cam = rig.camera
    c = cam.centre
    v = x - c
    dist = np.linalg.norm(v, axis=1)
    dirs = v / dist[:, None]
    tc, _ = scene.first_hit_t(np.broadcast_to(c, x.shape).copy(), dirs)
    faces_cam = np.einsum("ij,ij->i", nrm, -dirs) > 0
    vis = (tc > dist - 0.1) & faces_cam
    x, r, bright, alb, cos_i, dist = x[vis], r[vis], bright[vis], alb[vis], cos_i[vis], dist[vis]
    uv = cam.project(x)
    amp = rig.spec.dots.power * bright * alb * cos_i * (R0 / r) ** 2
    z = cam.to_camera(x)[:, 2]
    sig = np.maximum(dp.sigma * r * cam.fx / z, 0.3)
    img = np.zeros(h * w)
    rad = 4
    offs = np.arange(-rad, rad + 1)
    good = np.isfinite(uv).all(axis=1)
    uv, amp, sig = uv[good], amp[good], sig[good]
    iu = np.round(uv[:, 0]).astype(int)
    iv = np.round(uv[:, 1]).astype(int)
    du, dv = np.meshgrid(offs, offs)
    pu = iu[:, None] + du.ravel()[None, :]
    pv = iv[:, None] + dv.ravel()[None, :]
    wgt = amp[:, None] * np.exp(
        -0.5 * ((pu - uv[:, 0:1]) ** 2 + (pv - uv[:, 1:2]) ** 2) / sig[:, None] ** 2
    )
    inb = (pu >= 0) & (pu < w) & (pv >= 0) & (pv < h)
    np.add.at(img, (pv[inb] * w + pu[inb]), wgt[inb])
    return img.reshape(h, w)


def _rook_offsets(n: int) -> tuple[F64, F64]:
    """Offsets (n,), (n,) px of n samples in a pixel, on an n-rooks lattice.

    Sample i lies at ((i + 0.5) / n, (p_i + 0.5) / n) - 0.5 with p a permutation spreading
    the samples over the pixel (i * step mod n; for 4 samples the rotated grid 1, 3, 0, 2).
    No two samples share a row or a column, so an edge near a pixel axis sees n + 1 coverage
    levels (a square grid of n samples: sqrt(n) + 1), and the pixels along a straight edge
    (a marker's side) average to its true position.
    """
    i = np.arange(n)
    if n == 4:
        p = np.array([1, 3, 0, 2])
    else:
        step = max(1, round(n * 0.381966))  # near n / golden ratio^2: a well spread lattice
        while math.gcd(step, n) != 1:
            step += 1
        p = (i * step) % n
    return (i + 0.5) / n - 0.5, (p + 0.5) / n - 0.5


def render(
    rig: SimulatedRig,
    scene: Scene,
    rng: np.random.Generator,
    lasers: bool = True,
    ambient: bool = True,
) -> Rendered:
    """Render one camera image of ``scene``.

    Parameters
    ----------
    rig : the truth models (camera, slit projector, dot projector, sensor)
    scene : what is in front of the rig
    rng : the only source of randomness (speckle, noise)
    lasers : slits and dots on (False: the markers image: ambient light only, exposed
        ``sensor.markers_exposure`` times longer)
    ambient : ambient light on
    """
    cam = rig.camera
    w, h = cam.image_size
    o, d = camera_rays(rig)
    hit, rad, slit_e, slit_k, lit = _shade(rig, scene, o, d, lasers, ambient)
    depth = hit.t.reshape(h, w)
    obj = hit.obj.reshape(h, w)

    # supersample pixels at depth or object edges
    ss = rig.spec.sensor.supersample
    if ss > 1:
        # edges: a change of object, a depth jump (> 1 %), or an albedo edge (texture, markers)
        finite_depth = np.where(np.isfinite(depth), depth, 1e9)
        alb = hit.albedo.reshape(h, w)
        edge = np.zeros((h, w), bool)
        for axis in (0, 1):
            dz = np.abs(np.diff(finite_depth, axis=axis)) > 0.01 * np.minimum(
                np.delete(finite_depth, 0, axis=axis), np.delete(finite_depth, -1, axis=axis)
            )
            e = dz | (np.diff(obj, axis=axis) != 0) | (np.abs(np.diff(alb, axis=axis)) > 0.02)
            if axis == 0:
                edge[:-1, :] |= e
                edge[1:, :] |= e
            else:
                edge[:, :-1] |= e
                edge[:, 1:] |= e
        # a thin sliver of another region can hide between two pixel centres: widen the band
        edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        idx = np.flatnonzero(edge.ravel())
        if idx.size:
            ou, ov = _rook_offsets(ss * ss)
            base = np.stack([idx % w, idx // w], axis=1).astype(float)
            sub = (base[:, None, :] + np.stack([ou, ov], axis=1)[None, :, :]).reshape(-1, 2)
            so, sd = cam.rays(sub)
            _, srad, sslit, _, _ = _shade(rig, scene, so, sd, lasers, ambient)
            rad[idx] = srad.reshape(-1, ss * ss).mean(axis=1)
            slit_e[idx] = sslit.reshape(-1, ss * ss).mean(axis=1)

    laser = slit_e.reshape(h, w)
    if lasers:
        laser = laser + _dots_image(rig, scene, (h, w))
    sensor = rig.spec.sensor
    if lasers and sensor.speckle_contrast > 0:
        g = rng.standard_normal((h, w)).astype(np.float32)
        g = cv2.GaussianBlur(g, (0, 0), sensor.speckle_grain_px)
        g /= max(float(g.std()), 1e-9)
        laser = laser * np.clip(1.0 + sensor.speckle_contrast * g, 0, None)
    radiance = rad.reshape(h, w) + laser
    if not lasers:
        radiance = radiance * sensor.markers_exposure
    radiance = cv2.GaussianBlur(radiance.astype(np.float32), (0, 0), sensor.blur_sigma_px)
    image = expose(radiance, sensor, rng)
    snr = None
    if lasers:
        sigma = sensor.blur_sigma_px
        snr = stripe_snr(
            cv2.GaussianBlur(slit_e.reshape(h, w).astype(np.float32), (0, 0), sigma),
            cv2.GaussianBlur(rad.reshape(h, w).astype(np.float32), (0, 0), sigma),
            sensor,
        )
    xyz = hit.point.reshape(h, w, 3).astype(np.float32)
    return Rendered(
        image,
        xyz,
        slit_k.reshape(h, w).astype(np.int16),
        lit.reshape(h, w),
        radiance,
        obj.astype(np.int16),
        snr,
    )


def stripe_snr(slits: NDArray, background: NDArray, sensor) -> NDArray[np.float32]:
    """How far the slits' light stands out of a pixel's noise: the noise-free step the slits
    add to the pixel (DN, less where it saturates) over the pixel's noise (shot noise of all
    its light, read noise and the rounding to DN; the laser's speckle and the dots left out).

    Parameters
    ----------
    slits : (H, W) float32, the slits' radiance at the sensor, blurred as the image is (full
        scale = 1)
    background : (H, W) float32, the rest of the scene's light there (ambient), blurred alike
    sensor : the sensor's model (full well, read noise, bit depth, noise on or off)

    Returns
    -------
    (H, W) float32, the slits' step in noise sigmas (0 where no slit lights the pixel)
    """
    full = float(2**sensor.bit_depth - 1)
    bg = np.clip(background, 0, None)
    level = bg + np.clip(slits, 0, None)
    step = (np.minimum(level, 1.0) - np.minimum(bg, 1.0)) * full
    var = 1.0 / 12.0  # rounding to DN
    if sensor.noise:
        e = np.minimum(level, 1.0) * sensor.full_well_e + sensor.read_noise_e**2
        var = var + e * (full / sensor.full_well_e) ** 2
    return (step / np.sqrt(var)).astype(np.float32)


def expose(radiance: NDArray, sensor, rng: np.random.Generator) -> NDArray:
    """Sensor model: radiance (full scale = 1) -> electrons (shot noise) + read noise -> DN."""
    full = float(2**sensor.bit_depth - 1)
    e = np.clip(radiance, 0, None) * sensor.full_well_e
    if sensor.noise:
        e = rng.poisson(np.minimum(e, 4 * sensor.full_well_e)).astype(np.float32)
        e += rng.normal(0.0, sensor.read_noise_e, e.shape).astype(np.float32)
    dn = np.clip(np.round(e / sensor.full_well_e * full), 0, full)
    return dn.astype(np.uint8 if sensor.bit_depth == 8 else np.uint16)
