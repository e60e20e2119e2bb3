"""Holes among edge points: grouped per hole, one circle fitted per hole.

:func:`fit_holes` projects the edge points into the plate's plane, groups them per hole
(single linkage, the two edges of one gap kept together, arcs on one circle merged) and fits
one robust circle (:func:`~multislit.geometry.fit_circle`) per hole; holes crossed by too few
slits or seen over too short an arc are reported as not measurable instead of being fitted.

Units: mm, target frame. Planes are (4,) ``[nx, ny, nz, d]`` with ``n . X + d = 0``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist

from multislit.errors import MeasurementError
from multislit.geometry import (
    CircleFit,
    check_plane,
    finite_points,
    fit_circle,
    from_plane_coords,
    project_to_plane,
)
from multislit.io import json_safe
from multislit.measure.edges import check_labels
from multislit.summaries import Summarised

F64 = NDArray[np.float64]

__all__ = ["HoleResult", "fit_holes"]


# --------------------------------------------------------------------------- holes
@dataclass(frozen=True, eq=False, repr=False)
class HoleResult(Summarised):
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

    def summary(self) -> str:
        """One line: centre and diameter with the fit's figures, or why it is not measurable."""
        c = ", ".join(f"{x:.2f}" for x in self.centre)
        if not self.measurable:
            return f"near ({c}) mm, not measurable: {self.reason}"
        slits = f", {self.n_slits} slits" if self.n_slits is not None else ""
        return (
            f"centre ({c}) mm, diameter {self.diameter:.2f} mm, {self.n_inliers}/"
            f"{self.n_points} edge points{slits}, fit RMS {self.rms:.3f} mm"
        )

    def to_dict(self) -> dict[str, Any]:
        """The result as JSON-ready values (NaN as None; no indices)."""
        return {
            "centre": [float(x) for x in self.centre],
            "diameter": json_safe(self.diameter),
            "n_points": int(self.n_points),
            "n_inliers": int(self.n_inliers),
            "n_slits": None if self.n_slits is None else int(self.n_slits),
            "rms": json_safe(self.rms),
            "radius_std": json_safe(self.radius_std),
            "arc_deg": json_safe(self.arc_deg),
            "measurable": bool(self.measurable),
            "reason": self.reason,
        }


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


def _link_distance(q: F64, link_distance: float | None) -> float:
    """The single-linkage distance: given, or 2.5 x the median nearest-neighbour distance."""
    n = len(q)
    if link_distance is None:
        if n >= 2:
            dnn = cKDTree(q).query(q, k=2)[0][:, 1]
            link_distance = 2.5 * float(np.median(dnn))
        else:
            link_distance = 0.0
        return max(link_distance, 1e-9)
    if not (np.isfinite(link_distance) and link_distance > 0):
        raise MeasurementError(f"link_distance must be positive, got {link_distance}")
    return link_distance


def _fit_group(
    g: F64, n_slits: int | None, *, min_points: int, min_slits: int, min_arc: float, robust: bool
) -> tuple[CircleFit | None, str]:
    """The circle of one group of edge points (2D, in the plane), or why there is none."""
    reason = ""
    if n_slits is not None and n_slits < min_slits:
        reason = f"crossed by {n_slits} slit(s), need >= {min_slits}"
    elif len(g) < min_points:
        reason = f"{len(g)} edge point(s), need >= {min_points}"
    fit = None
    if not reason:
        try:
            fit = fit_circle(g, robust=robust)
        except MeasurementError as exc:
            reason = str(exc)
    if fit is not None and fit.n_inliers < min_points:
        reason = f"{fit.n_inliers} edge point(s) after outlier rejection, need >= {min_points}"
    elif fit is not None and fit.arc_deg < min_arc:
        reason = (
            f"edge points cover {fit.arc_deg:.0f} deg of the circle, need >= "
            f"{min_arc:.0f} (radius ill-determined)"
        )
    return fit, reason


def _hole_result(
    idx: NDArray[np.intp],
    g: F64,
    fit: CircleFit | None,
    reason: str,
    n_slits: int | None,
    pl: F64,
) -> HoleResult:
    nan = float("nan")
    if reason:
        return HoleResult(
            centre=from_plane_coords(g.mean(axis=0), pl)[0],
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
    assert fit is not None
    return HoleResult(
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


def _check_limits(min_points: int, min_slits: int, min_arc_deg: float) -> None:
    if min_points < 3:
        raise MeasurementError(f"min_points must be >= 3, got {min_points}")
    if min_slits < 1:
        raise MeasurementError(f"min_slits must be >= 1, got {min_slits}")
    if not (0 <= min_arc_deg <= 360):
        raise MeasurementError(f"min_arc_deg must be in [0, 360], got {min_arc_deg}")


def fit_holes(
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

    The points are projected into the plane (:func:`~multislit.geometry.project_to_plane`)
    and grouped by single linkage: points closer than ``link_distance`` are linked, and so are
    the two edges of one gap (same ``gap`` label, e.g. from
    :func:`~multislit.measure.hole_edges_from_profiles`). Without gap labels, the two arcs of
    a hole (above and below the slit ends) may fall apart; with ``merge_arcs`` groups whose
    union lies on one circle (fit RMS <= ``merge_tol_mm``) are merged. Each group is then
    measured unless

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
        Fewest edge points for a fit (>= 3). Default 6.
    min_slits : int
        Fewest distinct slits crossing a hole (checked only when ``slit`` is given). Default 2.
    slit : (N,) int, optional
        Slit number of each edge point (negative = unidentified, not counted).
    gap : (N,) int, optional
        Gap id of each edge point: the edges of one gap share it (negative = none).
    min_arc_deg : float, deg
        Smallest arc the fitted edge points must cover. Default 180.
    link_distance : float, mm, optional
        Single-linkage distance. Default: 2.5 x the median nearest-neighbour distance (about
        the slit spacing and the along-slit spacing of edges).
    merge_arcs : bool
        Merge groups lying on one circle (see above). Default True.
    merge_tol_mm : float, mm
        Largest circle-fit RMS for merging. Default 0.5.
    robust : bool
        Passed to :func:`~multislit.geometry.fit_circle`. Default True.

    Returns
    -------
    list of HoleResult
        One per group, ordered along the plane's e1 axis then e2. Empty for no points.

    Raises
    ------
    MeasurementError
        Bad shapes, non-finite values or parameters.
    """
    p = finite_points(edge_points, 3, "edge_points")
    pl = check_plane(plane)
    n = len(p)
    _check_limits(min_points, min_slits, min_arc_deg)
    sl = check_labels(slit, n, "slit")
    gp = check_labels(gap, n, "gap")
    if n == 0:
        return []
    q = project_to_plane(p, pl)
    link = _link_distance(q, link_distance)
    _, labels = _group(q, link, gp)
    if merge_arcs:
        labels = _merge_arcs(q, labels.astype(np.int64), link, merge_tol_mm)

    results = []
    for lab in np.unique(labels):  # loop over holes
        idx = np.flatnonzero(labels == lab)
        g = q[idx]
        n_slits = None if sl is None else int(np.unique(sl[idx][sl[idx] >= 0]).size)
        fit, reason = _fit_group(
            g,
            n_slits,
            min_points=min_points,
            min_slits=min_slits,
            min_arc=min_arc_deg,
            robust=robust,
        )
        res = _hole_result(idx, g, fit, reason, n_slits, pl)
        results.append((tuple(project_to_plane(res.centre, pl)[0]), res))
    results.sort(key=lambda t: t[0])
    return [r for _, r in results]
