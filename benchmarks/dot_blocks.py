"""Peer method for the benchmarks, in the simulator: Kinect-style dot block matching.

Dot block matching (single image, Kinect-style)
    With the dot projector alone, :func:`match_dots` rectifies the camera image and a reference
    image of a flat board at a known distance so that the baseline to the dot projector is the
    x axis, searches each pixel's window along its row by normalised cross-correlation and turns
    the disparity into depth by the reference-plane relation ``1/z = 1/z_ref + d / (f b)``
    (exact for the rectified camera, with z_ref the board's depth at the reference pixel).

Units: mm and px; camera pixels (u, v), (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MeasurementError
from multislit.geometry import PinholeCamera, intersect_rays_planes, rvec_from_rotation
from multislit.sim import SimulatedRig

F64 = NDArray[np.float64]

__all__ = ["DotDepth", "match_dots", "rectified_camera"]


def rectified_camera(rig: SimulatedRig) -> tuple[PinholeCamera, float]:
    """A distortion-free camera at the real one's centre whose x axis points at the dot projector.

    Its rows are the epipolar lines of the dot projector (a point on its x axis). The principal
    point keeps the real camera's optical axis at the image centre.

    Returns
    -------
    camera : PinholeCamera (same size and focal length as the rig's camera, no distortion)
    baseline : float, mm, camera centre to dot projector origin
    """
    cam = rig.camera
    c = cam.centre
    b_vec = rig.dots.origin - c
    baseline = float(np.linalg.norm(b_vec))
    x = b_vec / baseline
    z = cam.R[2] - (cam.R[2] @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w, h = cam.image_size
    f = cam.fx
    a = R @ cam.R[2]  # the real optical axis in the rectified frame
    cx = (w - 1) / 2 - f * a[0] / a[2]
    cy = (h - 1) / 2 - f * a[1] / a[2]
    rect = PinholeCamera(
        fx=f,
        fy=f,
        cx=cx,
        cy=cy,
        rvec=tuple(rvec_from_rotation(R)),
        tvec=tuple(-R @ c),
        image_size=(w, h),
    )
    return rect, baseline


def _rectify_maps(rig: SimulatedRig, rect: PinholeCamera) -> tuple[NDArray, NDArray]:
    w, h = rect.image_size
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    _, d = rect.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
    uv = rig.camera.project(rig.camera.centre + d)
    uv = np.nan_to_num(uv, nan=-1e6).astype(np.float32)
    return uv[:, 0].reshape(h, w), uv[:, 1].reshape(h, w)


@dataclass(frozen=True, eq=False)
class DotDepth:
    """Result of :func:`match_dots`, in the rectified camera's pixels.

    camera : the rectified camera (see :func:`rectified_camera`)
    xyz : (H, W, 3) float64, mm, world (NaN: no match)
    valid : (H, W) bool
    disparity : (H, W) float64, px, u_scene - u_reference (NaN: no match)
    score : (H, W) float64, the best normalised cross-correlation
    """

    camera: PinholeCamera
    xyz: F64
    valid: NDArray[np.bool_]
    disparity: F64
    score: F64


def _check_match_inputs(
    rig: SimulatedRig, img: NDArray, ref: NDArray, window: int, z_range: tuple[float, float]
) -> tuple[float, float]:
    """Validate :func:`match_dots`'s arguments; returns (near, far) in mm."""
    w, h = rig.camera.image_size
    if img.shape != (h, w) or ref.shape != (h, w):
        raise MeasurementError(
            f"image and reference must be {(h, w)}, got {img.shape}, {ref.shape}"
        )
    if window < 3 or window % 2 == 0:
        raise MeasurementError(f"window must be an odd number >= 3, got {window}")
    near, far = float(z_range[0]), float(z_range[1])
    if not (0 < near < far):
        raise MeasurementError(f"z_range must be 0 < near < far, got {z_range}")
    return near, far


def _rectify_pair(
    rig: SimulatedRig, rect: PinholeCamera, img: NDArray, ref: NDArray, window: int
) -> tuple[NDArray, NDArray, NDArray[np.bool_]]:
    """Scene and reference resampled into ``rect``, and where a whole window sees the real image."""
    w, h = rig.camera.image_size
    mx, my = _rectify_maps(rig, rect)
    S = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    Rf = cv2.remap(ref, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = cv2.remap(
        np.ones((h, w), np.float32), mx, my, cv2.INTER_NEAREST, borderValue=0
    ).astype(np.uint8)
    # windows must lie wholly inside the real image (its border would correlate strongly)
    inside = cv2.erode(
        inside, np.ones((window, window), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0
    ).astype(bool)
    return S, Rf, inside


def _reference_depth(rect: PinholeCamera, plane: F64) -> F64:
    """(H, W) depth of the reference plane along each rectified pixel's ray, mm."""
    w, h = rect.image_size
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    o, d = rect.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
    pts, _ = intersect_rays_planes(o, d, plane)
    return ((pts - rect.centre) @ rect.R[2]).reshape(h, w)


def _search_disparity(
    S: NDArray, Rf: NDArray, inside: NDArray[np.bool_], window: int, d_lo: int, d_hi: int
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """ZNCC at every disparity in [d_lo, d_hi]: best score and disparity, its two neighbours' scores
    (NaN where not evaluated) and the scene windows' standard deviation."""
    h, w = S.shape
    ksize = (window, window)

    def box(a: NDArray) -> NDArray:
        return cv2.boxFilter(a, -1, ksize, normalize=True, borderType=cv2.BORDER_CONSTANT)

    mS = box(S)
    vS = np.maximum(box(S * S) - mS * mS, 0)
    sS = np.sqrt(vS)
    best = np.full((h, w), -np.inf, np.float32)
    best_d = np.full((h, w), d_lo - 10, np.int32)
    left = np.full((h, w), np.nan, np.float32)
    right = np.full((h, w), np.nan, np.float32)
    prev = np.full((h, w), np.nan, np.float32)
    for dd in range(d_lo, d_hi + 1):
        # the reference shifted so that Rd[v, u] = Rf[v, u - dd]
        Rd = np.zeros_like(Rf)
        ok_d = np.zeros_like(inside)
        if 0 <= dd < w:
            Rd[:, dd:] = Rf[:, : w - dd]
            ok_d[:, dd:] = inside[:, : w - dd]
        elif -w < dd < 0:
            Rd[:, : w + dd] = Rf[:, -dd:]
            ok_d[:, : w + dd] = inside[:, -dd:]
        mR = box(Rd)
        vR = np.maximum(box(Rd * Rd) - mR * mR, 0)
        cov = box(S * Rd) - mS * mR
        with np.errstate(divide="ignore", invalid="ignore"):
            cur = cov / (sS * np.sqrt(vR) + 1e-6)
        cur[~ok_d] = -1.0
        m = best_d == dd - 1
        right[m] = cur[m]
        upd = cur > best
        left[upd] = prev[upd]
        right[upd] = np.nan
        best[upd] = cur[upd]
        best_d[upd] = dd
        prev = cur
    return best, best_d, left, right, sS


def match_dots(
    rig: SimulatedRig,
    image: ArrayLike,
    reference: ArrayLike,
    reference_plane: ArrayLike,
    z_range: tuple[float, float] = (600.0, 1300.0),
    window: int = 15,
    min_score: float = 0.6,
    min_std: float = 2.0,
) -> DotDepth:
    """Depth from one image of the dots by block matching against a reference board image.

    Both images are resampled into :func:`rectified_camera`; each pixel's ``window`` x
    ``window`` neighbourhood is compared by zero-mean normalised cross-correlation with the
    reference at every integer disparity along its row (the epipolar line), the best one
    refined by a parabola through its neighbours, and turned into depth by
    ``1/z = 1/z_ref + d / (f b)`` with z_ref the depth of the reference plane at the reference
    pixel (u - d, v), f the focal length and b the baseline to the dot projector.

    Parameters
    ----------
    rig : the true camera and dot projector
    image, reference : (H, W) camera images (scene; flat board at ``reference_plane``)
    reference_plane : (4,) world plane of the reference board, n.X + d = 0
    z_range : (near, far) depths searched, mm, along the rectified camera's axis
    window : odd window side, px
    min_score : matches with a lower correlation are rejected
    min_std : windows whose (scene) standard deviation is below this many DN are rejected
        (no dots in them)

    Returns
    -------
    DotDepth
    """
    img = np.asarray(image, np.float32)
    ref = np.asarray(reference, np.float32)
    w, h = rig.camera.image_size
    near, far = _check_match_inputs(rig, img, ref, window, z_range)
    plane = np.asarray(reference_plane, float).reshape(4)
    rect, b = rectified_camera(rig)
    S, Rf, inside = _rectify_pair(rig, rect, img, ref, window)
    z_ref = _reference_depth(rect, plane)
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    f = rect.fx
    zr = z_ref[np.isfinite(z_ref)]
    if zr.size == 0:
        raise MeasurementError("the reference plane is not in front of the camera")
    d_hi = int(np.ceil(f * b * (1 / near - 1 / zr.max()))) + 1
    d_lo = int(np.floor(f * b * (1 / far - 1 / zr.min()))) - 1
    best, best_d, left, right, sS = _search_disparity(S, Rf, inside, window, d_lo, d_hi)
    denom = left - 2 * best + right
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(denom < 0, 0.5 * (left - right) / denom, 0.0)
    delta = np.clip(np.nan_to_num(delta), -0.5, 0.5)
    disp = best_d + delta
    valid = (
        inside
        & (best >= min_score)
        & (sS >= min_std)
        & (best_d > d_lo)
        & (best_d < d_hi)
        & np.isfinite(left)
        & np.isfinite(right)
    )
    # the reference pixel's plane depth, interpolated along the row at u - d
    u_ref = uu - disp
    iu = np.clip(np.floor(u_ref).astype(int), 0, w - 2)
    t = np.clip(u_ref - iu, 0, 1)
    rows = np.arange(h)[:, None]
    zr_at = (1 - t) * z_ref[rows, iu] + t * z_ref[rows, iu + 1]
    valid &= (u_ref >= 0) & (u_ref <= w - 1) & np.isfinite(zr_at)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = 1.0 / (1.0 / zr_at + disp / (f * b))
    valid &= np.isfinite(z) & (z > 0)
    xn = (uu - rect.cx) / f
    yn = (vv - rect.cy) / f
    pc = np.stack([xn * z, yn * z, z], axis=-1)  # rectified camera frame
    xyz = (pc - rect.t) @ rect.R  # R^T (X_cam - t)
    xyz[~valid] = np.nan
    return DotDepth(
        rect,
        xyz,
        valid,
        np.where(valid, disp, np.nan),
        best.astype(float),
    )
