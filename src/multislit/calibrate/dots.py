"""The dot projector calibrated from the reference boards: its source and one ray per dot.

Each reference board is a plane posed by the bundle adjustment. A dot seen in a board's image,
its line of sight met with the board's plane, is a 3D point of that dot's ray; all rays pass
through one source. Each board is first read for its dots
(:func:`~multislit.calibrate.board_dots.read_board`: every dot fitted as a spot beside its
neighbours on a sharp response in which the stripes cancel). :func:`fit_dot_projector` then:

1. finds the source as the boards' clear dots agree on it: each is described by its slit
   coordinate (where it lies between the slit planes, about their common axis, in slit
   spacings) and its elevation along the axis. A dot keeps its slit coordinate from board to
   board when the dot source lies near the slit axis (a dot projector beside the slit
   projector, along the slits); dots of two boards with nearly the same coordinates are
   candidate pairs, and the line through a true pair passes through the source, so the
   source's place along the axis is the mode of where the lines come closest to it. The source
   is refined in 3D by least squares over the lines that pass near it, then over the lines of
   the dots matched across the boards;
2. makes candidate rays: every fitted dot of every board, seen from the source, is one.
   Candidates of different boards whose directions agree (each the other's nearest, within a
   pixel's angle) are one dot; a candidate's ray is the mean of its dots' directions weighted
   by their centres' inverse variances, and it takes the dot of another board that lies within
   a pixel of where the ray meets that board;
3. weighs each candidate by a likelihood ratio, a dot against chance: its dots' places as
   images of one ray (their standard errors scaled by how much the clear candidates scatter;
   each centre with a 10 % chance of being pulled off by speckle or a neighbour) against dots
   of other rays falling there by chance (at the board's density of dots at least as clear);
   and, on each board where it has no dot, the spot's height fitted where the ray meets the
   board against the height a dot as bright as on the other boards (relative to the stripe
   there) would have: a board where the dot would be too faint to see says little, an empty
   place where it would show counts against it. A board where the ray leaves the image or
   meets saturated pixels says nothing;
4. refines the source over the lines of the candidates that reach :data:`_ACCEPT_NATS` and
   makes the candidates again from it;
5. refines every candidate on all boards at once
   (:func:`~multislit.calibrate.board_dots.fit_rays_on_boards`): its direction and its
   spot's height on each board, fitted to each
   board's sharp response less the spots of the other rays and of the board's other dots. A
   ray is kept when its heights on the boards together, as a matched filter of a dot as bright
   on every board relative to the stripe nearest it, reach :data:`_RAY_Z` standard errors; of
   two rays closer than one dot's sigma the stronger is kept. A board shows the ray's dot where
   its height reaches :data:`_SEEN_Z` standard errors.

Each ray's brightness is its dot's response (the identification's: the image smoothed by the
dot's Gaussian less its mean along the stripe) where it meets a board, divided by the peak of
the stripe nearest it, the median over the boards that show it. The residuals are the image
distances between each board's own centre of a ray's dot and where the ray meets that board.

Units: mm in the world (target) frame, px in the image, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.special import erf as _erf

from multislit._groups import group_medians
from multislit.calibrate.board_dots import (
    Board,
    BoardDots,
    BoardView,
    fit_rays_on_boards,
    read_board,
)
from multislit.calibrate.boards import ReferenceStripes, board_points
from multislit.calibrate.slit_planes import SlitPlanes, common_line
from multislit.errors import CalibrationError
from multislit.geometry import PinholeCamera, intersect_rays_planes, orthonormal_basis
from multislit.geometry.camera import F64
from multislit.geometry.dots import DotProjector, angles_of, dot_frame
from multislit.stripes.dots import SharpResponse

#: Pairs of dots of two boards are candidates when their slit coordinates differ by at most
#: this many slit spacings ...
_PAIR_KAPPA = 0.15
#: ... and their elevations along the axis by at most this (rad): a source up to about 0.4 of
#: the board distance from the axis's nearest point to the camera.
_PAIR_ETA = 0.08
#: Candidate lines that pass farther than this from the slit axis are not counted (mm).
_AXIS_REACH = 40.0
#: Bin of the histogram of the source's place along the axis (mm).
_AXIS_BIN = 4.0
#: Tolerances (mm) of the lines kept in the successive least-squares refinements of the source.
_REFINE_MM = (12.0, 5.0, 2.5)
#: The source is found from the dots of at least this many standard errors of their height
#: (the clear ones; the _SOURCE_DOTS brightest of them per board) ...
_SOURCE_Z = 6.0
_SOURCE_DOTS = 3000
#: ... whose directions from it agree across boards within this many pixels' angle
#: (mutual nearest neighbours) ...
_TRACK_PX = 2.0
#: ... on at least this many boards, and on every posed board when they lie near a stripe
#: on one of them (speckle on a stripe lines up along the stripe from board to board).
_MIN_SEEN = 2
#: Least number of matched dots (and of rays) for a dot projector.
_MIN_TRACKS = 50
#: Dots of two boards whose directions from the source agree within this many pixels' angle
#: (each the other's nearest) are one candidate ray; a ray takes a board's dot within this
#: many px of where it meets the board.
_MATCH_PX = 1.0
#: The chance that a dot's centre on a board is pulled off its ray's image (by speckle or a
#: neighbour), anywhere within :data:`_MATCH_PX`.
_BAD_CENTRE = 0.1
#: A dot's centre is never taken as better known than this (px, standard error).
_MIN_SE_PX = 0.03
#: The chance that a dot in view of a board is among the board's fitted dots.
_FOUND = 0.9
#: A dot expected at mu standard errors of its height on a board is among the board's fitted
#: dots with the chance Phi(mu - _FOUND_Z), between _MIN_FOUND and _FOUND; where it is not,
#: its height fitted there counts at most _Z_ABOVE above mu (a neighbour's light).
_FOUND_Z = 3.0
_MIN_FOUND = 0.02
_Z_ABOVE = 2.0
#: The board's density of dots around a place is counted within this radius (px).
_DENSITY_PX = 8.0
#: A candidate is fitted as a ray when its likelihood ratio reaches this (nats); two
#: candidates within this many pixels' angle are one (the stronger kept).
_ACCEPT_NATS = 2.0
_CANDIDATE_MERGE_PX = 0.7
#: A fitted ray is kept when its spots' heights on the boards reach this many standard errors
#: together (:func:`_ray_evidence`); two rays within this many pixels' angle are one dot.
_RAY_Z = 5.0
_MERGE_SIGMAS = 1.0
#: The source is refined over the lines of the candidates found on every board with at least
#: this likelihood ratio (nats).
_SOURCE_NATS = 8.0
#: Rounds of the rays (each from the source the previous one refined).
_RAY_ROUNDS = 1
#: Rounds of the rays' joint fit on all boards.
_JOINT_ROUNDS = 3
#: The step (pixels' angle) of the finite differences of where a ray meets a board.
_JAC_PX = 0.5
#: A board shows a ray's dot when its spot's height there reaches this many standard errors.
_SEEN_Z = 3.0


@dataclass(frozen=True, eq=False)
class DotFit:
    """The dot projector fitted by :func:`fit_dot_projector`, with its figures.

    Attributes
    ----------
    projector : DotProjector, the rays
    found : (R,) int, the rays seen on each board (their dots fitted on it)
    spots : (R,) int, the dots fitted on each board (:class:`BoardDots`), rays or not
    tracked : int, the rays
    rms_px : float, px, RMS of every ray's images on the boards from where it meets them
    source_rms_mm : float, mm, RMS distance of the rays' lines (seen on two or more boards)
        from the source
    """

    projector: DotProjector
    found: NDArray[np.int_]
    spots: NDArray[np.int_]
    tracked: int
    rms_px: float
    source_rms_mm: float

    def report(self) -> dict:
        """Figures for people (the calibration report's ``dot_projector`` entry)."""
        p = self.projector
        seen = np.bincount(p.seen, minlength=4)
        b = p.brightness[np.isfinite(p.brightness)]
        return {
            "source_mm": [round(float(x), 2) for x in p.source],
            "dots_found_per_board": [int(n) for n in self.found],
            "spots_per_board": [int(n) for n in self.spots],
            "rays": int(self.tracked),
            "rays_by_boards_seen": {str(k): int(seen[k]) for k in range(1, len(seen)) if seen[k]},
            "rms_px": round(float(self.rms_px), 4),
            "source_rms_mm": round(float(self.source_rms_mm), 3),
            "brightness_median": round(float(np.median(b)), 4) if b.size else None,
        }


def _slit_axis(slit_planes: SlitPlanes) -> tuple[F64, F64]:
    """(point, unit direction) of the slit planes' common axis (fitted from the planes when the
    calibration kept none)."""
    if slit_planes.axis_point is not None and slit_planes.axis_direction is not None:
        a, u = np.asarray(slit_planes.axis_point), np.asarray(slit_planes.axis_direction)
    else:
        pl = slit_planes.planes[slit_planes.valid]
        if len(pl) < 3:
            raise CalibrationError("dot projector: fewer than 3 slit planes, no slit axis")
        a, u = common_line(pl)
    return a.astype(np.float64), u / np.linalg.norm(u)


def _axis_coordinates(
    X: F64, slit_planes: SlitPlanes, a: F64, u: F64, centre: F64
) -> tuple[F64, F64, F64]:
    """Per 3D point (M, 3): its slit coordinate (fractional slit number), its angle about the
    axis (rad) and its elevation along the axis seen from the axis point ``a`` (rad)."""
    e1, e2 = orthonormal_basis(u)
    q = X - a
    along = q @ u
    w = q - along[:, None] * u
    theta = np.arctan2(w @ e1, w @ e2)
    pl = slit_planes.planes
    ok = slit_planes.valid
    m = np.cross(u[None, :], pl[:, :3])  # in each plane, perpendicular to the axis
    # point the in-plane directions to the scene (away from the camera's side of the axis)
    toward = X.mean(axis=0) - a if len(X) else centre - a
    m *= np.sign(m @ toward)[:, None]
    th_k = np.arctan2(m @ e1, m @ e2)
    k = np.flatnonzero(ok)
    ang = np.unwrap(th_k[k])
    order = np.argsort(ang)
    kappa = np.interp(theta, ang[order], k[order].astype(float), left=np.nan, right=np.nan)
    # beyond the outer slits: extrapolate with the end spacings
    lo, hi = ang[order][[0, 1]], ang[order][[-2, -1]]
    kk = k[order].astype(float)
    left = theta < ang[order][0]
    right = theta > ang[order][-1]
    kappa[left] = kk[0] + (theta[left] - lo[0]) / (lo[1] - lo[0]) * (kk[1] - kk[0])
    kappa[right] = kk[-1] + (theta[right] - hi[1]) / (hi[1] - hi[0]) * (kk[-1] - kk[-2])
    eta = np.arctan2(along, np.linalg.norm(w, axis=1))
    return kappa, theta, eta


def _closest_point(points: F64, dirs: F64, weights: F64 | None = None) -> F64:
    """The point (3,) closest (least squares) to the lines through ``points`` (M, 3) along the
    unit ``dirs`` (M, 3)."""
    w = np.ones(len(points)) if weights is None else weights
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    A = np.einsum("m,mij->ij", w, P)
    b = np.einsum("m,mij,mj->i", w, P, points)
    return np.linalg.solve(A, b)


def _line_distances(o: F64, points: F64, dirs: F64) -> F64:
    """Distances (M,) of the point ``o`` (3,) from the lines (points, unit dirs) (M, 3)."""
    q = o - points
    return np.linalg.norm(q - np.einsum("ij,ij->i", q, dirs)[:, None] * dirs, axis=1)


def _candidate_lines(X: list[F64], kappa: list[F64], eta: list[F64]) -> tuple[F64, F64]:
    """The lines through candidate pairs of dots of two boards: (points, unit directions)."""
    pts, dirs = [], []
    for a in range(len(X)):
        for b in range(a + 1, len(X)):
            if len(X[a]) == 0 or len(X[b]) == 0:
                continue
            ta = cKDTree(np.c_[kappa[a] / _PAIR_KAPPA, eta[a] / _PAIR_ETA])
            tb = cKDTree(np.c_[kappa[b] / _PAIR_KAPPA, eta[b] / _PAIR_ETA])
            pairs = ta.sparse_distance_matrix(tb, 1.0, p=np.inf, output_type="ndarray")
            ia = pairs["i"].astype(np.intp)
            ib = pairs["j"].astype(np.intp)
            d = X[b][ib] - X[a][ia]
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            pts.append(X[a][ia])
            dirs.append(d)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pts), np.concatenate(dirs)


def _source_on_axis(points: F64, dirs: F64, a: F64, u: F64) -> F64:
    """The source's first estimate: the point of the axis (a, u) where most candidate lines
    come closest to it."""
    # closest points between each line (p + t d) and the axis (a + s u)
    w0 = points - a
    b = dirs @ u
    d_ = np.einsum("ij,ij->i", dirs, w0)
    e_ = w0 @ u
    den = 1.0 - b**2
    ok = den > 1e-9
    s = np.where(ok, (e_ - b * d_) / np.where(ok, den, 1.0), np.nan)
    t = np.where(ok, (b * e_ - d_) / np.where(ok, den, 1.0), np.nan)
    gap = np.linalg.norm(points + t[:, None] * dirs - (a + s[:, None] * u), axis=1)
    keep = ok & (gap < _AXIS_REACH) & np.isfinite(s)
    if keep.sum() < _MIN_TRACKS:
        raise CalibrationError(
            "dot projector: too few dots of the reference boards line up with the slit axis "
            f"({int(keep.sum())} candidate pairs); are the dots in the reference images, and is "
            "the dot projector beside the slit projector?"
        )
    ss = s[keep]
    lo, hi = np.percentile(ss, [1, 99])
    nb = max(1, int(np.ceil((hi - lo) / _AXIS_BIN)))
    hist, edges = np.histogram(ss, bins=nb, range=(lo, hi + 1e-9))
    sm = np.convolve(hist, [1, 2, 1], mode="same")
    i = int(np.argmax(sm))
    s0 = 0.5 * (edges[i] + edges[i + 1])
    return a + s0 * u


def _refine_source(o: F64, points: F64, dirs: F64) -> tuple[F64, NDArray[np.bool_]]:
    """Least squares over the candidate lines within the shrinking tolerances of the source."""
    keep = np.zeros(len(points), bool)
    for tol in _REFINE_MM:
        keep = _line_distances(o, points, dirs) < tol
        if keep.sum() < _MIN_TRACKS:
            break
        o = _closest_point(points[keep], dirs[keep])
    return o, keep


def _tracks(
    dirs: list[F64], tol: float
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Dots of all boards grouped by direction: (track id, board, index) of every grouped dot.

    A dot joins the dot of another board whose direction (unit vectors ``dirs``, (M_r, 3) per
    board) is nearest, within ``tol`` rad, when each is the other's nearest (mutual nearest
    neighbours)."""
    nb = len(dirs)
    offsets = np.cumsum([0] + [len(d) for d in dirs])
    n = int(offsets[-1])
    ea, eb = [], []
    trees = [cKDTree(d) if len(d) else None for d in dirs]
    for a in range(nb):
        for b in range(a + 1, nb):
            if trees[a] is None or trees[b] is None:
                continue
            dab, jab = trees[b].query(dirs[a], distance_upper_bound=tol)
            dba, jba = trees[a].query(dirs[b], distance_upper_bound=tol)
            i = np.flatnonzero(np.isfinite(dab))
            i = i[jba[jab[i]] == i]
            ea.append(offsets[a] + i)
            eb.append(offsets[b] + jab[i])
    e_a = np.concatenate(ea) if ea else np.zeros(0, np.intp)
    e_b = np.concatenate(eb) if eb else np.zeros(0, np.intp)
    graph = coo_matrix((np.ones(len(e_a)), (e_a, e_b)), shape=(n, n))
    _, roots = connected_components(graph, directed=False)
    board = np.repeat(np.arange(nb), np.diff(offsets))
    index = np.arange(n) - offsets[board]
    return roots.astype(np.intp), board, index


def _valid_tracks(
    X_l: list[F64], o: F64, pixel_angle: float, on_stripe: NDArray[np.bool_], boards: int
) -> tuple[NDArray[np.intp], NDArray[np.int_], NDArray[np.intp]]:
    """The tracks of dots seen on two or more boards (on every board when one of their
    images lies on a stripe): (track of each member (M,), dots per track (T,), the members'
    indices into the boards' dots concatenated (M,))."""
    vec = [(X - o) / np.linalg.norm(X - o, axis=1, keepdims=True) for X in X_l]
    root, _, _ = _tracks(vec, _TRACK_PX * pixel_angle)
    ids, inv, cnt = np.unique(root, return_inverse=True, return_counts=True)
    on_track = np.bincount(inv, weights=on_stripe.astype(float), minlength=len(ids)) > 0
    ok = (cnt >= _MIN_SEEN) & ~(on_track & (cnt < boards))
    new = np.cumsum(ok) - 1
    member = np.flatnonzero(ok[inv])
    return new[inv[member]], cnt[ok], member


def _track_lines(X: F64, tid: NDArray[np.intp], n: int, o: F64) -> tuple[F64, F64]:
    """Per track: its mean point (n, 3) and the direction of its points' largest spread
    (n, 3), pointing away from ``o`` (for a track of two points, the line through them)."""
    cnt = np.bincount(tid, minlength=n).astype(float)
    mean = np.zeros((n, 3))
    np.add.at(mean, tid, X)
    mean /= cnt[:, None]
    d = X - mean[tid]
    scatter = np.zeros((n, 3, 3))
    np.add.at(scatter, tid, d[:, :, None] * d[:, None, :])
    _, vec = np.linalg.eigh(scatter)
    line = vec[:, :, -1]
    away = mean - o
    line *= np.sign(np.einsum("ij,ij->i", line, away))[:, None]
    return mean, line


def _unit(v: F64) -> F64:
    """Rows of ``v`` (M, 3) scaled to unit length."""
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _source(
    X_l: list[F64],
    near_l: list[NDArray[np.bool_]],
    slit_planes: SlitPlanes,
    centre: F64,
    f: float,
    boards: int,
) -> F64:
    """The dot source (3,) mm from the clear dots of the boards (3D points ``X_l``, whether
    each lies near a stripe ``near_l``): the point of the slit axis most candidate pairs' lines
    come closest to, refined over them and then over the lines of the dots matched across the
    boards (twice)."""
    a, u = _slit_axis(slit_planes)
    kappa, eta = [], []
    for X in X_l:
        kp, _, et = _axis_coordinates(X, slit_planes, a, u, centre)
        kappa.append(kp)
        eta.append(et)
    points, dirs = _candidate_lines(X_l, kappa, eta)
    o = _source_on_axis(points, dirs, a, u)
    o, _ = _refine_source(o, points, dirs)
    Xall = np.concatenate(X_l)
    on_all = np.concatenate(near_l)
    for _ in range(2):
        tid, seen, member = _valid_tracks(X_l, o, 1.0 / f, on_all, boards)
        if seen.size < _MIN_TRACKS:
            raise CalibrationError(
                f"dot projector: only {seen.size} dots were found on two or more reference "
                "boards; the reference images must show the same dots at different distances"
            )
        mean_pt, line_d = _track_lines(Xall[member], tid, seen.size, o)
        o = _closest_point(mean_pt, line_d)
    return o


@dataclass(frozen=True, eq=False)
class _Rays:
    """One round of the rays (:func:`_make_rays`): per ray its unit direction (N, 3), its
    log-likelihood ratio (N,) nats, and its dots: ``ray``, ``board``, ``index`` (K,) (into the
    board's fitted dots)."""

    direction: F64
    llr: F64
    ray: NDArray[np.intp]
    board: NDArray[np.intp]
    index: NDArray[np.intp]


def _chi2_median(dof: NDArray[np.int_]) -> F64:
    """The median of the chi-square distribution of ``dof`` degrees of freedom (Wilson and
    Hilferty's approximation)."""
    k = np.maximum(dof, 1).astype(float)
    return k * (1.0 - 2.0 / (9.0 * k)) ** 3


def _predict(o: F64, d: F64, plane: F64, camera: PinholeCamera) -> F64:
    """(N, 2) px: where the rays from ``o`` along ``d`` (N, 3) meet ``plane``, in the image."""
    X, _ = intersect_rays_planes(np.broadcast_to(o, d.shape), d, plane)
    return camera.project(X)


def _make_rays(
    o: F64,
    cats: list[BoardDots],
    X_l: list[F64],
    views: list[BoardView],
    sharps: list[SharpResponse],
    board_planes: F64,
    camera: PinholeCamera,
    frame: F64,
    f: float,
) -> _Rays:
    """The rays from the source ``o``: candidates by direction, each weighed by its
    likelihood ratio; the candidates that reach :data:`_ACCEPT_NATS`, one per dot."""
    R = len(cats)
    offs = np.cumsum([0] + [len(c) for c in cats])
    n_all = int(offs[-1])
    board_of = np.repeat(np.arange(R), np.diff(offs))
    index_of = np.arange(n_all) - offs[board_of]
    se = np.concatenate([np.maximum(c.se_px, _MIN_SE_PX) for c in cats])
    dirs = [_unit(X - o) if len(X) else np.zeros((0, 3)) for X in X_l]
    D = np.concatenate(dirs)
    # angles seen from the source, in pixels' angle: where the candidates are compared
    ph, ps, _ = angles_of(D, frame)
    ang = f * np.stack([ph, ps], axis=1)
    # candidates: mutual nearest neighbours by direction; one dot per board (the best centred)
    root, _, _ = _tracks(dirs, _MATCH_PX / f)
    order = np.lexsort((se, board_of, root))
    first = np.ones(n_all, bool)
    first[1:] = (root[order][1:] != root[order][:-1]) | (
        board_of[order][1:] != board_of[order][:-1]
    )
    cand = np.empty(n_all, np.intp)
    cand[order] = np.where(first, root[order], n_all + order)  # extra dots: their own candidate
    _, cand = np.unique(cand, return_inverse=True)
    # every dot is a member of one candidate; a ray takes the dots it meets on other boards
    cand = _absorb(cand, board_of, se, cats, o, D, board_planes, camera, f)
    n_c = int(cand.max()) + 1 if n_all else 0
    ray_d, ang_c = _mean_rays(cand, n_c, D, se, frame, f)
    # the likelihood ratio of each candidate
    llr = np.zeros(n_c)
    cnt = np.bincount(cand, minlength=n_c)
    kappa = _kappa(cand, cnt, ang, ang_c, se, cats)
    trees = [cKDTree(c.uv) if len(c) else None for c in cats]
    area = math.pi * _MATCH_PX**2
    pos_llr = _positions_llr(cand, cnt, ang, kappa * se, area)
    llr += pos_llr
    is_member = np.zeros((n_c, R), bool)
    is_member[cand, board_of] = True
    beta = _candidate_brightness(cand, n_c, cats, views, board_of, index_of)
    assoc = np.full((n_c, R), np.nan)
    for b in range(R):
        if views[b] is None or trees[b] is None:
            continue
        uv = _predict(o, ray_d, board_planes[b], camera)
        h, w = views[b].shape
        inside = np.all(np.isfinite(uv), axis=1)
        inside &= (uv[:, 0] >= 2) & (uv[:, 0] <= w - 3) & (uv[:, 1] >= 2) & (uv[:, 1] <= h - 3)
        n_near = np.zeros(n_c)
        n_near[inside] = trees[b].query_ball_point(uv[inside], _DENSITY_PX, return_length=True)
        rho = np.maximum(n_near - is_member[:, b], 0.5) / (math.pi * _DENSITY_PX**2)
        p_chance = -np.expm1(-rho * area)
        # a board with one of the candidate's dots: found there, not by chance (by a dot at
        # least as clear: the board's share of such dots thins the density)
        m = inside & is_member[:, b]
        zb = np.sort(cats[b].z)
        z_m = np.full(n_c, np.nan)
        z_m[cand[board_of == b]] = cats[b].z[index_of[board_of == b]]
        share = 1.0 - np.searchsorted(zb, z_m[m], side="left") / len(zb)
        p_clear = -np.expm1(-rho[m] * np.maximum(share, 1.0 / len(zb)) * area)
        assoc[m, b] = math.log(_FOUND) - np.log(p_clear)
        # a board without: what the dots' response says where the ray meets it, against the
        # dot as bright as on the boards that show it (relative to the stripes)
        e = inside & ~is_member[:, b]
        z = np.full(n_c, np.nan)
        se_b = np.full(n_c, np.nan)
        z[e], se_b[e] = sharps[b].spot_fit(uv[e])
        e &= np.isfinite(z) & np.isfinite(beta) & (se_b > 0)
        mu = np.zeros(n_c)
        mu[e] = beta[e] * views[b].stripe_peak(uv[e, 0], uv[e, 1]) / se_b[e]
        e &= np.isfinite(mu)
        found = np.clip(_normal_cdf(mu[e] - _FOUND_Z), _MIN_FOUND, _FOUND)
        zz = np.minimum(z[e], mu[e] + _Z_ABOVE)
        llr[e] += np.log1p(-found) - np.log1p(-p_chance[e]) + mu[e] * zz - 0.5 * mu[e] ** 2
    # the first dot (the one found most by chance) is the candidate's own: no term for it
    a = np.where(np.isfinite(assoc), assoc, 0.0)
    a_max = np.where(np.isfinite(assoc), assoc, -np.inf).max(axis=1)
    llr += a.sum(axis=1) - np.where(np.isfinite(a_max), a_max, 0.0)
    keep = _one_per_dot(llr, ang_c, _ACCEPT_NATS, _CANDIDATE_MERGE_PX)
    new = np.full(n_c, -1, np.intp)
    new[keep] = np.arange(keep.size)
    m = new[cand] >= 0
    return _Rays(ray_d[keep], llr[keep], new[cand[m]], board_of[m], index_of[m])


def _normal_cdf(x: F64) -> F64:
    """The standard normal distribution function at ``x``."""
    return 0.5 * (1.0 + _erf(x / math.sqrt(2.0)))


def _candidate_brightness(
    cand: NDArray[np.intp],
    n_c: int,
    cats: list[BoardDots],
    views: list[BoardView],
    board_of: NDArray[np.intp],
    index_of: NDArray[np.intp],
) -> F64:
    """(N,) each candidate's dots' fitted height over the peak of the stripe nearest them,
    the median over its dots (NaN: unknown)."""
    ratio = np.full(len(cand), np.nan)
    for b, (c, view) in enumerate(zip(cats, views, strict=True)):
        m = board_of == b
        if m.any():
            i = index_of[m]
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio[m] = c.height[i] / view.stripe_peak(c.u[i], c.v[i])
    ratio[~(np.isfinite(ratio) & (ratio > 0))] = np.nan
    return group_medians(ratio, cand, n_c)


def _absorb(
    cand: NDArray[np.intp],
    board_of: NDArray[np.intp],
    se: F64,
    cats: list[BoardDots],
    o: F64,
    D: F64,
    board_planes: F64,
    camera: PinholeCamera,
    f: float,
) -> NDArray[np.intp]:
    """The candidates (``cand`` per dot) after each candidate of two or more dots took, on each
    board without one of its dots, the single-dot candidate within :data:`_MATCH_PX` of where
    its ray meets the board (the nearest claim wins)."""
    n_c = int(cand.max()) + 1 if cand.size else 0
    cnt = np.bincount(cand, minlength=n_c)
    frame_free = np.eye(3)
    ray_d, _ = _mean_rays(cand, n_c, D, se, frame_free, f)
    offs = np.cumsum([0] + [len(c) for c in cats])
    has = np.zeros((n_c, len(cats)), bool)
    has[cand, board_of] = True
    cand = cand.copy()
    for b, cat in enumerate(cats):
        if len(cat) == 0 or not np.all(np.isfinite(board_planes[b])):
            continue
        claim = np.flatnonzero((cnt >= 2) & ~has[:, b])
        if claim.size == 0:
            continue
        uv = _predict(o, ray_d[claim], board_planes[b], camera)
        ok = np.all(np.isfinite(uv), axis=1)
        dist, j = cKDTree(cat.uv).query(
            np.where(ok[:, None], uv, -1e9), distance_upper_bound=_MATCH_PX
        )
        hit = np.isfinite(dist)
        g = offs[b] + j[hit]  # the dots claimed
        single = cnt[cand[g]] == 1
        c_h, g, dist = claim[hit][single], g[single], dist[hit][single]
        order = np.argsort(dist)
        _, first = np.unique(g[order], return_index=True)
        take = order[first]
        cand[g[take]] = c_h[take]
    _, cand = np.unique(cand, return_inverse=True)
    return cand


def _mean_rays(
    cand: NDArray[np.intp], n_c: int, D: F64, se: F64, frame: F64, f: float
) -> tuple[F64, F64]:
    """Each candidate's ray: the mean of its dots' directions weighted by their centres'
    inverse variances (N, 3), and its angles in pixels' angle (N, 2)."""
    w = 1.0 / se**2
    s = np.zeros((n_c, 3))
    np.add.at(s, cand, w[:, None] * D)
    d = _unit(s)
    ph, ps, _ = angles_of(d, frame)
    return d, f * np.stack([ph, ps], axis=1)


def _kappa(
    cand: NDArray[np.intp],
    cnt: NDArray[np.int_],
    ang: F64,
    ang_c: F64,
    se: F64,
    cats: list[BoardDots],
) -> float:
    """How much the dots' places scatter about their rays beyond their standard errors: the
    factor on the errors that gives the clear candidates of two or more dots the median
    chi-square of their degrees of freedom (at least 1)."""
    z = np.concatenate([c.z for c in cats]) if cats else np.zeros(0)
    clear = np.ones(len(cnt), bool)
    np.logical_and.at(clear, cand, z >= _SOURCE_Z)
    chi2 = np.bincount(
        cand, weights=np.sum((ang - ang_c[cand]) ** 2, axis=1) / se**2, minlength=len(cnt)
    )
    use = clear & (cnt >= 2)
    if use.sum() < _MIN_TRACKS:
        return 1.0
    k2 = np.median(chi2[use] / _chi2_median(2 * (cnt[use] - 1)))
    return float(np.clip(math.sqrt(max(k2, 0.0)), 1.0, 5.0))


def _positions_llr(
    cand: NDArray[np.intp], cnt: NDArray[np.int_], ang: F64, sig: F64, area: float
) -> F64:
    """Per candidate (N,): the log-likelihood ratio of its dots' places (``ang`` (K, 2),
    pixels' angle, standard errors ``sig`` (K,)) as images of one ray against each dot beyond
    the first falling anywhere within :data:`_MATCH_PX` of it (area ``area`` px^2).

    The dots are taken best centred first; each next one is compared with the weighted mean of
    those before it (the chain rule of the evidence of points about one unknown place), as
    one of its images with the chance :data:`_BAD_CENTRE` of a centre pulled anywhere within
    :data:`_MATCH_PX` (by speckle or a neighbour) instead."""
    n_c = len(cnt)
    order = np.lexsort((sig, cand))
    c_s, a_s, s_s = cand[order], ang[order], sig[order]
    start = np.searchsorted(c_s, np.arange(n_c))
    rank = np.arange(len(c_s)) - start[c_s]
    out = np.zeros(n_c)
    w_sum = np.zeros(n_c)
    m_sum = np.zeros((n_c, 2))
    for k in range(int(cnt.max()) if n_c else 0):
        m = rank == k
        c = c_s[m]
        w = 1.0 / s_s[m] ** 2
        if k:
            mean = m_sum[c] / w_sum[c][:, None]
            var = s_s[m] ** 2 + 1.0 / w_sum[c]
            e2 = np.sum((a_s[m] - mean) ** 2, axis=1)
            good = np.exp(-0.5 * e2 / var) / (2.0 * math.pi * var)
            out[c] += np.log((1.0 - _BAD_CENTRE) * good + _BAD_CENTRE / area) + math.log(area)
        w_sum[c] += w
        m_sum[c] += w[:, None] * a_s[m]
    return out


def _one_per_dot(score: F64, ang: F64, floor: float, radius: float) -> NDArray[np.intp]:
    """The candidates whose ``score`` reaches ``floor``, strongest first, each leaving out the
    weaker ones within ``radius`` pixels' angle of it (``ang`` (N, 2)): one dot split in
    two."""
    llr = score
    ok = np.flatnonzero(llr >= floor)
    ok = ok[np.argsort(-llr[ok], kind="stable")]
    if ok.size == 0:
        return ok
    tree = cKDTree(ang[ok])
    pairs = tree.query_pairs(radius, output_type="ndarray")
    drop = np.zeros(ok.size, bool)
    if len(pairs):
        nb = [[] for _ in range(ok.size)]
        for i, j in pairs:
            nb[min(i, j)].append(max(i, j))
        for i in range(ok.size):
            if not drop[i]:
                for j in nb[i]:
                    drop[j] = True
    return np.sort(ok[~drop])


def _board_points(cat: BoardDots, plane: F64, camera: PinholeCamera) -> F64:
    """(M, 3) mm: the board's dots put on its plane (NaN rows: their line misses it)."""
    if len(cat) == 0:
        return np.zeros((0, 3))
    o, d = camera.rays(cat.uv)
    X, _ = intersect_rays_planes(o, d, plane)
    return X


def fit_dot_projector(
    boards: list[Board | None],
    board_planes: F64,
    camera: PinholeCamera,
    slit_planes: SlitPlanes,
) -> DotFit:
    """Calibrate the dot projector from the dots of the posed reference boards (see the module
    docstring).

    Parameters
    ----------
    boards : R Board, each reference image read for its dots and its dots fitted
        (:func:`~multislit.calibrate.board_dots.read_board`; None: a board left out)
    board_planes : (R, 4) float64, each board's plane (unit normal, n.X + d = 0, mm; NaN rows:
        a board not posed, left out)
    camera : the calibrated camera
    slit_planes : the calibrated slit planes (their common axis)

    Returns
    -------
    DotFit

    Raises
    ------
    CalibrationError
        Fewer than two boards posed, too few dots, or no source the dots agree on.
    ValueError
        ``boards`` and ``board_planes`` of different lengths.
    """
    board_planes = np.asarray(board_planes, np.float64)
    if len(boards) != len(board_planes):
        raise ValueError(
            f"boards has {len(boards)} entries for {len(board_planes)} board_planes rows"
        )
    posed = np.all(np.isfinite(board_planes), axis=1) & np.array([b is not None for b in boards])
    if posed.sum() < 2:
        raise CalibrationError(
            "dot projector: fewer than two reference boards are posed; the dots' rays need "
            "two or more board distances"
        )
    keep_b = np.flatnonzero(posed)
    boards = [boards[r] for r in keep_b]
    planes = board_planes[keep_b]
    views = [b.view for b in boards]
    sharps = [b.sharp for b in boards]
    cats = []
    for b, pl in zip(boards, planes, strict=True):
        X = _board_points(b.dots, pl, camera)
        cats.append(b.dots.subset(np.all(np.isfinite(X), axis=1)))
    X_l = [_board_points(c, pl, camera) for c, pl in zip(cats, planes, strict=True)]
    f = float(math.sqrt(camera.fx * camera.fy))
    # the source, from the clear dots
    clear = [c.z >= _SOURCE_Z for c in cats]
    for c, m in zip(cats, clear, strict=True):
        # a few thousand of them do: the brightest, the same dots on every board
        idx = np.flatnonzero(m)
        if len(idx) > _SOURCE_DOTS:
            m[:] = False
            m[idx[np.argsort(-c.height[idx])[:_SOURCE_DOTS]]] = True
    near = [v.lookup(c.u[m], c.v[m])[1] for v, c, m in zip(views, cats, clear, strict=True)]
    o = _source(
        [X[m] for X, m in zip(X_l, clear, strict=True)],
        near,
        slit_planes,
        camera.centre,
        f,
        len(boards),
    )
    _, axis = _slit_axis(slit_planes)
    frame = dot_frame(np.concatenate([_unit(X - o) for X in X_l if len(X)]), axis)
    source_rms = float("nan")
    for _ in range(_RAY_ROUNDS):
        rays = _make_rays(o, cats, X_l, views, sharps, planes, camera, frame, f)
        o, source_rms = _refined_source(o, rays, X_l)
    rays = _make_rays(o, cats, X_l, views, sharps, planes, camera, frame, f)
    # every ray refined on all boards at once, the other rays' spots beside it
    d, A, se_a, uv = _joint_fit(o, rays, cats, sharps, planes, camera, f)
    # the rays the boards' light confirms, one per dot
    t = _ray_evidence(A, se_a, uv, views)
    ph, ps, _ = angles_of(d, frame)
    merge = _MERGE_SIGMAS * float(np.median([sb.spot_sigma for sb in sharps]))
    keep = _one_per_dot(t, f * np.stack([ph, ps], axis=1), _RAY_Z, merge)
    new = np.full(len(d), -1, np.intp)
    new[keep] = np.arange(keep.size)
    m = new[rays.ray] >= 0
    rays = _Rays(d[keep], t[keep], new[rays.ray[m]], rays.board[m], rays.index[m])
    d, A, se_a, uv = d[keep], A[keep], se_a[keep], uv[keep]
    with np.errstate(invalid="ignore", divide="ignore"):
        seen_b = np.isfinite(uv[..., 0]) & (se_a > 0) & (A >= _SEEN_Z * se_a)
    n = len(d)
    if n < _MIN_TRACKS:
        raise CalibrationError(
            f"dot projector: only {n} dots of the reference boards make rays; the reference "
            "images must show the same dots at different distances"
        )
    # residuals: each board's own centre of a ray's dot against where the ray meets the board
    uv_obs = np.concatenate([c.uv for c in cats])[
        np.cumsum([0] + [len(c) for c in cats])[rays.board] + rays.index
    ]
    err = np.linalg.norm(uv[rays.ray, rays.board] - uv_obs, axis=1)
    n_obs = np.bincount(rays.ray, minlength=n)
    res = np.sqrt(np.bincount(rays.ray, weights=err**2, minlength=n) / np.maximum(n_obs, 1))
    res[n_obs < 2] = np.nan
    seen = seen_b.sum(axis=1)
    beta = _brightness(uv, seen_b, views)
    frame = dot_frame(d, axis)
    phi, psi, _ = angles_of(d, frame)
    sigma = float(np.median([sb.profile_sigma for sb in sharps]))
    proj = DotProjector(
        o, frame, phi, psi, np.maximum(seen, 1), res, brightness=beta, spot_sigma_px=sigma
    )
    found = np.zeros(len(board_planes), int)
    found[keep_b] = seen_b.sum(axis=0)
    spots = np.zeros(len(board_planes), int)
    spots[keep_b] = [len(c) for c in cats]
    two = (n_obs >= 2)[rays.ray]
    rms = float(np.sqrt(np.mean(err[two] ** 2))) if two.any() else float("nan")
    return DotFit(proj, found, spots, n, rms, source_rms)


def _ray_images(
    o: F64, d: F64, planes: F64, camera: PinholeCamera, f: float, shape: tuple[int, int]
) -> tuple[F64, F64, F64]:
    """Where each ray from ``o`` along ``d`` (N, 3) meets each board, in the image: (N, R, 2)
    px (NaN: off the image), the derivatives with respect to the ray's two angles (across and
    along, in pixels' angle) (N, R, 2, 2), and the two directions of those angles (N, 2, 3)."""
    h, w = shape
    e_a = _unit(np.cross(d, _along_hint(d)))
    e_b = np.cross(d, e_a)
    step = _JAC_PX / f
    uv = np.full((len(d), len(planes), 2), np.nan)
    jac = np.zeros((len(d), len(planes), 2, 2))
    for r, pl in enumerate(planes):
        p0 = _predict(o, d, pl, camera)
        pa = _predict(o, _unit(d + step * e_a), pl, camera)
        pb = _predict(o, _unit(d + step * e_b), pl, camera)
        inside = np.all(np.isfinite(p0), axis=1)
        inside &= (p0[:, 0] >= 1) & (p0[:, 0] <= w - 2) & (p0[:, 1] >= 1) & (p0[:, 1] <= h - 2)
        uv[inside, r] = p0[inside]
        jac[:, r, :, 0] = (pa - p0) / _JAC_PX
        jac[:, r, :, 1] = (pb - p0) / _JAC_PX
    return uv, np.nan_to_num(jac), np.stack([e_a, e_b], axis=1)


def _along_hint(d: F64) -> F64:
    """(N, 3): a direction not parallel to each of ``d`` (N, 3) (the axis least aligned)."""
    hint = np.zeros_like(d)
    hint[np.arange(len(d)), np.argmin(np.abs(d), axis=1)] = 1.0
    return hint


def _joint_fit(
    o: F64,
    rays: _Rays,
    cats: list[BoardDots],
    sharps: list[SharpResponse],
    planes: F64,
    camera: PinholeCamera,
    f: float,
) -> tuple[F64, F64, F64, F64]:
    """The rays refined on all boards at once (:func:`fit_rays_on_boards`, a few rounds), the
    board's other dots (those of no ray) held as fixed spots: each ray's direction (N, 3),
    its spot's height on each board (N, R) with its standard error (the noise's spread
    :attr:`~multislit.stripes.dots.SharpResponse.z_scale` included; 0: unknown), and
    where it meets each board (N, R, 2) px (NaN: off the image)."""
    R = len(cats)
    shape = sharps[0].response.shape
    n = len(rays.direction)
    d = rays.direction.copy()
    base = np.zeros((R,) + shape)
    A = np.zeros((n, R))
    for r, (c, sb) in enumerate(zip(cats, sharps, strict=True)):
        used = np.zeros(len(c), bool)
        m = rays.board == r
        used[rays.index[m]] = True
        free = ~used
        base[r] = sb.model(c.uv[free], c.height[free])
        A[rays.ray[m], r] = c.height[rays.index[m]]
    uv, jac, _ = _ray_images(o, d, planes, camera, f, shape)
    for r, sb in enumerate(sharps):  # boards without the ray's dot: the response where it lands
        m = np.isfinite(uv[:, r, 0]) & (A[:, r] == 0.0)
        iu = np.rint(uv[m, r, 0]).astype(np.intp)
        iv = np.rint(uv[m, r, 1]).astype(np.intp)
        A[m, r] = np.maximum(sb.response[iv, iu], 0.0)
    se = np.zeros((n, R + 1))
    for _ in range(_JOINT_ROUNDS):
        uv, jac, e = _ray_images(o, d, planes, camera, f, shape)
        step, se, _ = fit_rays_on_boards(sharps, uv, jac, A, base)
        d = _unit(d + (step[:, :1] * e[:, 0] + step[:, 1:] * e[:, 1]) / f)
    uv, _, _ = _ray_images(o, d, planes, camera, f, shape)
    se_a = se[:, :R] * np.array([sb.z_scale for sb in sharps])[None, :]
    return d, A, se_a, uv


def _ray_evidence(A: F64, se: F64, uv: F64, views: list[BoardView]) -> F64:
    """(N,) each ray's spots' heights on the boards (``A``, ``se`` (N, R)) in one figure: the
    matched filter of a dot as bright on every board relative to the stripe nearest it, in
    its standard errors (0 where no board shows its place)."""
    num = np.zeros(len(A))
    den = np.zeros(len(A))
    for r, view in enumerate(views):
        ok = np.isfinite(uv[:, r, 0]) & (se[:, r] > 0)
        if not ok.any():
            continue
        s_ = view.stripe_peak(uv[ok, r, 0], uv[ok, r, 1]) / se[ok, r]
        good = np.isfinite(s_)
        i = np.flatnonzero(ok)[good]
        num[i] += A[i, r] / se[i, r] * s_[good]
        den[i] += s_[good] ** 2
    return np.where(den > 0, num / np.sqrt(np.maximum(den, 1e-300)), 0.0)


def _refined_source(o: F64, rays: _Rays, X_l: list[F64]) -> tuple[F64, float]:
    """The source refined over the lines of the candidates found on every board with at
    least :data:`_SOURCE_NATS` (the point closest to them, least squares, over the lines
    within 12, 5 and 2.5 mm of it in turn: a chance match's line passes anywhere), and the
    kept lines' RMS distance from it (mm)."""
    offs = np.cumsum([0] + [len(X) for X in X_l])
    X = np.concatenate(X_l)[offs[rays.board] + rays.index]
    n = len(rays.direction)
    boards = sum(1 for x in X_l if len(x))
    cnt = np.bincount(rays.ray, minlength=n)
    use = (cnt >= max(boards, 2)) & (rays.llr >= _SOURCE_NATS)
    if np.count_nonzero(use) < _MIN_TRACKS:
        return o, float("nan")
    keep = np.flatnonzero(use)
    new = np.full(n, -1, np.intp)
    new[keep] = np.arange(keep.size)
    m = use[rays.ray]
    mean_pt, line_d = _track_lines(X[m], new[rays.ray[m]], keep.size, o)
    o2, near = _refine_source(o, mean_pt, line_d)
    if near.sum() < _MIN_TRACKS:
        return o, float("nan")
    dist = _line_distances(o2, mean_pt[near], line_d[near])
    return o2, float(np.sqrt(np.mean(dist**2)))


def _brightness(uv: F64, seen: NDArray[np.bool_], views: list[BoardView]) -> F64:
    """(N,) each ray's dot's response divided by the peak of the stripe nearest it, the
    median over the boards that show it (``seen`` (N, R); ``uv`` (N, R, 2) px where it meets
    them); NaN: unknown."""
    n, R = seen.shape
    ratio = np.full((n, R), np.nan)
    for r, view in enumerate(views):
        m = seen[:, r]
        if not m.any():
            continue
        u, v = uv[m, r, 0], uv[m, r, 1]
        a, _ = view.lookup(u, v)
        resp, _ = view.response.at(u, v, a)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio[m, r] = resp / view.stripe_peak(u, v)
    ratio[~(np.isfinite(ratio) & (ratio > 0))] = np.nan
    out = np.full(n, np.nan)
    has = np.isfinite(ratio).any(axis=1)
    out[has] = np.nanmedian(ratio[has], axis=1)
    return out


def _board_depths(camera: PinholeCamera, board_planes: F64) -> F64:
    """(R',) mm: the depth (camera axis) at which the image centre's line of sight meets each
    posed board."""
    w, h = camera.image_size
    o, d = camera.rays(np.array([[(w - 1) / 2.0, (h - 1) / 2.0]]))
    out = []
    for pl in board_planes[np.all(np.isfinite(board_planes), axis=1)]:
        X, _ = intersect_rays_planes(o, d, pl)
        if np.all(np.isfinite(X)):
            out.append(float((camera.to_camera(X))[0, 2]))
    return np.array([z for z in out if z > 0])


def capture_dot_projector(
    images: list[NDArray],
    stripes: ReferenceStripes,
    camera: PinholeCamera,
    slit_planes: SlitPlanes,
    stripe_width_px: float,
    dot_size_px: float,
    *,
    board_planes: F64 | None = None,
) -> DotFit:
    """The dot projector of a capture: the reference boards' dots fitted on each board
    (:func:`~multislit.calibrate.board_dots.board_catalogue`), put on the boards' planes and
    made into rays (:func:`fit_dot_projector`).

    Parameters
    ----------
    images : the capture's reference images (R)
    stripes : their numbered stripe centres (:func:`~multislit.calibrate.boards.reference_stripes`)
    camera : the calibrated camera
    slit_planes : the calibrated slit planes
    stripe_width_px, dot_size_px : px, the stripes' and the dots' FWHM in the references
    board_planes : (R, 4) float64, optional
        Each board's plane (mm, camera frame; NaN rows: not posed), e.g. from the bundle
        adjustment. Default: posed by the slit planes
        (:func:`~multislit.calibrate.boards.board_points`).

    Raises
    ------
    CalibrationError
        The boards cannot be posed, or the dots do not give a source (see
        :func:`fit_dot_projector`).
    """
    if board_planes is None:
        board_planes = board_points(stripes, camera, slit_planes.planes, slit_planes.valid).planes
    if len(board_planes) != len(images):
        raise ValueError(
            f"board_planes has {len(board_planes)} rows for {len(images)} reference images"
        )
    posed = np.all(np.isfinite(board_planes), axis=1)
    boards = [
        read_board(img, stripe_width_px, dot_size_px) if ok else None
        for img, ok in zip(images, posed, strict=True)
    ]
    fit = fit_dot_projector(boards, board_planes, camera, slit_planes)
    proj = replace(fit.projector, reference_depths=_board_depths(camera, board_planes))
    return replace(fit, projector=proj)
