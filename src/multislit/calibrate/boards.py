"""Points on the slits from the reference boards: every slit the references show gets points.

The reference images show a flat board at several distances with every slit on it, numbered
0..N-1 from left to right (:func:`multislit.identify.prepare_reference`). A board is a plane
whose pose follows from the slits already calibrated on the target: their stripe centres on the
board, triangulated with their planes, give the board's plane (a robust fit). The centres of
every other slit on that board, their lines of sight intersected with the board's plane, are
then points of that slit's plane. Boards at two or more distances give each slit points along
two or more lines at different depths, which determine its plane.

:func:`reference_stripes` finds and numbers the stripe centres of the reference images;
:func:`board_points` poses the boards and puts the centres on them; :func:`fit_with_boards`
gives the slits the target does not determine their planes from the boards;
:func:`plane_origins` says per slit where its plane came from.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from multislit.calibrate.projector import ProjectorFit, fit_projector
from multislit.calibrate.slit_planes import SlitPlanes
from multislit.calibrate.slit_points import EXTRACT_OPTIONS, SlitPointSet, _row_gap
from multislit.errors import MultislitError, ReferenceImageError
from multislit.geometry import PinholeCamera, fit_plane_robust, intersect_rays_planes
from multislit.geometry.camera import F64
from multislit.identify import ReferenceSet, curve_u
from multislit.identify.reference import reference_curves
from multislit.io import Capture
from multislit.stripes import extract_slits, refine_centres

#: A centre takes the slit of the nearest reference curve in its row when it lies within this
#: fraction of the slit spacing from it.
_LABEL_FRACTION = 0.25
#: Least number of slits with planes of their own that pose a board.
_MIN_POSE_SLITS = 3
#: Most points kept per slit and board (evenly along the stripe), so that the boards do not
#: outweigh the target in the common-axis fit.
_MAX_POINTS_PER_LINE = 150
#: Least number of centres of a slit on a board for its line to count.
_MIN_LINE_POINTS = 20


@dataclass(frozen=True, eq=False)
class ReferenceStripes:
    """Numbered stripe centres of the reference images.

    Attributes
    ----------
    names : (R,) reference image names (file stems)
    uv : list of R arrays (M_r, 2) float64, px, stripe centres (re-centred along the stripe
        where :func:`~multislit.stripes.refine_centres` can)
    slit : list of R arrays (M_r,) int, slit number of each centre
    num_slits : int
    notes : remarks for people (reference images left out, and why)
    """

    names: tuple[str, ...]
    uv: list[F64]
    slit: list[NDArray[np.intp]]
    num_slits: int
    notes: tuple[str, ...] = ()

    def shown(self) -> NDArray[np.bool_]:
        """(K,) bool, slits with a line of >= a few tens of centres on some board."""
        cnt = np.zeros(self.num_slits, int)
        for s in self.slit:
            cnt = np.maximum(cnt, np.bincount(s, minlength=self.num_slits))
        return cnt >= _MIN_LINE_POINTS


def reference_stripes(capture: Capture, reference: ReferenceSet | None = None) -> ReferenceStripes:
    """Stripe centres of the capture's reference images, numbered by the reference curves.

    Parameters
    ----------
    capture : the capture (its ``references`` images and ``num_slits``)
    reference : the prepared reference set of these images; default: each image's curves
        fitted on its own (:func:`~multislit.identify.reference.reference_curves`: no epipole
        needed), and images whose curves cannot be fitted left out (``notes`` says why)

    Returns
    -------
    ReferenceStripes

    Raises
    ------
    ReferenceImageError
        No reference image gives curves.
    """
    k = int(capture.num_slits)
    names, curves, vranges, spacings, imgs, notes = [], [], [], [], [], []
    for i, path in enumerate(capture.references):
        img = capture.image(path)
        if reference is not None:
            c, vr, sp = reference.curves[i], reference.vrange[i], reference.spacing_px
        else:
            try:
                c, vr, sp = reference_curves(img, k, path.stem)
            except ReferenceImageError as exc:
                notes.append(f"reference image {path.stem} not used: {exc}")
                continue
        names.append(path.stem)
        curves.append(c)
        vranges.append(vr)
        spacings.append(sp)
        imgs.append(img)
    if not names:
        raise ReferenceImageError("no reference image gives the slits' curves: " + "; ".join(notes))
    uvs, slits = [], []
    for img, c, vrange, sp in zip(imgs, curves, vranges, spacings, strict=True):
        tol = _LABEL_FRACTION * sp
        ex = extract_slits(img, **EXTRACT_OPTIONS)
        u, v = np.asarray(ex.u, float), np.asarray(ex.v, float)
        cu = curve_u(c[:, None, :], v[None, :])  # (K, M)
        kk = np.argmin(np.abs(cu - u[None, :]), axis=0)
        d = np.abs(cu[kk, np.arange(len(u))] - u)
        vr = vrange[kk]
        keep = (ex.segment >= 0) & (d < tol) & (v >= vr[:, 0]) & (v <= vr[:, 1])
        sw = ex.stripe_width_px if math.isfinite(ex.stripe_width_px) else 3.0
        kw = {"dot_size_px": ex.dot_size_px} if math.isfinite(ex.dot_size_px) else {}
        keep &= _row_gap(u, v) > 2.0 * sw  # a dot beside the stripe: which one is it?
        u2, ok = refine_centres(img, u, v, np.where(keep, ex.segment, -1), sw, **kw)
        u2 = np.where(ok, u2, u)  # where the stripe is not re-centred, its first centre
        uvs.append(np.stack([u2[keep], v[keep]], axis=1))
        slits.append(kk[keep].astype(np.intp))
    return ReferenceStripes(tuple(names), uvs, slits, k, tuple(notes))


@dataclass(frozen=True, eq=False)
class BoardPoints:
    """The reference boards posed by the calibrated slits, and the stripe centres on them.

    Attributes
    ----------
    xyz : (N, 3) float64, mm, centres on their board's plane
    slit : (N,) int, slit number
    uv : (N, 2) float64, px
    board : (N,) int, index of the reference image
    planes : (R, 4) float64, unit normal n.X + d = 0 of each board (NaN: not posed)
    rms_mm : (R,) float64, mm, RMS distance of the posing slits' points to the board's plane
    notes : remarks for people (boards that could not be posed)
    """

    xyz: F64
    slit: NDArray[np.intp]
    uv: F64
    board: NDArray[np.intp]
    planes: F64
    rms_mm: F64
    notes: tuple[str, ...] = ()


def board_points(
    stripes: ReferenceStripes, camera: PinholeCamera, slit_planes: F64, posing: NDArray[np.bool_]
) -> BoardPoints:
    """Pose each reference board from the slits ``posing`` and put every centre on it.

    Parameters
    ----------
    stripes : numbered centres of the reference images (:func:`reference_stripes`)
    camera : the calibrated camera (its ``rays``)
    slit_planes : (K, 4) float64, the slit planes fitted so far (NaN rows: none)
    posing : (K,) bool, slits whose planes are trusted to pose the boards

    Returns
    -------
    BoardPoints; a board with fewer than a few posing slits on it is left out (noted).
    """
    xyz_l, slit_l, uv_l, board_l, notes = [], [], [], [], []
    nb = len(stripes.uv)
    planes, rms_mm = np.full((nb, 4), np.nan), np.full(nb, np.nan)
    for r in range(nb):
        uv, s = stripes.uv[r], stripes.slit[r]
        s, uv = _thin(s, uv)
        if len(uv) == 0:
            notes.append(f"reference board {stripes.names[r]}: no stripe centres")
            continue
        o, d = camera.rays(uv)
        pose = posing[s] & np.all(np.isfinite(slit_planes[s]), axis=1)
        if len(np.unique(s[pose])) < _MIN_POSE_SLITS:
            notes.append(
                f"reference board {stripes.names[r]}: fewer than {_MIN_POSE_SLITS} calibrated "
                "slits on it, its pose is unknown"
            )
            continue
        X, _ = intersect_rays_planes(o[pose], d[pose], slit_planes[s[pose]])
        good = np.all(np.isfinite(X), axis=1)
        try:
            pl, inl = fit_plane_robust(X[good])
        except MultislitError as exc:
            notes.append(f"reference board {stripes.names[r]}: no plane ({exc})")
            continue
        dist = X[good][inl] @ pl[:3] + pl[3]
        planes[r], rms_mm[r] = pl, float(np.sqrt(np.mean(dist**2)))
        Y, _ = intersect_rays_planes(o, d, pl)
        ok = np.all(np.isfinite(Y), axis=1)
        xyz_l.append(Y[ok])
        slit_l.append(s[ok])
        uv_l.append(uv[ok])
        board_l.append(np.full(int(ok.sum()), r, np.intp))
    if not xyz_l:
        e3, e2 = np.zeros((0, 3)), np.zeros((0, 2))
        return BoardPoints(e3, np.zeros(0, np.intp), e2, np.zeros(0, np.intp), planes, rms_mm)
    return BoardPoints(
        np.concatenate(xyz_l),
        np.concatenate(slit_l),
        np.concatenate(uv_l),
        np.concatenate(board_l),
        planes,
        rms_mm,
        tuple(notes),
    )


def _thin(s: NDArray[np.intp], uv: F64) -> tuple[NDArray[np.intp], F64]:
    """At most :data:`_MAX_POINTS_PER_LINE` centres per slit, evenly along the stripe."""
    keep = np.zeros(len(s), bool)
    for j in np.unique(s):
        idx = np.flatnonzero(s == j)
        if len(idx) < _MIN_LINE_POINTS:
            continue
        idx = idx[np.argsort(uv[idx, 1])]
        take = np.linspace(0, len(idx) - 1, min(_MAX_POINTS_PER_LINE, len(idx))).round()
        keep[idx[take.astype(int)]] = True
    return s[keep], uv[keep]


@dataclass(frozen=True, eq=False)
class BoardFit:
    """Result of :func:`fit_with_boards`.

    Attributes
    ----------
    points : SlitPointSet, the target's points followed by the boards' (``face`` >= the
        target's faces: board ``face - first_board_face``)
    fit : ProjectorFit on ``points``
    boards : BoardPoints, the boards as posed and all centres on them
    first_board_face : int, the ``face`` index of the first board
    """

    points: SlitPointSet
    fit: ProjectorFit
    boards: BoardPoints
    first_board_face: int


def fit_with_boards(
    points: SlitPointSet,
    fit: ProjectorFit,
    stripes: ReferenceStripes,
    camera: PinholeCamera,
    num_faces: int,
) -> BoardFit:
    """Planes for the slits the target does not determine, from the reference boards.

    The boards are posed by the slits with planes of their own from the target
    (:func:`board_points`). The centres on the boards of every other slit (none or too few
    points on the target, or points along one line only) join the target's points, and all
    planes are refitted (:func:`~multislit.calibrate.projector.fit_projector`, common axis,
    robust). The slits the target determines keep their own points only: the boards are posed
    by them, so their centres there would only repeat their planes, with the camera's error
    at the image's edges added.

    Parameters
    ----------
    points : the target's points on the slits
    fit : the projector fit to ``points`` alone
    stripes : numbered centres of the reference images
    camera : the calibrated camera
    num_faces : number of target faces (the boards get the face numbers after them)

    Returns
    -------
    BoardFit
    """
    k = stripes.num_slits
    first = max(int(num_faces), int(points.face.max(initial=-1)) + 1)
    own = _own(fit.slit_planes)
    bp = board_points(stripes, camera, fit.slit_planes.planes, own)
    add = ~own[bp.slit]
    pts = SlitPointSet(
        np.concatenate([points.xyz, bp.xyz[add]]),
        np.concatenate([points.slit, bp.slit[add]]),
        np.concatenate([points.uv, bp.uv[add]]),
        np.concatenate([points.face, first + bp.board[add]]),
        points.source,
        points.steps + (("on the reference boards (slits the target misses)", int(add.sum())),),
    )
    return BoardFit(pts, fit_projector(pts, k) if add.any() else fit, bp, first)


def _own(sp: SlitPlanes) -> NDArray[np.bool_]:
    """(K,) bool, slits with planes of their own (not only through the common axis)."""
    own = sp.valid.copy()
    own[list(sp.from_axis)] = False
    return own


def plane_origins(
    fit: ProjectorFit, points: SlitPointSet, first_board_face: int | None = None
) -> tuple[str, ...]:
    """Where each slit's plane came from, for the report.

    Parameters
    ----------
    fit : the projector fit
    points : the points it was fitted to
    first_board_face : the ``face`` index of the first reference board in ``points`` (None:
        no boards)

    Returns
    -------
    (K,) str: "target faces", "reference boards" or "target faces + reference boards" (the
    points the plane was fitted to), with " + common axis" for a slit seen along one line
    whose plane passes through the projector's common axis; "" for a slit without a plane.
    """
    sp = fit.slit_planes
    k = sp.num_slits
    s = np.asarray(points.slit, np.intp)
    on_board = np.zeros(len(s), bool)
    if first_board_face is not None:
        on_board = np.asarray(points.face) >= first_board_face
    n_board = np.bincount(s[fit.inlier & on_board], minlength=k)
    n_target = np.bincount(s[fit.inlier & ~on_board], minlength=k)
    out = []
    for j in range(k):
        if not sp.valid[j]:
            out.append("")
            continue
        parts = [
            name
            for name, n in (("target faces", n_target[j]), ("reference boards", n_board[j]))
            if n
        ]
        if j in sp.from_axis:
            parts.append("common axis")
        out.append(" + ".join(parts))
    return tuple(out)
