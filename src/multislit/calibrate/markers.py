"""Checker markers in the calibration image: sub-pixel centre corners near their hints.

:func:`find_marker_corners` finds the centre corner of each 2x2 checker marker near its hint
(sub-pixel) and verifies that it really is a checker corner.

Units: px in the image; pixel (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter, map_coordinates, maximum_filter, spline_filter

from multislit.errors import CalibrationError
from multislit.geometry import as_points
from multislit.geometry.camera import F64


@dataclass(frozen=True, eq=False)
class MarkerDetection:
    """Result of :func:`find_marker_corners`.

    Attributes
    ----------
    ids : tuple of str, (M,)
    uv : (M, 2) float64, px, sub-pixel centre corner; NaN where not found
    found : (M,) bool
    reasons : tuple of str, (M,), why a marker was not found ('' where found)
    contrast : (M,) float64, grey levels, |bright - dark| around the corner (NaN if not measured)
    """

    ids: tuple[str, ...]
    uv: F64
    found: NDArray[np.bool_]
    reasons: tuple[str, ...]
    contrast: F64

    @property
    def rejected(self) -> dict[str, str]:
        """Marker id -> reason, for the markers that were not found."""
        return {i: r for i, r, f in zip(self.ids, self.reasons, self.found, strict=True) if not f}


def _noise_sigma(img: F64) -> float:
    """Robust estimate of the image noise (grey levels) from a Laplacian-like high-pass."""
    # Immerkaer's operator; flat and smooth regions dominate the median
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)
    h = cv2.filter2D(img.astype(np.float32), -1, k, borderType=cv2.BORDER_REFLECT)
    return float(1.4826 * np.median(np.abs(h[1:-1, 1:-1])) / 6.0)


def _ring_check(
    img: F64, uv: F64, radii: Sequence[float], noise: float, min_contrast: float
) -> tuple[NDArray[np.bool_], list[str], F64]:
    """Verify that each (u, v) is a 2x2 checker corner from intensity rings around it.

    On every ring the profile must alternate bright/dark/bright/dark (4 sectors: diagonal
    quadrants alike, adjacent ones different) with a contrast well above the noise.
    """
    n_ang = 72
    ang = np.linspace(0, 2 * np.pi, n_ang, endpoint=False)
    r = np.asarray(radii, float)
    # samples (M, R, A)
    us = uv[:, 0, None, None] + r[None, :, None] * np.cos(ang)[None, None, :]
    vs = uv[:, 1, None, None] + r[None, :, None] * np.sin(ang)[None, None, :]
    prof = map_coordinates(img, [vs.ravel(), us.ravel()], order=1, mode="nearest")
    prof = prof.reshape(us.shape)
    lo = np.percentile(prof, 10, axis=2, keepdims=True)
    hi = np.percentile(prof, 90, axis=2, keepdims=True)
    mid = 0.5 * (lo + hi)
    span = hi - lo
    # hysteresis classification: +1 bright, -1 dark, 0 undecided
    cls = np.where(prof > mid + 0.2 * span, 1, np.where(prof < mid - 0.2 * span, -1, 0))
    ok = np.ones(len(uv), bool)
    reasons = [""] * len(uv)
    contrast = np.full(len(uv), np.nan)
    for i in range(len(uv)):  # markers are few; the per-ring work is vectorised above
        c_all = []
        why = ""
        for j in range(len(r)):
            c = cls[i, j]
            c = c[c != 0]
            if c.size < 8:
                why = "no structure around the corner"
                break
            changes = int(np.count_nonzero(c != np.roll(c, 1)))
            if changes != 4:
                kind = {0: "a blank patch", 2: "an edge or an L-corner"}.get(
                    changes, f"{changes} bright/dark sectors instead of 4"
                )
                why = f"not a checker corner ({kind} at radius {r[j]:g} px)"
                break
            p = prof[i, j]
            bright = p[cls[i, j] == 1]
            dark = p[cls[i, j] == -1]
            c_all.append(np.median(bright) - np.median(dark))
        if not why:
            contrast[i] = float(np.min(c_all))
            if contrast[i] < max(min_contrast, 8.0 * noise):
                why = (
                    f"contrast {contrast[i]:.3g} too low (noise {noise:.2g}, "
                    f"need >= {max(min_contrast, 8.0 * noise):.3g})"
                )
        if why:
            ok[i] = False
            reasons[i] = why
    return ok, reasons, contrast


def _sector_balance(img: F64, uv: F64, radius: float) -> F64:
    """Max relative difference between the two bright (and the two dark) sectors (0 = equal)."""
    n_ang = 72
    ang = np.linspace(0, 2 * np.pi, n_ang, endpoint=False)
    us = uv[:, 0, None] + radius * np.cos(ang)[None, :]
    vs = uv[:, 1, None] + radius * np.sin(ang)[None, :]
    prof = map_coordinates(img, [vs.ravel(), us.ravel()], order=1, mode="nearest").reshape(us.shape)
    out = np.full(len(uv), np.inf)
    for i, p in enumerate(prof):
        mid = 0.5 * (p.max() + p.min())
        b = p > mid
        # rotate so the profile starts at a transition, then split into runs
        start = int(np.flatnonzero(b != np.roll(b, 1))[0]) if np.any(b != np.roll(b, 1)) else 0
        pr, br = np.roll(p, -start), np.roll(b, -start)
        edges = np.flatnonzero(br != np.roll(br, 1))
        if len(edges) != 4:
            continue
        runs = np.split(pr, edges[1:])
        lv = np.array([np.median(s) for s in runs])
        span = abs(lv[0] - lv[1]) + 1e-12
        out[i] = max(abs(lv[0] - lv[2]), abs(lv[1] - lv[3])) / span
    return out


def _saddle_refine(coef: F64, q: F64, half: int = 3, iterations: int = 6) -> tuple[F64, F64]:
    """Polish corners to the saddle point of a quadratic fitted to the smoothed image.

    A 2x2 checker is point-symmetric about its corner, so is its smoothed image, and the fitted
    quadratic's stationary point is the corner (no pixel-locking, unlike gradient criteria).

    Parameters
    ----------
    coef : (H, W) cubic-spline coefficients of the smoothed image
    q : (M, 2) float64, px, starting points

    Returns
    -------
    q : (M, 2) float64, px (NaN where the fit is not a saddle)
    det : (M,) float64, determinant of the fitted Hessian (< 0 for a saddle)
    """
    g = np.arange(-half, half + 1, dtype=float)
    dy, dx = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    sw = np.exp(-(dx * dx + dy * dy) / (4.0 * (half / 1.5) ** 2))  # sqrt of Gaussian weights
    A = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=1) * sw[:, None]
    pinv = np.linalg.pinv(A)
    q = np.array(q, dtype=float)
    det = np.full(len(q), np.nan)
    for _ in range(iterations):  # Newton steps on all corners at once
        # corners that diverged are NaN: never pass NaN coordinates to map_coordinates (SciPy
        # 1.17 can crash on them); sample them at 0 and let q + step keep them NaN
        live = np.all(np.isfinite(q), axis=1)
        qs = np.where(live[:, None], q, 0.0)
        vals = map_coordinates(
            coef,
            [qs[:, 1, None] + dy, qs[:, 0, None] + dx],
            order=3,
            prefilter=False,
            mode="nearest",
        )
        co = (vals * sw) @ pinv.T
        hxx, hxy, hyy = 2 * co[:, 3], co[:, 4], 2 * co[:, 5]
        det = hxx * hyy - hxy * hxy
        with np.errstate(divide="ignore", invalid="ignore"):
            step_u = -(hyy * co[:, 1] - hxy * co[:, 2]) / det
            step_v = -(-hxy * co[:, 1] + hxx * co[:, 2]) / det
        step = np.stack([step_u, step_v], axis=1)
        big = ~np.all(np.isfinite(step), axis=1) | (np.abs(step).max(axis=1) > 1.5)
        q = np.where(big[:, None], np.nan, q + step)
        if np.all(np.isnan(q) | (np.abs(step) < 1e-5)):
            break
    q[~(det < 0)] = np.nan
    return q, det


@dataclass(frozen=True, eq=False)
class _Maps:
    """Per-image data shared by all markers of :func:`find_marker_corners`."""

    img: NDArray[np.float32]  # (H, W) the image as float32
    noise: float  # grey levels, robust image noise
    saddle: F64  # (H, W) -det(Hessian) of the smoothed image, clipped at 0
    peaks: NDArray[np.bool_]  # (H, W) local maxima of ``saddle``
    coef: F64  # (H, W) cubic-spline coefficients of the smoothed image


def _saddle_maps(img: NDArray[np.float32]) -> _Maps:
    noise = _noise_sigma(img)
    smooth = gaussian_filter(img, 1.5)
    gy, gx = np.gradient(smooth)
    gyy, gyx = np.gradient(gy)
    _, gxx = np.gradient(gx)
    saddle = np.maximum(-(gxx * gyy - gyx * gyx), 0.0)
    coef = spline_filter(smooth.astype(np.float64), order=3)
    peaks = (saddle == maximum_filter(saddle, size=5)) & (saddle > 0)
    return _Maps(img, noise, saddle, peaks, coef)


def _candidates(maps: _Maps, hint: F64, search_radius: float) -> F64 | None:
    """Up to 5 saddle peaks (K, 2) float32 px within ``search_radius`` of ``hint``, nearest
    first (weak maxima dropped); None if there are none."""
    h, w = maps.img.shape
    u0, v0 = hint
    r = int(math.ceil(search_radius))
    x0, x1 = max(int(u0) - r, 0), min(int(u0) + r + 2, w)
    y0, y1 = max(int(v0) - r, 0), min(int(v0) + r + 2, h)
    pv, pu = np.nonzero(maps.peaks[y0:y1, x0:x1])
    pu, pv = pu + x0, pv + y0
    d = np.hypot(pu - u0, pv - v0)
    sel = d <= search_radius
    pu, pv, d, resp = pu[sel], pv[sel], d[sel], maps.saddle[pv[sel], pu[sel]]
    if resp.size:
        # drop weak maxima (noise) relative to the strongest saddle in the search area
        strong = resp >= 0.1 * resp.max()
        pu, pv, d = pu[strong], pv[strong], d[strong]
    if pu.size == 0:
        return None
    order = np.argsort(d)[:5]
    return np.stack([pu[order], pv[order]], axis=1).astype(np.float32)


def _off_border(cand: F64, margin: int, w: int, h: int) -> NDArray[np.bool_]:
    """(K,) bool: candidates at least ``margin`` px inside the image."""
    return (
        (cand[:, 0] >= margin)
        & (cand[:, 0] <= w - 1 - margin)
        & (cand[:, 1] >= margin)
        & (cand[:, 1] <= h - 1 - margin)
    )


def _verified_corner(
    maps: _Maps,
    cand: F64,
    hint: F64,
    search_radius: float,
    window: int,
    zero_zone: int,
    saddle_half: int,
    check_radii: Sequence[float],
    min_contrast: float,
    max_sector_imbalance: float,
) -> tuple[F64 | None, float, str]:
    """Refine the candidates (K, 2) and return the first that passes the checks.

    Returns (uv (2,) px, contrast, "") for the corner found, or (None, NaN, reason).
    """
    img = maps.img
    u0, v0 = hint
    term = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    ref = cv2.cornerSubPix(
        img, cand.reshape(-1, 1, 2).copy(), (window, window), (zero_zone, zero_zone), term
    )
    ref = ref.reshape(-1, 2).astype(float)
    polished, _ = _saddle_refine(maps.coef, ref, half=saddle_half)
    ref = np.where(np.isfinite(polished), polished, ref)
    moved = np.hypot(*(ref - cand).T)
    ok, why, con = _ring_check(img, ref, check_radii, maps.noise, min_contrast)
    bal = _sector_balance(img, ref, float(np.max(check_radii)))
    last = ""
    for j in range(len(ref)):
        if moved[j] > 3.0:
            last = "sub-pixel refinement did not converge on a corner"
            continue
        if np.hypot(ref[j, 0] - u0, ref[j, 1] - v0) > search_radius:
            last = f"no corner within {search_radius:g} px of the hint"
            continue
        if not ok[j]:
            last = why[j]
            continue
        if not bal[j] <= max_sector_imbalance:
            last = (
                f"not a checker corner (diagonal quadrants differ by {bal[j]:.0%} of the contrast)"
            )
            continue
        return ref[j], con[j], ""
    return None, float("nan"), last or "no checker corner near the hint"


def find_marker_corners(
    image: ArrayLike,
    hints: ArrayLike,
    ids: Sequence[str] | None = None,
    search_radius: float = 15.0,
    window: int = 5,
    zero_zone: int = -1,
    saddle_half: int = 3,
    check_radii: Sequence[float] = (3.0, 5.0),
    min_contrast: float | None = None,
    max_sector_imbalance: float = 0.35,
) -> MarkerDetection:
    """Find the centre corner of 2x2 checker markers near their hints, to sub-pixel accuracy.

    For each marker the saddle points (local maxima of -det(Hessian) of the smoothed image)
    within ``search_radius`` of the hint are refined with ``cv2.cornerSubPix``, polished to the
    saddle point of a quadratic fitted to the smoothed image (which removes cornerSubPix's
    pixel-locking bias on sharp edges), and verified, nearest first: on rings of ``check_radii`` around the corner the image must show four
    sectors, bright/dark/bright/dark, the two bright (and the two dark) alike, with a contrast
    well above the image noise. The first candidate that passes is the marker's corner; markers
    without one are reported with a reason and get NaN.

    Parameters
    ----------
    image : (H, W) uint8 or uint16, grayscale
    hints : (M, 2) float64, px, approximate corner positions
    ids : M marker ids (default "0", "1", ...)
    search_radius : float, px
    window : int, px, half size of cornerSubPix's window (keep it inside the marker's squares)
    zero_zone : int, px, half size of the window's centre left out by cornerSubPix (-1: none);
    saddle_half : int, px, half size of the window of the final saddle-point fit
    check_radii : radii (px) of the verification rings; keep them inside the squares
    min_contrast : grey levels; default 4 % of the type's range (10 for uint8)
    max_sector_imbalance : float
        Largest allowed difference of the two bright (or two dark) sectors, relative to the
        bright-dark contrast.

    Returns
    -------
    MarkerDetection
    """
    img0 = np.asarray(image)
    if img0.ndim != 2 or img0.dtype not in (np.uint8, np.uint16):
        raise CalibrationError(
            f"image must be a (H, W) uint8 or uint16 grayscale array, got {img0.dtype} {img0.shape}"
        )
    hints = as_points(hints, 2, "hints")
    m = len(hints)
    if ids is None:
        ids = [str(i) for i in range(m)]
    ids = tuple(str(i) for i in ids)
    if len(ids) != m:
        raise CalibrationError(f"ids has {len(ids)} entries but hints has {m} points")
    if search_radius <= 0:
        raise CalibrationError(f"search_radius must be > 0 px, got {search_radius}")
    if min_contrast is None:
        min_contrast = 0.04 * (255.0 if img0.dtype == np.uint8 else 65535.0)
    maps = _saddle_maps(img0.astype(np.float32))
    h, w = maps.img.shape

    uv = np.full((m, 2), np.nan)
    found = np.zeros(m, bool)
    reasons = [""] * m
    contrast = np.full(m, np.nan)
    finite = np.all(np.isfinite(hints), axis=1)
    inside = finite & (hints[:, 0] >= 0) & (hints[:, 0] <= w - 1)
    inside &= (hints[:, 1] >= 0) & (hints[:, 1] <= h - 1)
    for i in range(m):
        if not inside[i]:
            reasons[i] = (
                f"hint ({hints[i, 0]:.1f}, {hints[i, 1]:.1f}) is off the image ({w}x{h} px)"
                if finite[i]
                else "hint is not finite"
            )
            continue
        cand = _candidates(maps, hints[i], search_radius)
        if cand is None:
            reasons[i] = f"no corner within {search_radius:g} px of the hint"
            continue
        okpos = _off_border(cand, window + 2, w, h)
        if not np.any(okpos):
            reasons[i] = "the corner is too close to the image border"
            continue
        corner, con, why = _verified_corner(
            maps, cand[okpos], hints[i], search_radius, window, zero_zone, saddle_half,
            check_radii, min_contrast, max_sector_imbalance,
        )  # fmt: skip
        if corner is None:
            reasons[i] = why
            continue
        uv[i] = corner
        found[i] = True
        contrast[i] = con
    return MarkerDetection(ids, uv, found, tuple(reasons), contrast)
