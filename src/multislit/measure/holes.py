"""Hole measurement on a flat plate (the paper's section 6.2.3 and Table 1), made robust.

The paper measures the diameters of holes (100, 50 and 30 mm at about 0.9 m) in a flat board
from the points where the projected slits break at the hole's edge, by circle estimation. The
steps here:

1. :func:`fit_plane_robust` -- the plate's plane from the measured points (RANSAC / least
   median, then a total least squares refit on the inliers).
2. :func:`hole_edges_from_profiles` -- per slit, the points where the slit's stripe leaves the
   plate and comes back (the two edges of each gap), placed at a sub-sample position.
3. :func:`measure_holes` -- edge points projected into the plane (:func:`plane_basis`,
   :func:`project_to_plane`), grouped per hole, one robust circle fit (:func:`fit_circle`) per
   hole; holes crossed by too few slits or seen over too short an arc are reported as not
   measurable instead of being fitted.

Units: mm, target frame. Planes are (4,) ``[nx, ny, nz, d]`` with ``n . X + d = 0``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist
from scipy.stats import norm
from scipy.stats import t as student_t

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry import as_points

F64 = NDArray[np.float64]

__all__ = [
    "CircleFit",
    "EdgePoints",
    "HoleResult",
    "fit_circle",
    "fit_plane_robust",
    "from_plane_coords",
    "hole_edges_from_profiles",
    "measure_holes",
    "plane_basis",
    "project_to_plane",
]

_MAD = 1.4826  # MAD -> standard deviation for Gaussian noise


def _plane(plane: ArrayLike, name: str = "plane") -> F64:
    p = np.asarray(plane, dtype=np.float64)
    if p.shape != (4,) or not np.all(np.isfinite(p)):
        raise MeasurementError(f"{name} must be a finite (4,) [nx, ny, nz, d], got {p.shape}")
    n = np.linalg.norm(p[:3])
    if n < 1e-12:
        raise MeasurementError(f"{name} has a zero normal")
    return p / n


def _finite_points(a: ArrayLike, dim: int, name: str) -> F64:
    try:
        p = as_points(a, dim, name)
    except MeasurementError:
        raise
    except MultislitError as exc:  # as_points raises MultislitError; make it a MeasurementError
        raise MeasurementError(str(exc)) from exc
    if not np.all(np.isfinite(p)):
        raise MeasurementError(f"{name} must be finite (drop NaN/inf rows first)")
    return p


# --------------------------------------------------------------------------- planes
def _tls_plane(p: F64) -> F64:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    return np.append(n, -n @ c)


def fit_plane_robust(
    points: ArrayLike,
    threshold_mm: float | None = None,
    rng: np.random.Generator | None = None,
    *,
    iterations: int = 500,
    max_score_points: int = 5000,
) -> tuple[F64, NDArray[np.bool_]]:
    """Robust plane through points with outliers.

    Candidate planes through random point triples are scored on (a subsample of at most
    ``max_score_points``) points: by inlier count within ``threshold_mm`` (RANSAC) when a
    threshold is given, otherwise by the median absolute distance (least median of squares).
    The best candidate's inliers are refitted by total least squares, and inliers / refit are
    iterated until stable. Without ``threshold_mm`` the threshold is 3 sigma with sigma the
    inliers' noise estimated from their median absolute distance (MAD).

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame, N >= 3, finite
    threshold_mm : float, optional
        Inlier distance to the plane, mm. Default: from the data's noise (see above).
    rng : numpy.random.Generator, optional
        Source of the random samples. Default: ``np.random.default_rng(0)`` (reproducible).
    iterations : int
        Number of random triples tried (vectorised).
    max_score_points : int
        Candidates are scored on at most this many randomly chosen points.

    Returns
    -------
    plane : (4,) float64
        Unit normal and offset, ``n . X + d = 0``; the normal's sign is arbitrary.
    inliers : (N,) bool
        Points within the threshold of the final plane.

    Raises
    ------
    MeasurementError
        Fewer than 3 points, non-finite points, a bad threshold, or all points collinear.
    """
    p = _finite_points(points, 3, "points")
    n = len(p)
    if n < 3:
        raise MeasurementError(f"fit_plane_robust needs >= 3 points, got {n}")
    if threshold_mm is not None and not (np.isfinite(threshold_mm) and threshold_mm > 0):
        raise MeasurementError(f"threshold_mm must be positive, got {threshold_mm}")
    if iterations < 1:
        raise MeasurementError(f"iterations must be >= 1, got {iterations}")
    rng = np.random.default_rng(0) if rng is None else rng
    centre = p.mean(axis=0)
    q = p - centre  # centred: better conditioning of d
    extent = float(np.max(np.linalg.norm(q, axis=1)))
    eps = 1e-9 * extent + 1e-12
    _, s, _ = np.linalg.svd(q, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise MeasurementError("fit_plane_robust: the points are collinear, no unique plane")

    # candidate planes from random triples
    tri = rng.integers(0, n, size=(iterations, 3))  # repeated indices are degenerate, dropped
    a, b, c = q[tri[:, 0]], q[tri[:, 1]], q[tri[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-9 * (np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - a, axis=1) + 1e-300)
    if not np.any(ok):
        raise MeasurementError("fit_plane_robust: no non-degenerate sample (points collinear?)")
    normals = normals[ok] / norm[ok, None]
    offsets = -np.einsum("ij,ij->i", normals, a[ok])
    sub = q if n <= max_score_points else q[rng.choice(n, max_score_points, replace=False)]
    chunk = max(1, 4_000_000 // len(sub))
    scores = np.empty(len(normals))
    for i in range(0, len(normals), chunk):  # loop over candidate blocks, not points
        dist = np.abs(sub @ normals[i : i + chunk].T + offsets[i : i + chunk])
        if threshold_mm is None:
            scores[i : i + chunk] = np.median(dist, axis=0)
        else:
            scores[i : i + chunk] = -np.count_nonzero(dist <= threshold_mm, axis=0)
    best = int(np.argmin(scores))
    plane = np.append(normals[best], offsets[best])

    inliers = np.zeros(n, dtype=bool)
    for _ in range(20):
        r = np.abs(q @ plane[:3] + plane[3])
        if threshold_mm is None:
            ref = r[inliers] if np.count_nonzero(inliers) >= 3 else r
            # median |r| of the current inliers; the first pass uses all points (LMedS scale)
            thr = max(3.0 * _MAD * float(np.median(ref)), eps)
        else:
            thr = threshold_mm
        new = r <= thr
        if np.count_nonzero(new) < 3:
            raise MeasurementError("fit_plane_robust: fewer than 3 inliers; raise threshold_mm")
        if np.array_equal(new, inliers):
            break
        inliers = new
        plane = _tls_plane(q[inliers])
    plane = plane.copy()
    plane[3] -= plane[:3] @ centre  # back to the original frame
    return plane, inliers


def plane_basis(plane: ArrayLike) -> tuple[F64, F64, F64]:
    """Orthonormal 2D frame in a plane.

    Parameters
    ----------
    plane : (4,) float64, ``n . X + d = 0`` (any normal length)

    Returns
    -------
    origin : (3,) float64, mm
        The foot of the perpendicular from the frame origin onto the plane.
    e1, e2 : (3,) float64, unit
        In-plane axes; (e1, e2, n) is right-handed. e1 is the world x axis projected into the
        plane (the y axis if the normal is within ~25 deg of x).
    """
    p = _plane(plane)
    n = p[:3]
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return -p[3] * n, e1, e2


def project_to_plane(points: ArrayLike, plane: ArrayLike) -> F64:
    """3D points -> 2D coordinates in :func:`plane_basis` (orthogonal projection).

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame
    plane : (4,) float64

    Returns
    -------
    coords : (N, 2) float64, mm, along (e1, e2) from the basis origin
    """
    p = as_points(points, 3, "points")
    origin, e1, e2 = plane_basis(plane)
    d = p - origin
    return np.stack([d @ e1, d @ e2], axis=1)


def from_plane_coords(coords: ArrayLike, plane: ArrayLike) -> F64:
    """2D coordinates in :func:`plane_basis` -> 3D points on the plane.

    Parameters
    ----------
    coords : (N, 2) float64, mm
    plane : (4,) float64

    Returns
    -------
    points : (N, 3) float64, mm, target frame
    """
    c = as_points(coords, 2, "coords")
    origin, e1, e2 = plane_basis(plane)
    return origin + c[:, :1] * e1 + c[:, 1:] * e2


# --------------------------------------------------------------------------- circles
@dataclass(frozen=True, eq=False)
class CircleFit:
    """A circle fitted to 2D points.

    Attributes
    ----------
    centre : (2,) float64, mm
    radius : float, mm
    rms : float, mm
        RMS of the inliers' distances to the circle.
    n_points : int
        Points given.
    n_inliers : int
        Points used in the final fit.
    inliers : (n_points,) bool
    radius_std : float, mm
        Standard error of the radius from the fit's covariance (NaN with 3 inliers).
    arc_deg : float, deg
        Angle the inliers cover around the centre: 360 minus the largest angular gap.
    """

    centre: F64
    radius: float
    rms: float
    n_points: int
    n_inliers: int
    inliers: NDArray[np.bool_] = field(repr=False)
    radius_std: float = float("nan")
    arc_deg: float = float("nan")

    @property
    def diameter(self) -> float:
        """Diameter, mm."""
        return 2.0 * self.radius

    def to_dict(self) -> dict[str, Any]:
        return {
            "centre": [float(x) for x in self.centre],
            "radius": float(self.radius),
            "diameter": float(self.diameter),
            "rms": float(self.rms),
            "n_points": int(self.n_points),
            "n_inliers": int(self.n_inliers),
            "radius_std": _json_float(self.radius_std),
            "arc_deg": _json_float(self.arc_deg),
        }


def _json_float(x: float | None) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def _kasa(p: F64) -> tuple[F64, float]:
    """Algebraic (Kasa) circle on centred points: x^2 + y^2 = 2 a x + 2 b y + c."""
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, (p * p).sum(axis=1), rcond=None)
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


def _geometric(p: F64, centre: F64, radius: float) -> tuple[F64, float, float]:
    """Geometric least squares: minimise sum (|p - c| - r)^2. Returns centre, radius, r std."""

    def fun(x: F64) -> F64:
        return np.hypot(p[:, 0] - x[0], p[:, 1] - x[1]) - x[2]

    def jac(x: F64) -> F64:
        d = p - x[:2]
        rho = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-300)
        return np.column_stack([-d[:, 0] / rho, -d[:, 1] / rho, -np.ones(len(p))])

    res = least_squares(fun, np.array([*centre, radius]), jac=jac, method="lm", xtol=1e-14)
    x = res.x
    dof = len(p) - 3
    r_std = float("nan")
    if dof > 0:
        s2 = float(res.fun @ res.fun) / dof
        try:
            cov = np.linalg.inv(res.jac.T @ res.jac) * s2
            r_std = float(np.sqrt(max(cov[2, 2], 0.0)))
        except np.linalg.LinAlgError:
            pass
    return x[:2], abs(float(x[2])), r_std


def _lmeds_circle(
    p: F64, rng: np.random.Generator, max_samples: int = 2000
) -> tuple[F64, float, NDArray[np.int64]]:
    """Least-median circle from point triples (all triples if few, else random ones).

    Returns the centre, the radius and the indices of the triple through which it passes.
    """
    n = len(p)
    total = n * (n - 1) * (n - 2) // 6
    if total <= max_samples:
        tri = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64)
    else:
        tri = rng.integers(0, n, size=(max_samples, 3))  # repeats are degenerate, dropped
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    # circumcentre of each triple
    ba, ca = b - a, c - a
    det = 2 * (ba[:, 0] * ca[:, 1] - ba[:, 1] * ca[:, 0])
    bb, cc = (ba * ba).sum(1), (ca * ca).sum(1)
    scale = np.maximum(bb, cc)
    ok = np.abs(det) > 1e-9 * scale
    if not np.any(ok):
        raise MeasurementError("fit_circle: the points are collinear, no circle")
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (ca[:, 1] * bb - ba[:, 1] * cc) / det
        uy = (ba[:, 0] * cc - ca[:, 0] * bb) / det
    centres = a[ok] + np.column_stack([ux[ok], uy[ok]])
    radii = np.hypot(ux[ok], uy[ok])
    chunk = max(1, 2_000_000 // n)
    med = np.empty(len(radii))
    for i in range(0, len(radii), chunk):  # loop over candidate blocks, not points
        cc_ = centres[i : i + chunk]
        d = np.hypot(p[:, None, 0] - cc_[None, :, 0], p[:, None, 1] - cc_[None, :, 1])
        med[i : i + chunk] = np.median(np.abs(d - radii[None, i : i + chunk]), axis=0)
    best = int(np.argmin(med))
    return centres[best], float(radii[best]), tri[ok][best]


def _arc_deg(p: F64, centre: F64) -> float:
    if len(p) < 2:
        return 0.0
    ang = np.sort(np.arctan2(p[:, 1] - centre[1], p[:, 0] - centre[0]))
    gaps = np.diff(np.append(ang, ang[0] + 2 * np.pi))
    return float(np.degrees(2 * np.pi - gaps.max()))


def fit_circle(
    points2d: ArrayLike,
    robust: bool = True,
    *,
    k: float = 3.5,
    rng: np.random.Generator | None = None,
) -> CircleFit:
    """Fit a circle to 2D points.

    Non-robust: algebraic (Kasa) start, then geometric least squares on the distances to the
    circle (``scipy.optimize.least_squares``). Robust (default, with >= 5 points): a least
    median of squares start from point triples; points farther from that circle than ``k``
    sigma (sigma from the median residual of the points not in the triple) are set aside;
    then the geometric fit on the inliers and the inlier test are iterated until the inlier set
    is stable, with sigma the inliers' RMS residual (n - 3 degrees of freedom) and the
    threshold the Student t quantile with the same tail probability as ``k`` normal sigmas (so
    that few points do not lose good points to an uncertain sigma).

    Parameters
    ----------
    points2d : (N, 2) float64, mm, N >= 3, finite
    robust : bool
        Reject outliers (see above).
    k : float
        Rejection threshold in robust sigmas.
    rng : numpy.random.Generator, optional
        For the random triples when there are many points. Default: seeded (reproducible).

    Returns
    -------
    CircleFit

    Raises
    ------
    MeasurementError
        Fewer than 3 points, non-finite points, or collinear points.
    """
    p = _finite_points(points2d, 2, "points2d")
    n = len(p)
    if n < 3:
        raise MeasurementError(f"fit_circle needs >= 3 points, got {n}")
    if not (np.isfinite(k) and k > 0):
        raise MeasurementError(f"k must be positive, got {k}")
    rng = np.random.default_rng(0) if rng is None else rng
    mean = p.mean(axis=0)
    q = p - mean
    _, s, _ = np.linalg.svd(q, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise MeasurementError("fit_circle: the points are collinear, no circle")
    scale = float(np.max(np.abs(q)))
    eps = 1e-9 * scale + 1e-12

    inliers = np.ones(n, dtype=bool)
    if robust and n >= 5:
        centre, radius, triple = _lmeds_circle(q, rng)
        r = np.abs(np.hypot(q[:, 0] - centre[0], q[:, 1] - centre[1]) - radius)
        # noise scale from the points the circle was not drawn through (theirs are 0)
        others = np.ones(n, dtype=bool)
        others[triple] = False
        s0 = _MAD * float(np.median(r[others]))
        inliers = r <= max(k * s0, eps)
        tail = float(norm.sf(k))
        if np.count_nonzero(inliers) < 4:
            inliers = np.ones(n, dtype=bool)
        for _ in range(20):
            centre, radius, _ = _geometric(q[inliers], centre, radius)
            r = np.abs(np.hypot(q[:, 0] - centre[0], q[:, 1] - centre[1]) - radius)
            m = int(np.count_nonzero(inliers))
            # unbiased noise estimate of the inliers' 3-parameter fit; with few points it is
            # itself uncertain, so the threshold is the Student t quantile of k's tail
            dof = max(m - 3, 1)
            sigma = float(np.sqrt(np.sum(r[inliers] ** 2) / dof))
            new = r <= max(float(student_t.isf(tail, dof)) * sigma, eps)
            if np.count_nonzero(new) < 4 or np.array_equal(new, inliers):
                break
            inliers = new
    else:
        centre, radius = _kasa(q)
    centre, radius, r_std = _geometric(q[inliers], centre, radius)
    r_in = np.hypot(q[inliers, 0] - centre[0], q[inliers, 1] - centre[1]) - radius
    return CircleFit(
        centre=centre + mean,
        radius=radius,
        rms=float(np.sqrt(np.mean(r_in**2))),
        n_points=n,
        n_inliers=int(np.count_nonzero(inliers)),
        inliers=inliers,
        radius_std=r_std,
        arc_deg=_arc_deg(q[inliers], centre),
    )


# --------------------------------------------------------------------------- holes
@dataclass(frozen=True, eq=False)
class HoleResult:
    """One hole found among the edge points.

    Attributes
    ----------
    centre : (3,) float64, mm, target frame
        Fitted centre on the plane; for a hole that is not measurable, the centroid of its
        edge points (a location only).
    diameter : float, mm
        NaN when not measurable.
    n_points : int
        Edge points grouped to this hole.
    n_inliers : int
        Edge points used by the circle fit (0 when not fitted).
    n_slits : int or None
        Distinct slits (labels >= 0) among the edge points; None without slit labels.
    rms : float, mm
        Fit residual RMS (NaN when not fitted).
    radius_std : float, mm
        Standard error of the radius from the fit (NaN when not fitted).
    arc_deg : float, deg
        Angle covered by the fitted inliers around the centre (NaN when not fitted).
    measurable : bool
    reason : str
        Why the hole is not measurable ('' when it is).
    indices : (n_points,) int
        Rows of ``edge_points`` in this hole.
    """

    centre: F64
    diameter: float
    n_points: int
    n_inliers: int
    n_slits: int | None
    rms: float
    radius_std: float
    arc_deg: float
    measurable: bool
    reason: str
    indices: NDArray[np.int64] = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {
            "centre": [float(x) for x in self.centre],
            "diameter": _json_float(self.diameter),
            "n_points": int(self.n_points),
            "n_inliers": int(self.n_inliers),
            "n_slits": None if self.n_slits is None else int(self.n_slits),
            "rms": _json_float(self.rms),
            "radius_std": _json_float(self.radius_std),
            "arc_deg": _json_float(self.arc_deg),
            "measurable": bool(self.measurable),
            "reason": self.reason,
        }


def _labels(
    a: ArrayLike | None, n: int, name: str, like: str = "edge_points"
) -> NDArray[np.int64] | None:
    if a is None:
        return None
    arr = np.asarray(a)
    if arr.shape != (n,):
        raise MeasurementError(f"{name} must have shape ({n},) like {like}, got {arr.shape}")
    if arr.dtype.kind not in "iu" and not (
        arr.dtype.kind == "f" and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr))
    ):
        raise MeasurementError(f"{name} must hold integer labels, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def _group(q: F64, link: float, gap: NDArray[np.int64] | None) -> tuple[int, NDArray[np.int64]]:
    n = len(q)
    pairs = cKDTree(q).query_pairs(link, output_type="ndarray")
    rows, cols = [pairs[:, 0]], [pairs[:, 1]]
    if gap is not None:
        valid = np.flatnonzero(gap >= 0)
        order = valid[np.argsort(gap[valid], kind="stable")]
        same = gap[order[1:]] == gap[order[:-1]]
        rows.append(order[:-1][same])
        cols.append(order[1:][same])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    return connected_components(graph, directed=False)


def _merge_arcs(q: F64, labels: NDArray[np.int64], link: float, tol: float) -> NDArray[np.int64]:
    """Greedily merge groups whose union lies on one circle (the two arcs of a hole)."""
    labels = labels.copy()
    while True:
        ids = np.unique(labels)
        if len(ids) < 2:
            return labels
        cent = np.array([q[labels == i].mean(axis=0) for i in ids])
        ext = np.array(
            [np.max(np.linalg.norm(q[labels == i] - cent[j], axis=1)) for j, i in enumerate(ids)]
        )
        best: tuple[float, int, int] | None = None
        for a, b in itertools.combinations(range(len(ids)), 2):  # loop over groups
            if np.linalg.norm(cent[a] - cent[b]) > ext[a] + ext[b] + link:
                continue
            pts = q[(labels == ids[a]) | (labels == ids[b])]
            if len(pts) < 4:
                continue
            try:
                fit = fit_circle(pts, robust=False)
            except MeasurementError:
                continue
            span = float(pdist(pts).max())
            if fit.rms > tol or fit.diameter > 1.2 * span + link:
                continue
            if best is None or fit.rms < best[0]:
                best = (fit.rms, a, b)
        if best is None:
            return labels
        labels[labels == ids[best[2]]] = ids[best[1]]


def measure_holes(
    edge_points: ArrayLike,
    plane: ArrayLike,
    min_points: int = 6,
    min_slits: int = 2,
    slit: ArrayLike | None = None,
    *,
    gap: ArrayLike | None = None,
    min_arc_deg: float = 180.0,
    link_distance: float | None = None,
    merge_arcs: bool = True,
    merge_tol_mm: float = 0.5,
    robust: bool = True,
) -> list[HoleResult]:
    """Group hole-edge points per hole and measure each hole by a circle fit in the plane.

    The points are projected into the plane (:func:`project_to_plane`) and grouped by single
    linkage: points closer than ``link_distance`` are linked, and so are the two edges of one
    gap (same ``gap`` label, e.g. from :func:`hole_edges_from_profiles`). Without gap labels,
    the two arcs of a hole (above and below the slit ends) may fall apart; with ``merge_arcs``
    groups whose union lies on one circle (fit RMS <= ``merge_tol_mm``) are merged. Each group
    is then measured unless

    * it has fewer than ``min_slits`` distinct slits (when ``slit`` is given),
    * it has fewer than ``min_points`` edge points, or
    * the fitted inliers cover less than ``min_arc_deg`` of the circle (the radius is then
      ill-determined; 180 deg means the slits must bracket the hole's centre),

    in which case it is reported with ``measurable=False``, the reason, and no diameter.

    Parameters
    ----------
    edge_points : (N, 3) float64, mm, target frame
        Points on hole edges (on or near the plane).
    plane : (4,) float64
        The plate's plane, ``n . X + d = 0``.
    min_points : int
        Fewest edge points for a fit (>= 3).
    min_slits : int
        Fewest distinct slits crossing a hole (checked only when ``slit`` is given).
    slit : (N,) int, optional
        Slit number of each edge point (negative = unidentified, not counted).
    gap : (N,) int, optional
        Gap id of each edge point: the edges of one gap share it (negative = none).
    min_arc_deg : float, deg
        Smallest arc the fitted edge points must cover.
    link_distance : float, mm, optional
        Single-linkage distance. Default: 2.5 x the median nearest-neighbour distance (about
        the slit spacing and the along-slit spacing of edges).
    merge_arcs : bool
        Merge groups lying on one circle (see above).
    merge_tol_mm : float, mm
        Largest circle-fit RMS for merging.
    robust : bool
        Passed to :func:`fit_circle`.

    Returns
    -------
    list of HoleResult
        One per group, ordered along the plane's e1 axis then e2. Empty for no points.

    Raises
    ------
    MeasurementError
        Bad shapes, non-finite values or parameters.
    """
    p = _finite_points(edge_points, 3, "edge_points")
    pl = _plane(plane)
    n = len(p)
    if min_points < 3:
        raise MeasurementError(f"min_points must be >= 3, got {min_points}")
    if min_slits < 1:
        raise MeasurementError(f"min_slits must be >= 1, got {min_slits}")
    if not (0 <= min_arc_deg <= 360):
        raise MeasurementError(f"min_arc_deg must be in [0, 360], got {min_arc_deg}")
    sl = _labels(slit, n, "slit")
    gp = _labels(gap, n, "gap")
    if n == 0:
        return []
    q = project_to_plane(p, pl)
    if link_distance is None:
        if n >= 2:
            dnn = cKDTree(q).query(q, k=2)[0][:, 1]
            link_distance = 2.5 * float(np.median(dnn))
        else:
            link_distance = 0.0
        link_distance = max(link_distance, 1e-9)
    elif not (np.isfinite(link_distance) and link_distance > 0):
        raise MeasurementError(f"link_distance must be positive, got {link_distance}")

    _, labels = _group(q, link_distance, gp)
    if merge_arcs:
        labels = _merge_arcs(q, labels.astype(np.int64), link_distance, merge_tol_mm)

    results = []
    for lab in np.unique(labels):  # loop over holes
        idx = np.flatnonzero(labels == lab)
        g = q[idx]
        n_slits = None if sl is None else int(np.unique(sl[idx][sl[idx] >= 0]).size)
        reason = ""
        if n_slits is not None and n_slits < min_slits:
            reason = f"crossed by {n_slits} slit(s), need >= {min_slits}"
        elif len(idx) < min_points:
            reason = f"{len(idx)} edge point(s), need >= {min_points}"
        fit = None
        if not reason:
            try:
                fit = fit_circle(g, robust=robust)
            except MeasurementError as exc:
                reason = str(exc)
        if fit is not None and fit.n_inliers < min_points:
            reason = f"{fit.n_inliers} edge point(s) after outlier rejection, need >= {min_points}"
        elif fit is not None and fit.arc_deg < min_arc_deg:
            reason = (
                f"edge points cover {fit.arc_deg:.0f} deg of the circle, need >= "
                f"{min_arc_deg:.0f} (radius ill-determined)"
            )
        nan = float("nan")
        if reason:
            centre2 = g.mean(axis=0)
            res = HoleResult(
                centre=from_plane_coords(centre2, pl)[0],
                diameter=nan,
                n_points=len(idx),
                n_inliers=0,
                n_slits=n_slits,
                rms=nan,
                radius_std=nan,
                arc_deg=nan,
                measurable=False,
                reason=reason,
                indices=idx,
            )
        else:
            assert fit is not None
            res = HoleResult(
                centre=from_plane_coords(fit.centre, pl)[0],
                diameter=fit.diameter,
                n_points=len(idx),
                n_inliers=fit.n_inliers,
                n_slits=n_slits,
                rms=fit.rms,
                radius_std=fit.radius_std,
                arc_deg=fit.arc_deg,
                measurable=True,
                reason="",
                indices=idx,
            )
        results.append((tuple(project_to_plane(res.centre, pl)[0]), res))
    results.sort(key=lambda t: t[0])
    return [r for _, r in results]


# --------------------------------------------------------------------------- edges
@dataclass(frozen=True, eq=False)
class EdgePoints:
    """Points where slits leave the plate at a gap and where they come back.

    Attributes
    ----------
    points : (M, 3) float64, mm, target frame
        Edge positions (on the plane).
    slit : (M,) int
        Slit of each edge.
    gap : (M,) int
        Gap id: the two edges of one gap share it (ids 0..M/2-1).
    side : (M,) int
        -1: the edge before the gap (lower t), +1: the edge after it.
    t : (M,) float64
        Edge position in the profile parameter (sub-sample).
    source : (M,) int
        Row of the input of the last on-plane sample before the gap.
    """

    points: F64
    slit: NDArray[np.int64]
    gap: NDArray[np.int64]
    side: NDArray[np.int64]
    t: F64
    source: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.points)


EdgeOffset = float | ArrayLike | Callable[[NDArray[np.int64], NDArray[np.int64]], ArrayLike]


def hole_edges_from_profiles(
    points: ArrayLike,
    slit: ArrayLike,
    t: ArrayLike,
    plane: ArrayLike,
    *,
    max_plane_distance: float | None = None,
    min_gap: float | None = None,
    edge_offset: EdgeOffset = 0.5,
) -> EdgePoints:
    """Find where each slit's stripe leaves the plate (a hole) and comes back.

    Per slit the samples are ordered by ``t``. Samples within ``max_plane_distance`` of the
    plane are on the plate. Two consecutive on-plate samples of one slit bound a gap when
    off-plate samples lie between them (the stripe jumped behind the plate or onto a wall) or
    their ``t`` differ by more than ``min_gap`` (the stripe vanished). Only gaps with plate on
    both sides are returned (the slit's two ends are not hole edges).

    Each edge is placed beyond its last on-plate sample, towards the gap, by ``f`` sample
    steps along the plate's local direction: ``edge = p_last + f * dt * g`` where ``g`` is the
    displacement per unit ``t`` between the last two on-plate samples and ``dt`` the sampling
    step (the step to the next sample, at most the typical step). ``f = 0`` returns the last
    on-plate samples; the default ``f = 0.5`` (half a step) removes the average inward bias
    of the last sample; a sub-pixel edge locator can supply the exact fractions.

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame
        Measured points of all slits.
    slit : (N,) int
        Slit of each point.
    t : (N,) float64
        Position of each point along its slit (image v in px, or arc length), increasing
        along the stripe; sampled at a roughly regular step.
    plane : (4,) float64
        The plate's plane.
    max_plane_distance : float, mm, optional
        On-plate tolerance. Default: 5 sigma of the distances (sigma from their MAD),
        at least 1e-6 mm.
    min_gap : float, optional
        Smallest ``t`` difference between consecutive on-plate samples that counts as a gap
        when nothing off-plate lies between them. Default: 1.5 x the typical step.
    edge_offset : float, (N,) array, or callable
        The fraction ``f`` in [0, 1]: one value for all edges; or per input point (the value
        at each edge's last on-plate sample is used); or ``f(source, side) -> (M,)`` called
        with the rows of the last on-plate samples and the sides (-1 / +1).

    Returns
    -------
    EdgePoints

    Raises
    ------
    MeasurementError
        Bad shapes, non-finite values, or ``edge_offset`` outside [0, 1].
    """
    p = _finite_points(points, 3, "points")
    n = len(p)
    pl = _plane(plane)
    sl = _labels(slit, n, "slit", like="points")
    assert sl is not None
    tt = np.asarray(t, dtype=np.float64)
    if tt.shape != (n,) or not np.all(np.isfinite(tt)):
        raise MeasurementError(f"t must be a finite ({n},) array like points, got {tt.shape}")
    empty = EdgePoints(
        np.zeros((0, 3)),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0),
        np.zeros(0, np.int64),
    )
    if n < 2:
        return empty

    order = np.lexsort((tt, sl))
    ps, ss, ts = p[order], sl[order], tt[order]
    dist = ps @ pl[:3] + pl[3]
    if max_plane_distance is None:
        sigma = _MAD * float(np.median(np.abs(dist - np.median(dist))))
        max_plane_distance = max(5.0 * sigma, 1e-6)
    elif not (np.isfinite(max_plane_distance) and max_plane_distance > 0):
        raise MeasurementError(f"max_plane_distance must be positive, got {max_plane_distance}")
    same = ss[1:] == ss[:-1]
    steps = np.diff(ts)[same]
    steps = steps[steps > 0]
    if steps.size == 0:
        return empty
    dt = float(np.median(steps))
    if min_gap is None:
        min_gap = 1.5 * dt
    elif not (np.isfinite(min_gap) and min_gap > 0):
        raise MeasurementError(f"min_gap must be positive, got {min_gap}")

    on = np.flatnonzero(np.abs(dist) <= max_plane_distance)  # sorted positions on the plate
    if on.size < 2:
        return empty
    i, j = on[:-1], on[1:]
    is_gap = (ss[i] == ss[j]) & ((j - i > 1) | (ts[j] - ts[i] > min_gap))
    k = np.flatnonzero(is_gap)  # gap between on[k] and on[k+1]
    if k.size == 0:
        return empty
    g = len(k)
    # edge samples: before-gap = on[k], after-gap = on[k+1]; their inner neighbours on the plate
    last = np.concatenate([on[k], on[k + 1]])
    side = np.concatenate([-np.ones(g, np.int64), np.ones(g, np.int64)])
    kk = np.concatenate([k - 1, k + 2])  # index into `on` of the inner neighbour
    valid = (kk >= 0) & (kk < on.size)
    inner = on[np.clip(kk, 0, on.size - 1)]
    # inner neighbour must be on the same slit, and not across another gap
    gap_at = np.zeros(on.size, bool)
    gap_at[k] = True  # gap between on[m] and on[m+1]
    across = np.concatenate([gap_at[np.clip(k - 1, 0, on.size - 1)], gap_at[k + 1]])
    valid &= (ss[inner] == ss[last]) & ~across
    dts = np.abs(ts[last] - ts[inner])
    valid &= dts > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        gdir = np.where(valid[:, None], (ps[last] - ps[inner]) / dts[:, None], 0.0)
    # step to the next sample towards the gap (any sample), at most the typical step
    nxt = np.clip(np.concatenate([on[k] + 1, on[k + 1] - 1]), 0, n - 1)
    step = np.minimum(np.abs(ts[nxt] - ts[last]), dt)

    src = order[last]
    if callable(edge_offset):
        f = np.asarray(edge_offset(src.copy(), side.copy()), dtype=np.float64)
        if f.shape != (2 * g,):
            raise MeasurementError(f"edge_offset returned shape {f.shape}, expected ({2 * g},)")
    else:
        f = np.asarray(edge_offset, dtype=np.float64)
        if f.ndim == 0:
            f = np.full(2 * g, float(f))
        elif f.shape == (n,):
            f = f[src]
        else:
            raise MeasurementError(
                f"edge_offset must be a float, a ({n},) array or a callable, got shape {f.shape}"
            )
    if not np.all(np.isfinite(f)) or np.any((f < 0) | (f > 1)):
        raise MeasurementError("edge_offset fractions must be in [0, 1]")

    edge = ps[last] + (f * step)[:, None] * gdir
    edge -= (edge @ pl[:3] + pl[3])[:, None] * pl[:3]  # onto the plane
    t_edge = ts[last] - side * f * step * valid
    gid = np.concatenate([np.arange(g), np.arange(g)])
    o = np.lexsort((side, gid))
    return EdgePoints(
        points=edge[o],
        slit=ss[last][o],
        gap=gid[o],
        side=side[o],
        t=t_edge[o],
        source=src[o],
    )
