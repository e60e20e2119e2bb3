"""Points on the slits for the projector calibration, and where stripe centres lie on the target.

Two sources (:class:`SlitPointSet`):

- :func:`hand_slit_points`: the paper's way, ``target.json`` ``slit_points`` (slit number and
  world xyz read off the target's scales);
- :func:`auto_slit_points`: stripe centres of ``calibration/slits.png`` with slit labels (e.g.
  :func:`~multislit.calibrate.slit_labels.label_by_order`), re-centred by
  :func:`multislit.stripes.refine_centres` (a line fitted along the stripe on each face); each
  centre's line of sight (distortion removed) is intersected with the target face it falls on
  (:func:`points_on_faces`), and centres that are not trustworthy are dropped: outside every
  face, near a face's outline in the image (the stripe bends there), where the target's albedo
  changes under the stripe (the markers' squares shift the centre), and double detections in
  one row.

:func:`stripe_lines` gives the stripe segments that are straight lines in space, for the
camera's lens distortion.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import gaussian_filter, maximum_filter, minimum_filter

from multislit.errors import CalibrationError
from multislit.geometry import MatrixCamera, PinholeCamera, as_points, orthonormal_basis
from multislit.geometry.camera import F64
from multislit.io import Capture, Face
from multislit.stripes import extract_slits, refine_centres

#: Keyword arguments of :func:`multislit.stripes.extract_slits` for the calibration image. The
#: target's ramp shows the stripes slanted; a short vertical opening keeps them whole (the
#: default one, sized to remove dots, cuts them into two ridges either side of the centre).
#: Dots left in the stripe image make short segments (dropped) or outliers (rejected by the
#: robust plane fit). Steger's centres (zero of the derivative over the whole profile) are less
#: shifted by laser speckle than the 3-point Gaussian fit at the peak. The target's stripes run
#: near the vertical: the column pass (stripes leaning towards the horizontal) is left out.
EXTRACT_OPTIONS = MappingProxyType(
    {"dot_size_px": 0.5, "method": "steger", "leaning": False, "background": "median"}
)
#: Keyword arguments of :func:`multislit.stripes.refine_centres` for the labelled centres. The
#: fit along the stripe runs within one target face, and the dot refill uses the extraction's
#: dot size.
_REFINE: dict[str, Any] = {}
#: Centres closer than this to their face's outline in the image are dropped (px).
_EDGE_MARGIN_PX = 3.0
#: Stripe centres closer than this to their face's outline are left out of the straight lines.
_LINE_EDGE_MARGIN_PX = 8.0
#: Centres where the target's albedo (markers image) varies by more than this fraction under
#: the stripe are dropped.
_MAX_ALBEDO_VARIATION = 0.15


def as_capture(capture: str | Path | Capture) -> Capture:
    """``capture`` opened as a :class:`~multislit.io.Capture` (a folder path is opened)."""
    return capture if isinstance(capture, Capture) else Capture.open(capture)


def read_capture_image(capture: Capture, path: Path, what: str) -> NDArray:
    """The image at ``path`` of ``capture``; :class:`CalibrationError` naming ``what`` if missing."""
    if not path.is_file():
        raise CalibrationError(f"missing {what}: {path} (the capture folder must contain it)")
    return capture.image(path)


# --------------------------------------------------------------------------- points on faces
def _polygon_contains(poly: F64, plane: F64, pts: F64) -> NDArray[np.bool_]:
    """Points (N, 3) on ``plane`` inside the convex polygon (V, 3) (boundary counts as inside)."""
    n = plane[:3]
    e1, e2 = orthonormal_basis(n / np.linalg.norm(n))
    p2 = np.stack([poly @ e1, poly @ e2], axis=1)
    q2 = np.stack([pts @ e1, pts @ e2], axis=1)
    edge = np.roll(p2, -1, axis=0) - p2  # (V, 2)
    rel = q2[:, None, :] - p2[None, :, :]  # (N, V, 2)
    cross = edge[None, :, 0] * rel[..., 1] - edge[None, :, 1] * rel[..., 0]
    tol = 1e-9 * max(float(np.abs(p2).max()), 1.0) ** 2
    return np.all(cross >= -tol, axis=1) | np.all(cross <= tol, axis=1)


def points_on_faces(
    camera: PinholeCamera | MatrixCamera, uv: ArrayLike, faces: Sequence[Face]
) -> tuple[F64, NDArray[np.intp]]:
    """Intersect lines of sight with the target's faces.

    Parameters
    ----------
    camera : a calibrated camera (its ``rays``)
    uv : (N, 2) float64, px
    faces : sequence of :class:`~multislit.io.Face` (unit-normal plane, convex polygon)

    Returns
    -------
    xyz : (N, 3) float64, mm, target frame; NaN where the ray hits no face inside its polygon
    face_index : (N,) int, index into ``faces`` of the face hit (the nearest one), -1 where none
    """
    p = as_points(uv, 2, "uv")
    o, d = camera.rays(p)
    best_t = np.full(len(p), np.inf)
    xyz = np.full((len(p), 3), np.nan)
    face_index = np.full(len(p), -1, dtype=np.intp)
    for fi, f in enumerate(faces):  # faces are few; each is vectorised over all rays
        plane = np.asarray(f.plane, dtype=float)
        n = plane[:3] / np.linalg.norm(plane[:3])
        dd = plane[3] / np.linalg.norm(plane[:3])
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(o @ n + dd) / denom
        hit = np.isfinite(t) & (t > 0) & (np.abs(denom) > 1e-12)
        pts = o + np.where(hit, t, 0.0)[:, None] * d
        inside = hit & _polygon_contains(np.asarray(f.polygon, dtype=float), plane, pts)
        better = inside & (t < best_t)
        best_t[better] = t[better]
        xyz[better] = pts[better]
        face_index[better] = fi
    return xyz, face_index


def _edge_distance(camera: PinholeCamera | MatrixCamera, uv: F64, face: NDArray, faces) -> F64:
    """Distance (px, distortion removed) of each point to the outline of its face."""
    if isinstance(camera, PinholeCamera):
        pin = PinholeCamera(
            camera.fx, camera.fy, camera.cx, camera.cy, camera.rvec, camera.tvec,
            image_size=camera.image_size,
        )  # fmt: skip
        und = camera.undistort_pixels(uv)
    else:
        pin, und = camera, uv
    out = np.full(len(uv), np.inf)
    for fi, f in enumerate(faces):
        sel = face == fi
        if not np.any(sel):
            continue
        V = pin.project(np.asarray(f.polygon, dtype=float))
        p = und[sel]
        best = np.full(len(p), np.inf)
        for a, b in zip(V, np.roll(V, -1, axis=0), strict=True):
            ab = b - a
            t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(p - (a + t[:, None] * ab), axis=1))
        out[sel] = best
    return out


def _albedo_variation(markers_img: NDArray, u: F64, v: F64, half_width: int) -> F64:
    """Relative albedo variation (max - min) / max in a window around each point."""
    a = gaussian_filter(markers_img.astype(np.float32), 1.0)
    size = (7, 2 * half_width + 1)
    mx = maximum_filter(a, size=size)
    mn = minimum_filter(a, size=size)
    var = (mx - mn) / np.maximum(mx, 1e-6)
    h, w = a.shape
    iu = np.clip(np.round(u).astype(int), 0, w - 1)
    iv = np.clip(np.round(v).astype(int), 0, h - 1)
    return var[iv, iu]


def _row_gap(u: F64, v: F64) -> F64:
    """Distance (px) to the nearest other centre in the same row."""
    order = np.lexsort((u, v))
    uu, vv = u[order], v[order]
    gap = np.full(len(uu), np.inf)
    if len(uu) > 1:
        dg = np.where(vv[1:] == vv[:-1], uu[1:] - uu[:-1], np.inf)
        gap[:-1] = np.minimum(gap[:-1], dg)
        gap[1:] = np.minimum(gap[1:], dg)
    out = np.empty_like(gap)
    out[order] = gap
    return out


# --------------------------------------------------------------------------- straight stripes
def _straight_runs(
    u: F64, v: F64, key: NDArray[np.intp], min_points: int = 20, max_points: int = 80
) -> list[F64]:
    """Group points by ``key`` (>= 0) into (N, 2) arrays, each evenly thinned to max_points."""
    out = []
    for kk in np.unique(key[key >= 0]):
        idx = np.flatnonzero(key == kk)
        if len(idx) < min_points or np.ptp(v[idx]) < 2 * min_points:
            continue
        idx = idx[np.linspace(0, len(idx) - 1, min(max_points, len(idx))).round().astype(int)]
        out.append(np.stack([u[idx], v[idx]], axis=1))
    return out


def stripe_lines(capture: Capture, camera: PinholeCamera | MatrixCamera) -> list[F64]:
    """Image runs (N_i, 2) px of stripe centres that are straight lines in space.

    Stripe segments on each target face in ``calibration/slits.png`` (away from the face
    outlines, albedo edges and double detections) and stripe segments on the reference boards,
    for :func:`~multislit.calibrate.camera.refine_camera_with_lines`. No slit identification is
    needed.
    """
    lines: list[F64] = []
    if capture.slits_image.is_file() and capture.target is not None and capture.target.faces:
        faces = capture.target.faces
        img = capture.image(capture.slits_image)
        ex = extract_slits(img, **EXTRACT_OPTIONS)
        sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
        uv = np.stack([ex.u, ex.v], axis=1)
        keep = ex.segment >= 0
        face = np.full(len(uv), -1, np.intp)
        if np.any(keep):
            _, face[keep] = points_on_faces(camera, uv[keep], faces)
        keep &= face >= 0
        keep &= _edge_distance(camera, uv, face, faces) > _LINE_EDGE_MARGIN_PX
        keep &= _row_gap(ex.u, ex.v) > 2.0 * sw
        if capture.markers_image.is_file():
            var = _albedo_variation(
                capture.image(capture.markers_image), ex.u, ex.v, int(math.ceil(1.5 * sw))
            )
            keep &= var <= _MAX_ALBEDO_VARIATION
        key = np.where(keep, ex.segment * (len(faces) + 1) + face, -1)
        lines += _straight_runs(ex.u, ex.v, key)
    for path in capture.references:
        ex = extract_slits(capture.image(path), leaning=False, background="median")
        lines += _straight_runs(ex.u, ex.v, ex.segment)
    return lines


# --------------------------------------------------------------------------- slit points
@dataclass(frozen=True, eq=False)
class SlitPointSet:
    """Points on the slits for the projector calibration.

    Attributes
    ----------
    xyz : (N, 3) float64, mm, target frame
    slit : (N,) int, slit number 0..num_slits-1
    uv : (N, 2) float64, px, where the point is seen
    face : (N,) int, index of the target face (-1: unknown, e.g. hand readings)
    source : "hand" or "auto"
    steps : ordered (step, points left) of the automatic filtering, for the report
    """

    xyz: F64
    slit: NDArray[np.intp]
    uv: F64
    face: NDArray[np.intp]
    source: str
    steps: tuple[tuple[str, int], ...] = ()

    def __len__(self) -> int:
        return len(self.xyz)


def hand_slit_points(capture: str | Path | Capture) -> SlitPointSet:
    """The hand readings of target.json (``slit_points``), the paper's projector data."""
    cap = as_capture(capture)
    sp = () if cap.target is None else cap.target.slit_points
    if not sp:
        raise CalibrationError(
            f"{cap.root / 'target.json'} has no slit_points (hand readings); add readings of "
            "points on the slits or use the automatic source"
        )
    xyz = np.array([p.xyz for p in sp], dtype=float)
    slit = np.array([p.slit for p in sp], dtype=np.intp)
    uv = np.array([p.uv for p in sp], dtype=float)
    return SlitPointSet(xyz, slit, uv, np.full(len(sp), -1, np.intp), "hand", (("read", len(sp)),))


def transfer_labels(
    u_from: ArrayLike,
    v_from: ArrayLike,
    slit_from: ArrayLike,
    u: ArrayLike,
    v: ArrayLike,
    tol_px: float = 2.5,
) -> NDArray[np.intp]:
    """Label points (u, v) with the slit of the nearest labelled point in the same row.

    Points without a labelled point within ``tol_px`` in their row, or whose two nearest
    labelled neighbours in the row (within ``tol_px``) disagree, get -1.
    """
    uf, vf = np.asarray(u_from, float), np.round(np.asarray(v_from, float))
    sf = np.asarray(slit_from).astype(np.intp)
    good = (sf >= 0) & np.isfinite(uf) & np.isfinite(vf)
    uf, vf, sf = uf[good], vf[good], sf[good]
    uq, vq = np.asarray(u, float), np.round(np.asarray(v, float))
    out = np.full(len(uq), -1, np.intp)
    if not len(uf) or not len(uq):
        return out
    span = float(max(np.nanmax(np.abs(uf)), np.nanmax(np.abs(uq)))) * 4 + 10.0
    kf = vf * span + uf
    order = np.argsort(kf)
    kf, sf_s = kf[order], sf[order]
    kq = vq * span + uq
    j = np.searchsorted(kf, kq)
    lo = np.clip(j - 1, 0, len(kf) - 1)
    hi = np.clip(j, 0, len(kf) - 1)
    dlo, dhi = np.abs(kq - kf[lo]), np.abs(kq - kf[hi])
    best = np.where(dlo <= dhi, lo, hi)
    other = np.where(dlo <= dhi, hi, lo)
    dbest = np.minimum(dlo, dhi)
    dother = np.maximum(dlo, dhi)
    ok = dbest <= tol_px
    conflict = (dother <= tol_px) & (sf_s[other] != sf_s[best])
    out[ok & ~conflict] = sf_s[best][ok & ~conflict]
    return out


def _checked_labels(labels: Any) -> tuple[F64, F64, NDArray[np.intp]]:
    """(u, v, slit) of :func:`auto_slit_points`'s ``labels`` as arrays, checked."""
    try:
        u, v, slit = (np.asarray(a).reshape(-1) for a in labels)
    except (TypeError, ValueError):
        raise CalibrationError(
            "labels must be (u, v, slit): three arrays of stripe centres"
        ) from None
    if len(slit) != len(u) or len(v) != len(u):
        raise CalibrationError("labels: u, v and slit have different lengths")
    if slit.size and not np.issubdtype(slit.dtype, np.integer):
        raise CalibrationError(f"slit labels must be integers (-1 = unknown), got {slit.dtype}")
    return u.astype(float), v.astype(float), slit.astype(np.intp)


def _refined_u(
    img: NDArray, ex: Any, face: NDArray[np.intp], n_faces: int, opts: dict[str, Any]
) -> F64:
    """Columns (K,) px of the extraction's centres after :func:`~multislit.stripes.refine_centres`.

    Each linked segment is cut into its pieces on one face (``face`` (K,), -1: left as is), so
    the fit along the stripe never spans the fold between two faces.
    """
    seg = np.asarray(ex.segment, np.int64)
    piece = np.where((seg >= 0) & (face >= 0), seg * max(n_faces, 1) + face, -1)
    sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
    kw = dict(opts)
    if math.isfinite(ex.dot_size_px):
        kw.setdefault("dot_size_px", ex.dot_size_px)
    u, _ = refine_centres(img, ex.u, ex.v, piece, sw, **kw)
    return u


def auto_slit_points(
    capture: str | Path | Capture,
    camera: PinholeCamera | MatrixCamera,
    labels: tuple[ArrayLike, ArrayLike, ArrayLike],
    *,
    refine: bool = True,
) -> SlitPointSet:
    """Points on the slits from ``calibration/slits.png`` and slit labels of its stripe centres.

    Parameters
    ----------
    capture : capture folder or Capture (with target.json faces)
    camera : the calibrated camera (distortion is removed through its rays)
    labels : (u, v, slit), each (K,)
        Labelled stripe centres of the image: u, v in px, slit the slit number (int, -1 where
        unknown), e.g. those of :func:`~multislit.calibrate.slit_labels.label_by_order`. Each
        centre of the extraction (:data:`EXTRACT_OPTIONS`) takes the label of the nearest
        labelled centre in its row.
    refine : bool
        Re-centre the labelled centres on the target's faces with
        :func:`multislit.stripes.refine_centres` (False: keep the extraction's centres).
        Default True.

    Returns
    -------
    SlitPointSet with ``source="auto"`` and the count after each filtering step
    """
    cap = as_capture(capture)
    if cap.target is None or not cap.target.faces:
        raise CalibrationError(
            f"{cap.root / 'target.json'} lists no faces; automatic projector calibration needs "
            "the target's faces (or use the hand readings)"
        )
    faces = cap.target.faces
    img = read_capture_image(cap, cap.slits_image, "slit image")
    ex = extract_slits(img, **EXTRACT_OPTIONS)
    steps: list[tuple[str, int]] = [("stripe centres", len(ex.u))]
    keep = ex.segment >= 0
    steps.append(("in linked segments", int(keep.sum())))
    uf, vf, sf = _checked_labels(labels)
    sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
    slit = transfer_labels(uf, vf, sf, ex.u, ex.v, tol_px=max(1.0, 0.8 * sw))
    bad = (slit >= cap.num_slits) | (slit < -1)
    if np.any(bad):
        raise CalibrationError(
            f"the slit labelling returned slit numbers outside 0..{cap.num_slits - 1} "
            f"(e.g. {int(slit[bad][0])})"
        )
    keep &= slit >= 0
    steps.append(("labelled", int(keep.sum())))
    uv = np.stack([ex.u, ex.v], axis=1)
    xyz = np.full((len(uv), 3), np.nan)
    face = np.full(len(uv), -1, np.intp)
    if np.any(keep):
        xyz[keep], face[keep] = points_on_faces(camera, uv[keep], faces)
    if refine and np.any(keep):
        uv[:, 0] = _refined_u(img, ex, np.where(keep, face, -1), len(faces), _REFINE)
        xyz[keep], face[keep] = points_on_faces(camera, uv[keep], faces)
    keep &= face >= 0
    steps.append(("on a target face", int(keep.sum())))
    keep &= _edge_distance(camera, uv, face, faces) > _EDGE_MARGIN_PX
    steps.append((f"> {_EDGE_MARGIN_PX:g} px from the face outline", int(keep.sum())))
    keep &= _row_gap(uv[:, 0], ex.v) > 2.0 * sw
    steps.append(("single detection in the row", int(keep.sum())))
    if cap.markers_image.is_file():
        mimg = cap.image(cap.markers_image)
        var = _albedo_variation(mimg, uv[:, 0], ex.v, int(math.ceil(1.5 * sw)))
        keep &= var <= _MAX_ALBEDO_VARIATION
        steps.append(("uniform albedo under the stripe", int(keep.sum())))
    return SlitPointSet(xyz[keep], slit[keep], uv[keep], face[keep], "auto", tuple(steps))
