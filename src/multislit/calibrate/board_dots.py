"""The dots of one reference board, each centred with its neighbours fitted beside it.

A reference board is a plain flat board: its image holds the stripes, the dots and noise.
:func:`board_view` reads one reference image as the identification reads a frame: the
extraction's stripes, the dots' response (:func:`~multislit.stripes.dots.dot_response`, in noise
sigmas per zone and level) and, for the stripes' direction, one smooth field over the image (on
a flat board the stripes are straight lines whose direction changes slowly across the image; a
direction taken from the nearest stripe point jumps between neighbouring stripes, and the
response on a stripe's flank jumps with it).

The board's dots (:func:`board_catalogue`) are found and centred on its sharp response
(:func:`~multislit.stripes.dots.sharp_response`, its noise measured over the whole board): the
image smoothed by a Gaussian of half a pixel, less its mean a little before and after along the
stripes, less its median at its zone (near a stripe or not) and level. On it a dot is a round
spot (a Gaussian, its sigma fitted on the board's bright dots with no other dot near: the
references' dot size is measured on the dots' cores), with two negative copies of half its
height before and after it along the stripe (the mean it is compared with). Every dot is fitted
as that spot, with its own centre and height, beside the spots of all the other dots, and the
places where the response less every fitted spot still shows a dot clearly get one more spot
(:func:`~multislit.stripes.dots.fit_dot_spots`: a scan centres the dots it identified with the
same fit). Each dot's standard errors follow from its fit and the response's noise.
:func:`fit_rays_on_boards` fits rays the same way, each on all boards at once.

Units: px, (u, v) = (column, row), (0, 0) the centre of the top-left pixel; intensity units of
the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from multislit.geometry.camera import F64
from multislit.stripes import SlitExtraction, extract_slits
from multislit.stripes.dots import (
    SPOT_FIT_HALF,
    SPOT_KEEP_Z,
    STRIPE_CLEARANCE,
    DotResponse,
    SharpResponse,
    add_spot,
    dot_response,
    fit_dot_spots,
    near_stripes,
    sharp_image,
    sharp_response,
    splat_spots,
    spot_at,
    stripe_spacing,
)
from multislit.stripes.separation import saturation_level_of
from multislit.stripes.sizes import FWHM_PER_SIGMA

#: Degree of the polynomial in (u, v) of the stripes' direction over a board, fitted to at
#: most this many of the stripes' points.
_ANGLE_DEGREE = 3
_ANGLE_POINTS = 20000
#: Places of a board taken at random to measure the spread of a spot's height fitted there.
_Z_PLACES = 20000
#: The rays' fit takes this share of each step, of the rays' angles at most _MAX_RAY_STEP
#: pixels' angle.
_RAY_DAMPING = 0.8
_MAX_RAY_STEP = 0.5


@dataclass(frozen=True, eq=False)
class BoardView:
    """One reference image read for its dots.

    Attributes
    ----------
    extraction : SlitExtraction, the stripes found in the image
    response : DotResponse, the dots' response (the identification's: smoothed by the dot's
        Gaussian, in noise sigmas of its zone and level)
    sharp : (H, W) float32, the image smoothed by a Gaussian of half a pixel (NaN near
        saturated pixels)
    angle : (H, W) float32, rad, the stripes' direction from the image's vertical, one smooth
        field over the image
    near : (H, W) bool, the places near a stripe (closer than 0.9 stripe widths to a centre)
    sigma_img : px, the dots' Gaussian sigma in the image (from their FWHM)
    """

    extraction: SlitExtraction
    response: DotResponse
    sharp: NDArray[np.float32]
    angle: NDArray[np.float32]
    near: NDArray[np.bool_]
    sigma_img: float
    _stripes: cKDTree | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the image."""
        return self.near.shape

    def lookup(self, u: F64, v: F64) -> tuple[F64, NDArray[np.bool_]]:
        """The stripes' direction (rad) and whether near a stripe, at (u, v) (M,) px (the
        nearest pixel; clipped to the image)."""
        h, w = self.shape
        r = np.clip(np.rint(np.nan_to_num(v)).astype(np.intp), 0, h - 1)
        c = np.clip(np.rint(np.nan_to_num(u)).astype(np.intp), 0, w - 1)
        return self.angle[r, c].astype(np.float64), self.near[r, c]

    def z(self, u: F64, v: F64) -> F64:
        """(M,) the dots' response at (u, v) px in noise sigmas (NaN outside the image or near
        saturated pixels)."""
        a, near = self.lookup(u, v)
        return self.response.z(u, v, a, near)

    def stripe_peak(self, u: F64, v: F64) -> F64:
        """(M,) the peak of the stripe centre nearest each (u, v) px (NaN: no stripes)."""
        ex = self.extraction
        if len(ex.u) == 0:
            return np.full(len(u), np.nan)
        if self._stripes is None:
            object.__setattr__(self, "_stripes", cKDTree(np.stack([ex.u, ex.v], axis=1)))
        _, i = self._stripes.query(np.stack([u, v], axis=1))
        return ex.peak[i].astype(np.float64)


@dataclass(frozen=True, eq=False)
class BoardDots:
    """The dots fitted on one board (:func:`board_catalogue`).

    Attributes
    ----------
    u, v : (M,) float64, px, the dots' centres
    height : (M,) float64, the fitted spot's height on the sharp response (intensity units)
    z : (M,) float64, the height in its standard errors
    se_px : (M,) float64, px, the centre's standard error (per axis, the larger of the two)
    """

    u: F64
    v: F64
    height: F64
    z: F64
    se_px: F64

    def __len__(self) -> int:
        return len(self.u)

    @property
    def uv(self) -> F64:
        """(M, 2) float64, px."""
        return np.stack([self.u, self.v], axis=1)

    def subset(self, keep: NDArray[np.bool_]) -> BoardDots:
        """The dots where ``keep`` (M,) bool is True."""
        return BoardDots(
            self.u[keep], self.v[keep], self.height[keep], self.z[keep], self.se_px[keep]
        )


def angle_field(ex: SlitExtraction, shape: tuple[int, int]) -> NDArray[np.float32]:
    """(H, W) float32, rad: the stripes' direction over the image, a polynomial of degree 3 in
    (u, v) fitted to the extraction's angles (weighted down where far from the fit, in four
    rounds); 0 (vertical) without linked stripes."""
    h, w = shape
    ok = np.isfinite(ex.angle)
    if ok.sum() < 20:
        return np.zeros(shape, np.float32)
    sx, sy = 2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)

    def basis(u: F64, v: F64) -> F64:
        x, y = u * sx - 1.0, v * sy - 1.0
        d = _ANGLE_DEGREE
        return np.stack([x**i * y**j for i in range(d + 1) for j in range(d + 1 - i)], axis=-1)

    pick = np.flatnonzero(ok)[:: max(1, int(ok.sum()) // _ANGLE_POINTS)]
    b = basis(ex.u[pick], ex.v[pick])
    a = ex.angle[pick]
    wt = np.ones(len(a))
    coef = np.zeros(b.shape[1])
    for _ in range(4):
        coef, *_ = np.linalg.lstsq(b * wt[:, None], a * wt, rcond=None)
        res = a - b @ coef
        s = 1.4826 * float(np.median(np.abs(res))) + 1e-6
        wt = 1.0 / np.maximum(1.0, np.abs(res) / (2.5 * s))
    # the polynomial over the image, one power of y at a time
    x = np.arange(w) * sx - 1.0
    y = np.arange(h) * sy - 1.0
    out = np.zeros(shape)
    d = _ANGLE_DEGREE
    terms = [(i, j) for i in range(d + 1) for j in range(d + 1 - i)]
    for j in range(d + 1):
        row = sum(coef[k] * x**i for k, (i, jj) in enumerate(terms) if jj == j)
        out += np.outer(y**j, row)
    return out.astype(np.float32)


def board_view(image: NDArray, stripe_width_px: float, dot_size_px: float) -> BoardView:
    """Read one reference image for its dots (:class:`BoardView`).

    Parameters
    ----------
    image : (H, W) the reference image (a colour image: its laser plane, as the extraction
        takes it)
    stripe_width_px, dot_size_px : px, the stripes' and the dots' FWHM in the references
    """
    ex = extract_slits(
        image,
        stripe_width_px=stripe_width_px,
        dot_size_px=dot_size_px,
        leaning=False,
        background="median",
    )
    h, w = ex.dots.shape
    clearance = STRIPE_CLEARANCE * ex.stripe_width_px
    near = near_stripes(ex.u, ex.v, (h, w), clearance)
    angle = angle_field(ex, (h, w))
    r = np.clip(np.rint(ex.v).astype(np.intp), 0, h - 1)
    c = np.clip(np.rint(ex.u).astype(np.intp), 0, w - 1)
    a_pts = angle[r, c].astype(np.float64)
    spacing = stripe_spacing(ex.u, ex.v)
    spread = 0.5 * max(spacing if math.isfinite(spacing) else 0.0, 2.0 * clearance)
    sat = saturation_level_of(ex.plane)
    resp = dot_response(ex.plane, ex.dot_size_px, ex.u, ex.v, a_pts, near, spread, sat)
    sharp = sharp_image(ex.plane, sat)
    return BoardView(ex, resp, sharp, angle, near, float(ex.dot_size_px) / FWHM_PER_SIGMA)


def board_catalogue(view: BoardView) -> tuple[BoardDots, SharpResponse]:
    """The dots of one board, each fitted as a spot beside its neighbours
    (:func:`~multislit.stripes.dots.fit_dot_spots`, see the module docstring), and the board's
    sharp response they were fitted to (its :attr:`~SharpResponse.z_scale` measured at places
    of the board taken at random).

    Returns
    -------
    dots : BoardDots, the dots whose height reaches 2 of its standard errors
    sharp : SharpResponse
    """
    sr = sharp_response(view.sharp, view.angle, view.near, view.sigma_img)
    h, w = sr.response.shape
    P, A, se, sr = fit_dot_spots(sr, view.sigma_img)
    rng = np.random.default_rng(0)
    places = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0], (_Z_PLACES, 2))
    zr, _ = sr.spot_fit(places)
    zr = zr[np.isfinite(zr)]
    if zr.size > 100:
        sr = replace(sr, z_scale=max(1.4826 * float(np.median(np.abs(zr - np.median(zr)))), 1e-6))
    zfit = np.where(se[:, 2] > 0, A / np.where(se[:, 2] > 0, se[:, 2], 1.0), 0.0)
    inside = (P[:, 0] >= 0) & (P[:, 0] <= w - 1) & (P[:, 1] >= 0) & (P[:, 1] <= h - 1)
    keep = inside & (zfit >= SPOT_KEEP_Z) & np.isfinite(P).all(axis=1)
    se_px = np.maximum(se[:, 0], se[:, 1])
    return BoardDots(P[keep, 0], P[keep, 1], A[keep], zfit[keep], se_px[keep]), sr


def fit_rays_on_boards(
    boards: list[SharpResponse], uv: F64, jac: F64, A: F64, base: F64
) -> tuple[F64, F64, F64]:
    """One round of the joint fit of rays to the boards: every ray's direction (two angles,
    in pixels' angle) and its spot's height on each board, fitted to all boards at once, each
    board's response less the other rays' spots and the fixed spots ``base``; the rays in turn,
    each seeing the steps of those before it (Gauss-Seidel).

    Parameters
    ----------
    boards : R SharpResponse (one image size)
    uv : (N, R, 2) float64, px, where each ray meets each board (NaN: it does not, or off
        the image)
    jac : (N, R, 2, 2) float64, px per pixel's angle, the derivatives of ``uv`` with respect
        to the ray's two angles
    A : (N, R) float64, the spots' heights (updated in place)
    base : (R, H, W) float64, the spots that are not rays (fixed)

    Returns
    -------
    step : (N, 2) float64, pixels' angle, the step of each ray's two angles (damped and
        clipped: to be taken as it is)
    se : (N, R + 1) float64, the standard errors of the heights on each board and of the
        direction (pixels' angle, the larger axis); 0 where unknown
    chi : (N,) float64, the residuals' sum of squares over the rays' pixels, in noise sigmas
    """
    R = len(boards)
    resp = np.stack([b.response for b in boards])
    valid = np.stack([b.valid for b in boards])
    sig = np.stack([b.sigma for b in boards])
    ang = np.stack([b.angle for b in boards])
    n_p = max(len(b.profile) for b in boards)
    sg = np.zeros((R, n_p))
    for r, b in enumerate(boards):
        sg[r, : len(b.profile)] = b.profile
    reach = np.array([b.reach for b in boards])
    model = base.copy()
    for r in range(R):
        splat_spots(uv[:, r], A[:, r], ang[r], sg[r], reach[r], model[r])
    step = np.zeros((len(uv), 2))
    se = np.zeros((len(uv), R + 1))
    chi = np.zeros(len(uv))
    _ray_step(resp, valid, sig, ang, model, uv, jac, A, sg, reach, SPOT_FIT_HALF, step, se, chi)
    return step, se, chi


@njit(cache=True)
def _ray_step(resp, valid, sig, ang, model, uv, jac, A, prof, reach, half, step, se, chi):
    """The kernel of :func:`fit_rays_on_boards`: per ray, one Gauss-Newton step of its two
    angles and its heights on every board, over the pixels around where it meets each board,
    weighted by their noise; the heights updated in place."""
    nb, h, w = resp.shape
    n = uv.shape[0]
    npar = 2 + nb
    for i in range(n):
        M = np.zeros((npar, npar))
        b = np.zeros(npar)
        npx = 0
        ss = 0.0
        for r in range(nb):
            pu = uv[i, r, 0]
            pv = uv[i, r, 1]
            if not (np.isfinite(pu) and np.isfinite(pv)):
                continue
            cu = int(np.rint(pu))
            cv = int(np.rint(pv))
            if cu < 0 or cu >= w or cv < 0 or cv >= h:
                continue
            a = ang[r, cv, cu]
            tu = math.sin(a)
            tv = math.cos(a)
            ai = A[i, r]
            j00 = jac[i, r, 0, 0]
            j01 = jac[i, r, 0, 1]
            j10 = jac[i, r, 1, 0]
            j11 = jac[i, r, 1, 1]
            for y in range(max(cv - half, 0), min(cv + half + 1, h)):
                for x in range(max(cu - half, 0), min(cu + half + 1, w)):
                    if not valid[r, y, x]:
                        continue
                    k, ku, kv = spot_at(x - pu, y - pv, tu, tv, prof[r], reach[r])
                    wt = 1.0 / (sig[r, y, x] * sig[r, y, x])
                    e = resp[r, y, x] - model[r, y, x]
                    d0 = ai * (ku * j00 + kv * j10)
                    d1 = ai * (ku * j01 + kv * j11)
                    g = (d0, d1, k)
                    idx = (0, 1, 2 + r)
                    for p in range(3):
                        b[idx[p]] += wt * g[p] * e
                        for q in range(3):
                            M[idx[p], idx[q]] += wt * g[p] * g[q]
                    ss += wt * e * e
                    npx += 1
        chi[i] = ss
        if npx < 6:
            continue
        used = np.zeros(npar, np.bool_)
        for p in range(npar):
            used[p] = M[p, p] > 0.0
        if not (used[0] and used[1]):
            continue
        tr = 0.0
        for p in range(npar):
            tr += M[p, p]
        lam = 1e-9 + 1e-4 * tr / npar
        for p in range(npar):
            M[p, p] += lam if used[p] else 1.0
        x_ = np.linalg.solve(M, b)
        cov = np.linalg.inv(M)
        s0 = _RAY_DAMPING * min(max(x_[0], -_MAX_RAY_STEP), _MAX_RAY_STEP)
        s1 = _RAY_DAMPING * min(max(x_[1], -_MAX_RAY_STEP), _MAX_RAY_STEP)
        step[i, 0] = s0
        step[i, 1] = s1
        se[i, nb] = math.sqrt(max(max(cov[0, 0], cov[1, 1]), 0.0))
        for r in range(nb):
            if not used[2 + r]:
                continue
            a_old = A[i, r]
            A[i, r] = max(a_old + _RAY_DAMPING * x_[2 + r], 0.0)
            se[i, r] = math.sqrt(max(cov[2 + r, 2 + r], 0.0))
            # the boards' model follows at once (Gauss-Seidel)
            pu = uv[i, r, 0]
            pv = uv[i, r, 1]
            nu = pu + jac[i, r, 0, 0] * s0 + jac[i, r, 0, 1] * s1
            nv = pv + jac[i, r, 1, 0] * s0 + jac[i, r, 1, 1] * s1
            add_spot(model[r], pu, pv, -a_old, ang[r], prof[r], reach[r])
            add_spot(model[r], nu, nv, A[i, r], ang[r], prof[r], reach[r])
            uv[i, r, 0] = nu
            uv[i, r, 1] = nv


@dataclass(frozen=True, eq=False)
class Board:
    """One reference board read for its dots: the image's view, its fitted dots and its sharp
    response (:func:`read_board`)."""

    view: BoardView
    dots: BoardDots
    sharp: SharpResponse


def read_board(image: NDArray, stripe_width_px: float, dot_size_px: float) -> Board:
    """One reference image read for its dots (:func:`board_view`) and its dots fitted
    (:func:`board_catalogue`)."""
    view = board_view(image, stripe_width_px, dot_size_px)
    dots, sharp = board_catalogue(view)
    return Board(view, dots, sharp)
