"""Hole edges: where a slit's stripe leaves a flat plate at a hole and comes back.

* :func:`hole_edges_from_profiles` -- per slit, from the measured points ordered along the
  stripe: the last points on the plate before each gap, placed a fraction of a sample step
  beyond (geometric edges).
* :func:`locate_edge_subpixel` -- the same edge located in the image, where the stripe's
  intensity falls to half the plate's level.
* :func:`subpixel_edges` -- the 3D edge points of those image positions, on the line where
  the slit's plane meets the plate.

Units: mm, target frame; px in the image. Planes are (4,) ``[nx, ny, nz, d]``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.calibrate import Calibration
from multislit.errors import MeasurementError
from multislit.geometry import MAD_TO_SIGMA, check_plane, finite_points

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

__all__ = [
    "EdgePoints",
    "HoleEdges",
    "check_labels",
    "hole_edges_from_profiles",
    "locate_edge_subpixel",
    "subpixel_edges",
]

_PROFILE_HALF_MM = 15.0  # the image profile's line runs this far either side of the edge, mm


def check_labels(a: ArrayLike | None, n: int, name: str, like: str = "edge_points") -> I64 | None:
    """Integer labels (n,) as int64 (None stays None), or MeasurementError naming ``name``.

    Parameters
    ----------
    a : (n,) int, or floats holding whole numbers; optional
    n : int, the expected length
    name, like : str, the argument and the argument whose length it must have (messages)
    """
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


# --------------------------------------------------------------------------- geometric edges
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
    slit: I64
    gap: I64
    side: I64
    t: F64
    source: I64

    def __len__(self) -> int:
        return len(self.points)


EdgeOffset = float | ArrayLike | Callable[[I64, I64], ArrayLike]


def _no_edges() -> EdgePoints:
    return EdgePoints(
        np.zeros((0, 3)),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0),
        np.zeros(0, np.int64),
    )


def _profile_scales(
    dist: F64, ss: I64, ts: F64, max_plane_distance: float | None, min_gap: float | None
) -> tuple[float, float, float] | None:
    """The on-plate tolerance, the typical sample step and the smallest gap (defaults from
    the data), or None when no slit has two samples at different ``t``."""
    if max_plane_distance is None:
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(dist - np.median(dist))))
        max_plane_distance = max(5.0 * sigma, 1e-6)
    elif not (np.isfinite(max_plane_distance) and max_plane_distance > 0):
        raise MeasurementError(f"max_plane_distance must be positive, got {max_plane_distance}")
    same = ss[1:] == ss[:-1]
    steps = np.diff(ts)[same]
    steps = steps[steps > 0]
    if steps.size == 0:
        return None
    dt = float(np.median(steps))
    if min_gap is None:
        min_gap = 1.5 * dt
    elif not (np.isfinite(min_gap) and min_gap > 0):
        raise MeasurementError(f"min_gap must be positive, got {min_gap}")
    return max_plane_distance, dt, min_gap


def _gaps(
    dist: F64, ss: I64, ts: F64, max_plane_distance: float, min_gap: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Sorted positions on the plate ``on`` and the gaps ``k`` (a gap between on[k], on[k+1])."""
    on = np.flatnonzero(np.abs(dist) <= max_plane_distance)  # sorted positions on the plate
    if on.size < 2:
        return on, np.zeros(0, np.intp)
    i, j = on[:-1], on[1:]
    is_gap = (ss[i] == ss[j]) & ((j - i > 1) | (ts[j] - ts[i] > min_gap))
    return on, np.flatnonzero(is_gap)


def _edge_samples(
    on: NDArray[np.intp], k: NDArray[np.intp], ps: F64, ss: I64, ts: F64, dt: float
) -> tuple[NDArray[np.intp], I64, NDArray[np.bool_], F64, F64]:
    """Per edge (before-gap edges, then after-gap ones): its last on-plate sample, its side,
    whether its direction is known, the plate's direction per unit t and the step towards
    the gap (at most ``dt``)."""
    n = len(ps)
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
    return last, side, valid, gdir, step


def _edge_fractions(edge_offset: EdgeOffset, src: NDArray[np.intp], side: I64, n: int) -> F64:
    """The fraction f (2g,) of a step each edge lies beyond its last on-plate sample."""
    m = len(src)
    if callable(edge_offset):
        f = np.asarray(edge_offset(src.copy(), side.copy()), dtype=np.float64)
        if f.shape != (m,):
            raise MeasurementError(f"edge_offset returned shape {f.shape}, expected ({m},)")
    else:
        f = np.asarray(edge_offset, dtype=np.float64)
        if f.ndim == 0:
            f = np.full(m, float(f))
        elif f.shape == (n,):
            f = f[src]
        else:
            raise MeasurementError(
                f"edge_offset must be a float, a ({n},) array or a callable, got shape {f.shape}"
            )
    if not np.all(np.isfinite(f)) or np.any((f < 0) | (f > 1)):
        raise MeasurementError("edge_offset fractions must be in [0, 1]")
    return f


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
        with the rows of the last on-plate samples and the sides (-1 / +1). Default 0.5.

    Returns
    -------
    EdgePoints

    Raises
    ------
    MeasurementError
        Bad shapes, non-finite values, or ``edge_offset`` outside [0, 1].
    """
    p = finite_points(points, 3, "points")
    n = len(p)
    pl = check_plane(plane)
    sl = check_labels(slit, n, "slit", like="points")
    assert sl is not None
    tt = np.asarray(t, dtype=np.float64)
    if tt.shape != (n,) or not np.all(np.isfinite(tt)):
        raise MeasurementError(f"t must be a finite ({n},) array like points, got {tt.shape}")
    if n < 2:
        return _no_edges()

    order = np.lexsort((tt, sl))
    ps, ss, ts = p[order], sl[order], tt[order]
    dist = ps @ pl[:3] + pl[3]
    scales = _profile_scales(dist, ss, ts, max_plane_distance, min_gap)
    if scales is None:
        return _no_edges()
    max_plane_distance, dt, min_gap = scales
    on, k = _gaps(dist, ss, ts, max_plane_distance, min_gap)
    if k.size == 0:
        return _no_edges()
    g = len(k)
    last, side, valid, gdir, step = _edge_samples(on, k, ps, ss, ts, dt)
    src = order[last]
    f = _edge_fractions(edge_offset, src, side, n)

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


# --------------------------------------------------------------------------- image edges
@dataclass(frozen=True, eq=False)
class HoleEdges:
    """Hole-edge points found in a scan (where slits leave the plate and come back).

    Attributes
    ----------
    points : (M, 3) float64, mm, target frame, on the plate's plane
    uv : (M, 2) float64, px, edge position in the image (NaN for geometric edges)
    slit : (M,) int64
    gap : (M,) int64, the two edges of one gap share it
    side : (M,) int64, -1 the edge at the end of a stripe piece (larger v), +1 at its start
    """

    points: F64
    uv: F64
    slit: I64
    gap: I64
    side: I64

    def __len__(self) -> int:
        return len(self.points)

    @classmethod
    def geometric(cls, edges: EdgePoints) -> HoleEdges:
        """The edges of :func:`hole_edges_from_profiles` without image positions."""
        return cls(
            edges.points,
            np.full((len(edges), 2), np.nan),
            edges.slit.astype(np.int64),
            edges.gap,
            edges.side,
        )


def _line_of_planes(p1: F64, p2: F64) -> tuple[F64, F64]:
    """The line where two planes (4,) meet: a point (3,) and a unit direction (3,)."""
    e = np.cross(p1[:3], p2[:3])
    ne = np.linalg.norm(e)
    if ne < 1e-9:
        raise MeasurementError("a slit plane is parallel to the plate; no edge line")
    e /= ne
    A = np.stack([p1[:3], p2[:3], e])
    x0 = np.linalg.solve(A, -np.array([p1[3], p2[3], 0.0]))
    return x0, e


def _stripe_line_in_image(
    calibration: Calibration,
    line: tuple[F64, F64],
    near: F64,
    half_mm: float = _PROFILE_HALF_MM,
) -> tuple[F64, F64]:
    """Where the calibration puts a slit's stripe on the plate in the image, around the 3D
    point ``near``: 7 points (u, v) px of ``line`` (point, unit direction: the slit plane x
    the plate plane, :func:`_line_of_planes`), +-``half_mm`` along it, projected by the camera
    (with its distortion).

    The hole-edge profile is taken along this line rather than along a line fitted to the
    stripe's last centres: where a rim cuts the stripe obliquely, those centres lean towards
    the side of the stripe that runs on, and a profile taken there crosses half intensity late.
    """
    x0, e = line
    t0 = float((np.asarray(near, float) - x0) @ e)
    q = x0 + (t0 + np.linspace(-half_mm, half_mm, 7))[:, None] * e
    uv = calibration.camera.project(q)
    return uv[:, 0], uv[:, 1]


def _closest_on_lines(x0: F64, e: F64, o: F64, d: F64) -> F64:
    """Points on lines (x0, e) (N, 3) nearest to rays (o, d) (N, 3)."""
    w = x0 - o
    a = np.einsum("ij,ij->i", e, e)
    b = np.einsum("ij,ij->i", e, d)
    c = np.einsum("ij,ij->i", d, d)
    dd = np.einsum("ij,ij->i", d, w)
    ee = np.einsum("ij,ij->i", e, w)
    den = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * dd - c * ee) / den
    return x0 + s[:, None] * e


def _bilinear(img: F64, u: F64, v: F64) -> F64:
    h, w = img.shape
    u = np.clip(u, 0, w - 1.000001)
    v = np.clip(v, 0, h - 1.000001)
    u0 = np.floor(u).astype(np.intp)
    v0 = np.floor(v).astype(np.intp)
    fu, fv = u - u0, v - v0
    return (
        img[v0, u0] * (1 - fu) * (1 - fv)
        + img[v0, u0 + 1] * fu * (1 - fv)
        + img[v0 + 1, u0] * (1 - fu) * fv
        + img[v0 + 1, u0 + 1] * fu * fv
    )


def locate_edge_subpixel(
    image: F64,
    u_pts: F64,
    v_pts: F64,
    v_last: float,
    direction: int,
    search_px: float = 12.0,
    inner_px: float = 10.0,
) -> tuple[float, float] | None:
    """Where a stripe fades out at a hole's rim, to a fraction of a row.

    Along the stripe's centre line (a line u = a + b v fitted to the given points,
    extrapolated), the stripe's intensity (bilinear, weighted 1/4, 1/2, 1/4 across the centre
    line) is taken on every row from ``inner_px`` rows inside the edge to ``search_px`` rows
    beyond it. The plate's level is the median on the rows inside, the hole's the low tail
    beyond; the edge is the first row where the profile falls below the mean of the two,
    interpolated linearly between that row and the one before.

    Parameters
    ----------
    image : (H, W) float64
    u_pts, v_pts : (n,) float64, px, points of the stripe's centre line next to the edge
    v_last : float, px, row of the last stripe centre before the edge
    direction : +1 the edge lies at larger v than ``v_last``, -1 at smaller v
    search_px : float, px, rows searched beyond ``v_last``. Default 12.
    inner_px : float, px, rows inside ``v_last`` that give the plate's level. Default 10.

    Returns
    -------
    (u, v) px of the edge, or None when the stripe does not fade out (not a rim) or the
    profile is unusable.
    """
    if len(u_pts) >= 3 and np.ptp(v_pts) > 0:
        b, a = np.polyfit(v_pts, u_pts, 1)
    else:
        a, b = float(np.median(u_pts)), 0.0
    rows = v_last + direction * np.arange(-inner_px, search_px + 1.0)
    h, w = image.shape
    if rows.min() < 0 or rows.max() > h - 1:
        return None
    uc = a + b * rows
    if uc.min() < 2 or uc.max() > w - 3:
        return None
    prof = (
        0.5 * _bilinear(image, uc, rows)
        + 0.25 * _bilinear(image, uc - 1, rows)
        + 0.25 * _bilinear(image, uc + 1, rows)
    )
    k_in = int(inner_px) - 2  # rows 0..k_in-1 are inside (on the plate)
    plate = float(np.median(prof[:k_in]))
    beyond = prof[int(inner_px) + 1 :]
    if beyond.size < 3:
        return None
    low = float(np.percentile(beyond, 20))
    if plate - low < max(8.0, 0.35 * plate):  # the stripe does not fade out: not a rim
        return None
    half = 0.5 * (plate + low)
    below = np.flatnonzero(prof[k_in:] < half)
    if below.size == 0:
        return None
    j = k_in + int(below[0])
    if j == 0 or j + 2 >= len(prof) or np.any(prof[j : j + 3] >= half):
        return None  # a dip, not an edge (the stripe comes back right away)
    f = (prof[j - 1] - half) / (prof[j - 1] - prof[j])
    ve = float(rows[j - 1] + direction * f)
    return float(a + b * ve), ve


def subpixel_edges(
    edges: EdgePoints,
    points: F64,
    v: F64,
    plane: F64,
    image: ArrayLike,
    calibration: Calibration,
    search_px: float = 12.0,
) -> tuple[HoleEdges, int]:
    """The edges of :func:`hole_edges_from_profiles` (with ``edge_offset=0``) located in the
    image (:func:`locate_edge_subpixel`), each edge's 3D point the point of the line (slit
    plane x plate plane) nearest to the edge pixel's line of sight.

    Parameters
    ----------
    edges : EdgePoints, from the scan's ``points`` with ``t = v``
    points : (N, 3) float64, mm, the scan's points; v : (N,) float64, px, their rows
    plane : (4,) float64, the plate's plane, unit normal
    image : (H, W) the scan image
    calibration : the rig's calibration (camera and slit planes)
    search_px : float, px, how far beyond the last point (rows) the edge is searched

    Returns
    -------
    edges : HoleEdges, the edges found in the image
    rejected : int, gap ends whose stripe does not fade out (no rim) or whose slit has no plane
    """
    img = np.asarray(image, dtype=np.float64)
    assert calibration.slit_planes is not None
    calibration.check_image_size((img.shape[1], img.shape[0]))
    planes = calibration.slit_planes.planes
    # the line where each edge's slit plane meets the plate: the profile runs along its
    # image and the edge's 3D point lies on it; an edge whose slit has no plane is rejected
    valid = np.all(np.isfinite(planes[edges.slit]), axis=1)
    lines = {int(k): _line_of_planes(planes[k], plane) for k in np.unique(edges.slit[valid])}
    uv = np.full((len(edges), 2), np.nan)
    for i in np.flatnonzero(valid):  # per edge: a short image profile
        s = int(edges.source[i])
        uu, vv = _stripe_line_in_image(calibration, lines[int(edges.slit[i])], points[s])
        direction = -int(edges.side[i])  # side -1: the stripe ends at larger v
        loc = locate_edge_subpixel(img, uu, vv, float(v[s]), direction, search_px)
        if loc is not None:
            uv[i] = loc
    ok = np.all(np.isfinite(uv), axis=1)
    rejected = int(np.count_nonzero(~ok))
    pts = np.full((len(edges), 3), np.nan)
    if ok.any():
        o, d = calibration.camera.rays(uv[ok])
        x0 = np.array([lines[int(k)][0] for k in edges.slit[ok]])
        ed = np.array([lines[int(k)][1] for k in edges.slit[ok]])
        pts[ok] = _closest_on_lines(x0, ed, o, d)
    found = HoleEdges(pts[ok], uv[ok], edges.slit[ok], edges.gap[ok], edges.side[ok])
    return found, rejected
