"""Fitting circles (2D) and spheres (3D) to points.

* :func:`fit_circle` -- circle through 2D points: algebraic start, geometric least squares;
  robust by default (least median of squares start through :func:`~multislit.geometry.ransac`,
  then iterated outlier rejection).
* :func:`fit_sphere` -- least squares sphere through 3D points.

Units: mm.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.stats import norm
from scipy.stats import t as student_t

from multislit.errors import MeasurementError
from multislit.geometry.camera import F64
from multislit.geometry.fit import MAD_TO_SIGMA, CircleModel, finite_points, ransac

__all__ = ["CircleFit", "SphereFit", "fit_circle", "fit_sphere"]


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
        """The fit as plain Python values (NaN stays NaN; ``multislit.io.json_safe`` for JSON)."""
        return {
            "centre": [float(x) for x in self.centre],
            "radius": float(self.radius),
            "diameter": float(self.diameter),
            "rms": float(self.rms),
            "n_points": int(self.n_points),
            "n_inliers": int(self.n_inliers),
            "radius_std": float(self.radius_std),
            "arc_deg": float(self.arc_deg),
        }


def _algebraic_sphere(q: F64) -> tuple[F64, float]:
    """Algebraic circle / sphere of centred points (N, D): ``|q|^2 = 2 c . q + k``."""
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(A, (q * q).sum(axis=1), rcond=None)
    dim = q.shape[1]
    centre = sol[:dim]
    return centre, float(np.sqrt(max(sol[dim] + centre @ centre, 0.0)))


def _geometric_circle(p: F64, centre: F64, radius: float) -> tuple[F64, float, float]:
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
) -> tuple[F64, float, NDArray[np.intp]]:
    """Least-median circle from point triples (all triples if few, else random ones).

    Returns the centre, the radius and the indices of the triple through which it passes.
    """
    n = len(p)
    total = n * (n - 1) * (n - 2) // 6
    if total <= max_samples:
        tri = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int64)
    else:
        tri = rng.integers(0, n, size=(max_samples, 3))  # repeats are degenerate, dropped
    best = ransac(CircleModel(), p, tri, block_elements=2_000_000)
    if best is None:
        raise MeasurementError("fit_circle: the points are collinear, no circle")
    return best.params[:2], float(best.params[2]), best.sample


def _arc_deg(p: F64, centre: F64) -> float:
    if len(p) < 2:
        return 0.0
    ang = np.sort(np.arctan2(p[:, 1] - centre[1], p[:, 0] - centre[0]))
    gaps = np.diff(np.append(ang, ang[0] + 2 * np.pi))
    return float(np.degrees(2 * np.pi - gaps.max()))


def _robust_circle_inliers(
    q: F64, k: float, eps: float, rng: np.random.Generator
) -> tuple[NDArray[np.bool_], F64, float]:
    """Inliers of a robust circle (least median start, then iterated geometric fits)."""
    n = len(q)
    centre, radius, triple = _lmeds_circle(q, rng)
    r = np.abs(np.hypot(q[:, 0] - centre[0], q[:, 1] - centre[1]) - radius)
    # noise scale from the points the circle was not drawn through (theirs are 0)
    others = np.ones(n, dtype=bool)
    others[triple] = False
    s0 = MAD_TO_SIGMA * float(np.median(r[others]))
    inliers = r <= max(k * s0, eps)
    tail = float(norm.sf(k))
    if np.count_nonzero(inliers) < 4:
        inliers = np.ones(n, dtype=bool)
    for _ in range(20):
        centre, radius, _ = _geometric_circle(q[inliers], centre, radius)
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
    return inliers, centre, radius


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
        Reject outliers (see above). Default True.
    k : float
        Rejection threshold in robust sigmas. Default 3.5.
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
    p = finite_points(points2d, 2, "points2d")
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

    if robust and n >= 5:
        inliers, centre, radius = _robust_circle_inliers(q, k, eps, rng)
    else:
        inliers = np.ones(n, dtype=bool)
        centre, radius = _algebraic_sphere(q)
    centre, radius, r_std = _geometric_circle(q[inliers], centre, radius)
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


# --------------------------------------------------------------------------- spheres
@dataclass(frozen=True, eq=False)
class SphereFit:
    """A least squares sphere (radial distances, radius free).

    Attributes
    ----------
    centre : (3,) float64, mm
    radius : float, mm
    residuals : (N,) float64, mm
        Signed radial residuals ``|p - centre| - radius`` (positive outside).
    rms : float, mm
        RMS of the residuals.
    """

    centre: F64
    radius: float
    residuals: F64
    rms: float

    @property
    def diameter(self) -> float:
        """Diameter, mm."""
        return 2.0 * self.radius


def fit_sphere(points: ArrayLike) -> SphereFit:
    """Least squares sphere through points: algebraic start, then geometric least squares.

    The start solves ``|p|^2 = 2 c . p + k`` linearly (on centred points); the geometric fit
    minimises ``sum (|p - c| - r)^2`` with Levenberg-Marquardt.

    Parameters
    ----------
    points : (N, 3) float64, mm, N >= 4, finite, not all in one plane

    Returns
    -------
    SphereFit

    Raises
    ------
    MeasurementError
        Fewer than 4 points, non-finite points, or points (nearly) coplanar, so that no sphere
        is determined.
    """
    p = finite_points(points, 3, "points")
    if len(p) < 4:
        raise MeasurementError(f"points: need >= 4 points, got {len(p)}")
    mean = p.mean(axis=0)
    q = p - mean
    _, s, _ = np.linalg.svd(q, full_matrices=False)
    if s[0] <= 0 or s[2] <= 1e-6 * s[0]:
        raise MeasurementError("fit_sphere: the points are (nearly) coplanar, no unique sphere")
    c0, r0 = _algebraic_sphere(q)
    if not np.isfinite(r0) or r0 <= 0:
        r0 = float(np.linalg.norm(q - c0, axis=1).mean())

    def fun(x: F64) -> F64:
        return np.linalg.norm(q - x[:3], axis=1) - x[3]

    def jac(x: F64) -> F64:
        d = q - x[:3]
        rho = np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        return np.column_stack([-d / rho[:, None], -np.ones(len(q))])

    res = least_squares(fun, np.array([*c0, r0]), jac=jac, method="lm", xtol=1e-14, ftol=1e-14)
    centre = res.x[:3] + mean
    radius = abs(float(res.x[3]))
    resid = np.linalg.norm(p - centre, axis=1) - radius
    return SphereFit(centre, radius, resid, float(np.sqrt(np.mean(resid * resid))))
