"""The folds of the target in the markers image: straight 3D lines at known places.

Where two of the target's faces meet (their polygons in ``target.json`` share an edge), the
markers image shows a straight fold: the faces are lit alike but turned differently to the
light and the camera, so one is brighter. The fold is a 3D line whose position is known, like
the markers, but it runs across the target in depth, from its deepest corner towards the rig,
and every point along it is an observation: it pins the camera's depth scale (focal length
against distance) that markers of a shallow target leave loose.

:func:`target_folds` finds the folds from the faces; :func:`fold_points` finds each fold in the
image, to sub-pixel precision: intensity profiles across the fold's image (as the starting
camera puts it) are fitted with a blurred step, and profiles that do not look like one (a
marker nearby, no contrast) are left out.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.special import erf

from multislit.geometry import PinholeCamera
from multislit.geometry.camera import F64
from multislit.io import Face

#: Two faces share a fold when two vertices of one lie within this distance (mm) of the other's
#: plane and polygon edge.
_SHARED_MM = 1e-3
#: Profiles across a fold are sampled every this many px along it, ...
_STEP_PX = 3.0
#: ... leaving out this share of the fold at each end (the corner where three faces meet).
_END_SHARE = 0.08
#: Half length (px) of a profile across the fold, and its sampling step (px).
_HALF_PX = 5.0
_PROFILE_STEP = 0.25
#: A fold is found where the step's contrast is at least this many times the profile's
#: residual noise, its blur width within these limits (px) and it lies within this distance
#: (px) of where the starting camera puts it.
_MIN_CONTRAST = 8.0
_WIDTH_PX = (0.3, 2.5)
_MAX_SHIFT_PX = 2.0
#: Gauss-Newton steps of the step fit.
_FIT_STEPS = 8


@dataclass(frozen=True, eq=False)
class FoldPoints:
    """Points of the target's folds found in the markers image.

    Attributes
    ----------
    uv : (N, 2) float64, px, points on the folds' images
    fold : (N,) int, the fold of each point (index into ``P``, ``D``, ``names``)
    P, D : (L, 3) float64, each fold's 3D line: a point (mm) and a unit direction
    names : (L,) str, "F1/F2": the faces that meet there
    """

    uv: F64
    fold: NDArray[np.intp]
    P: F64
    D: F64
    names: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.uv)


def target_folds(faces: Sequence[Face]) -> list[tuple[str, F64, F64]]:
    """The folds (name, end a (3,) mm, end b (3,) mm) where two faces' polygons share an edge."""
    out = []
    for i, fi in enumerate(faces):
        pi = np.asarray(fi.polygon, float)
        for fj in faces[i + 1 :]:
            plane = np.asarray(fj.plane, float)
            n = np.linalg.norm(plane[:3])
            on = np.abs(pi @ plane[:3] + plane[3]) / n < _SHARED_MM
            if on.sum() != 2:
                continue
            a, b = pi[on]
            pj = np.asarray(fj.polygon, float)
            # both ends must be vertices (or on the outline) of the other face too
            if min(np.linalg.norm(pj - a, axis=1).min(), np.linalg.norm(pj - b, axis=1).min()) > (
                _SHARED_MM * 1e3
            ):
                continue
            out.append((f"{fi.id}/{fj.id}", a, b))
    return out


def _fit_steps(t: F64, prof: F64) -> tuple[F64, F64, F64, F64]:
    """Fit I(t) = a + b erf((t - t0) / (sqrt(2) w)) to each profile (M, T) sampled at ``t``
    (T,): returns t0, w, b (M,) and the residual RMS (M,)."""
    m = len(prof)
    a = 0.5 * (prof[:, :3].mean(axis=1) + prof[:, -3:].mean(axis=1))
    b = 0.5 * (prof[:, -3:].mean(axis=1) - prof[:, :3].mean(axis=1))
    t0 = np.zeros(m)
    w = np.ones(m)
    for _ in range(_FIT_STEPS):
        z = (t[None, :] - t0[:, None]) / (np.sqrt(2.0) * w[:, None])
        e = erf(z)
        g = np.exp(-z * z) * (2.0 / np.sqrt(np.pi))
        r = a[:, None] + b[:, None] * e - prof
        J = np.stack(
            [
                np.ones_like(e),
                e,
                -b[:, None] * g / (np.sqrt(2.0) * w[:, None]),
                -b[:, None] * g * z / w[:, None],
            ],
            axis=2,
        )  # (M, T, 4)
        A = np.einsum("mti,mtj->mij", J, J) + 1e-9 * np.eye(4)
        step = np.linalg.solve(A, np.einsum("mti,mt->mi", J, r)[..., None])[..., 0]
        a, b, t0, w = a - step[:, 0], b - step[:, 1], t0 - step[:, 2], w - step[:, 3]
        w = np.clip(np.abs(w), 0.05, 10.0)
    z = (t[None, :] - t0[:, None]) / (np.sqrt(2.0) * w[:, None])
    res = a[:, None] + b[:, None] * erf(z) - prof
    return t0, w, b, np.sqrt(np.mean(res * res, axis=1))


def fold_points(image: NDArray, camera: PinholeCamera, faces: Sequence[Face]) -> FoldPoints:
    """Find the target's folds in the markers image, near where ``camera`` puts them.

    Parameters
    ----------
    image : (H, W) the markers image (lasers off)
    camera : the starting camera (from the markers)
    faces : the target's faces (``target.json``)

    Returns
    -------
    FoldPoints (empty if the target has no folds or none is found)
    """
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape[:2]
    t = np.arange(-_HALF_PX, _HALF_PX + 1e-9, _PROFILE_STEP)
    uv_l, fold_l, P_l, D_l, names = [], [], [], [], []
    for name, a, b in target_folds(faces):
        d = (b - a) / np.linalg.norm(b - a)
        length = float(np.linalg.norm(b - a))
        ends = camera.project(np.stack([a, b]))
        n_pts = int(max(2, np.linalg.norm(ends[1] - ends[0]) / _STEP_PX))
        s = np.linspace(_END_SHARE, 1.0 - _END_SHARE, n_pts) * length
        X = a + s[:, None] * d
        uv0 = camera.project(X)
        tan = camera.project(X + 0.5 * d) - camera.project(X - 0.5 * d)
        tan /= np.linalg.norm(tan, axis=1, keepdims=True)
        nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
        inside = np.all(np.isfinite(uv0), axis=1)
        inside &= (uv0[:, 0] > _HALF_PX + 1) & (uv0[:, 0] < w - _HALF_PX - 2)
        inside &= (uv0[:, 1] > _HALF_PX + 1) & (uv0[:, 1] < h - _HALF_PX - 2)
        uv0, nrm = uv0[inside], nrm[inside]
        if not len(uv0):
            continue
        pts = uv0[:, None, :] + t[None, :, None] * nrm[:, None, :]
        prof = map_coordinates(img, [pts[..., 1].ravel(), pts[..., 0].ravel()], order=1)
        prof = prof.reshape(len(uv0), len(t))
        t0, width, contrast, noise = _fit_steps(t, prof)
        ok = np.isfinite(t0) & (np.abs(t0) < _MAX_SHIFT_PX)
        ok &= (width > _WIDTH_PX[0]) & (width < _WIDTH_PX[1])
        ok &= np.abs(contrast) > _MIN_CONTRAST * np.maximum(noise, 1e-6)
        if ok.sum() < 10:
            continue
        # one fold, one sign of contrast: the other sign is something else (a marker)
        sign = np.sign(np.median(contrast[ok]))
        ok &= np.sign(contrast) == sign
        uv_l.append(uv0[ok] + t0[ok, None] * nrm[ok])
        fold_l.append(np.full(int(ok.sum()), len(names), np.intp))
        P_l.append(a)
        D_l.append(d)
        names.append(name)
    if not names:
        e = np.zeros((0, 3))
        return FoldPoints(np.zeros((0, 2)), np.zeros(0, np.intp), e, e, ())
    return FoldPoints(
        np.concatenate(uv_l),
        np.concatenate(fold_l),
        np.array(P_l),
        np.array(D_l),
        tuple(names),
    )
