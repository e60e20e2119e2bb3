"""The dot projector calibrated from the reference boards: its source and one ray per dot.

Each reference board is a plane posed by the calibrated slits on it
(:func:`~multislit.calibrate.boards.board_points`). A dot found in a board's image, its line of
sight met with the board's plane, is a 3D point of that dot's ray; the same dot on two or three
boards gives its ray, and all rays pass through one source. :func:`fit_dot_projector`:

1. puts every dot of every board in 3D, and describes it by its slit coordinate (where it lies
   between the slit planes, about their common axis, in slit spacings) and its elevation along
   the axis. A dot keeps its slit coordinate from board to board when the dot source lies near
   the slit axis (as in a rig that puts the dot projector beside the slit projector, along the
   slits); its elevation changes with the source's offset along the axis;
2. pairs dots of two boards with nearly the same slit coordinate and elevation; the line
   through a true pair passes through the source, so the source's place along the axis is
   the mode of where the lines come closest to it;
3. refines the source in 3D by least squares over the lines that pass near it, then matches
   the dots of all boards by their direction from the source into tracks (a dot seen on two
   or more boards) and refines the source again over the tracks;
4. gives each track its ray (the mean direction), and reports the residuals: the distance in
   the image between each dot's image on a board and where its ray meets that board.

Units: mm in the world (target) frame, px in the image, rad.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from multislit.calibrate.boards import ReferenceStripes, board_points
from multislit.calibrate.slit_planes import SlitPlanes, common_line
from multislit.errors import CalibrationError
from multislit.geometry import PinholeCamera, intersect_rays_planes, orthonormal_basis
from multislit.geometry.camera import F64
from multislit.geometry.dots import DotProjector, angles_of, dot_frame
from multislit.stripes import extract_slits
from multislit.stripes.dots import (
    MIN_DOT_RATIO,
    STRIPE_CLEARANCE,
    DotCentres,
    dots_clear_of_stripes,
    find_dots,
    stripe_maps,
)

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
#: Dots of two boards are one dot when their directions from the source differ by at most this
#: many pixels' angle.
_TRACK_PX = 2.0
#: A dot's ray is kept when it was found on at least this many boards ...
_MIN_SEEN = 2
#: ... and on every posed board when it lies within this many stripe widths (FWHM) of a stripe
#: centre on one of them: speckle on a stripe lines up along the stripe from board to board.
_ON_STRIPE = 0.5
#: Least number of tracks for a dot projector.
_MIN_TRACKS = 50


@dataclass(frozen=True, eq=False)
class DotFit:
    """The dot projector fitted by :func:`fit_dot_projector`, with its figures.

    Attributes
    ----------
    projector : DotProjector, the rays of the dots seen on at least two boards
    found : (R,) int, dots found per board (after the stripes' neighbourhood is left out)
    tracked : int, dots found on two or more boards (the projector's rays)
    rms_px : float, px, RMS of every ray's images on the boards from where it meets them
    source_rms_mm : float, mm, RMS distance of the tracks' lines from the source
    """

    projector: DotProjector
    found: NDArray[np.int_]
    tracked: int
    rms_px: float
    source_rms_mm: float

    def report(self) -> dict:
        """Figures for people (the calibration report's ``dot_projector`` entry)."""
        return {
            "source_mm": [round(float(x), 2) for x in self.projector.source],
            "dots_found_per_board": [int(n) for n in self.found],
            "rays": int(self.tracked),
            "rms_px": round(float(self.rms_px), 4),
            "source_rms_mm": round(float(self.source_rms_mm), 3),
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
            ta = np.c_[kappa[a] / _PAIR_KAPPA, eta[a] / _PAIR_ETA]
            tb = cKDTree(np.c_[kappa[b] / _PAIR_KAPPA, eta[b] / _PAIR_ETA])
            lists = tb.query_ball_point(ta, 1.0, p=np.inf)
            n = np.fromiter((len(x) for x in lists), int, len(lists))
            ia = np.repeat(np.arange(len(lists)), n)
            ib = np.fromiter((j for x in lists for j in x), int, int(n.sum()))
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
    dirs: list[F64], pixel_angle: float
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
    """Dots of all boards grouped by direction: (track id, board, index) of every grouped dot.

    A dot joins the dot of another board whose direction is nearest, within ``_TRACK_PX``
    pixels' angle, when each is the other's nearest (mutual nearest neighbours)."""
    nb = len(dirs)
    offsets = np.cumsum([0] + [len(d) for d in dirs])
    parent = np.arange(offsets[-1])

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    tol = _TRACK_PX * pixel_angle
    trees = [cKDTree(d) if len(d) else None for d in dirs]
    for a in range(nb):
        for b in range(a + 1, nb):
            if trees[a] is None or trees[b] is None:
                continue
            dab, jab = trees[b].query(dirs[a], distance_upper_bound=tol)
            dba, jba = trees[a].query(dirs[b], distance_upper_bound=tol)
            for i in np.flatnonzero(np.isfinite(dab)):
                j = jab[i]
                if jba[j] == i:
                    ra, rb = find(offsets[a] + i), find(offsets[b] + j)
                    if ra != rb:
                        parent[rb] = ra
    roots = np.array([find(i) for i in range(offsets[-1])], np.intp)
    board = np.repeat(np.arange(nb), np.diff(offsets))
    index = np.arange(offsets[-1]) - offsets[board]
    return roots, board, index


def _valid_tracks(
    X_l: list[F64], o: F64, pixel_angle: float, on_stripe: NDArray[np.bool_], boards: int
) -> tuple[NDArray[np.intp], NDArray[np.int_], NDArray[np.intp]]:
    """The tracks of dots seen on two or more boards (on every board when one of their
    images lies on a stripe): (track of each member (M,), dots per track (T,), the members'
    indices into the boards' dots concatenated (M,))."""
    vec = [(X - o) / np.linalg.norm(X - o, axis=1, keepdims=True) for X in X_l]
    root, _, _ = _tracks(vec, pixel_angle)
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


def fit_dot_projector(
    dots: list[DotCentres],
    board_planes: F64,
    camera: PinholeCamera,
    slit_planes: SlitPlanes,
    stripe_distance: list[F64] | None = None,
    stripe_width_px: float = 3.0,
) -> DotFit:
    """Calibrate the dot projector from the dots of the posed reference boards.

    Parameters
    ----------
    dots : R DotCentres, the dots found in each reference image, speckle on the stripes left
        out (:func:`board_dots`)
    board_planes : (R, 4) float64, each board's plane (unit normal, n.X + d = 0, mm; NaN rows:
        a board not posed, left out)
    camera : the calibrated camera
    slit_planes : the calibrated slit planes (their common axis)
    stripe_distance : R arrays (M_r,) float64, px, each dot's distance to the nearest stripe
        centre (:func:`board_dots`); default: none is near a stripe
    stripe_width_px : float, px, the stripes' FWHM

    Returns
    -------
    DotFit

    Raises
    ------
    CalibrationError
        Fewer than two boards posed, too few dots, or no source the dots agree on.
    """
    posed = np.all(np.isfinite(board_planes), axis=1)
    if posed.sum() < 2:
        raise CalibrationError(
            "dot projector: fewer than two reference boards are posed; the dots' rays need "
            "two or more board distances"
        )
    a, u = _slit_axis(slit_planes)
    centre = camera.centre
    uv_l, X_l, on_l, found = [], [], [], []
    for r, dc in enumerate(dots):
        uv = dc.uv
        sd = np.full(len(uv), np.inf)
        if stripe_distance is not None:
            sd = np.asarray(stripe_distance[r], np.float64)
        if not posed[r] or len(uv) == 0:
            uv, sd = np.zeros((0, 2)), np.zeros(0)
        on = sd < _ON_STRIPE * stripe_width_px
        o, dr = camera.rays(uv)
        X, _ = (
            intersect_rays_planes(o, dr, board_planes[r]) if len(uv) else (np.zeros((0, 3)), None)
        )
        ok = np.all(np.isfinite(X), axis=1)
        uv_l.append(uv[ok])
        X_l.append(X[ok])
        on_l.append(on[ok])
        found.append(int(ok.sum()))
    kappa, eta = [], []
    for X in X_l:
        kp, _, et = _axis_coordinates(X, slit_planes, a, u, centre)
        kappa.append(kp)
        eta.append(et)
    points, dirs = _candidate_lines(X_l, kappa, eta)
    o = _source_on_axis(points, dirs, a, u)
    o, _ = _refine_source(o, points, dirs)
    f = float(np.sqrt(camera.fx * camera.fy))
    pixel_angle = 1.0 / f
    Xall = np.concatenate(X_l)
    on_all = np.concatenate(on_l)
    offs = np.cumsum([0] + [len(x) for x in X_l])
    # tracks by direction from the source, the source refined over their lines; twice
    for _ in range(2):
        tid, seen, member = _valid_tracks(X_l, o, pixel_angle, on_all, int(posed.sum()))
        if seen.size < _MIN_TRACKS:
            raise CalibrationError(
                f"dot projector: only {seen.size} dots were found on two or more reference "
                "boards; the reference images must show the same dots at different distances"
            )
        mean_pt, line_d = _track_lines(Xall[member], tid, seen.size, o)
        o = _closest_point(mean_pt, line_d)
    dist = _line_distances(o, mean_pt, line_d)
    source_rms = float(np.sqrt(np.mean(dist**2)))
    # the rays: each track's mean direction from the final source ...
    dv = Xall[member] - o
    dv /= np.linalg.norm(dv, axis=1, keepdims=True)
    ray = np.zeros((seen.size, 3))
    np.add.at(ray, tid, dv)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    # ... and the residuals: each dot's image against its ray met with its board
    board = np.repeat(np.arange(len(X_l)), np.diff(offs))
    b_m = board[member]
    Y, _ = intersect_rays_planes(np.broadcast_to(o, (len(tid), 3)), ray[tid], board_planes[b_m])
    uv_obs = np.concatenate(uv_l)[member]
    err = np.linalg.norm(camera.project(Y) - uv_obs, axis=1)
    res = np.sqrt(np.bincount(tid, weights=err**2, minlength=len(ray)) / seen)
    frame = dot_frame(ray, u)
    phi, psi, _ = angles_of(ray, frame)
    proj = DotProjector(o, frame, phi, psi, seen, res)
    rms = float(np.sqrt(np.mean(err**2)))
    return DotFit(proj, np.asarray(found), len(ray), rms, source_rms)


def board_dots(
    images: list[NDArray], stripe_width_px: float, dot_size_px: float
) -> tuple[list[DotCentres], list[F64]]:
    """The dots of each reference image, speckle on the stripes left out
    (:func:`~multislit.stripes.dots.dots_clear_of_stripes`, with the identification's
    clearance and ratio), and each dot's distance to the nearest stripe centre (px)."""
    out, dist_l = [], []
    for img in images:
        ex = extract_slits(
            img, stripe_width_px=stripe_width_px, dot_size_px=dot_size_px, leaning=False
        )
        found = find_dots(ex.dots, ex.noise_sigma, ex.dot_size_px)
        clearance = STRIPE_CLEARANCE * ex.stripe_width_px
        dist, peak = stripe_maps(ex.u, ex.v, ex.peak, img.shape, clearance)
        kept, _ = dots_clear_of_stripes(found, dist, peak, clearance, MIN_DOT_RATIO)
        out.append(kept)
        r = np.clip(np.rint(kept.v).astype(np.intp), 0, img.shape[0] - 1)
        c = np.clip(np.rint(kept.u).astype(np.intp), 0, img.shape[1] - 1)
        dist_l.append(dist[r, c].astype(np.float64))
    return out, dist_l


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
    """The dot projector of a capture: the reference boards' dots put in 3D on the boards'
    planes and fitted (:func:`fit_dot_projector`).

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
    dots, dist = board_dots(images, stripe_width_px, dot_size_px)
    fit = fit_dot_projector(dots, board_planes, camera, slit_planes, dist, stripe_width_px)
    proj = replace(fit.projector, reference_depths=_board_depths(camera, board_planes))
    return replace(fit, projector=proj)
