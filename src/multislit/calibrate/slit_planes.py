"""One plane per slit, optionally all through a common line (the grating's axis).

:class:`SlitPlanes` is our projector model: one plane per slit. :func:`fit_slit_planes` fits it
from points on the slits, optionally constrained to share one common line.
:func:`slit_plane_rms` measures how well any set of slit planes explains points on the slits,
e.g. the systematic error of the paper's 2x4 model for a diffraction grating.

Units: mm in the world (target) frame.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from multislit.calibrate.camera import check_finite
from multislit.errors import CalibrationError, MultislitError
from multislit.geometry import (
    as_points,
    fit_plane,
    line_rms,
    orthonormal_basis,
    rotation_from_rvec,
)
from multislit.geometry.camera import F64
from multislit.io import json_safe

#: Least number of slits with planes of their own for the common axis to give planes to slits
#: seen along one line.
MIN_AXIS_SLITS = 3

#: A slit seen along one line gets the plane through the axis only if its points are at least
#: this fraction of the other slits' median RMS distance from the axis.
MIN_AXIS_LEVER = 0.2

#: ... and only if that plane's angle about the axis is within this many local slit spacings of
#: where a smooth curve through the other slits' angles puts its slit number.
MAX_AXIS_ANGLE_DEVIATION = 0.25


def _array(x: Any, name: str, shape: tuple[int, ...] | None = None) -> F64:
    try:
        a = np.array([np.nan if v is None else v for v in np.ravel(np.array(x, dtype=object))])
        a = a.astype(float).reshape(np.shape(np.array(x, dtype=object)))
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"calibration JSON: {name} is malformed: {exc}") from None
    if shape is not None and a.shape != shape:
        raise CalibrationError(f"calibration JSON: {name} must have shape {shape}, got {a.shape}")
    return a


def slit_indices(slits: ArrayLike, num_slits: int, name: str = "slits") -> NDArray[np.intp]:
    if int(num_slits) < 1:
        raise CalibrationError(f"num_slits must be >= 1, got {num_slits}")
    s = np.asarray(slits).reshape(-1)
    if s.size and not np.issubdtype(s.dtype, np.integer):
        if not np.all(np.isfinite(s.astype(float))) or np.any(s != np.round(s)):
            raise CalibrationError(f"{name} must be integer slit numbers")
    s = s.astype(np.intp)
    bad = (s < 0) | (s >= num_slits)
    if np.any(bad):
        raise CalibrationError(
            f"{name} has values outside 0..{num_slits - 1} (e.g. {int(s[bad][0])}); "
            "check the slit numbering or num_slits"
        )
    return s


@dataclass(frozen=True, eq=False)
class SlitPlanes:
    """One plane per slit (our projector model).

    Attributes
    ----------
    planes : (K, 4) float64, unit normals, n.X + d = 0 (mm); NaN rows for slits without a fit
    rms_mm : (K,) float64, mm, RMS distance of each slit's points to its plane (NaN: no fit)
    counts : (K,) int, number of points used per slit
    axis_point, axis_direction : (3,) float64 mm / unit, the common line (None if not fitted)
    excluded : tuple of (slit, reason) for slits left out
    from_axis : tuple of int, slits seen along one line only, whose plane is the plane through
        the common axis and their points (see :func:`fit_slit_planes`)
    """

    planes: F64
    rms_mm: F64
    counts: NDArray[np.int_]
    axis_point: F64 | None = None
    axis_direction: F64 | None = None
    excluded: tuple[tuple[int, str], ...] = field(default=())
    from_axis: tuple[int, ...] = field(default=())

    @property
    def num_slits(self) -> int:
        return len(self.planes)

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(K,) bool, slits with a plane."""
        return np.all(np.isfinite(self.planes), axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "planes": json_safe(self.planes.tolist()),
            "rms_mm": json_safe(self.rms_mm.tolist()),
            "counts": [int(c) for c in self.counts],
            "axis_point": None if self.axis_point is None else self.axis_point.tolist(),
            "axis_direction": None if self.axis_direction is None else self.axis_direction.tolist(),
            "excluded": [[int(k), r] for k, r in self.excluded],
            "from_axis": [int(j) for j in self.from_axis],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SlitPlanes:
        try:
            planes = _array(d["planes"], "slit_planes.planes")
            k = len(planes)
            planes = planes.reshape(k, 4)
            ap, ad = d.get("axis_point"), d.get("axis_direction")
            return cls(
                planes=planes,
                rms_mm=_array(d["rms_mm"], "slit_planes.rms_mm", (k,)),
                counts=np.asarray(d["counts"], dtype=int).reshape(k),
                axis_point=None if ap is None else _array(ap, "axis_point", (3,)),
                axis_direction=None if ad is None else _array(ad, "axis_direction", (3,)),
                excluded=tuple((int(a), str(b)) for a, b in d.get("excluded", [])),
                from_axis=tuple(int(j) for j in d.get("from_axis", [])),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"malformed slit planes: {exc!r}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, s: str) -> SlitPlanes:
        return cls.from_dict(json.loads(s))


def common_line(planes: ArrayLike) -> tuple[F64, F64]:
    """Least-squares common line of planes (K, 4) (unit normals): (point (3,) mm, direction (3,)).

    The direction minimises sum (n_k . u)^2; the point minimises sum (n_k . a + d_k)^2 and is
    the one closest to the origin.
    """
    pl = as_points(planes, 4, "planes")
    n = pl[:, :3]
    _, _, vt = np.linalg.svd(n, full_matrices=False)
    u = vt[-1]
    A = np.vstack([n, u[None, :]])
    b = np.concatenate([-pl[:, 3], [0.0]])
    a = np.linalg.lstsq(A, b, rcond=None)[0]
    return a, u


def fit_slit_planes(
    points: ArrayLike,
    slits: ArrayLike,
    num_slits: int,
    common_axis: bool = True,
    min_width_mm: float = 0.0,
    weights: ArrayLike | None = None,
) -> SlitPlanes:
    """Fit one plane per slit, optionally all through one common line.

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame, points on the slits
    slits : (N,) int, slit number 0..num_slits-1 of each point
    num_slits : int
    common_axis : bool
        Constrain all planes to contain one line (the grating's axis through the projector's
        source): parameters are the axis (point + direction) and one angle per slit, fitted by
        non-linear least squares from independent total-least-squares planes.
    min_width_mm : float, mm
        A slit whose points spread less than this (RMS distance from their best line) across
        their line counts as seen along one line (e.g. on one flat face of the target), like a
        slit with exactly collinear points. One line does not determine a plane by itself.
    weights : (N,) float64 >= 0, optional
        Weight of each point in the least-squares fits (e.g. 1 / variance, mm^-2); default
        all 1. The reported ``rms_mm`` stays the plain (unweighted) RMS.

    Returns
    -------
    SlitPlanes
        Slits with fewer than 3 points get NaN and are listed in ``excluded`` with the reason.
        Slits seen along one line are left out of the axis fit. With ``common_axis`` they get
        the plane through the fitted axis and their points (the axis and a line off it span
        one plane, also when the line is parallel to the axis) and are listed in
        ``from_axis``; their ``rms_mm`` is the RMS distance of their points to that plane.
        They stay excluded (NaN, with the reason) when the axis is fitted from fewer than
        :data:`MIN_AXIS_SLITS` slits, when their points are too close to the axis (RMS
        distance below :data:`MIN_AXIS_LEVER` times the other slits' median) for the angle
        to be determined, or when the plane's angle about the axis is more than
        :data:`MAX_AXIS_ANGLE_DEVIATION` slit spacings from where the other slits' angles put
        that slit number (mislabelled points). Without ``common_axis`` they are excluded.

    Raises
    ------
    CalibrationError
        Bad input, no slit with a plane, or ``common_axis`` with fewer than 2 fitted slits.
    """
    X = as_points(points, 3, "points")
    s = slit_indices(slits, num_slits)
    if len(s) != len(X):
        raise CalibrationError(f"points has {len(X)} rows but slits has {len(s)} values")
    check_finite(X, "points")
    if not (math.isfinite(min_width_mm) and min_width_mm >= 0):
        raise CalibrationError(f"min_width_mm must be a finite value >= 0 mm, got {min_width_mm}")
    wt = _point_weights(weights, len(X))
    k = int(num_slits)
    counts = np.bincount(s, minlength=k)
    order = np.argsort(s, kind="stable")
    starts = np.searchsorted(s[order], np.arange(k + 1))
    planes, excluded, line_why = _own_planes(X, wt, counts, order, starts, min_width_mm)
    ok = np.all(np.isfinite(planes), axis=1)
    if not np.any(ok):
        raise CalibrationError(
            "no slit has >= 3 points off one line; read points along each slit on two faces"
        )
    # consistent normal orientation: agree with the middle valid slit
    ref = planes[np.flatnonzero(ok)[np.count_nonzero(ok) // 2], :3]
    flip = (planes[:, :3] @ ref) < 0
    planes[flip] *= -1
    axis_point = axis_dir = None
    from_axis: list[int] = []
    if common_axis:
        if np.count_nonzero(ok) < 2:
            raise CalibrationError(
                "common_axis=True needs >= 2 slits with planes to define the axis; "
                "read more slits or pass common_axis=False"
            )
        planes, axis_point, axis_dir = _fit_common_axis(X, s, planes, ok, wt)
        for j, why in _planes_from_axis(
            X, wt, order, starts, planes, ok, sorted(line_why), axis_point, axis_dir, ref
        ).items():
            if why:
                excluded.append((j, f"{line_why[j]}: no plane of its own, and {why}"))
            else:
                from_axis.append(j)
    else:
        excluded += [
            (j, f"{why}: no unique plane (common_axis=False)") for j, why in line_why.items()
        ]
    excluded.sort()
    rms_mm = _plane_rms(X, s, planes, counts)
    return SlitPlanes(
        planes, rms_mm, counts, axis_point, axis_dir, tuple(excluded), tuple(from_axis)
    )


def _point_weights(weights: ArrayLike | None, n: int) -> F64:
    """The weights (n,) of :func:`fit_slit_planes`, checked (default all 1)."""
    if weights is None:
        return np.ones(n)
    wt = np.asarray(weights, dtype=float).reshape(-1)
    if len(wt) != n or not np.all(np.isfinite(wt)) or np.any(wt < 0):
        raise CalibrationError(
            f"weights must be {n} finite values >= 0 (one per point), got {len(wt)} values"
        )
    return wt


def _own_planes(
    X: F64,
    wt: F64,
    counts: NDArray[np.int_],
    order: NDArray[np.intp],
    starts: NDArray[np.intp],
    min_width_mm: float,
) -> tuple[F64, list[tuple[int, str]], dict[int, str]]:
    """One weighted total-least-squares plane per slit from its own points.

    Returns the planes (K, 4) (NaN where a slit has none), the slits excluded for too few
    points with the reason, and the slits seen along one line -> why they have no own plane.
    """
    k = len(counts)
    planes = np.full((k, 4), np.nan)
    excluded: list[tuple[int, str]] = []
    line_why: dict[int, str] = {}
    for j in range(k):  # one TLS fit per slit (vectorised over its points)
        if counts[j] == 0:
            continue
        if counts[j] < 3:
            excluded.append((j, f"only {counts[j]} point(s); a plane needs >= 3"))
            continue
        pts = X[order[starts[j] : starts[j + 1]]]
        try:
            planes[j] = fit_plane(pts, weights=wt[order[starts[j] : starts[j + 1]]])[0]
        except MultislitError:
            line_why[j] = "its points are collinear"
            continue
        if min_width_mm > 0:
            width = line_rms(pts)
            if width < min_width_mm:
                planes[j] = np.nan
                line_why[j] = (
                    f"its points lie along one line (spread {width:.2g} mm across it, "
                    f"< min_width_mm {min_width_mm:g})"
                )
    return planes, excluded, line_why


def _plane_rms(X: F64, s: NDArray[np.intp], planes: F64, counts: NDArray[np.int_]) -> F64:
    """(K,) mm, RMS distance of each slit's points to its plane (NaN where no plane)."""
    k = len(planes)
    ok = np.all(np.isfinite(planes), axis=1)
    valid_pt = ok[s]
    d = np.einsum("ij,ij->i", X[valid_pt], planes[s[valid_pt], :3]) + planes[s[valid_pt], 3]
    ssq = np.bincount(s[valid_pt], weights=d * d, minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, np.sqrt(ssq / np.maximum(counts, 1)), np.nan)


def _planes_from_axis(
    X: F64,
    wt: F64,
    order: NDArray[np.intp],
    starts: NDArray[np.intp],
    planes: F64,
    ok: NDArray[np.bool_],
    lines: Sequence[int],
    axis_point: F64,
    axis_dir: F64,
    ref: F64,
) -> dict[int, str]:
    """Give slits seen along one line the plane through the common axis and their points.

    Fills ``planes[j]`` (in place) for each slit ``j`` of ``lines`` that is determined; returns
    slit -> "" for those, or slit -> why not.
    """
    out: dict[int, str] = {}
    if not lines:
        return out
    idx = np.flatnonzero(ok)
    if len(idx) < MIN_AXIS_SLITS:
        why = (
            f"the common axis is fitted from only {len(idx)} slit(s) (>= {MIN_AXIS_SLITS} "
            "with planes of their own give it the plane through the axis)"
        )
        return dict.fromkeys(lines, why)
    # angle of each plane about the axis, measured from the reference normal
    b1 = ref - (ref @ axis_dir) * axis_dir
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(axis_dir, b1)

    def cross_section(j: int) -> F64:
        q = X[order[starts[j] : starts[j + 1]]] - axis_point
        return np.stack([q @ b1, q @ b2], axis=1)  # (n, 2) mm, perpendicular to the axis

    phi = np.arctan2(planes[idx, :3] @ b2, planes[idx, :3] @ b1)
    lever = np.array([math.sqrt(np.mean(np.sum(cross_section(j) ** 2, axis=1))) for j in idx])
    ref_lever = float(np.median(lever))
    deg = min(3, len(idx) - 1)
    t = (idx - idx.mean()) / max(float(np.ptp(idx)), 1.0)
    coef = np.polyfit(t, phi, deg)
    for j in lines:
        c = cross_section(j)
        wj = wt[order[starts[j] : starts[j + 1]]]
        w, V = np.linalg.eigh((c * wj[:, None]).T @ c / max(float(wj.sum()), 1e-300))
        lev = math.sqrt(max(float(w[1]), 0.0))
        if lev < MIN_AXIS_LEVER * ref_lever:
            out[j] = (
                f"its points pass within {lev:.3g} mm (RMS) of the common axis (the other slits' "
                f"points: {ref_lever:.3g} mm): the plane through the axis is undetermined"
            )
            continue
        n2 = V[:, 0]
        n = n2[0] * b1 + n2[1] * b2
        if n @ ref < 0:
            n = -n
        phi_j = math.atan2(n @ b2, n @ b1)
        tj = (j - idx.mean()) / max(float(np.ptp(idx)), 1.0)
        pred = float(np.polyval(coef, tj))
        spacing = abs(float(np.polyval(np.polyder(coef), tj))) / max(float(np.ptp(idx)), 1.0)
        dev = abs(phi_j - pred) / max(spacing, 1e-12)
        if not dev <= MAX_AXIS_ANGLE_DEVIATION:
            out[j] = (
                f"the plane through the common axis and its points is {dev:.2g} slit spacings "
                f"from where the other slits' planes put slit {j} (mislabelled points?)"
            )
            continue
        planes[j, :3] = n
        planes[j, 3] = -(n @ axis_point)
        out[j] = ""
    return out


def _fit_common_axis(X: F64, s: NDArray[np.intp], planes: F64, ok: NDArray[np.bool_], wt: F64):
    idx = np.flatnonzero(ok)
    a0, u0 = common_line(planes[idx])
    e1, e2 = orthonormal_basis(u0)
    frame0 = np.stack([e1, e2, u0])  # rows
    phi0 = np.arctan2(planes[idx, :3] @ e2, planes[idx, :3] @ e1)
    pos = np.full(len(planes), -1)
    pos[idx] = np.arange(len(idx))
    use = ok[s]
    Xu, col, sw = X[use], pos[s[use]], np.sqrt(wt[use])
    scale = max(float(np.abs(Xu - a0).max()), 1.0)

    def unpack(q: F64):
        R = rotation_from_rvec(q[0] * e1 + q[1] * e2)
        f = frame0 @ R.T  # rotated basis vectors as rows
        a = a0 + scale * (q[2] * e1 + q[3] * e2)
        n = np.cos(q[4:, None]) * f[0] + np.sin(q[4:, None]) * f[1]
        return a, f[2], n

    def fun(q: F64) -> F64:
        a, _, n = unpack(q)
        return sw * np.einsum("ij,ij->i", Xu - a, n[col])

    m = len(idx)
    J = lil_matrix((len(Xu), 4 + m), dtype=int)
    J[:, :4] = 1
    J[np.arange(len(Xu)), 4 + col] = 1
    q0 = np.concatenate([np.zeros(4), phi0])
    sol = least_squares(fun, q0, jac_sparsity=J, method="trf", x_scale="jac", xtol=1e-12)
    a, u, n = unpack(sol.x)
    out = np.full_like(planes, np.nan)
    out[idx, :3] = n
    out[idx, 3] = -(n @ a)
    # closest point of the axis to the origin
    a = a - (a @ u) * u
    return out, a, u


def slit_plane_rms(planes: ArrayLike, points: ArrayLike, slits: ArrayLike) -> tuple[F64, F64]:
    """How well a set of slit planes explains points on the slits.

    Use it to measure a model's systematic error: with noise-free points on the true slit planes
    (e.g. a diffraction grating whose planes are not equally spaced in the projective sense),
    the per-slit RMS of the paper's 2x4 model (:meth:`ProjectorMatrix.planes`) is its systematic
    plane error, while per-slit planes (:func:`fit_slit_planes`) leave only the noise.

    Parameters
    ----------
    planes : (K, 4) float64, unit normals, n.X + d = 0
    points : (N, 3) float64, mm
    slits : (N,) int, 0..K-1

    Returns
    -------
    rms_mm : (K,) float64, mm, RMS distance of each slit's points to its plane (NaN: no points
        or no plane)
    distances : (N,) float64, mm, signed distance of each point to its slit's plane
    """
    pl = as_points(planes, 4, "planes")
    X = as_points(points, 3, "points")
    s = slit_indices(slits, len(pl))
    if len(s) != len(X):
        raise CalibrationError(f"points has {len(X)} rows but slits has {len(s)} values")
    d = np.einsum("ij,ij->i", X, pl[s, :3]) + pl[s, 3]
    good = np.isfinite(d)
    cnt = np.bincount(s[good], minlength=len(pl))
    ssq = np.bincount(s[good], weights=d[good] ** 2, minlength=len(pl))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(cnt > 0, np.sqrt(ssq / np.maximum(cnt, 1)), np.nan)
    return r, d


def _axis_angles(sp: SlitPlanes, idx: NDArray[np.intp]) -> tuple[F64, F64, F64]:
    """Angles (rad) about the common axis of the planes ``idx``, and the frame (b1, b2) they are
    measured in (unit vectors normal to the axis; b1 along the middle plane's normal)."""
    u = sp.axis_direction / np.linalg.norm(sp.axis_direction)
    ref = sp.planes[idx[len(idx) // 2], :3]
    b1 = ref - (ref @ u) * u
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(u, b1)
    n = sp.planes[idx, :3] * np.sign(sp.planes[idx, :3] @ b1)[:, None]
    return np.arctan2(n @ b2, n @ b1), b1, b2


def axis_order_deviation(sp: SlitPlanes) -> F64:
    """How far each slit's plane turns from where the other slits' planes put it, in spacings.

    A grating's slit planes pass through one axis and turn about it monotonically with the slit
    number (``sin(theta_m) = m lambda / pitch``): their angles about the axis lie on a smooth
    curve of the slit number. For each slit, a cubic through the other slits' angles predicts
    its angle; the deviation is the difference in local slit spacings (the curve's slope). A
    mislabelled slit or a plane pulled by wrong points shows up as a deviation of a large
    fraction of a spacing, or as a plane out of order.

    Parameters
    ----------
    sp : SlitPlanes with a common axis

    Returns
    -------
    (K,) float64, slit spacings, signed (NaN: no plane, no axis, or fewer than 5 planes)
    """
    out = np.full(sp.num_slits, np.nan)
    idx = np.flatnonzero(sp.valid)
    if sp.axis_direction is None or len(idx) < 5:
        return out
    phi, _, _ = _axis_angles(sp, idx)
    t = (idx - idx.mean()) / max(float(np.ptp(idx)), 1.0)
    for i, j in enumerate(idx):
        others = np.arange(len(idx)) != i
        coef = np.polyfit(t[others], phi[others], 3)
        slope = float(np.polyval(np.polyder(coef), t[i])) / max(float(np.ptp(idx)), 1.0)
        out[j] = (phi[i] - float(np.polyval(coef, t[i]))) / max(abs(slope), 1e-12)
    return out


def planes_between(sp: SlitPlanes) -> tuple[SlitPlanes, tuple[int, ...]]:
    """Planes for slits without one between slits with planes, from the common-axis model.

    The angle about the axis of such a slit is read off a cubic through the other planes'
    angles against the slit number (see :func:`axis_order_deviation`); its plane is the plane
    through the axis at that angle. Slits beyond the first or last plane are not extrapolated.

    Returns
    -------
    planes : SlitPlanes with those slits filled in (their ``rms_mm`` stays NaN: no points)
    filled : the slits filled in
    """
    idx = np.flatnonzero(sp.valid)
    if sp.axis_direction is None or sp.axis_point is None or len(idx) < 5:
        return sp, ()
    gaps = [j for j in range(int(idx[0]) + 1, int(idx[-1])) if not sp.valid[j]]
    if not gaps:
        return sp, ()
    phi, b1, b2 = _axis_angles(sp, idx)
    coef = np.polyfit(idx.astype(float), phi, min(3, len(idx) - 1))
    planes = sp.planes.copy()
    for j in gaps:
        phi = float(np.polyval(coef, float(j)))
        nj = math.cos(phi) * b1 + math.sin(phi) * b2
        planes[j] = [*nj, -(nj @ sp.axis_point)]
    keep = tuple((j, why) for j, why in sp.excluded if j not in gaps)
    return replace(sp, planes=planes, excluded=keep), tuple(gaps)
