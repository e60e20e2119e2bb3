"""The dots of one reference board, each centred with its neighbours fitted beside it.

A reference board is a plain flat board: its image holds the stripes, the dots and noise.
:func:`board_view` reads one reference image as the identification reads a frame: the
extraction's stripes, the dots' response (:func:`~multislit.stripes.dots.dot_response`, in noise
sigmas per zone and level) and, for the stripes' direction, one smooth field over the image (on
a flat board the stripes are straight lines whose direction changes slowly across the image; a
direction taken from the nearest stripe point jumps between neighbouring stripes, and the
response on a stripe's flank jumps with it).

The board's dots (:func:`board_catalogue`) are found and centred on a sharp response: the image
smoothed by a Gaussian of half a pixel, less its mean a little before and after along the
stripes, less its median at its zone (near a stripe or not) and level, with its noise measured
per zone and level over the image. On it a dot is a round spot (a Gaussian, its sigma fitted on
the board's bright dots with no other dot near: the references' dot size is measured on the
dots' cores), with two negative copies of half its height before and after it along the stripe
(the mean it is compared with). Dots closer than about three pixels blend into one peak in the
smoothed response, and a peak-based centre then lies between them; here every dot is fitted as
that spot, with its own centre and height, to the response less the spots of all the other
dots (a few rounds, all dots at once: Jacobi iterations of one joint least-squares fit), and
the places where the response less every fitted spot still shows a dot clearly get one more
spot. Each dot's standard errors follow from its fit and the response's noise.
:func:`fit_rays_on_boards` fits rays the same way, each on all boards at once.

Units: px, (u, v) = (column, row), (0, 0) the centre of the top-left pixel; intensity units of
the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from multislit.geometry.camera import F64
from multislit.stripes import SlitExtraction, extract_slits
from multislit.stripes.dots import STRIPE_CLEARANCE, DotResponse, dot_response, stripe_maps
from multislit.stripes.separation import saturation_level_of
from multislit.stripes.sizes import FWHM_PER_SIGMA

#: The sharp response smooths the image by a Gaussian of this sigma (px): the least that keeps
#: its noise from being one pixel's.
_SHARP_SIGMA = 0.5
#: Degree of the polynomial in (u, v) of the stripes' direction over a board, fitted to at
#: most this many of the stripes' points.
_ANGLE_DEGREE = 3
_ANGLE_POINTS = 20000
#: A place is a dot's first guess when the sharp response there is a local maximum of at
#: least this many noise sigmas ...
_DETECT_Z = 3.0
#: ... and a place where the response less every fitted spot still is, at least this far from
#: every fitted dot (px), gets one more spot.
_ADD_Z = 3.0
_ADD_CLEAR_SIGMAS = 1.0
#: The sharp response compares a place with the mean this many dot sigmas (plus one px)
#: before and after it along the stripes: clear of the dot's own light.
_REACH_SIGMAS = 2.5
#: Level bins of the sharp response's noise table, per zone; a bin's noise is never taken as
#: less than this share of its zone's median.
_NOISE_BINS = 12
_NOISE_FLOOR = 0.25
#: The dots' sigma on the sharp response is first taken as this many times the one of the
#: references' dot FWHM (whose tails on a board reach farther), then fitted: the trial factors,
#: on up to _SIGMA_MAX_DOTS dots of at least _SIGMA_Z noise sigmas with no other dot within
#: _SIGMA_CLEAR first sigmas (at least _SIGMA_MIN_DOTS of them). A spot is drawn out to
#: _PROFILE_SIGMAS of its sigma, its radial profile tabulated every _PROFILE_STEP px.
_SIZE_GUESS = 1.2
_SIGMA_TRIALS = (0.7, 0.85, 1.0, 1.2, 1.45, 1.75)
_SIGMA_Z = 8.0
_SIGMA_CLEAR = 5.0
_SIGMA_MIN_DOTS = 20
_SIGMA_MAX_DOTS = 200
_PROFILE_SIGMAS = 3.0
_PROFILE_STEP = 0.05
#: A place is a second spot only where the response less the fitted spots also exceeds this
#: share of the fitted spots there (their shape is not exactly a Gaussian's).
_ADD_SHARE = 0.5
#: The spots added, and the spots within this many sigmas of them, are fitted again (the
#: others held).
_ACTIVE_SIGMAS = 2.5
#: Rounds of the joint fit before the dots are added, and of the added dots and their
#: neighbours after.
_ROUNDS = (2, 10)
#: Places of a board taken at random to measure the spread of a spot's height fitted there.
_Z_PLACES = 20000
#: The rays' fit takes this share of each step, of the rays' angles at most _MAX_RAY_STEP
#: pixels' angle.
_RAY_DAMPING = 0.8
_MAX_RAY_STEP = 0.5
#: Half side of the square of pixels each dot is fitted to (px).
_FIT_HALF = 3
#: A step of a dot's centre in one round is at most this (px) ...
_MAX_STEP = 0.5
#: ... and the rounds take this share of each step (simultaneous steps of neighbouring dots
#: would overshoot).
_DAMPING = 1.0
#: A fitted dot whose height is below this many of its standard errors is left out.
_KEEP_Z = 2.0


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


def stripe_spacing(ex: SlitExtraction) -> float:
    """px, the median gap between neighbouring stripe centres along the rows (NaN: none)."""
    row = np.rint(ex.v).astype(np.intp)
    o = np.lexsort((ex.u, row))
    du = np.diff(ex.u[o])
    same = (np.diff(row[o]) == 0) & (du > 2.0)
    return float(np.median(du[same])) if same.any() else float("nan")


def board_view(image: NDArray, stripe_width_px: float, dot_size_px: float) -> BoardView:
    """Read one reference image for its dots (:class:`BoardView`).

    Parameters
    ----------
    image : (H, W) the reference image (a colour image: its laser plane, as the extraction
        takes it)
    stripe_width_px, dot_size_px : px, the stripes' and the dots' FWHM in the references
    """
    ex = extract_slits(
        image, stripe_width_px=stripe_width_px, dot_size_px=dot_size_px, leaning=False
    )
    h, w = ex.dots.shape
    clearance = STRIPE_CLEARANCE * ex.stripe_width_px
    dist, _ = stripe_maps(ex.u, ex.v, ex.peak, (h, w), clearance)
    near = dist < clearance
    angle = angle_field(ex, (h, w))
    r = np.clip(np.rint(ex.v).astype(np.intp), 0, h - 1)
    c = np.clip(np.rint(ex.u).astype(np.intp), 0, w - 1)
    a_pts = angle[r, c].astype(np.float64)
    spacing = stripe_spacing(ex)
    spread = 0.5 * max(spacing if math.isfinite(spacing) else 0.0, 2.0 * clearance)
    sat = saturation_level_of(ex.plane)
    resp = dot_response(ex.plane, ex.dot_size_px, ex.u, ex.v, a_pts, near, spread, sat)
    sharp = cv2.GaussianBlur(np.asarray(ex.plane).astype(np.float32), (0, 0), _SHARP_SIGMA)
    if sat is not None:
        clipped = (np.asarray(ex.plane) >= sat).astype(np.uint8)
        if clipped.any():
            rad = int(math.ceil(2.0 * _SHARP_SIGMA)) + 1
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
            sharp[cv2.dilate(clipped, k) > 0] = np.nan
    return BoardView(ex, resp, sharp, angle, near, float(ex.dot_size_px) / FWHM_PER_SIGMA)


@dataclass(frozen=True, eq=False)
class SharpBoard:
    """A board's sharp response, ready for fitting spots to it.

    Attributes
    ----------
    response : (H, W) float64, the sharp response less its median at its zone and level
        (intensity units; 0 where unknown)
    valid : (H, W) bool, where it is known (inside the image, clear of saturated pixels)
    sigma : (H, W) float64, its noise sigma at each pixel (per zone and level)
    angle : (H, W) float64, rad, the stripes' direction (:attr:`BoardView.angle`)
    profile : (L,) float64, the dots' radial profile on it (a Gaussian's: 1 at the centre,
        every :data:`_PROFILE_STEP` px, 0 at the end)
    reach : px, how far along the stripe it compares
    z_scale : the spread of a spot's height in its standard errors fitted at places of the
        board taken at random (the noise is correlated over neighbouring pixels):
        :meth:`spot_fit` scales by it
    """

    response: F64
    valid: NDArray[np.bool_]
    sigma: F64
    angle: F64
    profile: F64
    reach: float
    z_scale: float = 1.0

    @property
    def spot_sigma(self) -> float:
        """px, the radius at which the profile falls to exp(-1/2) (a Gaussian's sigma)."""
        p = self.profile
        i = int(np.argmax(p < math.exp(-0.5))) if np.any(p < math.exp(-0.5)) else len(p) - 1
        if i == 0:
            return _PROFILE_STEP
        f = (p[i - 1] - math.exp(-0.5)) / max(p[i - 1] - p[i], 1e-12)
        return (i - 1 + f) * _PROFILE_STEP

    def spot_fit(self, uv: F64) -> tuple[F64, F64]:
        """A dot's spot fitted at each place ``uv`` (M, 2) px, its centre held there: its
        height in standard errors, and the standard error (intensity units), both with the
        noise's spread :attr:`z_scale` (M,) each; NaN where no pixel is known."""
        uv = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
        z = np.full(len(uv), np.nan)
        se = np.full(len(uv), np.nan)
        _spot_z(
            self.response,
            self.valid,
            self.sigma,
            self.angle,
            uv,
            self.profile,
            self.reach,
            _FIT_HALF,
            z,
            se,
        )
        return z / self.z_scale, se * self.z_scale

    def model(self, P: F64, A: F64) -> F64:
        """(H, W) float64: the spots of heights ``A`` (N,) centred at ``P`` (N, 2) px."""
        out = np.zeros(self.response.shape)
        _splat(P, A, self.angle, self.profile, self.reach, out)
        return out


def _sharp_maps(
    view: BoardView, sg: float
) -> tuple[NDArray[np.float32], NDArray[np.float32], float]:
    """The sharp response over the image for dots of sigma ``sg`` px on it: (H, W) float32
    (NaN outside or near saturated pixels), its noise sigma at each pixel (per zone and level,
    robust over the image's pixels: the dots are few of them), and its reach (px)."""
    sm = view.sharp
    h, w = sm.shape
    reach = _REACH_SIGMAS * sg + 1.0
    ys, xs = np.mgrid[:h, :w].astype(np.float32)
    su = np.sin(view.angle) * np.float32(reach)
    sv = np.cos(view.angle) * np.float32(reach)
    nan = float("nan")
    border = cv2.BORDER_CONSTANT
    a = cv2.remap(sm, xs - su, ys - sv, cv2.INTER_LINEAR, borderMode=border, borderValue=nan)
    b = cv2.remap(sm, xs + su, ys + sv, cv2.INTER_LINEAR, borderMode=border, borderValue=nan)
    level = 0.5 * (a + b)
    r = sm - level
    sig = np.full((h, w), np.nan, np.float32)
    ok = np.isfinite(r)
    for zone in (False, True):
        m = ok & (view.near == zone)
        if m.sum() < 4 * _NOISE_BINS:
            continue
        lv = level[m]
        x = r[m]
        e = np.quantile(lv[:: max(1, lv.size // 100000)], np.linspace(0.0, 1.0, _NOISE_BINS + 1))
        b_ = np.clip(np.searchsorted(e, lv, side="right") - 1, 0, _NOISE_BINS - 1)
        med = np.zeros(_NOISE_BINS)
        s_ = np.zeros(_NOISE_BINS)
        for k in range(_NOISE_BINS):
            xb = x[b_ == k][:: max(1, int(np.count_nonzero(b_ == k)) // 20000)]
            if xb.size:
                med[k] = np.median(xb)
                s_[k] = 1.4826 * np.median(np.abs(xb - med[k]))
        s_ = np.maximum(s_, _NOISE_FLOOR * max(float(np.median(s_)), 1e-9))
        sig[m] = s_[b_]
        r[m] -= med[b_].astype(np.float32)
    fallback = float(np.nanmedian(sig)) if np.isfinite(sig).any() else 1.0
    sig[~np.isfinite(sig)] = fallback
    return r, sig, float(reach)


def _local_maxima(z: NDArray[np.float32], floor: float, margin: int) -> tuple[F64, F64]:
    """(u, v) px of the 3 x 3 local maxima of ``z`` above ``floor``, ``margin`` px clear of the
    image's sides."""
    zz = np.nan_to_num(z, nan=-np.inf).astype(np.float32)
    pk = (zz >= cv2.dilate(zz, np.ones((3, 3), np.uint8))) & (zz > floor)
    pk[:margin] = pk[-margin:] = False
    pk[:, :margin] = pk[:, -margin:] = False
    v, u = np.nonzero(pk)
    return u.astype(np.float64), v.astype(np.float64)


def _fit(sb: SharpBoard, P: F64, A: F64, rounds: int, held: F64 | None = None):
    """``rounds`` rounds of the joint fit of the spots (centres ``P`` (N, 2), heights ``A``)
    on ``sb``, beside the spots ``held`` (H, W) (fixed; default none): the fitted centres and
    heights, their standard errors and residual sums of squares (N, 4), and the fitted model
    (H, W)."""
    sg = sb.profile
    P = P.copy()
    A = A.copy()
    model = np.zeros(sb.response.shape)
    se = np.zeros((len(P), 4))
    for _ in range(rounds):
        if held is None:
            model[:] = 0.0
        else:
            model[:] = held
        _splat(P, A, sb.angle, sg, sb.reach, model)
        _jacobi(
            sb.response,
            sb.valid,
            sb.sigma,
            model,
            P,
            A,
            sb.angle,
            sg,
            sb.reach,
            _FIT_HALF,
            _MAX_STEP,
            _DAMPING,
            se,
        )
    model[:] = 0.0 if held is None else held
    _splat(P, A, sb.angle, sg, sb.reach, model)
    return P, A, se, model


def _gaussian_profile(sg: float, extent: float) -> F64:
    """(L,) a Gaussian's radial profile of sigma ``sg`` px out to ``extent`` px, 0 at the
    end."""
    r = np.arange(int(math.ceil(extent / _PROFILE_STEP)) + 1) * _PROFILE_STEP
    g = np.exp(-0.5 * (r / sg) ** 2)
    return np.clip((g - g[-1]) / (1.0 - g[-1]), 0.0, None)


def _spot_sigma(sb: SharpBoard, P: F64, A: F64, sg0: float) -> float:
    """The dots' sigma on the sharp response (px): per bright dot with no other dot near
    (``P``, ``A``), the trial sigma around ``sg0`` (refined by a parabola) whose Gaussian spot
    fits it best; their median (two dots blended into one peak want a wider spot, and are few).
    """
    trials = sg0 * np.array(_SIGMA_TRIALS)
    ss = np.stack(
        [
            _fit(replace(sb, profile=_gaussian_profile(t, _PROFILE_SIGMAS * t)), P, A, 3)[2][:, 3]
            for t in trials
        ],
        axis=1,
    )
    k = np.argmin(ss, axis=1)
    kk = np.clip(k, 1, len(trials) - 2)
    rows = np.arange(len(ss))
    a, b, c = ss[rows, kk - 1], ss[rows, kk], ss[rows, kk + 1]
    den = a - 2.0 * b + c
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.where(den > 0, np.clip(0.5 * (a - c) / den, -0.5, 0.5), 0.0)
    pos = np.where((k > 0) & (k < len(trials) - 1), kk + off, k)
    return float(np.interp(np.median(pos), np.arange(len(trials)), trials))


def board_catalogue(view: BoardView) -> tuple[BoardDots, SharpBoard]:
    """The dots of one board, each fitted as a spot beside its neighbours (see the module
    docstring), and the board's sharp response they were fitted to.

    Returns
    -------
    dots : BoardDots, the dots whose height reaches 2 of its standard errors
    sharp : SharpBoard
    """
    sg0 = math.hypot(_SIZE_GUESS * view.sigma_img, _SHARP_SIGMA)
    r, sig, reach = _sharp_maps(view, sg0)
    h, w = r.shape
    extent = _PROFILE_SIGMAS * sg0
    sb = SharpBoard(
        np.nan_to_num(r).astype(np.float64),
        np.isfinite(r),
        sig.astype(np.float64),
        view.angle.astype(np.float64),
        _gaussian_profile(sg0, extent),
        reach,
    )
    z = r / sig
    u, v = _local_maxima(z, _DETECT_Z, _FIT_HALF)
    P = np.stack([u, v], axis=1)
    A = np.maximum(sb.response[v.astype(np.intp), u.astype(np.intp)], 0.0)
    zp = z[v.astype(np.intp), u.astype(np.intp)]
    if len(P) > 1:
        d, _ = cKDTree(P).query(P, k=2)
        iso = (zp > _SIGMA_Z) & (d[:, 1] > _SIGMA_CLEAR * sg0)
        if iso.sum() >= _SIGMA_MIN_DOTS:
            pick = np.flatnonzero(iso)[:: max(1, int(iso.sum()) // _SIGMA_MAX_DOTS)]
            sg = _spot_sigma(sb, P[pick], A[pick], sg0)
            sb = replace(sb, profile=_gaussian_profile(sg, _PROFILE_SIGMAS * sg))
    P, A, se, model = _fit(sb, P, A, _ROUNDS[0])
    # one more spot where the response less every fitted spot still shows a dot clearly
    res = np.where(sb.valid, sb.response - model, np.nan)
    add = (res / sb.sigma > _ADD_Z) & (res > _ADD_SHARE * np.abs(model))
    au, av = _local_maxima(
        np.where(add, res / sb.sigma, np.nan).astype(np.float32), _ADD_Z, _FIT_HALF
    )
    if len(au) and len(P):
        d, j = cKDTree(P).query(np.stack([au, av], axis=1))
        keep = d > _ADD_CLEAR_SIGMAS * sb.spot_sigma
        # one spot more per fitted spot at most: the clearest of the places beside it (a
        # spot fitted between two blended dots leaves one on either side)
        zr = (res / sb.sigma)[av.astype(np.intp), au.astype(np.intp)]
        order = np.lexsort((-zr, j))
        first = np.ones(len(j), bool)
        first[1:] = j[order][1:] != j[order][:-1]
        best = np.zeros(len(j), bool)
        best[order[first]] = True
        keep &= best
        au, av = au[keep], av[keep]
    n_old = len(P)
    P = np.concatenate([P, np.stack([au, av], axis=1)])
    A = np.concatenate([A, np.maximum(sb.response[av.astype(np.intp), au.astype(np.intp)], 0.0)])
    # the added spots and their neighbours, fitted on, the others held
    active = np.zeros(len(P), bool)
    active[n_old:] = True
    if n_old < len(P) and n_old:
        near = cKDTree(P[n_old:]).query_ball_point(P[:n_old], _ACTIVE_SIGMAS * sb.spot_sigma)
        active[:n_old] = np.array([len(x) > 0 for x in near], bool)
    held = sb.model(P[~active], A[~active])
    Pa, Aa, _, _ = _fit(sb, P[active], A[active], _ROUNDS[1], held)
    P[active], A[active] = Pa, Aa
    P, A, se, _ = _fit(sb, P, A, 1)
    rng = np.random.default_rng(0)
    places = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0], (_Z_PLACES, 2))
    zr, _ = sb.spot_fit(places)
    zr = zr[np.isfinite(zr)]
    if zr.size > 100:
        sb = replace(sb, z_scale=max(1.4826 * float(np.median(np.abs(zr - np.median(zr)))), 1e-6))
    zfit = np.where(se[:, 2] > 0, A / np.where(se[:, 2] > 0, se[:, 2], 1.0), 0.0)
    inside = (P[:, 0] >= 0) & (P[:, 0] <= w - 1) & (P[:, 1] >= 0) & (P[:, 1] <= h - 1)
    keep = inside & (zfit >= _KEEP_Z) & np.isfinite(P).all(axis=1)
    se_px = np.maximum(se[:, 0], se[:, 1])
    return BoardDots(P[keep, 0], P[keep, 1], A[keep], zfit[keep], se_px[keep]), sb


def fit_rays_on_boards(
    boards: list[SharpBoard], uv: F64, jac: F64, A: F64, base: F64
) -> tuple[F64, F64, F64]:
    """One round of the joint fit of rays to the boards: every ray's direction (two angles,
    in pixels' angle) and its spot's height on each board, fitted to all boards at once, each
    board's response less the other rays' spots and the fixed spots ``base``; the rays in turn,
    each seeing the steps of those before it (Gauss-Seidel).

    Parameters
    ----------
    boards : R SharpBoard (one image size)
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
        _splat(uv[:, r], A[:, r], ang[r], sg[r], reach[r], model[r])
    step = np.zeros((len(uv), 2))
    se = np.zeros((len(uv), R + 1))
    chi = np.zeros(len(uv))
    _ray_step(resp, valid, sig, ang, model, uv, jac, A, sg, reach, _FIT_HALF, step, se, chi)
    return step, se, chi


@njit(cache=True, inline="always")
def _lobe(eu, ev, prof):
    """A unit spot's radial profile ``prof`` (every :data:`_PROFILE_STEP` px) at offset
    (eu, ev) px from its centre, and its derivatives with respect to the centre's u and v."""
    n = prof.shape[0]
    r2 = eu * eu + ev * ev
    ext = (n - 1) * _PROFILE_STEP
    if r2 >= ext * ext:
        return 0.0, 0.0, 0.0
    rr = math.sqrt(r2)
    x = rr / _PROFILE_STEP
    i = int(x)
    f = x - i
    g = prof[i] + f * (prof[i + 1] - prof[i])
    if rr < 1e-9:
        return g, 0.0, 0.0
    dg = (prof[i + 1] - prof[i]) / (_PROFILE_STEP * rr)
    return g, -dg * eu, -dg * ev


@njit(cache=True, inline="always")
def _spot(du, dv, tu, tv, prof, reach):
    """The sharp response of a unit dot at offset (du, dv) px from its centre (its radial
    profile ``prof``) with its two negative half copies at ``reach`` px before and after it
    along the stripe (``tu``, ``tv``), and its derivatives with respect to the centre's u
    and v."""
    k, ku, kv = _lobe(du, dv, prof)
    for s in (-1.0, 1.0):
        g, gu, gv = _lobe(du + s * reach * tu, dv + s * reach * tv, prof)
        k -= 0.5 * g
        ku -= 0.5 * gu
        kv -= 0.5 * gv
    return k, ku, kv


@njit(cache=True)
def _splat(P, A, ang, prof, reach, out):
    """Add every dot's spot (height ``A``, centre ``P`` (N, 2)) to ``out`` (H, W)."""
    for i in range(P.shape[0]):
        if np.isfinite(P[i, 0]) and np.isfinite(P[i, 1]):
            _add_spot(out, P[i, 0], P[i, 1], A[i], ang, prof, reach)


@njit(cache=True)
def _jacobi(r, valid, sig, model, P, A, ang, prof, reach, half, max_step, damping, se):
    """One round of the joint fit: every dot's centre and height fitted in turn (one
    Gauss-Newton step) to ``r`` less the other dots' spots (``model`` less its own), the
    ``model`` updated after each dot (Gauss-Seidel); ``se`` (N, 4) gets the standard errors of (u, v, height) from the response's
    noise ``sig`` at the dot, and the sum of squares of the response less the spots over the
    dot's pixels."""
    h, w = r.shape
    n = P.shape[0]
    for i in range(n):
        pu = P[i, 0]
        pv = P[i, 1]
        if not (np.isfinite(pu) and np.isfinite(pv)):
            continue
        cu = int(np.rint(pu))
        cv = int(np.rint(pv))
        if cu < 0 or cu >= w or cv < 0 or cv >= h:
            continue
        a = ang[cv, cu]
        tu = math.sin(a)
        tv = math.cos(a)
        ai = A[i]
        m00 = m01 = m02 = m11 = m12 = m22 = 0.0
        b0 = b1 = b2 = 0.0
        ss = 0.0
        npx = 0
        for y in range(max(cv - half, 0), min(cv + half + 1, h)):
            for x in range(max(cu - half, 0), min(cu + half + 1, w)):
                if not valid[y, x]:
                    continue
                k, ku, kv = _spot(x - pu, y - pv, tu, tv, prof, reach)
                e = r[y, x] - model[y, x]  # the data less every spot, its own included
                j0 = ai * ku
                j1 = ai * kv
                j2 = k
                m00 += j0 * j0
                m01 += j0 * j1
                m02 += j0 * j2
                m11 += j1 * j1
                m12 += j1 * j2
                m22 += j2 * j2
                ss += e * e
                b0 += j0 * e
                b1 += j1 * e
                b2 += j2 * e
                npx += 1
        if npx < 6 or m22 <= 0.0:
            se[i, 0] = se[i, 1] = se[i, 2] = se[i, 3] = 0.0
            continue
        tr = (m00 + m11 + m22) / 3.0
        lam = 1e-9 + 1e-4 * tr
        M = np.array([[m00 + lam, m01, m02], [m01, m11 + lam, m12], [m02, m12, m22 + lam]])
        b = np.array([b0, b1, b2])
        step = np.linalg.solve(M, b)
        cov = np.linalg.inv(M)
        s2 = sig[cv, cu] ** 2
        se[i, 0] = math.sqrt(max(cov[0, 0] * s2, 0.0))
        se[i, 1] = math.sqrt(max(cov[1, 1] * s2, 0.0))
        se[i, 2] = math.sqrt(max(cov[2, 2] * s2, 0.0))
        se[i, 3] = ss
        su = min(max(step[0], -max_step), max_step)
        sv = min(max(step[1], -max_step), max_step)
        nu = pu + damping * su
        nv = pv + damping * sv
        na = max(ai + damping * step[2], 0.0)
        # the model follows at once (Gauss-Seidel: a blended neighbour fitted next sees it)
        _add_spot(model, pu, pv, -ai, ang, prof, reach)
        _add_spot(model, nu, nv, na, ang, prof, reach)
        P[i, 0] = nu
        P[i, 1] = nv
        A[i] = na


@njit(cache=True, inline="always")
def _add_spot(out, pu, pv, a_i, ang, prof, reach):
    """Add a spot of height ``a_i`` centred at (pu, pv) px to ``out`` (H, W)."""
    if a_i == 0.0:
        return
    h, w = out.shape
    ext = (prof.shape[0] - 1) * _PROFILE_STEP
    half = int(math.ceil(ext))
    cu = int(np.rint(pu))
    cv = int(np.rint(pv))
    a = ang[min(max(cv, 0), h - 1), min(max(cu, 0), w - 1)]
    tu = math.sin(a)
    tv = math.cos(a)
    for j in range(3):  # the spot and its two negative half copies along the stripe
        s = 0.0 if j == 0 else (-1.0 if j == 1 else 1.0)
        c = 1.0 if j == 0 else -0.5
        qu = pu + s * reach * tu
        qv = pv + s * reach * tv
        iu = int(np.rint(qu))
        iv = int(np.rint(qv))
        for y in range(max(iv - half, 0), min(iv + half + 1, h)):
            for x in range(max(iu - half, 0), min(iu + half + 1, w)):
                g, _, _ = _lobe(x - qu, y - qv, prof)
                out[y, x] += c * a_i * g


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
                    k, ku, kv = _spot(x - pu, y - pv, tu, tv, prof[r], reach[r])
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
            _add_spot(model[r], pu, pv, -a_old, ang[r], prof[r], reach[r])
            _add_spot(model[r], nu, nv, A[i, r], ang[r], prof[r], reach[r])
            uv[i, r, 0] = nu
            uv[i, r, 1] = nv


@dataclass(frozen=True, eq=False)
class Board:
    """One reference board read for its dots: the image's view, its fitted dots and its sharp
    response (:func:`read_board`)."""

    view: BoardView
    dots: BoardDots
    sharp: SharpBoard


def read_board(image: NDArray, stripe_width_px: float, dot_size_px: float) -> Board:
    """One reference image read for its dots (:func:`board_view`) and its dots fitted
    (:func:`board_catalogue`)."""
    view = board_view(image, stripe_width_px, dot_size_px)
    dots, sharp = board_catalogue(view)
    return Board(view, dots, sharp)


@njit(cache=True)
def _spot_z(resp, valid, sig, ang, uv, prof, reach, half, out, out_se):
    """Per place (M, 2): the height of a spot fitted there (its centre held) over its standard
    error, weighted by the pixels' noise ``sig`` (``out``), and the standard error
    (``out_se``); both untouched where no pixel is known."""
    h, w = resp.shape
    for i in range(uv.shape[0]):
        pu = uv[i, 0]
        pv = uv[i, 1]
        if not (np.isfinite(pu) and np.isfinite(pv)):
            continue
        cu = int(np.rint(pu))
        cv = int(np.rint(pv))
        if cu < 0 or cu >= w or cv < 0 or cv >= h:
            continue
        a = ang[cv, cu]
        tu = math.sin(a)
        tv = math.cos(a)
        skr = 0.0
        skk = 0.0
        for y in range(max(cv - half, 0), min(cv + half + 1, h)):
            for x in range(max(cu - half, 0), min(cu + half + 1, w)):
                if not valid[y, x]:
                    continue
                k, _, _ = _spot(x - pu, y - pv, tu, tv, prof, reach)
                wt = 1.0 / (sig[y, x] * sig[y, x])
                skr += wt * k * resp[y, x]
                skk += wt * k * k
        if skk > 0.0:
            out[i] = skr / math.sqrt(skk)
            out_se[i] = 1.0 / math.sqrt(skk)
