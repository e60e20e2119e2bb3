"""Fitting planes and lines to points, plainly or robustly, and the one random-sample driver.

* :func:`fit_plane` -- total least squares plane (optionally weighted).
* :func:`fit_plane_robust` -- plane through points with outliers (RANSAC / least median of
  squares, then total least squares on the inliers).
* :func:`ransac` -- the random-sample driver: candidate models through sampled rows
  (:class:`PlaneModel`, :class:`LineModel`, :class:`CircleModel`), scored by inlier count
  within a threshold (RANSAC) or by the median residual (least median of squares).

Circles and spheres are fitted in :mod:`multislit.geometry.circles`.

Units: mm. Planes are (4,) ``[nx, ny, nz, d]`` with ``n . X + d = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry.camera import F64, as_points

__all__ = [
    "MAD_TO_SIGMA",
    "CircleModel",
    "LineModel",
    "PlaneModel",
    "RansacResult",
    "fit_plane",
    "fit_plane_robust",
    "finite_points",
    "ransac",
]

#: Median absolute deviation -> standard deviation, for Gaussian noise.
MAD_TO_SIGMA = 1.4826
_GROUP_SHARE = 0.05  # ransac's group rule: inliers needed per group, as a share of the points
_MIN_GROUP_INLIERS = 3  # ... and at least this many


def finite_points(a: ArrayLike, dim: int, name: str) -> F64:
    """``a`` as a (N, dim) finite float64 array, or MeasurementError naming ``name``."""
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
def _svd_plane(p: F64, w: F64 | None = None) -> tuple[F64, F64]:
    """Total least squares plane (4,) of points (N, 3) and the singular values (3,).

    With weights ``w`` (N,) the centroid and the scatter are weighted.
    """
    if w is None:
        c = p.mean(axis=0)
        _, s, vt = np.linalg.svd(p - c, full_matrices=False)
    else:
        c = (w[:, None] * p).sum(axis=0) / w.sum()
        _, s, vt = np.linalg.svd(np.sqrt(w)[:, None] * (p - c), full_matrices=False)
    n = vt[2]
    return np.append(n, -n @ c), s


def fit_plane(points: ArrayLike, *, weights: ArrayLike | None = None) -> tuple[F64, F64]:
    """Total least squares plane through points.

    Parameters
    ----------
    points : (N, 3) float64, mm, N >= 3
    weights : (N,) float64, >= 0, optional
        Weight of each point in the centroid and the scatter (weighted total least squares).
        Default: none (all points count equally).

    Returns
    -------
    plane : (4,) float64, unit normal and offset, n.X + d = 0
    residuals : (N,) float64, mm, signed distances of the points to the plane

    Raises
    ------
    MultislitError
        Fewer than 3 points, all weights 0, or collinear points.
    """
    p = as_points(points, 3, "points")
    if len(p) < 3:
        raise MultislitError(f"fit_plane needs >= 3 points, got {len(p)}")
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(p),):
            raise MultislitError(f"weights must have shape ({len(p)},), got {w.shape}")
        if not np.any(w > 0):
            raise MultislitError("fit_plane: all weights are 0")
    plane, s = _svd_plane(p, w)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise MultislitError("fit_plane: the points are collinear, no unique plane")
    return plane, p @ plane[:3] + plane[3]


# --------------------------------------------------------------------------- ransac
class Model(Protocol):
    """What :func:`ransac` needs of a model."""

    min_samples: ClassVar[int]

    def from_samples(
        self, data: F64, samples: NDArray[np.intp]
    ) -> tuple[F64, NDArray[np.bool_]]: ...

    def residuals(self, data: F64, params: F64) -> F64: ...


@dataclass(frozen=True)
class PlaneModel:
    """Planes through point triples; parameters (4,) ``[nx, ny, nz, d]``, unit normal.

    Parameters
    ----------
    min_cross : float, mm^2, optional
        A triple is degenerate when ``|(b - a) x (c - a)|`` is at most this. Default: relative,
        ``1e-9 |b - a| |c - a|``.
    """

    min_cross: float | None = None
    min_samples: ClassVar[int] = 3

    def from_samples(self, data: F64, samples: NDArray[np.intp]) -> tuple[F64, NDArray[np.bool_]]:
        """Candidate planes (T', 4) of the non-degenerate triples and the mask (T,) of those."""
        a, b, c = data[samples[:, 0]], data[samples[:, 1]], data[samples[:, 2]]
        normals = np.cross(b - a, c - a)
        length = np.linalg.norm(normals, axis=1)
        if self.min_cross is None:
            scale = np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - a, axis=1) + 1e-300
            ok = length > 1e-9 * scale
        else:
            ok = length > self.min_cross
        normals = normals[ok] / length[ok, None]
        offsets = -np.einsum("ij,ij->i", normals, a[ok])
        return np.column_stack([normals, offsets]), ok

    def residuals(self, data: F64, params: F64) -> F64:
        """Distances (N, T) of the points (N, 3) to the planes (T, 4), mm."""
        normals = np.ascontiguousarray(params[:, :3])
        return np.abs(data @ normals.T + params[:, 3])


@dataclass(frozen=True)
class LineModel:
    """3D lines through point pairs; parameters (6,) a point and a unit direction.

    Parameters
    ----------
    min_length : float, mm
        A pair is degenerate when its points are at most this far apart. Default 0.
    """

    min_length: float = 0.0
    min_samples: ClassVar[int] = 2

    def from_samples(self, data: F64, samples: NDArray[np.intp]) -> tuple[F64, NDArray[np.bool_]]:
        """Candidate lines (T', 6) of the non-degenerate pairs and the mask (T,) of those."""
        a, b = data[samples[:, 0]], data[samples[:, 1]]
        d = b - a
        length = np.linalg.norm(d, axis=1)
        ok = length > self.min_length
        return np.column_stack([a[ok], d[ok] / length[ok, None]]), ok

    def residuals(self, data: F64, params: F64) -> F64:
        """SQUARED distances (N, T) of the points (N, 3) to the lines (T, 6), mm^2."""
        a = np.ascontiguousarray(params[:, :3])
        d = np.ascontiguousarray(params[:, 3:])
        rel = data[:, None, :] - a[None, :, :]  # (N, T, 3)
        along = np.einsum("ntk,tk->nt", rel, d)
        return np.einsum("ntk,ntk->nt", rel, rel) - along * along


@dataclass(frozen=True)
class CircleModel:
    """Circles through 2D point triples (circumcircles); parameters (3,) ``[cx, cy, r]``."""

    min_samples: ClassVar[int] = 3

    def from_samples(self, data: F64, samples: NDArray[np.intp]) -> tuple[F64, NDArray[np.bool_]]:
        """Circumcircles (T', 3) of the non-collinear triples and the mask (T,) of those."""
        a, b, c = data[samples[:, 0]], data[samples[:, 1]], data[samples[:, 2]]
        ba, ca = b - a, c - a
        det = 2 * (ba[:, 0] * ca[:, 1] - ba[:, 1] * ca[:, 0])
        bb, cc = (ba * ba).sum(1), (ca * ca).sum(1)
        scale = np.maximum(bb, cc)
        ok = np.abs(det) > 1e-9 * scale
        with np.errstate(divide="ignore", invalid="ignore"):
            ux = (ca[:, 1] * bb - ba[:, 1] * cc) / det
            uy = (ba[:, 0] * cc - ca[:, 0] * bb) / det
        centres = a[ok] + np.column_stack([ux[ok], uy[ok]])
        return np.column_stack([centres, np.hypot(ux[ok], uy[ok])]), ok

    def residuals(self, data: F64, params: F64) -> F64:
        """Distances (N, T) of the points (N, 2) to the circles (T, 3), mm."""
        c = params[:, :2]
        d = np.hypot(data[:, None, 0] - c[None, :, 0], data[:, None, 1] - c[None, :, 1])
        return np.abs(d - params[None, :, 2])


@dataclass(frozen=True, eq=False)
class RansacResult:
    """The best candidate of :func:`ransac`.

    Attributes
    ----------
    params : (P,) float64, the model's parameters
    sample : (k,) int, the rows of ``data`` it was drawn through
    score : float
        With a threshold: the number of inliers (-1 when the group rule rejects every
        candidate); without: the median residual.
    inliers : (M,) bool or None
        With a threshold: the scored points whose residual is within it; None without.
    """

    params: F64
    sample: NDArray[np.intp]
    score: float
    inliers: NDArray[np.bool_] | None = field(default=None, repr=False)


def _scores(residuals: F64, threshold: float | None, groups: NDArray[np.int64] | None) -> F64:
    """Scores (T,) of candidates from their residuals (M, T); the best is the smallest."""
    if threshold is None:
        return np.median(residuals, axis=0)
    inl = residuals <= threshold
    counts = np.count_nonzero(inl, axis=0)
    if groups is None:
        return -counts
    ids = np.unique(groups[groups >= 0])
    if len(ids) < 2:
        return -counts
    per_group = np.stack([inl[groups == g].sum(axis=0) for g in ids])  # (G, T)
    need = max(_MIN_GROUP_INLIERS, int(_GROUP_SHARE * len(residuals)))
    return -np.where((per_group >= need).sum(axis=0) >= 2, counts, -1)


def ransac(
    model: Model,
    data: ArrayLike,
    samples: ArrayLike,
    *,
    threshold: float | None = None,
    score_data: ArrayLike | None = None,
    block_elements: int | None = None,
    groups: ArrayLike | None = None,
) -> RansacResult | None:
    """The best of the candidate models through sampled rows of ``data``.

    Each row of ``samples`` gives the rows of ``data`` one candidate is drawn through
    (``model.from_samples``); degenerate samples are dropped. Candidates are scored on
    ``score_data`` (default ``data``): with ``threshold``, by the number of points whose
    residual is within it (RANSAC, most wins); without, by the median residual (least median
    of squares, smallest wins). Ties go to the first candidate.

    Parameters
    ----------
    model : PlaneModel, LineModel or CircleModel (or any object with ``from_samples`` and
        ``residuals``)
    data : (N, D) float64, the points the candidates are drawn through
    samples : (T, k) int, rows of ``data`` per candidate (k = ``model.min_samples``), e.g.
        ``rng.integers(0, N, size=(T, k))``
    threshold : float, optional
        Inlier residual, in the model's residual unit (mm; mm^2 for :class:`LineModel`).
        Default: none (least median).
    score_data : (M, D) float64, optional
        The points the candidates are scored on. Default: ``data``.
    block_elements : int, optional
        Residuals are computed for blocks of candidates of about this many (point, candidate)
        pairs, to bound memory. Default: all candidates at once.
    groups : (M,) int, optional
        Group of each scored point (negative: none); with a threshold and points in two or
        more groups, only candidates with at least ``max(3, 5 % of M)`` inliers in each of two
        groups count (a face of a target holds all points on it, whichever slit they are on).

    Returns
    -------
    RansacResult, or None when every sample is degenerate.
    """
    x = np.asarray(data, dtype=np.float64)
    s = np.asarray(samples, dtype=np.intp)
    params, ok = model.from_samples(x, s)
    if not np.any(ok):
        return None
    s = s[ok]
    xs = x if score_data is None else np.asarray(score_data, dtype=np.float64)
    g = None if groups is None else np.asarray(groups, dtype=np.int64)
    block = len(params) if block_elements is None else max(1, block_elements // len(xs))
    scores = np.empty(len(params))
    for i in range(0, len(params), block):  # loop over candidate blocks, not points
        scores[i : i + block] = _scores(model.residuals(xs, params[i : i + block]), threshold, g)
    best = int(np.argmin(scores))
    if threshold is None:
        return RansacResult(params[best], s[best], float(scores[best]))
    j = best - best % block  # the best's block, recomputed as it was scored
    inliers = model.residuals(xs, params[j : j + block])[:, best - j] <= threshold
    return RansacResult(params[best], s[best], -float(scores[best]), inliers)


# --------------------------------------------------------------------------- robust plane
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
        Number of random triples tried (vectorised). Default 500.
    max_score_points : int
        Candidates are scored on at most this many randomly chosen points. Default 5000.

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
    p = finite_points(points, 3, "points")
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

    tri = rng.integers(0, n, size=(iterations, 3))  # repeated indices are degenerate, dropped
    sub = q if n <= max_score_points else q[rng.choice(n, max_score_points, replace=False)]
    best = ransac(
        PlaneModel(), q, tri, threshold=threshold_mm, score_data=sub, block_elements=4_000_000
    )
    if best is None:
        raise MeasurementError("fit_plane_robust: no non-degenerate sample (points collinear?)")
    plane = best.params
    inliers = np.zeros(n, dtype=bool)
    for _ in range(20):
        r = np.abs(q @ plane[:3] + plane[3])
        if threshold_mm is None:
            ref = r[inliers] if np.count_nonzero(inliers) >= 3 else r
            # median |r| of the current inliers; the first pass uses all points (LMedS scale)
            thr = max(3.0 * MAD_TO_SIGMA * float(np.median(ref)), eps)
        else:
            thr = threshold_mm
        new = r <= thr
        if np.count_nonzero(new) < 3:
            raise MeasurementError("fit_plane_robust: fewer than 3 inliers; raise threshold_mm")
        if np.array_equal(new, inliers):
            break
        inliers = new
        plane = _svd_plane(q[inliers])[0]
    plane = plane.copy()
    plane[3] -= plane[:3] @ centre  # back to the original frame
    return plane, inliers


def line_rms(points: ArrayLike) -> float:
    """RMS distance (mm) of points (N, 3) from their total-least-squares line."""
    pts = np.asarray(points, dtype=np.float64)
    sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return float(np.sqrt(np.sum(sv[1:] ** 2) / len(pts)))
