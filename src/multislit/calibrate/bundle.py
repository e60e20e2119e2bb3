"""Calibration as one bundle adjustment: camera, slit planes and reference boards together.

Every image of a capture constrains the camera and the projector at once: the markers of
``calibration/markers.png`` (known 3D points), the stripes of ``calibration/slits.png`` on the
target's known faces, and the stripes on every reference board (a plane of unknown pose). A
stripe on a flat surface is the image of a straight 3D line, the slit's plane cut by the
surface's, so its position and its curvature in the image (the plumb-line principle) measure the
camera, its lens distortion and the slit planes over the whole image, where the markers alone
leave the distortion poorly determined. The paper's hand readings (3D points on the slits, read
off the target's scales) are one more set of observations.

The adjustment is assembled from parts:

* **parameter blocks** (:class:`ParamBlock`): the camera (fx, fy, cx, cy, rvec, tvec, k1, k2,
  p1, p2, k3), the boards' planes (one item of 3 parameters per board), the slit planes (one
  item per slit; or, in the common-axis model, a shared axis of 4 parameters and one angle per
  slit). A block is either *shared* (every observation that uses it depends on all of it) or
  *indexed* (each observation depends on one item);
* **observation blocks** (:class:`ObservationBlock`): a residual function of the derived
  geometry (the camera, the planes) with, per residual row, the item of each indexed parameter
  block it depends on. That is the Jacobian's sparsity pattern, and the finite-difference
  Jacobian perturbs all items of an indexed block at once.

Further observations plug in as one more observation block and their parameters as more
parameter blocks, e.g. dots seen on the boards (a dot source, shared, and one direction per dot,
indexed; each dot centroid's residual depends on the camera, its board, the source and its dot).

:func:`adjust` runs SciPy's ``least_squares`` (MINPACK's Levenberg-Marquardt, with the
Jacobian above) in rounds: the residuals of each observation block are divided by that block's
noise, estimated robustly from the block's own residuals (and inflated where neighbouring
stripe centres err together), a soft-L1 robust loss enters as weights from the last round's
residuals (iteratively reweighted least squares), and observations further than a few noise
levels from their own stripe are left out before the next round. :class:`BundleResult` holds the fitted geometry, the parameters'
standard errors, the residuals per source, per image and per image region, and the predicted 3D
uncertainty of triangulated points over the measuring volume.

Units: mm in the world (target) frame, px in the image, rad.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.stats
from numpy.typing import NDArray
from scipy.ndimage import median_filter
from scipy.optimize import least_squares

from multislit.calibrate.slit_planes import common_line
from multislit.errors import CalibrationError
from multislit.geometry import (
    MAD_TO_SIGMA,
    PinholeCamera,
    intersect_rays_planes,
    orthonormal_basis,
    rotation_from_rvec,
)
from multislit.geometry.camera import F64, _distort

#: Camera parameters, in the order of the camera block.
CAMERA_PARAMS = ("fx", "fy", "cx", "cy", "r1", "r2", "r3", "t1", "t2", "t3", "k1", "k2", "p1",
                 "p2", "k3")  # fmt: skip
#: Residuals further than this many noise levels from the fit are left out of the next round.
OUTLIER_SIGMA = 5.0
#: The soft-L1 loss turns from quadratic to linear at this many noise levels.
_LOSS_SCALE = 3.0
#: Most rounds of (fit, noise estimate, outliers, robust weights).
_MAX_ROUNDS = 6
#: Most rounds (of robust weights) under a fixed noise model.
_FIXED_ROUNDS = 3
#: The score tests' level: the chance that a chi-square decrease this large arises from noise
#: alone (three standard deviations of a Gaussian, two-sided).
_TEST_LEVEL = 0.0027
#: Least noise level per unit (a block's residuals may be nearly exact, e.g. simulated readings).
_MIN_SIGMA = {"px": 0.005, "mm": 0.002}
#: Newton steps that put a point of a 3D line on an observation's image row.
_LINE_NEWTON_STEPS = 3
#: Relative finite-difference step of each parameter (times max(1, |value|)).
_FD_STEP = 1e-6
#: Regions of the image in the report: a 3 x 3 grid.
REGIONS = ("top left", "top", "top right", "left", "centre", "right", "bottom left", "bottom",
           "bottom right")  # fmt: skip


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True, eq=False)
class ParamBlock:
    """A named block of parameters.

    Attributes
    ----------
    name : str
    x0 : (items, width) float64, starting values (one row for a shared block)
    indexed : bool, each observation depends on one item (False: on all of the block)
    free : (width,) bool, the columns that are fitted (the others keep ``x0``)
    labels : (width,) str, the columns' names, for the report
    """

    name: str
    x0: F64
    indexed: bool
    free: NDArray[np.bool_]
    labels: tuple[str, ...]

    @property
    def items(self) -> int:
        return int(self.x0.shape[0])

    @property
    def width(self) -> int:
        return int(self.x0.shape[1])

    @property
    def size(self) -> int:
        """Number of fitted parameters."""
        return self.items * int(self.free.sum())


def param_block(
    name: str,
    x0: Any,
    *,
    indexed: bool,
    labels: Sequence[str],
    free: Sequence[bool] | None = None,
) -> ParamBlock:
    """A :class:`ParamBlock` from plain values (x0 (items, width), or (width,) if shared)."""
    x = np.atleast_2d(np.asarray(x0, dtype=float))
    fr = np.ones(x.shape[1], bool) if free is None else np.asarray(free, bool)
    if len(labels) != x.shape[1] or fr.shape != (x.shape[1],):
        raise CalibrationError(f"parameter block {name}: labels and free need {x.shape[1]} values")
    return ParamBlock(name, x, indexed, fr, tuple(labels))


class Layout:
    """Where each parameter block's free values sit in the solver's vector."""

    def __init__(self, blocks: Sequence[ParamBlock]) -> None:
        self.blocks = {b.name: b for b in blocks}
        self.offset: dict[str, int] = {}
        n = 0
        for b in blocks:
            self.offset[b.name] = n
            n += b.size
        self.size = n

    def pack(self, values: Mapping[str, F64]) -> F64:
        out = np.empty(self.size)
        for name, b in self.blocks.items():
            o = self.offset[name]
            out[o : o + b.size] = values[name][:, b.free].ravel()
        return out

    def unpack(self, x: F64) -> dict[str, F64]:
        out = {}
        for name, b in self.blocks.items():
            v = b.x0.copy()
            o = self.offset[name]
            v[:, b.free] = x[o : o + b.size].reshape(b.items, -1)
            out[name] = v
        return out

    def column(self, name: str, item: NDArray[np.intp] | int, col: int) -> NDArray[np.intp]:
        """Solver columns of column ``col`` (of the block's free columns) of ``item``."""
        b = self.blocks[name]
        nf = int(b.free.sum())
        return self.offset[name] + np.asarray(item) * nf + col

    def labels(self) -> list[str]:
        """Names of the solver's parameters, e.g. ``camera.fx``, ``slits[3].d``."""
        out = []
        for name, b in self.blocks.items():
            cols = [lab for lab, f in zip(b.labels, b.free, strict=True) if f]
            for i in range(b.items):
                item = f"{name}[{i}]" if b.indexed else name
                out += [f"{item}.{c}" for c in cols]
        return out


# --------------------------------------------------------------------------- geometry
def camera_vector(camera: PinholeCamera) -> F64:
    """(15,) the camera block's values of a :class:`PinholeCamera` (k3 = 0 if it has 4)."""
    dist = list(camera.dist) + [0.0] * (5 - len(camera.dist))
    return np.array(
        [camera.fx, camera.fy, camera.cx, camera.cy, *camera.rvec, *camera.tvec, *dist], float
    )


def vector_camera(p: F64, image_size: tuple[int, int]) -> PinholeCamera:
    """The :class:`PinholeCamera` of the camera block's values ``p`` (15,)."""
    return PinholeCamera(
        fx=float(p[0]), fy=float(p[1]), cx=float(p[2]), cy=float(p[3]), rvec=tuple(p[4:7]),
        tvec=tuple(p[7:10]), dist=tuple(p[10:15]), image_size=image_size,
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class PlaneParams:
    """Planes as small turns of their starting normals: n = unit(n0 + a e1 + b e2), and d.

    Attributes
    ----------
    n0, e1, e2 : (M, 3) float64, the starting normals and two unit vectors normal to each
    """

    n0: F64
    e1: F64
    e2: F64

    @classmethod
    def start(cls, planes: F64) -> tuple[PlaneParams, F64]:
        """The parameterisation around ``planes`` (M, 4) (unit normals) and its x0 (M, 3)."""
        n0 = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
        e = [orthonormal_basis(n) for n in n0]
        e1 = np.array([a for a, _ in e]).reshape(-1, 3)
        e2 = np.array([b for _, b in e]).reshape(-1, 3)
        x0 = np.zeros((len(planes), 3))
        x0[:, 2] = planes[:, 3] / np.linalg.norm(planes[:, :3], axis=1)
        return cls(n0, e1, e2), x0

    def planes(self, q: F64) -> F64:
        """(M, 4) unit-normal planes of the values ``q`` (M, 3)."""
        n = self.n0 + q[:, :1] * self.e1 + q[:, 1:2] * self.e2
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return np.concatenate([n, q[:, 2:3]], axis=1)


@dataclass(frozen=True, eq=False)
class AxisParams:
    """Slit planes through one common axis (a grating's): one angle per slit about the axis.

    The axis is the starting axis turned by two small angles and moved by two offsets normal
    to it (the shared block ``axis``); slit k's normal is cos(phi_k) f1 + sin(phi_k) f2 in the
    turned frame (f1, f2 normal to the axis).
    """

    a0: F64
    frame0: F64  # (3, 3) rows e1, e2, u0

    @classmethod
    def start(cls, planes: F64) -> tuple[AxisParams, F64, F64]:
        """The parameterisation around ``planes`` (M, 4), its axis x0 (4,) and angles (M, 1)."""
        a0, u0 = common_line(planes)
        e1, e2 = orthonormal_basis(u0)
        frame0 = np.stack([e1, e2, u0])
        phi = np.arctan2(planes[:, :3] @ e2, planes[:, :3] @ e1)
        return cls(a0, frame0), np.zeros(4), phi[:, None]

    def planes(self, axis: F64, phi: F64) -> F64:
        """(M, 4) planes of the axis values (4,) and the angles (M, 1)."""
        R = rotation_from_rvec(axis[0] * self.frame0[0] + axis[1] * self.frame0[1])
        f = self.frame0 @ R.T
        a = self.a0 + axis[2] * self.frame0[0] + axis[3] * self.frame0[1]
        n = np.cos(phi) * f[0] + np.sin(phi) * f[1]
        return np.concatenate([n, -(n @ a)[:, None]], axis=1)

    def axis(self, axis: F64) -> tuple[F64, F64]:
        """The axis's point (3,) mm (closest to the origin) and unit direction (3,)."""
        R = rotation_from_rvec(axis[0] * self.frame0[0] + axis[1] * self.frame0[1])
        u = R @ self.frame0[2]
        a = self.a0 + axis[2] * self.frame0[0] + axis[3] * self.frame0[1]
        return a - (a @ u) * u, u


#: The derived geometry the observation blocks read: "camera" (15,), "slit_planes" (K, 4),
#: "board_planes" (B, 4), ...
Geometry = dict[str, F64]


@dataclass(frozen=True, eq=False)
class Model:
    """The parameter blocks and how they make the geometry.

    Attributes
    ----------
    blocks : the parameter blocks
    derive : values of every block -> the geometry
    slit_deps : which parameter blocks a slit plane depends on: block name -> indexed (True)
        or shared (False)
    """

    blocks: tuple[ParamBlock, ...]
    derive: Callable[[Mapping[str, F64]], Geometry]
    slit_deps: Mapping[str, bool]


# --------------------------------------------------------------------------- projection
def _rotation_translation(cam: F64) -> tuple[F64, F64]:
    return rotation_from_rvec(cam[4:7]), cam[7:10]


def project(cam: F64, X: F64) -> F64:
    """Pixels (N, 2) of world points ``X`` (N, 3) mm by the camera block's values ``cam``."""
    R, t = _rotation_translation(cam)
    pc = X @ R.T + t
    xyd = _distort(pc[:, :2] / pc[:, 2:3], cam[10:15])
    return xyd * cam[:2] + cam[2:4]


def _line_pixel(cam: F64, P: F64, D: F64, s: F64) -> tuple[F64, F64, F64, F64]:
    """Pixel (u, v) of P + s D (camera frame, (N, 3)) and its derivatives du/ds, dv/ds."""
    X = P + s[:, None] * D
    iz = 1.0 / X[:, 2]
    x, y = X[:, 0] * iz, X[:, 1] * iz
    dx = (D[:, 0] - x * D[:, 2]) * iz
    dy = (D[:, 1] - y * D[:, 2]) * iz
    k1, k2, p1, p2, k3 = cam[10:15]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    radp = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    cross = 2 * x * y * radp + 2 * p1 * x + 2 * p2 * y
    dxd = (rad + 2 * x * x * radp + 2 * p1 * y + 6 * p2 * x) * dx + cross * dy
    dyd = cross * dx + (rad + 2 * y * y * radp + 6 * p1 * y + 2 * p2 * x) * dy
    return cam[0] * xd + cam[2], cam[1] * yd + cam[3], cam[0] * dxd, cam[1] * dyd


def plane_lines(pa: F64, pb: F64) -> tuple[F64, F64]:
    """Lines where planes ``pa`` and ``pb`` (N, 4) (unit normals) meet: points (N, 3) (closest
    to the origin) and unit directions (N, 3)."""
    n1, n2 = pa[:, :3], pb[:, :3]
    c = np.einsum("ij,ij->i", n1, n2)
    den = 1.0 - c * c
    c1 = (-pa[:, 3] + c * pb[:, 3]) / den
    c2 = (-pb[:, 3] + c * pa[:, 3]) / den
    D = np.cross(n1, n2)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    return c1[:, None] * n1 + c2[:, None] * n2, D


def line_residuals(cam: F64, P: F64, D: F64, uv: F64) -> F64:
    """Signed image distance (N,) px from each observation ``uv`` (N, 2) to the image of its
    3D line (points ``P``, directions ``D``, (N, 3), world): the line's point imaged in the
    observation's row (its column, where the line's image runs more along the rows than
    across them), and the distance across the line's image there.
    """
    R, t = _rotation_translation(cam)
    Pc, Dc = P @ R.T + t, D @ R.T
    u, v = uv[:, 0], uv[:, 1]
    xd, yd = (u - cam[2]) / cam[0], (v - cam[3]) / cam[1]
    r2 = xd * xd + yd * yd
    rad = 1 + r2 * (cam[10] + r2 * (cam[11] + r2 * cam[14]))
    x0, y0 = xd / rad, yd / rad
    with np.errstate(divide="ignore", invalid="ignore"):
        # the line's image direction at its point nearest the world's origin (the target)
        _, _, du0, dv0 = _line_pixel(cam, Pc, Dc, np.zeros(len(P)))
        by_col = np.abs(du0) > np.abs(dv0)
        s_row = (y0 * Pc[:, 2] - Pc[:, 1]) / (Dc[:, 1] - y0 * Dc[:, 2])
        s_col = (x0 * Pc[:, 2] - Pc[:, 0]) / (Dc[:, 0] - x0 * Dc[:, 2])
        s = np.where(by_col, s_col, s_row)
        target = np.where(by_col, u, v)
        for _ in range(_LINE_NEWTON_STEPS):
            up, vp, du, dv = _line_pixel(cam, Pc, Dc, s)
            s = s - np.where(by_col, (up - target) / du, (vp - target) / dv)
        up, vp, du, dv = _line_pixel(cam, Pc, Dc, s)
        e = ((up - u) * dv - (vp - v) * du) / np.hypot(du, dv)
    return e * np.where(by_col, -np.sign(du), np.sign(dv))


# --------------------------------------------------------------------------- observations
@dataclass(frozen=True, eq=False)
class ObservationBlock:
    """One kind of observation and its residual function.

    Attributes
    ----------
    source : what the observations are ("markers", "target stripes", "board stripes",
        "hand readings", ...)
    unit : "px" or "mm", the residuals' unit
    residual : geometry -> (n,) residuals in ``unit``, for the rows ``rows`` of the block's data
        (called with the row indices into the full data)
    deps : parameter block name -> (n,) item per row for indexed blocks (-1: none), None for
        shared blocks the rows depend on
    image : (n,) int, index into the images' names of the image each row comes from
    uv : (n, 2) float64, px, where each row's observation lies in the image
    run : (n,) int, rows of one run along which errors may be correlated (one stripe on one
        surface, in the order of ``uv``'s rows); -1: independent rows
    slit : (n,) int, the slit item of each row for observations of a slit (None: none)
    points : geometry -> (n, 3) mm, each row's 3D point (a stripe centre on its surface, a hand
        reading), for the slit planes' RMS in mm (None: not points on a slit)
    """

    source: str
    unit: str
    residual: Callable[[Geometry, NDArray[np.intp]], F64]
    deps: Mapping[str, NDArray[np.intp] | None]
    image: NDArray[np.intp]
    uv: F64
    run: NDArray[np.intp] | None = None
    slit: NDArray[np.intp] | None = None
    points: Callable[[Geometry], F64] | None = None

    def __len__(self) -> int:
        return len(self.image)


def marker_block(xyz: F64, uv: F64, image: int) -> ObservationBlock:
    """Marker corners: world points ``xyz`` (M, 3) mm seen at ``uv`` (M, 2) px; 2 rows each."""

    def residual(g: Geometry, rows: NDArray[np.intp]) -> F64:
        return (project(g["camera"], xyz) - uv).ravel()[rows]

    n = 2 * len(xyz)
    return ObservationBlock(
        "markers", "px", residual, {"camera": None}, np.full(n, image, np.intp), np.repeat(uv, 2, 0)
    )


def stripe_block(
    source: str,
    uv: F64,
    slit: NDArray[np.intp],
    surface: NDArray[np.intp],
    image: NDArray[np.intp],
    slit_deps: Mapping[str, bool],
    *,
    fixed_planes: F64 | None = None,
) -> ObservationBlock:
    """Stripe centres ``uv`` (N, 2) px of slit ``slit`` (N,) (an item of the slit blocks) on a
    flat surface: a target face (``fixed_planes`` (F, 4), ``surface`` indexes it) or a
    reference board (``surface`` is the board's item in the ``boards`` block)."""
    pair, pair_of = np.unique(np.stack([slit, surface], axis=1), axis=0, return_inverse=True)
    pair_of = pair_of.reshape(-1)

    def residual(g: Geometry, rows: NDArray[np.intp]) -> F64:
        surf = fixed_planes if fixed_planes is not None else g["board_planes"]
        P, D = plane_lines(g["slit_planes"][pair[:, 0]], surf[pair[:, 1]])
        p = pair_of[rows]
        return line_residuals(g["camera"], P[p], D[p], uv[rows])

    deps: dict[str, NDArray[np.intp] | None] = {"camera": None}
    deps.update({k: (slit if ind else None) for k, ind in slit_deps.items()})
    if fixed_planes is None:
        deps["boards"] = surface
    run = (pair_of * (int(image.max(initial=0)) + 1) + image).astype(np.intp)

    def points(g: Geometry) -> F64:
        surf = fixed_planes if fixed_planes is not None else g["board_planes"]
        o, d = vector_camera(g["camera"], (1, 1)).rays(uv)
        X, _ = intersect_rays_planes(o, d, surf[surface])
        return X

    return ObservationBlock(source, "px", residual, deps, image, uv, run, slit, points)


def reading_block(
    xyz: F64, slit: NDArray[np.intp], image: int, uv: F64, slit_deps: Mapping[str, bool]
) -> ObservationBlock:
    """Hand readings: points ``xyz`` (N, 3) mm on slit ``slit`` (N,) (items of the slit blocks);
    residual: their distance to the slit's plane (mm)."""

    def residual(g: Geometry, rows: NDArray[np.intp]) -> F64:
        pl = g["slit_planes"][slit[rows]]
        return np.einsum("ij,ij->i", xyz[rows], pl[:, :3]) + pl[:, 3]

    deps = {k: (slit if ind else None) for k, ind in slit_deps.items()}
    return ObservationBlock(
        "hand readings", "mm", residual, deps, np.full(len(xyz), image, np.intp), uv, None, slit,
        lambda g: xyz,
    )  # fmt: skip


# --------------------------------------------------------------------------- the problem
class _Problem:
    """The residuals and Jacobian of the observation blocks' kept rows, each divided by its
    block's noise level."""

    def __init__(
        self,
        model: Model,
        obs: Sequence[ObservationBlock],
        rows: Sequence[NDArray[np.intp]],
        sigma: Sequence[float],
        weights: F64 | None = None,
    ) -> None:
        self.model, self.obs, self.rows, self.sigma = model, obs, rows, sigma
        self.layout = Layout(model.blocks)
        self.start = np.cumsum([0] + [len(r) for r in rows])
        self._cache: tuple[F64, list[F64]] | None = None
        #: (m,) each row's weight (the square root of its robust loss's IRLS weight)
        self.weights = np.ones(int(self.start[-1])) if weights is None else weights

    def block_residuals(self, x: F64) -> list[F64]:
        if self._cache is not None and np.array_equal(self._cache[0], x):
            return self._cache[1]
        g = self.model.derive(self.layout.unpack(x))
        res = [
            ob.residual(g, r) / s for ob, r, s in zip(self.obs, self.rows, self.sigma, strict=True)
        ]
        self._cache = (x.copy(), res)
        return res

    def fun(self, x: F64) -> F64:
        r = np.concatenate(self.block_residuals(x))
        return np.where(np.isfinite(r), r, 1e6) * self.weights

    def robust_weights(self, x: F64) -> F64:
        """(m,) the square roots of the soft-L1 loss's IRLS weights at ``x``: 1 / (1 + z)^(1/4)
        with z the squared residual over the loss's scale (:data:`_LOSS_SCALE` noise levels)."""
        r = np.concatenate(self.block_residuals(x))
        z = np.where(np.isfinite(r), r / _LOSS_SCALE, 1e3) ** 2
        return (1.0 + z) ** -0.25

    def jac(self, x: F64) -> F64:
        """(m, P) forward differences: each column of a shared block alone, each column of an
        indexed block for all its items at once (an observation depends on one item)."""
        base = self.block_residuals(x)
        values = self.layout.unpack(x)
        J = np.zeros((int(self.start[-1]), self.layout.size))
        for name, b in self.layout.blocks.items():
            users = [j for j, ob in enumerate(self.obs) if name in ob.deps and len(self.rows[j])]
            if not users:
                continue
            for c_free, col in enumerate(np.flatnonzero(b.free)):
                v = dict(values)
                v[name] = values[name].copy()
                h = _FD_STEP * np.maximum(1.0, np.abs(v[name][:, col]))
                v[name][:, col] += h
                g = self.model.derive(v)
                for j in users:
                    ob, rows = self.obs[j], self.rows[j]
                    d = ob.residual(g, rows) / self.sigma[j] - base[j]
                    item = ob.deps[name]
                    at = self.start[j] + np.arange(len(rows))
                    if item is None:
                        J[at, self.layout.column(name, 0, c_free)] = d / h[0]
                    else:
                        it = item[rows]
                        keep = it >= 0
                        J[at[keep], self.layout.column(name, it[keep], c_free)] = (
                            d[keep] / h[it[keep]]
                        )
        return np.where(np.isfinite(J), J, 0.0) * self.weights[:, None]


# --------------------------------------------------------------------------- result
@dataclass(frozen=True, eq=False)
class BlockStats:
    """Residuals of one observation block after the adjustment.

    Attributes
    ----------
    source, unit : as the block's
    sigma : float, the block's noise level (robust, from its kept residuals), in ``unit``
    inflation : float, how much the errors' correlation along runs inflates their variance
        (:func:`correlation_inflation`); the block's residuals are weighted by
        1 / (sigma sqrt(inflation))
    residuals : (n,) float64, every row's residual in ``unit`` (NaN: not computable)
    kept : (n,) bool, rows used in the last round (the rest are outliers)
    image : (n,) int, each row's image
    region : (n,) int, each row's image region (index into :data:`REGIONS`)
    run : (n,) int or None, the block's runs (see :class:`ObservationBlock`)
    order : (n,) float64, each row's position along its run (its image row)
    """

    source: str
    unit: str
    sigma: float
    inflation: float
    residuals: F64
    kept: NDArray[np.bool_]
    image: NDArray[np.intp]
    region: NDArray[np.intp]
    run: NDArray[np.intp] | None = None
    order: F64 | None = None

    def rms(self, mask: NDArray[np.bool_] | None = None) -> float:
        """RMS of the kept residuals (within ``mask``), NaN if none."""
        m = self.kept if mask is None else self.kept & mask
        r = self.residuals[m]
        r = r[np.isfinite(r)]
        return float(np.sqrt(np.mean(r * r))) if len(r) else float("nan")

    def run_offsets(self, mask: NDArray[np.bool_] | None = None) -> tuple[float, float]:
        """The kept residuals (within ``mask``) split into their runs' means and the rest:
        RMS (over the rows) of the means, and of the residuals about them (NaN without runs).

        A model that fits leaves runs (stripes) that scatter about zero; one that does not (an
        image taken with the target moved, or from another set-up) leaves whole stripes off.
        """
        if self.run is None:
            return float("nan"), float("nan")
        m = (self.kept if mask is None else self.kept & mask) & np.isfinite(self.residuals)
        m &= self.run >= 0
        if not m.any():
            return float("nan"), float("nan")
        _, k = np.unique(self.run[m], return_inverse=True)
        r = self.residuals[m]
        mean = np.bincount(k, r) / np.bincount(k)
        off = mean[k]
        return float(np.sqrt(np.mean(off**2))), float(np.sqrt(np.mean((r - off) ** 2)))


@dataclass(frozen=True, eq=False)
class BundleResult:
    """Result of :func:`adjust`.

    Attributes
    ----------
    values : parameter block name -> fitted values (items, width)
    geometry : the fitted geometry ("camera" (15,), "slit_planes" (K, 4), "board_planes" (B, 4))
    camera : PinholeCamera, the fitted camera
    stats : tuple of BlockStats, one per observation block
    labels : (P,) str, the fitted parameters' names
    x : (P,) float64, the fitted parameters
    std_errors : (P,) float64, their standard errors (from the Jacobian at the solution, the
        residuals scaled by their blocks' noise; NaN: not determined)
    covariance : (P, P) float64, the parameters' covariance
    converged : bool, the solver stopped on a tolerance (not on the iteration limit)
    message : str, the solver's message
    rounds : int, rounds of (fit, noise estimate, outliers)
    images : (I,) str, the images' names that the blocks' ``image`` index
    """

    values: dict[str, F64]
    geometry: Geometry
    camera: PinholeCamera
    stats: tuple[BlockStats, ...]
    labels: tuple[str, ...]
    x: F64
    std_errors: F64
    covariance: F64
    converged: bool
    message: str
    rounds: int
    images: tuple[str, ...]

    @property
    def noise(self) -> Noise:
        """The noise model the fit used."""
        return Noise(
            tuple(st.kept for st in self.stats),
            tuple(st.sigma for st in self.stats),
            tuple(st.inflation for st in self.stats),
        )

    def std_error(self, label: str) -> float:
        """The standard error of the parameter named ``label`` (e.g. ``camera.k1``)."""
        try:
            return float(self.std_errors[self.labels.index(label)])
        except ValueError:
            return float("nan")

    def per_source(self) -> dict[str, dict[str, Any]]:
        """Source -> {unit, count, kept, sigma, rms, regions: {region: [count, rms]}}."""
        out: dict[str, dict[str, Any]] = {}
        for st in self.stats:
            regions = {}
            for i, name in enumerate(REGIONS):
                m = st.region == i
                if np.any(m & st.kept):
                    regions[name] = [int(np.sum(m & st.kept)), st.rms(m)]
            out[st.source] = {
                "unit": st.unit,
                "count": len(st.residuals),
                "kept": int(st.kept.sum()),
                "sigma": st.sigma,
                "inflation": st.inflation,
                "rms": st.rms(),
                "regions": regions,
            }
        return out

    def per_image(self) -> dict[str, dict[str, Any]]:
        """Image -> {source: {unit, count, kept, rms}} over the blocks' rows from that image."""
        out: dict[str, dict[str, Any]] = {}
        for st in self.stats:
            for i in np.unique(st.image):
                m = st.image == i
                out.setdefault(self.images[i], {})[st.source] = {
                    "unit": st.unit,
                    "count": int(m.sum()),
                    "kept": int((m & st.kept).sum()),
                    "rms": st.rms(m),
                }
        return out


def image_regions(uv: F64, image_size: tuple[int, int]) -> NDArray[np.intp]:
    """(N,) index into :data:`REGIONS` of each pixel ``uv`` (N, 2): a 3 x 3 grid."""
    w, h = image_size
    cu = np.clip((uv[:, 0] / w * 3).astype(int), 0, 2)
    cv = np.clip((uv[:, 1] / h * 3).astype(int), 0, 2)
    return (3 * cv + cu).astype(np.intp)


#: Lags (rows of a run) over which the residuals' autocorrelation is summed, at most.
_MAX_LAG = 64


def correlation_inflation(r: F64, run: NDArray[np.intp] | None, order: F64) -> float:
    """How much serially correlated errors along runs inflate a block's variance of the mean:
    1 + 2 sum_k rho_k over the lags k until the autocorrelation rho falls below 0.05 (>= 1).

    Parameters
    ----------
    r : (n,) residuals
    run : (n,) run of each row (-1: independent rows), None: all independent
    order : (n,) the position of each row along its run (e.g. its image row)
    """
    if run is None:
        return 1.0
    ok = np.isfinite(r) & (run >= 0)
    idx = np.flatnonzero(ok)
    idx = idx[np.lexsort((order[idx], run[idx]))]
    rr, kk = r[idx], run[idx]
    var = float(rr @ rr)
    if var <= 0:
        return 1.0
    total = 0.0
    for lag in range(1, _MAX_LAG + 1):
        same = kk[lag:] == kk[:-lag]
        if not same.any():
            break
        rho = float(rr[lag:][same] @ rr[:-lag][same]) / var * len(rr) / max(int(same.sum()), 1)
        if rho < 0.05:
            break
        total += rho
    return 1.0 + 2.0 * total


def _run_medians(r: F64, run: NDArray[np.intp] | None) -> F64:
    """(n,) each row's run's median residual (0 for rows without a run): an outlier is a row
    far from its own stripe, not a stripe that the model does not fit (that is a misfit,
    which the model tests and the image checks must see)."""
    out = np.zeros(len(r))
    if run is None:
        return out
    ok = np.isfinite(r) & (run >= 0)
    if not ok.any():
        return out
    _, inv = np.unique(run[ok], return_inverse=True)
    order = np.lexsort((r[ok], inv))
    counts = np.bincount(inv)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    sorted_r = r[ok][order]
    med = 0.5 * (sorted_r[starts + (counts - 1) // 2] + sorted_r[starts + counts // 2])
    out[ok] = med[inv]
    return out


def _robust_sigma(r: F64, unit: str) -> float:
    r = r[np.isfinite(r)]
    s = MAD_TO_SIGMA * float(np.median(np.abs(r))) if len(r) else 1.0
    return max(s, _MIN_SIGMA[unit])


@dataclass(frozen=True, eq=False)
class Noise:
    """The noise model of the observation blocks: per block, the rows kept (not outliers), the
    noise level and the correlation inflation (see :class:`BlockStats`)."""

    kept: tuple[NDArray[np.bool_], ...]
    sigma: tuple[float, ...]
    inflation: tuple[float, ...]

    def scale(self) -> list[float]:
        """Per block, what its residuals are divided by: sigma sqrt(inflation)."""
        return [s * math.sqrt(f) for s, f in zip(self.sigma, self.inflation, strict=True)]


def adjust(
    model: Model,
    obs: Sequence[ObservationBlock],
    images: Sequence[str],
    image_size: tuple[int, int],
    *,
    noise: Noise | None = None,
    max_nfev: int = 60,
) -> BundleResult:
    """Fit the model's parameters to all observation blocks at once (see the module docstring).

    Parameters
    ----------
    model : the parameter blocks and the geometry they make
    obs : the observation blocks
    images : (I,) the images' names (the blocks' ``image`` index them)
    image_size : (W, H) px
    noise : a fixed noise model (one fit, e.g. to compare two models on the same footing);
        default: estimated in rounds (fit, noise levels and outliers from the residuals, until
        they settle)
    max_nfev : most solver iterations per round

    Returns
    -------
    BundleResult

    Raises
    ------
    CalibrationError
        Fewer residuals than parameters, or residuals that cannot be computed at the start.
    """
    layout = Layout(model.blocks)
    x = layout.pack({b.name: b.x0 for b in model.blocks})
    g0 = model.derive(layout.unpack(x))
    rows = [np.arange(len(ob)) for ob in obs]
    r0 = [ob.residual(g0, r) for ob, r in zip(obs, rows, strict=True)]
    for ob, r in zip(obs, r0, strict=True):
        if len(r) and not np.any(np.isfinite(r)):
            raise CalibrationError(f"bundle adjustment: no {ob.source} residual can be computed")
    fixed = noise is not None
    if noise is None:
        noise = Noise(
            tuple(np.isfinite(r) for r in r0),
            tuple(_robust_sigma(r, ob.unit) for ob, r in zip(obs, r0, strict=True)),
            (1.0,) * len(obs),
        )
    n_obs = sum(int(k.sum()) for k in noise.kept)
    if n_obs <= layout.size:
        raise CalibrationError(
            f"bundle adjustment: {n_obs} observations for {layout.size} parameters"
        )
    sol = None
    rounds = 0
    weights = None
    while rounds < _MAX_ROUNDS:
        rounds += 1
        prob = _Problem(model, obs, [np.flatnonzero(k) for k in noise.kept], noise.scale(), weights)
        # MINPACK's Levenberg-Marquardt (its QR is single-threaded: fast on a busy machine);
        # the robust loss by reweighting, each round's weights from the last round's residuals
        sol = least_squares(
            prob.fun, x, jac=prob.jac, method="lm", x_scale="jac", max_nfev=max_nfev,
            xtol=1e-8, ftol=1e-8, gtol=1e-8,
        )  # fmt: skip
        x = sol.x
        new_w = prob.robust_weights(x)
        settled = weights is not None and float(np.max(np.abs(new_w - weights))) < 0.02
        if fixed:
            weights = new_w
            if settled or rounds >= _FIXED_ROUNDS:
                break
            continue
        g = model.derive(layout.unpack(x))
        res = [ob.residual(g, r) for ob, r in zip(obs, rows, strict=True)]
        sigma = [
            _robust_sigma(r[k], ob.unit) for ob, r, k in zip(obs, res, noise.kept, strict=True)
        ]
        kept = [
            np.isfinite(r) & (np.abs(r - _run_medians(r, ob.run)) <= OUTLIER_SIGMA * s)
            for ob, r, s in zip(obs, res, sigma, strict=True)
        ]
        infl = [
            correlation_inflation(np.where(k, r, np.nan), ob.run, ob.uv[:, 1])
            for ob, r, k in zip(obs, res, kept, strict=True)
        ]
        new = Noise(tuple(kept), tuple(sigma), tuple(infl))
        same = all(np.array_equal(a, b) for a, b in zip(noise.kept, new.kept, strict=True))
        steady = all(abs(a / b - 1) < 0.05 for a, b in zip(noise.scale(), new.scale(), strict=True))
        noise = new
        # the next round's weights, on its rows and scales
        nxt = _Problem(model, obs, [np.flatnonzero(k) for k in noise.kept], noise.scale())
        weights = nxt.robust_weights(x)
        if same and steady and settled:
            break
    assert sol is not None
    prob = _Problem(model, obs, [np.flatnonzero(k) for k in noise.kept], noise.scale())
    prob.weights = prob.robust_weights(x)
    cov, se = _covariance(prob, x)
    g = model.derive(layout.unpack(x))
    stats = []
    for ob, k, s, f in zip(obs, noise.kept, noise.sigma, noise.inflation, strict=True):
        r = ob.residual(g, np.arange(len(ob)))
        reg = image_regions(ob.uv, image_size)
        stats.append(BlockStats(ob.source, ob.unit, s, f, r, k, ob.image, reg, ob.run, ob.uv[:, 1]))
    return BundleResult(
        values=layout.unpack(x),
        geometry=g,
        camera=vector_camera(g["camera"], image_size),
        stats=tuple(stats),
        labels=tuple(layout.labels()),
        x=x,
        std_errors=se,
        covariance=cov,
        converged=bool(sol.status > 0),
        message=str(sol.message),
        rounds=rounds,
        images=tuple(images),
    )


def _covariance(prob: _Problem, x: F64) -> tuple[F64, F64]:
    """The parameters' covariance (P, P) and standard errors (P,) at ``x``: (J^T J)^-1 of the
    residuals divided by their blocks' noise (NaN where J^T J is singular)."""
    J = prob.jac(x)
    JtJ = J.T @ J
    d = np.sqrt(np.diag(JtJ))
    d = np.where(d > 0, d, 1.0)
    A = JtJ / d[:, None] / d[None, :]
    w, V = np.linalg.eigh(A)
    ok = w > w.max() * 1e-12
    inv = (V[:, ok] / w[ok]) @ V[:, ok].T
    cov = inv / d[:, None] / d[None, :]
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    if not ok.all():  # the directions not determined make their parameters' errors unknown
        weak = np.abs(V[:, ~ok]).max(axis=1) > 1e-3
        se[weak] = np.nan
    return cov, se


# --------------------------------------------------------------------------- 3D uncertainty
def point_uncertainty(
    result: BundleResult,
    model: Model,
    uv: F64,
    slit: NDArray[np.intp],
) -> F64:
    """Predicted 1-sigma 3D error (N,) mm of points triangulated at pixels ``uv`` (N, 2) on slit
    items ``slit`` (N,), from the parameters' covariance (the camera's and the slit planes').

    The error is the square root of the trace of the point's covariance (its RMS distance from
    the truth): J C J^T with J the point's derivative by the parameters.
    """
    layout = Layout(model.blocks)
    x = result.x
    values = layout.unpack(x)
    size = result.camera.image_size

    def points(v: Mapping[str, F64]) -> F64:
        g = model.derive(v)
        o, d = vector_camera(g["camera"], size).rays(uv)
        X, _ = intersect_rays_planes(o, d, g["slit_planes"][slit])
        return X

    X0 = points(values)
    n = len(uv)
    J = np.zeros((3 * n, layout.size))
    names = ["camera", *model.slit_deps]
    for name in names:
        b = layout.blocks[name]
        indexed = b.indexed
        for c_free, col in enumerate(np.flatnonzero(b.free)):
            v = {k: a.copy() for k, a in values.items()}
            h = _FD_STEP * np.maximum(1.0, np.abs(v[name][:, col]))
            v[name][:, col] += h
            dX = (points(v) - X0) / (h[slit][:, None] if indexed else h[0])
            cols = layout.column(name, slit if indexed else np.zeros(n, np.intp), c_free)
            for a in range(3):
                J[np.arange(n) * 3 + a, cols] = dX[:, a]
    A = J @ result.covariance
    var = np.einsum("ij,ij->i", A, J).reshape(n, 3).sum(axis=1)
    return np.sqrt(np.clip(var, 0, None))


# --------------------------------------------------------------------------- models
def free_planes_model(
    camera: PinholeCamera,
    slit_planes: F64,
    board_planes: F64,
    *,
    fit_k3: bool = True,
) -> tuple[Model, PlaneParams]:
    """The model with one free plane per slit (3 parameters each).

    Parameters
    ----------
    camera : the starting camera
    slit_planes : (K, 4) float64, the starting planes of the fitted slits (finite rows)
    board_planes : (B, 4) float64, the starting planes of the fitted boards (finite rows)
    fit_k3 : fit k3 (else it stays at the starting camera's value)
    """
    cam = _camera_block(camera, fit_k3)
    sp, sx = PlaneParams.start(slit_planes)
    blocks = [cam, param_block("slits", sx, indexed=True, labels=("a", "b", "d"))]
    bp = None
    if len(board_planes):
        bp, bx = PlaneParams.start(board_planes)
        blocks.append(param_block("boards", bx, indexed=True, labels=("a", "b", "d")))

    def derive(v: Mapping[str, F64]) -> Geometry:
        g = {"camera": v["camera"][0], "slit_planes": sp.planes(v["slits"])}
        if bp is not None:
            g["board_planes"] = bp.planes(v["boards"])
        return g

    return Model(tuple(blocks), derive, {"slits": True}), sp


def axis_planes_model(
    camera: PinholeCamera,
    slit_planes: F64,
    board_planes: F64,
    *,
    fit_k3: bool = True,
) -> tuple[Model, AxisParams]:
    """The model with slit planes through one common axis (4 shared parameters, 1 per slit)."""
    cam = _camera_block(camera, fit_k3)
    ap, ax, phi = AxisParams.start(slit_planes)
    blocks = [
        cam,
        param_block("axis", ax, indexed=False, labels=("turn1", "turn2", "shift1", "shift2")),
        param_block("slits", phi, indexed=True, labels=("angle",)),
    ]
    bp = None
    if len(board_planes):
        bp, bx = PlaneParams.start(board_planes)
        blocks.append(param_block("boards", bx, indexed=True, labels=("a", "b", "d")))

    def derive(v: Mapping[str, F64]) -> Geometry:
        g = {"camera": v["camera"][0], "slit_planes": ap.planes(v["axis"][0], v["slits"])}
        if bp is not None:
            g["board_planes"] = bp.planes(v["boards"])
        return g

    return Model(tuple(blocks), derive, {"axis": False, "slits": True}), ap


def camera_model(camera: PinholeCamera, *, fit_k3: bool = True) -> Model:
    """The model of a camera alone (for markers, or any known 3D points, alone)."""
    cam = _camera_block(camera, fit_k3)
    return Model((cam,), lambda v: {"camera": v["camera"][0]}, {})


def _camera_block(camera: PinholeCamera, fit_k3: bool) -> ParamBlock:
    free = np.ones(len(CAMERA_PARAMS), bool)
    free[14] = fit_k3
    return param_block(
        "camera", camera_vector(camera), indexed=False, labels=CAMERA_PARAMS, free=free
    )


# --------------------------------------------------------------------------- a capture
#: Images whose residuals are this many times the median image's of the same source (or, for
#: markers, above :data:`MAX_MARKER_RMS_PX`) are named as the ones to retake.
MAX_RMS_FACTOR = 3.0
#: ... and images whose stripes lie off the fit as a whole (the RMS of their stripes' mean
#: residuals) by more than this many times their scatter along the stripes (a capture that
#: fits: 0.1-0.4).
RUN_OFFSET_FACTOR = 1.0
#: Stripes off the fit by less than this RMS (px) are never an error, whatever their scatter.
MIN_MISFIT_PX = 0.1
#: Largest RMS (px) of the markers' residuals that is not an error.
MAX_MARKER_RMS_PX = 0.5
#: Largest share of an image's observations that may be outliers.
MAX_OUTLIER_SHARE = 0.3
#: The common-axis model is rejected only when the free planes would move some slit's plane
#: by more than this many times the predicted 3D error of triangulated points (and their
#: chi-square decrease is significant).
AXIS_MISFIT = 3.0
#: Most observations per slit and surface: consecutive stripe centres are averaged in bins
#: (:func:`bin_lines`), so every centre counts and the adjustment's size stays bounded.
MAX_PER_LINE = 60
#: Before binning, a centre further than this (px, across the stripe) from the running median
#: of its stripe over this many centres is left out (another slit is a stripe spacing away).
_BIN_MAX_OFF_PX = 2.0
_BIN_MEDIAN_ROWS = 9
#: Least stripe centres of a slit on a surface for them to count.
MIN_PER_LINE = 12


@dataclass(frozen=True, eq=False)
class CaptureObservations:
    """What a capture's images give the adjustment.

    Attributes
    ----------
    image_size : (W, H) px
    marker_xyz : (M, 3) float64, mm, the markers used
    marker_uv : (M, 2) float64, px, where they were found in the markers image
    faces : (F, 4) float64, the target's face planes (unit normals)
    target_uv : (T, 2) float64, px, stripe centres on the target's faces (may be empty)
    target_slit, target_face : (T,) int
    readings_xyz : (H, 3) float64, mm, hand readings of points on the slits (may be empty)
    readings_slit : (H,) int
    readings_uv : (H, 2) float64, px, where the readings were taken (for the report's regions)
    board_uv : per reference board, (N_b, 2) float64 px, stripe centres
    board_slit : per reference board, (N_b,) int
    names : image names: markers image, slits image, hand readings, then the boards
    fold_uv : (E, 2) float64, px, points of the target's folds in the markers image (may be
        empty; :func:`~multislit.calibrate.edges.fold_points`)
    fold_line : (E,) int, the fold of each point (index into ``fold_P``, ``fold_D``)
    fold_P, fold_D : (L, 3) float64, each fold's 3D line (a point, mm; a unit direction)
    """

    image_size: tuple[int, int]
    marker_xyz: F64
    marker_uv: F64
    faces: F64
    target_uv: F64
    target_slit: NDArray[np.intp]
    target_face: NDArray[np.intp]
    readings_xyz: F64
    readings_slit: NDArray[np.intp]
    readings_uv: F64
    board_uv: tuple[F64, ...]
    board_slit: tuple[NDArray[np.intp], ...]
    names: tuple[str, ...]
    fold_uv: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    fold_line: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))
    fold_P: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    fold_D: F64 = field(default_factory=lambda: np.zeros((0, 3)))


def bin_lines(
    key: NDArray[np.intp], uv: F64, most: int = MAX_PER_LINE, least: int = MIN_PER_LINE
) -> tuple[F64, NDArray[np.intp]]:
    """Stripe centres averaged in bins of consecutive rows: at most ``most`` per ``key`` (a
    stripe on one surface), every centre in one bin; keys with fewer than ``least`` centres
    are left out. Over a few rows a stripe's image is straight, so a bin's mean lies on it
    with the noise of its centres averaged.

    Centres more than :data:`_BIN_MAX_OFF_PX` from the running median of their stripe (over
    :data:`_BIN_MEDIAN_ROWS` centres) are left out first: a scattered centre of another slit
    under this one's number would pull its bin's mean.

    Returns the bins' mean positions (B, 2) px and the key of each bin (B,).
    """
    if not len(key):
        return np.zeros((0, 2)), np.zeros(0, np.intp)
    idx = np.lexsort((uv[:, 1], key))
    ks = key[idx]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[starts, len(ks)])
    run = np.repeat(np.arange(len(starts)), counts)
    pos = np.arange(len(ks)) - starts[run]  # rank of each centre in its stripe
    size = np.ceil(counts / most).astype(int)  # centres per bin, per stripe
    ok = counts[run] >= least
    # a centre far from its stripe's running median (another slit's, under this one's
    # number) would pull its bin's mean: it is left out
    u = uv[idx, 0]
    for a, c in zip(starts, counts, strict=True):
        med = median_filter(u[a : a + c], size=_BIN_MEDIAN_ROWS, mode="nearest")
        ok[a : a + c] &= np.abs(u[a : a + c] - med) <= _BIN_MAX_OFF_PX
    bin_id = run * (int(counts.max()) + 1) + pos // size[run]
    _, inv = np.unique(bin_id[ok], return_inverse=True)
    n = np.bincount(inv).astype(float)
    mean = np.stack(
        [np.bincount(inv, uv[idx][ok, 0]) / n, np.bincount(inv, uv[idx][ok, 1]) / n], axis=1
    )
    first = np.zeros(len(n), np.intp)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    return mean, ks[ok][first]


@dataclass(frozen=True, eq=False)
class CaptureBundle:
    """Result of :func:`adjust_capture`.

    Attributes
    ----------
    result : BundleResult of the model kept
    model : Model of the result
    kind : "free" (one free plane per slit) or "common axis"
    camera : PinholeCamera, the fitted camera
    slit_planes : (K, 4) float64, the fitted slit planes (NaN: slits not fitted)
    slit_rms_mm : (K,) float64, mm, RMS distance of each slit's stripe centres (on their
        surfaces, through the fitted camera) and hand readings to its plane
    slit_counts : (K,) int, observations per slit kept
    slit_item : (K,) int, each slit's item in the slit parameter blocks (-1: not fitted)
    slit_sources : {source: (K,) int}, per observation source, the observations of each slit
        kept
    axis : (point (3,), direction (3,)) of the common axis (the planes' common line if free)
    board_planes : (B, 4) float64, the fitted boards (NaN: not fitted)
    tests : {what: {chi2, gain, dof, limit, significant, added, ...}}: the score tests of the
        parameters added when the data ask for them ("k3", "free planes": one free plane per
        slit instead of the common axis): the chi-square of the fit without them, its
        predicted decrease with them, their number, the decrease that is significant, and
        whether they were added; "free planes" also has ``change`` (mm, the largest move of a
        slit's plane) and ``uncertainty_mm`` (the predicted 3D error it is compared with)
    uncertainty : list of dict per board: name, distance (mm from the camera), points,
        median and 95th percentile of the predicted 1-sigma 3D error (mm)
    problems : tuple of str, why the fit cannot be trusted, naming the images to retake
    """

    result: BundleResult
    model: Model
    kind: str
    camera: PinholeCamera
    slit_planes: F64
    slit_rms_mm: F64
    slit_counts: NDArray[np.int_]
    slit_item: NDArray[np.intp]
    slit_sources: dict[str, NDArray[np.int_]]
    axis: tuple[F64, F64]
    board_planes: F64
    tests: dict[str, dict[str, float]]
    uncertainty: tuple[dict[str, Any], ...]
    problems: tuple[str, ...]


def _capture_blocks(
    obs: CaptureObservations,
    slit_item: NDArray[np.intp],
    board_item: NDArray[np.intp],
    slit_deps: Mapping[str, bool],
) -> list[ObservationBlock]:
    """The observation blocks of a capture (markers, target stripes or hand readings, boards)."""
    blocks = [marker_block(obs.marker_xyz, obs.marker_uv, 0)]
    if len(obs.fold_uv):
        blocks.append(_fold_block(obs))
    t = slit_item[obs.target_slit] >= 0 if len(obs.target_slit) else np.zeros(0, bool)
    if np.any(t):
        key = obs.target_slit[t] * 64 + obs.target_face[t]
        uv, key = bin_lines(key, obs.target_uv[t])
        if len(uv):
            blocks.append(
                stripe_block(
                    "target stripes", uv, slit_item[key // 64], key % 64,
                    np.full(len(uv), 1, np.intp), slit_deps, fixed_planes=obs.faces,
                )
            )  # fmt: skip
    h = slit_item[obs.readings_slit] >= 0 if len(obs.readings_slit) else np.zeros(0, bool)
    if np.any(h):
        blocks.append(
            reading_block(
                obs.readings_xyz[h], slit_item[obs.readings_slit[h]], 2, obs.readings_uv[h],
                slit_deps,
            )
        )  # fmt: skip
    uv_l, s_l, b_l = [], [], []
    for b, (uv, s) in enumerate(zip(obs.board_uv, obs.board_slit, strict=True)):
        if board_item[b] < 0 or not len(s):
            continue
        ok = slit_item[s] >= 0
        buv, bs = bin_lines(s[ok], uv[ok])
        uv_l.append(buv)
        s_l.append(slit_item[bs])
        b_l.append(np.full(len(bs), b, np.intp))
    if uv_l:
        bb = np.concatenate(b_l)
        blocks.append(
            stripe_block(
                "board stripes", np.concatenate(uv_l), np.concatenate(s_l), board_item[bb],
                3 + bb, slit_deps,
            )
        )  # fmt: skip
    return blocks


def _fold_block(obs: CaptureObservations) -> ObservationBlock:
    """The target's folds seen in the markers image: known 3D lines, residuals across them."""
    P, D, uv = obs.fold_P[obs.fold_line], obs.fold_D[obs.fold_line], obs.fold_uv

    def residual(g: Geometry, rows: NDArray[np.intp]) -> F64:
        return line_residuals(g["camera"], P[rows], D[rows], uv[rows])

    image = np.zeros(len(uv), np.intp)
    return ObservationBlock(
        "target folds", "px", residual, {"camera": None}, image, uv, obs.fold_line.copy()
    )


def _surfaces_seen(obs: CaptureObservations, k: int, boards_ok: NDArray[np.bool_]) -> NDArray:
    """(K,) int, per slit: the surfaces (target faces, posed boards) it is seen on with at
    least :data:`MIN_PER_LINE` centres, plus 2 if its hand readings span a plane (>= 3 points
    off one line), 1 if they lie along one line. A free plane needs 2, one through the common
    axis 1."""
    n = np.zeros(k, int)
    if len(obs.target_slit):
        pairs = obs.target_slit * 64 + obs.target_face
        u, c = np.unique(pairs, return_counts=True)
        n += np.bincount(u[c >= MIN_PER_LINE] // 64, minlength=k)[:k]
    for b, s in enumerate(obs.board_slit):
        if boards_ok[b] and len(s):
            n += np.bincount(s, minlength=k)[:k] >= MIN_PER_LINE
    for j in np.unique(obs.readings_slit):
        X = obs.readings_xyz[obs.readings_slit == j]
        if len(X) >= 3 and np.linalg.svd(X - X.mean(axis=0), compute_uv=False)[1] > 1e-3:
            n[j] += 2
        elif len(X) >= 2:
            n[j] += 1
    return n


def _chi2(result: BundleResult) -> float:
    """Sum of the kept residuals squared, each divided by its block's weight scale."""
    total = 0.0
    for st in result.stats:
        r = st.residuals[st.kept]
        r = r[np.isfinite(r)]
        total += float(np.sum(r * r)) / (st.sigma * st.sigma * st.inflation)
    return total


@dataclass(frozen=True, eq=False)
class _Fit:
    """One adjustment of a capture: its result, model, slit parameterisation and blocks."""

    result: BundleResult
    model: Model
    params: PlaneParams | AxisParams
    blocks: list[ObservationBlock]
    noise: Noise | None

    def __iter__(self) -> Any:  # unpacking: result, model, params, blocks
        return iter((self.result, self.model, self.params, self.blocks))


def _fit_capture(
    obs: CaptureObservations,
    kind: str,
    camera: PinholeCamera,
    slit_planes: F64,
    board_planes: F64,
    slit_item: NDArray[np.intp],
    board_item: NDArray[np.intp],
    fit_k3: bool,
    noise: Noise | None = None,
    *,
    solve: bool = True,
) -> _Fit:
    """One adjustment of a capture with the slit model ``kind`` ("free" or "common axis").

    With ``solve=False`` the model is only set up (its result is None): for a score test.
    """
    make = axis_planes_model if kind == "common axis" else free_planes_model
    model, par = make(camera, slit_planes, board_planes, fit_k3=fit_k3)
    blocks = _capture_blocks(obs, slit_item, board_item, model.slit_deps)
    if not solve:
        return _Fit(None, model, par, blocks, noise)  # type: ignore[arg-type]
    return _Fit(
        adjust(model, blocks, obs.names, obs.image_size, noise=noise), model, par, blocks, noise
    )


def _score_test(
    fit: _Fit, big: _Fit, change: Callable[[dict[str, F64]], float] | None = None
) -> dict[str, Any]:
    """Whether the extra parameters of ``big`` (set up at ``fit``'s solution) are supported.

    The score (Lagrange multiplier) test: the chi-square decrease one Gauss-Newton step of the
    bigger model would bring, g^T (J^T W J)^-1 g with g = J^T W r at the smaller model's
    solution (W the robust loss's weights), under ``fit``'s noise model. The decrease is
    significant when a chi-square with d degrees of freedom (d extra parameters) exceeds it
    with a chance below :data:`_TEST_LEVEL`. ``change`` (of the stepped parameters' values) measures what
    the step would change (e.g. mm), for the caller to judge whether it matters.
    """
    noise = fit.result.noise
    layout = Layout(big.model.blocks)
    x = layout.pack({b.name: b.x0 for b in big.model.blocks})
    prob = _Problem(big.model, big.blocks, [np.flatnonzero(k) for k in noise.kept], noise.scale())
    r = prob.fun(x)
    J = prob.jac(x)
    w = np.sqrt(1.0 / np.sqrt(1.0 + (r / _LOSS_SCALE) ** 2))  # soft-L1's IRLS weights
    Jw, rw = J * w[:, None], r * w
    g = Jw.T @ rw
    step = np.linalg.lstsq(Jw.T @ Jw, g, rcond=1e-12)[0]
    gain = float(g @ step)
    dof = max(len(x) - len(fit.result.x), 1)
    limit = float(scipy.stats.chi2.isf(_TEST_LEVEL, dof))
    out: dict[str, Any] = {
        "chi2": _chi2(fit.result),
        "gain": gain,
        "dof": dof,
        "limit": limit,
        "significant": gain > limit,
    }
    if change is not None:
        out["change"] = float(change(layout.unpack(x - step)))
    out["added"] = out["significant"]
    return out


def _plane_change(fit: _Fit, big: _Fit) -> Callable[[dict[str, F64]], float]:
    """The largest RMS distance (mm) over the slits between ``fit``'s slit planes and ``big``'s
    planes of the values given, at each slit's observed 3D points (where the planes are used)."""
    g = fit.result.geometry
    pts, sl = [], []
    for ob, st in zip(fit.blocks, fit.result.stats, strict=True):
        if ob.points is not None and ob.slit is not None:
            pts.append(ob.points(g)[st.kept])
            sl.append(ob.slit[st.kept])
    X, s = np.concatenate(pts), np.concatenate(sl)
    ok = np.all(np.isfinite(X), axis=1)
    X, s = X[ok], s[ok]
    old = g["slit_planes"][s]
    d0 = np.einsum("ij,ij->i", X, old[:, :3]) + old[:, 3]

    def change(values: dict[str, F64]) -> float:
        pl = big.model.derive(values)["slit_planes"][s]
        pl = pl * np.sign(np.einsum("ij,ij->i", pl[:, :3], old[:, :3]))[:, None]
        d = np.einsum("ij,ij->i", X, pl[:, :3]) + pl[:, 3] - d0
        n = np.bincount(s)
        per = np.sqrt(np.bincount(s, d * d) / np.maximum(n, 1))
        return float(per[n > 0].max()) if np.any(n > 0) else 0.0

    return change


def _refit(fit: _Fit, big: _Fit, obs: CaptureObservations) -> _Fit:
    """``big`` fitted from ``fit``'s solution under ``fit``'s noise model."""
    res = adjust(big.model, big.blocks, obs.names, obs.image_size, noise=fit.result.noise)
    return _Fit(res, big.model, big.params, big.blocks, fit.result.noise)


def _significant(result: BundleResult, label: str, z: float = 3.0) -> bool:
    """Whether the parameter ``label`` differs from 0 by more than ``z`` standard errors."""
    se = result.std_error(label)
    value = result.x[result.labels.index(label)] if label in result.labels else 0.0
    return bool(np.isfinite(se) and abs(value) > z * se)


def adjust_capture(
    obs: CaptureObservations,
    camera: PinholeCamera,
    slit_planes: F64,
    board_planes: F64,
    *,
    fit_k3: bool = True,
) -> CaptureBundle:
    """The bundle adjustment of a capture: camera, slit planes and boards from all its images.

    The slit planes pass through one common axis (a grating's) and the camera has k1, k2, p1,
    p2, with the noise model estimated in rounds (:func:`adjust`). Then score tests
    (:func:`_score_test`) ask whether k3, and one free plane per slit instead of the common
    axis, would lower the chi-square by more than noise explains (at three standard
    deviations); the free planes must also move some slit's plane by more than
    :data:`AXIS_MISFIT` times the predicted 3D error of triangulated points (a misfit that
    matters, not one that the stripes' correlated errors make significant). What is supported
    is added and fitted from that solution under the same noise model. With fewer than 3 slits
    the planes are free.

    Parameters
    ----------
    obs : the observations (:class:`CaptureObservations`)
    camera : the starting camera (e.g. from the markers)
    slit_planes : (K, 4) float64, starting planes (NaN rows: slits left out)
    board_planes : (B, 4) float64, starting board planes (NaN rows: boards left out)
    fit_k3 : fit k3 as well (else it keeps the starting camera's value)

    Returns
    -------
    CaptureBundle
    """
    k = len(slit_planes)
    bv = np.all(np.isfinite(board_planes), axis=1)
    finite = np.all(np.isfinite(slit_planes), axis=1)
    seen = _surfaces_seen(obs, k, bv)
    # through a common axis a slit seen along one line has its plane (the axis and the line);
    # free, it needs two
    axis_model = int(np.sum(finite & (seen >= 2))) >= 3
    sv = finite & (seen >= (1 if axis_model else 2))
    slit_item = np.full(k, -1, np.intp)
    slit_item[sv] = np.arange(int(sv.sum()))
    board_item = np.full(len(board_planes), -1, np.intp)
    board_item[bv] = np.arange(int(bv.sum()))
    bstart = board_planes[bv]
    start = slit_planes[sv]
    cam0 = replace(camera, dist=camera.dist[:4])  # k3 = 0 unless the data ask for it
    tests: dict[str, dict[str, float]] = {}
    kind = "common axis" if axis_model else "free"
    fit = _fit_capture(obs, kind, cam0, start, bstart, slit_item, board_item, False)
    if fit_k3:
        # k3: the chi-square decrease the fit with k3 free would bring (a score test)
        big = _fit_capture(
            obs, kind, fit.result.camera, fit.result.geometry["slit_planes"],
            fit.result.geometry.get("board_planes", bstart), slit_item, board_item, True,
            fit.result.noise, solve=False,
        )  # fmt: skip
        tests["k3"] = _score_test(fit, big)
        if tests["k3"]["added"]:
            fit = _refit(fit, big, obs)
    if kind == "common axis":
        k3 = "camera.k3" in fit.result.labels
        big = _fit_capture(
            obs, "free", fit.result.camera, fit.result.geometry["slit_planes"],
            fit.result.geometry.get("board_planes", bstart), slit_item, board_item, k3,
            fit.result.noise, solve=False,
        )  # fmt: skip
        t = _score_test(fit, big, _plane_change(fit, big))
        sigma = _uncertainty(fit.result, fit.model, obs, bstart, slit_item, board_item)
        t["uncertainty_mm"] = float(np.median([u["median_mm"] for u in sigma])) if sigma else 0.0
        t["matters_mm"] = AXIS_MISFIT * t["uncertainty_mm"]
        t["added"] = t["significant"] and t["change"] > t["matters_mm"]
        tests["free planes"] = t
        if t["added"]:
            fit, kind = _refit(fit, big, obs), "free"
    res, model, par, blocks = fit
    g = res.geometry
    planes = np.full((k, 4), np.nan)
    planes[sv] = g["slit_planes"]
    boards = np.full((len(board_planes), 4), np.nan)
    if "board_planes" in g:
        boards[bv] = g["board_planes"]
    if isinstance(par, AxisParams):
        axis_line = par.axis(res.values["axis"][0])
    else:
        a, u = common_line(g["slit_planes"])
        axis_line = (a - (a @ u) * u, u)
    rms_mm, counts = _slit_rms(res, blocks, slit_item)
    return CaptureBundle(
        result=res,
        model=model,
        kind=kind,
        camera=res.camera,
        slit_planes=planes,
        slit_rms_mm=rms_mm,
        slit_counts=counts,
        slit_item=slit_item,
        slit_sources=_slit_sources(res, blocks, slit_item),
        axis=axis_line,
        board_planes=boards,
        tests=tests,
        uncertainty=_uncertainty(res, model, obs, boards, slit_item, board_item),
        problems=_culprit(fit, obs) or _problems(res),
    )


def _stripe_points(camera: PinholeCamera, uv: F64, surfaces: F64) -> F64:
    """3D points (N, 3) mm where the lines of sight of ``uv`` (N, 2) meet ``surfaces`` (N, 4)."""
    o, d = camera.rays(uv)
    X, _ = intersect_rays_planes(o, d, surfaces)
    return X


def _slit_rms(
    res: BundleResult, blocks: Sequence[ObservationBlock], slit_item: NDArray[np.intp]
) -> tuple[F64, NDArray[np.int_]]:
    """Per slit (K,), the RMS distance (mm) of its kept observations' 3D points to its plane
    (stripe centres put on their surfaces by the fitted camera, hand readings), and their
    count."""
    k = len(slit_item)
    item_slit = np.flatnonzero(slit_item >= 0)
    ssq, cnt = np.zeros(k), np.zeros(k, int)
    g = res.geometry
    for ob, st in zip(blocks, res.stats, strict=True):
        if ob.points is None or ob.slit is None:
            continue
        keep = st.kept & np.isfinite(st.residuals)
        pl = g["slit_planes"][ob.slit[keep]]
        d = np.einsum("ij,ij->i", ob.points(g)[keep], pl[:, :3]) + pl[:, 3]
        sl = item_slit[ob.slit[keep]]
        ok = np.isfinite(d)
        ssq += np.bincount(sl[ok], d[ok] ** 2, minlength=k)
        cnt += np.bincount(sl[ok], minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(cnt > 0, np.sqrt(ssq / np.maximum(cnt, 1)), np.nan)
    return rms, cnt


def _slit_sources(
    res: BundleResult, blocks: Sequence[ObservationBlock], slit_item: NDArray[np.intp]
) -> dict[str, NDArray[np.int_]]:
    """Per observation source, the kept observations of each slit (K,)."""
    item_slit = np.flatnonzero(slit_item >= 0)
    out = {}
    for ob, st in zip(blocks, res.stats, strict=True):
        if ob.slit is not None:
            sl = item_slit[ob.slit[st.kept]]
            out[ob.source] = np.bincount(sl, minlength=len(slit_item))
    return out


def _uncertainty(
    res: BundleResult,
    model: Model,
    obs: CaptureObservations,
    boards: F64,
    slit_item: NDArray[np.intp],
    board_item: NDArray[np.intp],
    per_board: int = 400,
) -> tuple[dict[str, Any], ...]:
    """Predicted 1-sigma 3D error of points triangulated on each reference board (the measuring
    volume's near to far end), from the parameters' covariance."""
    out = []
    centre = res.camera.centre
    for b, (uv, s) in enumerate(zip(obs.board_uv, obs.board_slit, strict=True)):
        if board_item[b] < 0 or not len(s):
            continue
        ok = np.flatnonzero(slit_item[s] >= 0)
        if not len(ok):
            continue
        ok = ok[np.linspace(0, len(ok) - 1, min(per_board, len(ok))).round().astype(int)]
        sig = point_uncertainty(res, model, uv[ok], slit_item[s[ok]])
        X = _stripe_points(res.camera, uv[ok], np.broadcast_to(boards[b], (len(ok), 4)))
        dist = float(np.nanmedian(np.linalg.norm(X - centre, axis=1)))
        good = np.isfinite(sig)
        out.append(
            {
                "board": obs.names[3 + b],
                "distance_mm": dist,
                "points": int(good.sum()),
                "median_mm": float(np.median(sig[good])) if good.any() else float("nan"),
                "p95_mm": float(np.percentile(sig[good], 95)) if good.any() else float("nan"),
            }
        )
    return tuple(out)


def bundle_report(b: CaptureBundle, slit_numbers: Sequence[int]) -> dict[str, Any]:
    """The bundle's figures for the calibration report (plain JSON values).

    Parameters
    ----------
    b : the bundle
    slit_numbers : the slit number of each slit item (the fitted slits, in order)
    """
    res = b.result
    cam = res.geometry["camera"]
    camera = {}
    for i, name in enumerate(CAMERA_PARAMS):
        label = f"camera.{name}"
        if label in res.labels:
            camera[name] = [float(cam[i]), res.std_error(label)]
    slits = {}
    for lab, v, se in zip(res.labels, res.x, res.std_errors, strict=True):
        if lab.startswith("slits["):
            item, what = lab[len("slits[") :].split("].")
            slits.setdefault(str(slit_numbers[int(item)]), {})[what] = [float(v), float(se)]
        elif lab.startswith(("axis.", "boards[")):
            slits.setdefault(lab.split(".")[0], {})[lab.split(".")[1]] = [float(v), float(se)]
    return {
        "slit_model": b.kind,
        "parameters": len(res.x),
        "converged": res.converged,
        "message": res.message,
        "rounds": res.rounds,
        "tests": b.tests,
        "sources": res.per_source(),
        "images": res.per_image(),
        "camera": camera,
        "other_parameters": slits,
        "uncertainty": list(b.uncertainty),
    }


def _culprit(fit: _Fit, obs: CaptureObservations, most: int = 4) -> tuple[str, ...]:
    """When the fit has problems: the one stripe image without which the others fit.

    One image that does not belong (a reference board numbered one slit off, an image of
    another set-up) pulls the fit, and the images it pulls look wrong too. Each stripe image
    found wrong (at most ``most``, worst first) is left out in turn and the rest refitted
    (same noise model); if the rest then fit, that image is the one to retake. Returns its
    findings, or () if there are no problems or no single image explains them.
    """
    problems = _problems(fit.result)
    if not problems:
        return ()
    res = fit.result
    stripe_images = {int(i) for st in res.stats if st.run is not None for i in np.unique(st.image)}
    names = [n for n in res.images if n in "".join(p.split(":")[0] for p in problems)]
    tried = [res.images.index(n) for n in names if res.images.index(n) in stripe_images]
    for i in tried[:most]:
        noise = res.noise
        kept = tuple(k & (st.image != i) for k, st in zip(noise.kept, res.stats, strict=True))
        try:
            out = adjust(
                fit.model, fit.blocks, res.images, obs.image_size,
                noise=Noise(kept, noise.sigma, noise.inflation),
            )  # fmt: skip
        except CalibrationError:
            continue
        if not _problems(out, ignore=i):
            return (
                f"{res.images[i]} does not fit the other images (without it they fit; with it: "
                + "; ".join(p for p in problems if p.startswith(res.images[i]))
                + f"); retake {res.images[i]}",
            )
    return problems


def _problems(res: BundleResult, ignore: int = -1) -> tuple[str, ...]:
    """Why the fit cannot be trusted, naming the images to retake, worst first (empty: it can).

    An image is named when its markers lie further than :data:`MAX_MARKER_RMS_PX` from the
    camera, its stripes lie off the fit as whole stripes (:meth:`BlockStats.run_offsets`) by
    more than :data:`RUN_OFFSET_FACTOR` times their scatter along the stripes (and
    :data:`MIN_MISFIT_PX`), its residuals are :data:`MAX_RMS_FACTOR` times the other images'
    of the same source, or more than :data:`MAX_OUTLIER_SHARE` of its observations are
    outliers. Each finding is scored by how far it is beyond its limit.
    """
    found: list[tuple[float, str]] = []
    per = res.per_image()
    if not res.converged:
        worst = sorted(
            per, key=lambda n: -max((v["rms"] for v in per[n].values() if v["unit"] == "px"),
                                    default=0.0),
        )[:2]  # fmt: skip
        found.append(
            (np.inf, f"the adjustment did not converge ({res.message}); retake {', '.join(worst)}")
        )
    for st in res.stats:
        imgs = np.unique(st.image)
        rms = {int(i): st.rms(st.image == i) for i in imgs}
        finite = [v for v in rms.values() if math.isfinite(v)]
        typical = float(np.median(finite)) if finite else float("nan")
        for i in imgs:
            if i == ignore:
                continue
            m = st.image == i
            share = 1.0 - float(np.mean(st.kept[m]))
            name, r = res.images[int(i)], rms[int(i)]
            off, scatter = st.run_offsets(m)
            if st.source == "markers" and r > MAX_MARKER_RMS_PX:
                found.append((
                    r / MAX_MARKER_RMS_PX,
                    f"{name}: the markers lie {r:.2f} px (RMS) from the fitted camera (> "
                    f"{MAX_MARKER_RMS_PX} px); retake {name} (did the target or the camera move?)",
                ))  # fmt: skip
            elif off > max(RUN_OFFSET_FACTOR * scatter, MIN_MISFIT_PX):
                moved = (
                    " (did the target move after the markers image? retake both)"
                    if st.source == "target stripes"
                    else ""
                )
                found.append((
                    off / scatter / RUN_OFFSET_FACTOR,
                    f"{name}: its {st.source} lie {off:.3f} {st.unit} (RMS) off the fit as whole "
                    f"stripes, {off / scatter:.1f} times their scatter along the stripes; retake "
                    f"{name}{moved}",
                ))  # fmt: skip
            elif len(imgs) > 1 and r > MAX_RMS_FACTOR * typical:
                found.append((
                    r / typical / MAX_RMS_FACTOR,
                    f"{name}: its {st.source} lie {r:.3f} {st.unit} (RMS) from the fit, "
                    f"{r / typical:.1f} times the other images'; retake {name}",
                ))  # fmt: skip
            elif share > MAX_OUTLIER_SHARE:
                found.append((
                    share / MAX_OUTLIER_SHARE,
                    f"{name}: {share:.0%} of its {st.source} do not fit the others; retake {name}",
                ))  # fmt: skip
    found.sort(key=lambda x: -x[0])
    return tuple(msg for _, msg in found)


__all__ = [
    "CAMERA_PARAMS",
    "CaptureBundle",
    "CaptureObservations",
    "adjust_capture",
    "bundle_report",
    "bin_lines",
    "REGIONS",
    "AxisParams",
    "BlockStats",
    "BundleResult",
    "Layout",
    "Model",
    "ObservationBlock",
    "ParamBlock",
    "PlaneParams",
    "adjust",
    "axis_planes_model",
    "camera_model",
    "camera_vector",
    "free_planes_model",
    "image_regions",
    "line_residuals",
    "marker_block",
    "param_block",
    "plane_lines",
    "point_uncertainty",
    "project",
    "reading_block",
    "stripe_block",
    "vector_camera",
]
