"""Scene geometry for the simulator: textures and primitives with vectorised ray casting.

World frame = target frame (mm): X right, Y up, Z towards the rig. The default rig sits at
Z = 1000 and looks towards -Z, so an object at Z = 0 is about 1 m away.
Every primitive answers, for N rays at once, the distance ``t`` to its first hit (``inf`` for a
miss), and at hit points its unit normal and albedo.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from multislit.errors import MultislitError

F64 = NDArray[np.float64]
Texture = Callable[[F64, F64], F64]  # local (a, b) mm -> albedo (N,)

_EPS = 1e-6


def constant(albedo: float) -> Texture:
    """A uniform albedo."""
    return lambda a, b: np.full(a.shape, float(albedo))


def checker_markers(
    centres: F64, size: float, base: float = 0.75, dark: float = 0.04, light: float = 0.92
) -> Texture:
    """Albedo of a face carrying 2x2 checker markers.

    Parameters
    ----------
    centres : (M, 2) float, mm, face-local (a, b) of each marker's centre corner
    size : float, mm, side of the whole 2x2 marker
    """
    c = np.asarray(centres, float).reshape(-1, 2)
    h = size / 2

    def tex(a: F64, b: F64) -> F64:
        out = np.full(a.shape, base)
        for ca, cb in c:
            da, db = a - ca, b - cb
            inside = (np.abs(da) < h) & (np.abs(db) < h)
            dark_q = (da * db) > 0
            out = np.where(inside, np.where(dark_q, dark, light), out)
        return out

    return tex


def noise_texture(
    rng: np.random.Generator, scale_mm: float, lo: float, hi: float, n: int = 96
) -> Texture:
    """A smooth random albedo (printed texture), periodic over ``n * scale_mm`` mm."""
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(rng.random((n, n)), 1.2, mode="wrap")
    g = (g - g.min()) / max(float(g.max() - g.min()), 1e-9)

    def tex(a: F64, b: F64) -> F64:
        x = (a / scale_mm) % n
        y = (b / scale_mm) % n
        x0 = np.floor(x).astype(int)
        y0 = np.floor(y).astype(int)
        fx, fy = x - x0, y - y0
        x1, y1 = (x0 + 1) % n, (y0 + 1) % n
        v = (
            g[y0, x0] * (1 - fx) * (1 - fy)
            + g[y0, x1] * fx * (1 - fy)
            + g[y1, x0] * (1 - fx) * fy
            + g[y1, x1] * fx * fy
        )
        return lo + (hi - lo) * v

    return tex


def albedo_steps(width_mm: float, values: Sequence[float]) -> Texture:
    """Vertical bands of different albedo (paint changes), ``width_mm`` wide each."""
    vals = np.asarray(values, float)

    def tex(a: F64, b: F64) -> F64:
        return vals[np.floor(a / width_mm).astype(int) % len(vals)]

    return tex


# --------------------------------------------------------------------------- primitives
class Primitive:
    """Base class. Subclasses implement ``intersect``, ``normal`` and ``albedo``."""

    name: str = "primitive"

    def intersect(self, o: F64, d: F64) -> F64:
        raise NotImplementedError

    def normal(self, x: F64) -> F64:
        raise NotImplementedError

    def albedo(self, x: F64) -> F64:
        raise NotImplementedError


def _frame(normal: Sequence[float], up_hint: Sequence[float] = (0, 1, 0)) -> tuple[F64, F64, F64]:
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    up = np.asarray(up_hint, float)
    if abs(n @ up) > 0.99:
        up = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(up, n)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return e1, e2, n


@dataclass(eq=False)
class Polygon(Primitive):
    """A flat convex polygon (or an unbounded plane) with optional circular holes.

    Parameters
    ----------
    origin : (3,) mm, a point of the plane, origin of the face-local (a, b) coordinates
    normal : (3,) the side that faces the viewer
    outline : (K, 2) mm, convex polygon in local (a, b), any orientation; None = unbounded
    holes : (H, 3) mm, local (a, b, radius) of circular through-holes
    texture : local (a, b) -> albedo
    up : (3,) a direction that fixes the local b axis (projected into the plane)
    """

    origin: Sequence[float]
    normal_vec: Sequence[float]
    outline: F64 | None = None
    holes: F64 | None = None
    texture: Texture = field(default_factory=lambda: constant(0.8))
    up: Sequence[float] = (0.0, 1.0, 0.0)
    name: str = "polygon"

    def __post_init__(self) -> None:
        self.p0 = np.asarray(self.origin, float)
        self.e1, self.e2, self.n = _frame(self.normal_vec, self.up)
        if self.outline is not None:
            ol = np.asarray(self.outline, float)
            # orient counter-clockwise in (a, b)
            area = np.sum(ol[:, 0] * np.roll(ol[:, 1], -1) - np.roll(ol[:, 0], -1) * ol[:, 1])
            self._ol = ol if area > 0 else ol[::-1]
        else:
            self._ol = None
        self._holes = None if self.holes is None else np.asarray(self.holes, float).reshape(-1, 3)

    @property
    def plane(self) -> F64:
        """(4,) unit normal n and d with n.X + d = 0."""
        return np.append(self.n, -self.n @ self.p0)

    def local(self, x: F64) -> tuple[F64, F64]:
        r = x - self.p0
        return r @ self.e1, r @ self.e2

    def to_world(self, a: F64, b: F64) -> F64:
        return self.p0 + np.multiply.outer(a, self.e1) + np.multiply.outer(b, self.e2)

    def polygon_world(self) -> F64:
        if self._ol is None:
            raise MultislitError(f"{self.name} is unbounded")
        return self.to_world(self._ol[:, 0], self._ol[:, 1])

    def contains(self, a: F64, b: F64) -> NDArray[np.bool_]:
        ok = np.ones(a.shape, bool)
        if self._ol is not None:
            p, q = self._ol, np.roll(self._ol, -1, axis=0)
            ea, eb = (q - p)[:, 0], (q - p)[:, 1]
            cross = ea[None, :] * (b[:, None] - p[None, :, 1]) - eb[None, :] * (
                a[:, None] - p[None, :, 0]
            )
            ok &= np.all(cross >= 0, axis=1)
        if self._holes is not None:
            for ha, hb, hr in self._holes:
                ok &= (a - ha) ** 2 + (b - hb) ** 2 > hr * hr
        return ok

    def intersect(self, o: F64, d: F64) -> F64:
        denom = d @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.p0 - o) @ self.n) / denom
        t = np.where((np.abs(denom) > 1e-12) & (t > _EPS), t, np.inf)
        fin = np.isfinite(t)
        if np.any(fin):
            x = o[fin] + t[fin, None] * d[fin]
            a, b = self.local(x)
            keep = self.contains(a, b)
            idx = np.flatnonzero(fin)
            t[idx[~keep]] = np.inf
        return t

    def normal(self, x: F64) -> F64:
        return np.broadcast_to(self.n, x.shape).copy()

    def albedo(self, x: F64) -> F64:
        a, b = self.local(x)
        return self.texture(a, b)


@dataclass(eq=False)
class Sphere(Primitive):
    """A sphere: ``centre`` (3,) mm, world; ``radius`` mm; a uniform albedo."""

    centre: Sequence[float]
    radius: float
    texture_albedo: float = 0.8
    name: str = "sphere"

    def __post_init__(self) -> None:
        self.c = np.asarray(self.centre, float)

    def intersect(self, o: F64, d: F64) -> F64:
        oc = o - self.c
        b = np.einsum("ij,ij->i", oc, d)
        cc = np.einsum("ij,ij->i", oc, oc) - self.radius**2
        disc = b * b - cc
        sq = np.sqrt(np.maximum(disc, 0))
        t1 = -b - sq
        t2 = -b + sq
        t = np.where(t1 > _EPS, t1, np.where(t2 > _EPS, t2, np.inf))
        return np.where(disc >= 0, t, np.inf)

    def normal(self, x: F64) -> F64:
        return (x - self.c) / self.radius

    def albedo(self, x: F64) -> F64:
        return np.full(len(x), self.texture_albedo)


@dataclass(eq=False)
class Box(Primitive):
    """An oriented box: ``axes`` rows are its local x, y, z axes in the world."""

    centre: Sequence[float]
    half: Sequence[float]
    axes: F64 = field(default_factory=lambda: np.eye(3))
    texture_albedo: float = 0.7
    name: str = "box"

    def __post_init__(self) -> None:
        self.c = np.asarray(self.centre, float)
        self.h = np.asarray(self.half, float)
        self.A = np.asarray(self.axes, float)

    def intersect(self, o: F64, d: F64) -> F64:
        ol = (o - self.c) @ self.A.T
        dl = d @ self.A.T
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dl
            t1 = (-self.h - ol) * inv
            t2 = (self.h - ol) * inv
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        t = np.where(tmin > _EPS, tmin, tmax)
        return np.where((tmax >= tmin) & (t > _EPS), t, np.inf)

    def normal(self, x: F64) -> F64:
        xl = (x - self.c) @ self.A.T
        r = np.abs(xl) / self.h
        k = np.argmax(r, axis=1)
        nl = np.zeros_like(xl)
        nl[np.arange(len(x)), k] = np.sign(xl[np.arange(len(x)), k])
        return nl @ self.A

    def albedo(self, x: F64) -> F64:
        return np.full(len(x), self.texture_albedo)


@dataclass(eq=False)
class Cylinder(Primitive):
    """A closed circular cylinder (side and both end caps): rods, posts, stems.

    Parameters
    ----------
    base : (3,) mm, world: the centre of one end cap
    axis : (3,) direction from ``base`` to the other end cap (normalised here)
    length : mm, distance between the end caps
    radius : mm
    texture_albedo : albedo of the whole surface
    """

    base: Sequence[float]
    axis: Sequence[float]
    length: float
    radius: float
    texture_albedo: float = 0.7
    name: str = "cylinder"

    def __post_init__(self) -> None:
        self.p0 = np.asarray(self.base, float)
        a = np.asarray(self.axis, float)
        self.a = a / np.linalg.norm(a)

    def intersect(self, o: F64, d: F64) -> F64:
        oc = o - self.p0
        oa, da = oc @ self.a, d @ self.a
        op = oc - oa[:, None] * self.a  # components across the axis
        dp = d - da[:, None] * self.a
        qa = np.einsum("ij,ij->i", dp, dp)
        qb = np.einsum("ij,ij->i", op, dp)
        qc = np.einsum("ij,ij->i", op, op) - self.radius**2
        disc = qb * qb - qa * qc
        sq = np.sqrt(np.maximum(disc, 0))
        t = np.full(len(o), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for ts in ((-qb - sq) / qa, (-qb + sq) / qa):
                z = oa + ts * da
                ok = (disc >= 0) & (qa > 1e-12) & (ts > _EPS) & (z >= 0) & (z <= self.length)
                t = np.where(ok & (ts < t), ts, t)
            for zc in (0.0, self.length):
                tc = (zc - oa) / da
                r2 = np.einsum("ij,ij->i", op + tc[:, None] * dp, op + tc[:, None] * dp)
                ok = (np.abs(da) > 1e-12) & (tc > _EPS) & (r2 <= self.radius**2)
                t = np.where(ok & (tc < t), tc, t)
        return t

    def normal(self, x: F64) -> F64:
        r = x - self.p0
        z = r @ self.a
        radial = r - z[:, None] * self.a
        rn = np.linalg.norm(radial, axis=1)
        n = radial / np.maximum(rn, 1e-12)[:, None]
        # a point on a cap: nearer the cap's plane than the side's surface
        cap_lo = np.abs(z) < np.abs(rn - self.radius)
        cap_hi = np.abs(z - self.length) < np.abs(rn - self.radius)
        n[cap_lo] = -self.a
        n[cap_hi] = self.a
        return n

    def albedo(self, x: F64) -> F64:
        return np.full(len(x), self.texture_albedo)


@dataclass(eq=False)
class HeightField(Primitive):
    """A free-form surface: height h(a, b) = sum of Gaussian bumps above a base plane.

    The surface is ``origin + a e1 + b e2 + h(a, b) n`` over |a| <= half_a, |b| <= half_b.
    ``bumps`` rows are (a0, b0, sigma_a, sigma_b, height) in mm.
    """

    origin: Sequence[float]
    normal_vec: Sequence[float]
    bumps: F64
    half_a: float
    half_b: float
    texture_albedo: float = 0.75
    steps: int = 40
    name: str = "freeform"

    def __post_init__(self) -> None:
        self.p0 = np.asarray(self.origin, float)
        self.e1, self.e2, self.n = _frame(self.normal_vec)
        self.B = np.asarray(self.bumps, float).reshape(-1, 5)
        # a height grid for the coarse march (the bisection refines on the analytic surface)
        self._res = 1.0
        ga = np.arange(-self.half_a, self.half_a + self._res, self._res)
        gb = np.arange(-self.half_b, self.half_b + self._res, self._res)
        A, Bm = np.meshgrid(ga, gb)
        self._grid = self.height(A, Bm).astype(np.float32)
        self.hmax = float(self._grid.max()) + 2.0

    def height(self, a: F64, b: F64) -> F64:
        h = np.zeros(np.shape(a))
        for a0, b0, sa, sb, amp in self.B:
            h += amp * np.exp(-0.5 * (((a - a0) / sa) ** 2 + ((b - b0) / sb) ** 2))
        return h

    def _height_lookup(self, a: F64, b: F64) -> F64:
        """Bilinear height from the grid; -1e6 outside the support (no surface there)."""
        import cv2

        shape = a.shape
        mx = ((a + self.half_a) / self._res).astype(np.float32).ravel()
        my = ((b + self.half_b) / self._res).astype(np.float32).ravel()
        n = mx.size
        cols = 4096
        rows = -(-n // cols)
        pad = rows * cols - n
        mx = np.pad(mx, (0, pad)).reshape(rows, cols)
        my = np.pad(my, (0, pad)).reshape(rows, cols)
        out = np.empty((rows, cols), np.float32)
        for r0 in range(0, rows, 8000):  # remap maps must stay below 32767 rows
            out[r0 : r0 + 8000] = cv2.remap(
                self._grid,
                mx[r0 : r0 + 8000],
                my[r0 : r0 + 8000],
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=-1e6,
            )
        return out.ravel()[:n].reshape(shape)

    def _grad(self, a: F64, b: F64) -> tuple[F64, F64]:
        ga = np.zeros(np.shape(a))
        gb = np.zeros(np.shape(a))
        for a0, b0, sa, sb, amp in self.B:
            e = amp * np.exp(-0.5 * (((a - a0) / sa) ** 2 + ((b - b0) / sb) ** 2))
            ga -= e * (a - a0) / sa**2
            gb -= e * (b - b0) / sb**2
        return ga, gb

    def intersect(self, o: F64, d: F64) -> F64:
        t_out = np.full(len(o), np.inf)
        ol = o - self.p0
        oa, ob, oz = ol @ self.e1, ol @ self.e2, ol @ self.n
        da, db, dz = d @ self.e1, d @ self.e2, d @ self.n
        with np.errstate(divide="ignore", invalid="ignore"):
            t_top = (self.hmax - oz) / dz
            t_bot = (0.0 - oz) / dz
        cand = (dz < -1e-9) & (t_bot > _EPS)
        # only rays that cross the support's bounding slab |a| <= half_a, |b| <= half_b
        for oc, dc, half in ((oa, da, self.half_a), (ob, db, self.half_b)):
            c_top, c_bot = oc + t_top * dc, oc + t_bot * dc
            cand &= ~(((c_top > half) & (c_bot > half)) | ((c_top < -half) & (c_bot < -half)))
        idx = np.flatnonzero(cand)
        if idx.size == 0:
            return t_out
        t0 = np.maximum(t_top[idx], _EPS)
        t1 = t_bot[idx]
        ts = t0[:, None] + (t1 - t0)[:, None] * np.linspace(0, 1, self.steps)[None, :]
        a = oa[idx, None] + ts * da[idx, None]
        b = ob[idx, None] + ts * db[idx, None]
        z = oz[idx, None] + ts * dz[idx, None]
        below = z <= self._height_lookup(a, b)
        has = below.any(axis=1)
        first = np.argmax(below, axis=1)
        ok = has & (first > 0)
        rows = np.flatnonzero(ok)
        lo = ts[rows, first[rows] - 1]
        hi = ts[rows, first[rows]]
        ii = idx[rows]
        for _ in range(22):
            mid = 0.5 * (lo + hi)
            am, bm, zm = oa[ii] + mid * da[ii], ob[ii] + mid * db[ii], oz[ii] + mid * dz[ii]
            inside = (np.abs(am) <= self.half_a) & (np.abs(bm) <= self.half_b)
            below_m = (zm <= self.height(am, bm)) & inside
            hi = np.where(below_m, mid, hi)
            lo = np.where(below_m, lo, mid)
        t_out[ii] = 0.5 * (lo + hi)
        return t_out

    def normal(self, x: F64) -> F64:
        r = x - self.p0
        a, b = r @ self.e1, r @ self.e2
        ga, gb = self._grad(a, b)
        nl = -ga[:, None] * self.e1 - gb[:, None] * self.e2 + self.n
        return nl / np.linalg.norm(nl, axis=1, keepdims=True)

    def albedo(self, x: F64) -> F64:
        return np.full(len(x), self.texture_albedo)


@dataclass
class Hit:
    """Result of casting N rays into a scene."""

    t: F64  # (N,) mm, inf = miss
    obj: NDArray[np.int32]  # (N,) primitive index, -1 = miss
    point: F64  # (N, 3) mm (NaN on miss)
    normal: F64  # (N, 3) unit, facing the ray's origin
    albedo: F64  # (N,)


@dataclass(eq=False)
class Scene:
    """A list of primitives plus metadata (ground truth for measurements).

    Parameters
    ----------
    name : the scene's name (the scan image is named after it)
    primitives : what the rays can hit
    info : ground truth for measurements (planes, spheres, holes), JSON-serialisable
    backdrop : names of the primitives that are the background (walls, boards behind the
        objects); every other primitive is an object. Default: none.
    """

    name: str
    primitives: list[Primitive]
    info: dict = field(default_factory=dict)
    backdrop: tuple[str, ...] = ()

    @property
    def names(self) -> list[str]:
        """The primitives' names, in order (index = ``Hit.obj``)."""
        return [p.name for p in self.primitives]

    def is_object(self, obj: NDArray[np.integer]) -> NDArray[np.bool_]:
        """True where primitive index ``obj`` (any shape, -1 = nothing) is an object, not backdrop."""
        flags = np.array([p.name not in self.backdrop for p in self.primitives] + [False])
        idx = np.asarray(obj)
        return flags[np.where(idx >= 0, idx, len(self.primitives))]

    def first_hit_t(self, o: F64, d: F64) -> tuple[F64, NDArray[np.int32]]:
        t = np.full(len(o), np.inf)
        obj = np.full(len(o), -1, np.int32)
        for i, p in enumerate(self.primitives):
            ti = p.intersect(o, d)
            closer = ti < t
            t = np.where(closer, ti, t)
            obj[closer] = i
        return t, obj

    def cast(self, o: F64, d: F64) -> Hit:
        t, obj = self.first_hit_t(o, d)
        x = o + np.where(np.isfinite(t), t, np.nan)[:, None] * d
        n = np.full_like(x, np.nan)
        alb = np.zeros(len(o))
        for i, p in enumerate(self.primitives):
            m = obj == i
            if np.any(m):
                n[m] = p.normal(x[m])
                alb[m] = p.albedo(x[m])
        flip = np.einsum("ij,ij->i", n, d) > 0
        n[flip] *= -1
        return Hit(t, obj, x, n, alb)
