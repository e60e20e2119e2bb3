"""The projector: the paper's 2x4 matrix and the robust fit of the slit planes.

:func:`fit_projector_matrix` is the paper's eq. (3)-(4): one 2x4 matrix P for all slits, the
plane of slit X_p being (P_1 - X_p P_2) . [X, 1] = 0 (:class:`ProjectorMatrix`).
:func:`fit_projector` fits our model (:class:`~multislit.calibrate.slit_planes.SlitPlanes`,
one plane per slit through a common axis) robustly from points on the slits: a RANSAC plane
per slit first, then least squares with points further than a few robust sigmas from their
plane dropped and the planes refitted until nothing changes, so that mislabelled points cannot
pull the planes. A slit seen on one target face only (its points along one line) is left out
of the axis's fit and then gets the plane through the axis and its line, when its angle about
the axis fits the other slits'. Slits with too few points are reported and get NaN planes;
they are never guessed. The 2x4 matrix is fitted to the same points for comparison; its
per-slit RMS on them is its systematic error.

Units: mm in the world (target) frame.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.calibrate.camera import check_finite, hartley_normalisation, homogeneous
from multislit.calibrate.slit_planes import (
    SlitPlanes,
    fit_slit_planes,
    slit_indices,
    slit_plane_rms,
)
from multislit.calibrate.slit_points import SlitPointSet
from multislit.errors import CalibrationError, MultislitError
from multislit.geometry import LineModel, PlaneModel, as_points, ransac
from multislit.geometry.camera import F64

#: Least number of points for the 2x4 projector matrix.
MIN_PROJECTOR_POINTS = 8
#: Least number of points for a slit's plane from automatic points (hand readings: 3).
_MIN_AUTO_POINTS = 20
#: Points further than this many robust sigmas from their slit's plane are outliers.
_OUTLIER_SIGMA = 4.0
#: Inlier band (mm) of the first, RANSAC, plane (or line) of each slit; well below the slit
#: spacing on the target.
_COARSE_TOL_MM = 1.0
#: RANSAC candidates drawn per slit for the coarse outlier removal.
_RANSAC_TRIALS = 300
#: Least robust sigma (mm) of a slit's distances to its plane.
_MIN_SIGMA_MM = 0.002
#: Most rounds of dropping outliers and refitting.
_MAX_ITERATIONS = 8
#: A slit whose points spread less than this (RMS, mm) across their best line, or whose points
#: lie on one target face, is seen along one line.
_MIN_WIDTH_MM = 0.5


# --------------------------------------------------------------------------- 2x4 matrix
def _normalise_pointwise_1d(xp: F64) -> F64:
    c = xp.mean()
    s = np.abs(xp - c).mean()
    if not s > 0:
        raise CalibrationError(
            "all points have the same X_p: the projector matrix needs points on >= 2 slits"
        )
    return np.array([[1 / s, -c / s], [0.0, 1.0]])


def fit_projector_matrix(points: ArrayLike, xp: ArrayLike) -> tuple[F64, F64]:
    """Projector matrix P of eq. (3) by linear least squares on eq. (4), normalised.

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame, points on slits; N >= 8
    xp : (N,) float64, slit coordinate X_p of each point (e.g. the slit number)

    Returns
    -------
    P : (2, 4) float64, scaled to unit Frobenius norm; the plane of slit X_p is
        (P[0] - X_p P[1]) . [X, Y, Z, 1] = 0
    residuals : (N,) float64, mm, signed distance of each point to the plane of its X_p

    Raises
    ------
    CalibrationError
        Fewer than 8 points, non-finite input, all on one slit, or a degenerate solution
        (e.g. all points on one line).
    """
    X = as_points(points, 3, "points")
    x = np.asarray(xp, dtype=float).reshape(-1)
    if len(x) != len(X):
        raise CalibrationError(f"points has {len(X)} rows but xp has {len(x)} values")
    if len(X) < MIN_PROJECTOR_POINTS:
        raise CalibrationError(
            f"the projector matrix needs >= {MIN_PROJECTOR_POINTS} points on the slits, "
            f"{len(X)} given; read more points off the slits"
        )
    check_finite(X, "points")
    check_finite(x[:, None], "xp")
    U = hartley_normalisation(X, "points")
    T = _normalise_pointwise_1d(x)
    Xn = homogeneous(X) @ U.T
    xn = x * T[0, 0] + T[0, 1]
    A = np.concatenate([Xn, -xn[:, None] * Xn], axis=1)
    _, sv, vt = np.linalg.svd(A, full_matrices=False)
    if sv[-2] < 1e-9 * sv[0]:
        raise CalibrationError(
            "the projector matrix is not determined by these points (use points spread along "
            "several slits and over at least two faces)"
        )
    Pn = vt[-1].reshape(2, 4)
    P = np.linalg.inv(T) @ Pn @ U
    P /= np.linalg.norm(P)
    pl = _pencil_planes(P, x)
    res = np.einsum("ij,ij->i", pl[:, :3], X) + pl[:, 3]
    return P, res


def _pencil_planes(P: F64, xp: F64) -> F64:
    raw = P[0][None, :] - xp[:, None] * P[1][None, :]
    n = np.linalg.norm(raw[:, :3], axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return raw / n


@dataclass(frozen=True, eq=False)
class ProjectorMatrix:
    """The paper's projector model, eq. (3): one 2x4 matrix P for all slits.

    Parameters
    ----------
    P : (2, 4) float64
    xp_values : (K,) float64, the X_p value of each slit 0..K-1 (default: the slit number)
    """

    P: F64
    xp_values: F64

    def __post_init__(self) -> None:
        P = np.asarray(self.P, dtype=float)
        if P.shape != (2, 4) or not np.all(np.isfinite(P)):
            raise CalibrationError(f"P must be a finite (2, 4) matrix, got shape {P.shape}")
        xv = np.asarray(self.xp_values, dtype=float).reshape(-1)
        if not np.all(np.isfinite(xv)):
            raise CalibrationError("xp_values must be finite")
        object.__setattr__(self, "P", P)
        object.__setattr__(self, "xp_values", xv)

    @classmethod
    def fit(
        cls,
        points: ArrayLike,
        slits: ArrayLike,
        num_slits: int,
        xp_values: ArrayLike | None = None,
    ) -> tuple[ProjectorMatrix, F64]:
        """Fit P from points with slit numbers (X_p = ``xp_values[slit]``, default the number).

        Returns the model and the residuals (N,) mm of :func:`fit_projector_matrix`.
        """
        s = slit_indices(slits, num_slits)
        xv = (
            np.arange(num_slits, dtype=float) if xp_values is None else np.asarray(xp_values, float)
        )
        if xv.shape != (num_slits,):
            raise CalibrationError(f"xp_values must have {num_slits} values, got {xv.shape}")
        P, res = fit_projector_matrix(points, xv[s])
        return cls(P, xv), res

    @property
    def num_slits(self) -> int:
        return len(self.xp_values)

    def planes(self) -> F64:
        """(K, 4) float64: the plane of each slit from eq. (4), unit normals, n.X + d = 0."""
        return _pencil_planes(self.P, self.xp_values)

    def to_dict(self) -> dict[str, Any]:
        return {"P": self.P.tolist(), "xp_values": self.xp_values.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ProjectorMatrix:
        try:
            return cls(np.array(d["P"], dtype=float), np.array(d["xp_values"], dtype=float))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"malformed projector matrix: {exc!r}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, s: str) -> ProjectorMatrix:
        return cls.from_dict(json.loads(s))


# --------------------------------------------------------------------------- robust fit
@dataclass(frozen=True, eq=False)
class ProjectorFit:
    """Result of :func:`fit_projector`.

    Attributes
    ----------
    slit_planes : SlitPlanes (common axis), NaN rows for slits left out
    projector : ProjectorMatrix, the paper's 2x4 model on the same points (None if not fitted)
    projector_rms_mm : (K,) float64, mm, per-slit RMS of the 2x4 model's planes on the points
    inlier : (N,) bool, points used in the final fit
    dropped : (K,) int, outliers dropped per slit
    excluded : tuple of (slit, reason), slits without a plane
    """

    slit_planes: SlitPlanes
    projector: ProjectorMatrix | None
    projector_rms_mm: F64
    inlier: NDArray[np.bool_]
    dropped: NDArray[np.int_]
    excluded: tuple[tuple[int, str], ...] = field(default=())


def fit_projector(points: SlitPointSet, num_slits: int) -> ProjectorFit:
    """Slit planes (common axis) and the paper's 2x4 matrix from points on the slits, robustly.

    Parameters
    ----------
    points : SlitPointSet
        Hand readings need >= 3 points per slit, automatic points >= 20; a slit whose points lie
        on one target face (a few stray points on other faces are dropped) is seen along one
        line and gets the plane through the common axis and its line
        (:func:`~multislit.calibrate.slit_planes.fit_slit_planes`).
    num_slits : int

    Returns
    -------
    ProjectorFit

    Raises
    ------
    CalibrationError
        No points, or fewer than 2 slits whose points determine a plane by themselves.
    """
    X = np.asarray(points.xyz, dtype=float)
    s = np.asarray(points.slit, dtype=np.intp)
    k = int(num_slits)
    min_points = 3 if points.source == "hand" else _MIN_AUTO_POINTS
    if len(X) == 0:
        raise CalibrationError("no points on the slits to calibrate the projector from")
    use, one_face, excluded = _coarse_inliers(points, k, min_points)
    _check_enough_slits(X, s, use, one_face, excluded, k, min_points, points.source)
    sp, use = _robust_planes(X, s, use, k, min_points)
    excluded += [e for e in sp.excluded if e[0] not in {x[0] for x in excluded}]
    dropped = np.bincount(s[~use], minlength=k) - np.bincount(
        s[~use & np.isin(s, [e[0] for e in excluded])], minlength=k
    )
    proj = None
    proj_rms = np.full(k, np.nan)
    fit_slits = sp.valid[s] & use
    try:
        proj, _ = ProjectorMatrix.fit(X[fit_slits], s[fit_slits], k)
        proj_rms, _ = slit_plane_rms(proj.planes(), X[fit_slits], s[fit_slits])
    except MultislitError:
        proj = None
    return ProjectorFit(sp, proj, proj_rms, use, dropped, tuple(sorted(excluded)))


def _spread(X: F64) -> float:
    """Largest distance (mm) of a point from the points' mean."""
    return float(np.linalg.norm(X - X.mean(axis=0), axis=1).max())


def _plane_inliers(
    X: F64, face: NDArray[np.intp], tol: float, rng: np.random.Generator
) -> NDArray[np.bool_] | None:
    """Inliers (within ``tol`` mm) of the best RANSAC plane through 3 of the points, or None.

    With points on several faces only planes with inliers on >= 2 faces count: a face's own
    plane holds every point on it, whichever slit it belongs to.
    """
    if len(X) < 3:
        return None
    min_cross = 1e-3 * _spread(X) ** 2
    idx = rng.integers(0, len(X), size=(_RANSAC_TRIALS, 3))
    best = ransac(PlaneModel(min_cross=min_cross), X, idx, threshold=tol, groups=face)
    return None if best is None or best.score < 3 else best.inliers


def _line_inliers(X: F64, tol: float, rng: np.random.Generator) -> NDArray[np.bool_] | None:
    """Inliers (within ``tol`` mm) of the best RANSAC line through 2 of the points, or None."""
    if len(X) < 3:
        return None
    idx = rng.integers(0, len(X), size=(_RANSAC_TRIALS, 2))
    best = ransac(LineModel(min_length=0.1 * _spread(X)), X, idx, threshold=tol * tol)
    return None if best is None or best.score < 3 else best.inliers


def _coarse_inliers(
    points: SlitPointSet, k: int, min_points: int
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], list[tuple[int, str]]]:
    """First selection of the points, slit by slit.

    Slits with too few points are excluded; a slit on one target face keeps the points on its
    main face only; automatic points keep the inliers of a RANSAC plane (or line, for one face).
    Returns the points used (N,) bool, the slits seen on one face (K,) bool and the exclusions.
    """
    X = np.asarray(points.xyz, dtype=float)
    s = np.asarray(points.slit, dtype=np.intp)
    rng = np.random.default_rng(0)
    use = np.ones(len(X), bool)
    counts0 = np.bincount(s, minlength=k)
    fc = np.asarray(points.face)
    excluded: list[tuple[int, str]] = []
    one_face = np.zeros(k, bool)
    for j in range(k):
        if counts0[j] == 0:
            excluded.append((j, "no points"))
            continue
        if counts0[j] < min_points:
            excluded.append((j, f"only {counts0[j]} point(s), need >= {min_points}"))
            use[s == j] = False
            continue
        sel = np.flatnonzero(s == j)
        if np.any(fc[sel] >= 0):  # a plane needs points off one line, e.g. on two faces
            nf = np.bincount(fc[sel][fc[sel] >= 0])
            big = nf >= max(5, 0.02 * len(sel))
            if np.count_nonzero(big) < 2:
                one_face[j] = True
                main_face = int(np.argmax(nf))
                use[sel[fc[sel] != main_face]] = False  # stray points elsewhere
                sel = sel[fc[sel] == main_face]
        if points.source != "hand":
            if one_face[j]:
                inl = _line_inliers(X[sel], _COARSE_TOL_MM, rng)
            else:
                inl = _plane_inliers(X[sel], fc[sel], _COARSE_TOL_MM, rng)
            if inl is not None:
                use[sel[~inl]] = False
    return use, one_face, excluded


def _check_enough_slits(
    X: F64,
    s: NDArray[np.intp],
    use: NDArray[np.bool_],
    one_face: NDArray[np.bool_],
    excluded: list[tuple[int, str]],
    k: int,
    min_points: int,
    source: str,
) -> None:
    """Raise unless >= 2 slits have points that determine a plane by themselves."""
    own = np.zeros(k, bool)  # slits whose points determine a plane by themselves
    for j in range(k):
        m = use & (s == j)
        if m.sum() >= 3 and not one_face[j]:
            sv = np.linalg.svd(X[m] - X[m].mean(axis=0), compute_uv=False)
            own[j] = sv[1] / math.sqrt(m.sum()) >= _MIN_WIDTH_MM
    n_ok = int(own.sum())
    if n_ok < 2 and np.any(use):
        lines = sorted(set(np.unique(s[use]).tolist()) - set(np.flatnonzero(own).tolist()))
        raise CalibrationError(
            f"only {n_ok} of {k} slits have points that determine a plane by themselves "
            "(>= 2 are needed for the common axis; "
            + (f"slits {lines}: points along one line, e.g. on one target face; " if lines else "")
            + "; ".join(f"slit {j}: {r}" for j, r in excluded[:5])
            + "); the slits must be seen on two target faces"
            + ("; try the hand readings (--source hand)" if source != "hand" else "")
        )
    if not np.any(use):
        raise CalibrationError(
            f"no slit has >= {min_points} points on the target; "
            + "; ".join(f"slit {j}: {r}" for j, r in excluded[:5])
        )


def _robust_planes(
    X: F64, s: NDArray[np.intp], use: NDArray[np.bool_], k: int, min_points: int
) -> tuple[SlitPlanes, NDArray[np.bool_]]:
    """Fit the slit planes, drop points far from their plane and refit until nothing changes.

    A slit never loses points below ``min_points``. Returns the planes and the points used.
    """
    sp = None
    for _ in range(_MAX_ITERATIONS):
        sp = fit_slit_planes(X[use], s[use], k, common_axis=True, min_width_mm=_MIN_WIDTH_MM)
        pl = sp.planes
        d = np.einsum("ij,ij->i", X, pl[s, :3]) + pl[s, 3]
        ad = np.abs(d)
        sig = np.full(k, np.nan)
        for j in np.flatnonzero(sp.valid):
            m = use & (s == j)
            if m.any():
                sig[j] = max(1.4826 * float(np.median(ad[m])), _MIN_SIGMA_MM)
        glob = float(np.nanmedian(sig)) if np.any(np.isfinite(sig)) else _MIN_SIGMA_MM
        sig = np.where(np.isfinite(sig), sig, glob)
        new = use & np.isfinite(ad) & (ad <= _OUTLIER_SIGMA * sig[s])
        if np.array_equal(new, use):
            break
        # never let the clipping drop a slit below min_points: keep its previous points then
        cnt = np.bincount(s[new], minlength=k)
        for j in np.flatnonzero((cnt < min_points) & (np.bincount(s[use], minlength=k) > 0)):
            new[use & (s == j)] = True
        if np.array_equal(new, use):
            break
        use = new
    assert sp is not None
    return sp, use


def auto_fit_problem(fit: ProjectorFit, points: SlitPointSet, num_slits: int) -> str | None:
    """Why slit planes from automatic points cannot be trusted, or None when they can.

    Automatic points are noisy measurements labelled by identification; planes are trusted only
    when most slits get one, each from enough inliers that leave a real (non-zero) residual.
    A plane that fits its points exactly was fitted to too few points to check itself.
    """
    sp = fit.slit_planes
    s = np.asarray(points.slit, dtype=np.intp)
    inliers = np.bincount(s[fit.inlier], minlength=num_slits)
    ok = sp.valid & (inliers >= _MIN_AUTO_POINTS) & (np.nan_to_num(sp.rms_mm) > 1e-6)
    need = max(3, math.ceil(0.5 * num_slits))
    if ok.sum() < need:
        return (
            f"only {int(ok.sum())} of {num_slits} slits got a well-supported plane from the "
            f"automatically identified stripes (need >= {need})"
        )
    return None
