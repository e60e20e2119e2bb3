"""The local lean of the stripes (du/dv) from the structure tensor of the highpass image: the
slope along which the dots on a leaning stripe are refilled and its opening follows it."""

from __future__ import annotations

import functools

import cv2
import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic
from numpy.typing import NDArray

F32 = NDArray[np.float32]


@njit(cache=True)
def reflect101(i: int, n: int) -> int:
    """cv2.BORDER_REFLECT_101 index (gfedcb|abcdefgh|gfedcba)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * n - 2 - i
    return i


def slope_sigma(length: int) -> float:
    """Integration scale (px) of :func:`stripe_slope` for an opening of ``length`` px: half the
    line, a few stripe widths."""
    return 0.5 * length


def _structure_tensor(hp: NDArray, sigma: float) -> tuple[F32, F32]:
    """J_uu and J_uv of :func:`stripe_slope`: the products gu^2, gu gv of the Sobel
    derivatives of ``hp`` (uint8, uint16 or float32) integrated over a Gaussian of ``sigma``
    px, (H, W) float32 each."""
    # Sobel straight from integer data: its sums are integers below 2^24, exact in float32
    gu = cv2.Sobel(hp, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(hp, cv2.CV_32F, 0, 1, ksize=3)
    juv = cv2.GaussianBlur(cv2.multiply(gu, gv, dst=gv), (0, 0), sigma)
    juu = cv2.GaussianBlur(cv2.multiply(gu, gu, dst=gu), (0, 0), sigma)
    return juu, juv


def stripe_slope(hp: NDArray, sigma: float) -> NDArray[np.float32]:
    """(H, W) float32, px per row: the local lean of the stripes, du/dv, from the structure
    tensor of ``hp`` integrated over a Gaussian of ``sigma`` px (a stripe f(u - s v) has
    gradients (f', -s f'), so s = -J_uv / J_uu); clipped to +-1."""
    x = hp if hp.dtype in (np.uint8, np.uint16, np.float32) else hp.astype(np.float32)
    juu, juv = _structure_tensor(x, sigma)
    s = -juv / np.maximum(juu, 1e-6)
    return np.clip(s, -1.0, 1.0)


@intrinsic
def _fma32(typingctx, a, b, c):
    """``a * b + c`` in float32 rounded once (LLVM's fma: the CPU's fused multiply-add)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        f32 = ir.FloatType()
        fn = builder.module.declare_intrinsic("llvm.fma", [f32], ir.FunctionType(f32, [f32] * 3))
        return builder.call(fn, args)

    return sig, codegen


# The slope's Gaussian, as cv2.GaussianBlur computes it on float32 data (OpenCV's separable
# filter): a pass along each row, the taps summed in order from the first, then a pass along
# each column, the centre tap first and then the pairs of rows symmetric about it; each step a
# multiply-add rounded to float32. OpenCV's vector loops fuse the multiply and the add (one
# rounding) and its scalar tail does not: the columns below ``_ROW_FUSED_LANES * (W //
# _ROW_FUSED_LANES)`` are fused in the row pass, those below ``_COL_FUSED_LANES * (W //
# _COL_FUSED_LANES)`` in the column pass (its AVX2 build). A dimension of 1 px is not
# filtered. :func:`_blur_is_opencvs` checks this against cv2.GaussianBlur once per process.
_ROW_FUSED_LANES = 4
_COL_FUSED_LANES = 8
#: Columns per block of the row pass's bookkeeping (which rows of which columns to make).
_TENSOR_BLOCK = 8


@njit(cache=True, inline="always")
def _fma8(p, x, g0, g1, g2, g3, g4, g5, g6, g7, acc):
    """``acc`` plus the taps ``g0`` .. ``g7`` times ``p[x]`` .. ``p[x + 7]``, summed in order,
    each a fused multiply-add rounded to float32 (``x`` unsigned: no wraparound test)."""
    acc = _fma32(p[x], g0, acc)
    acc = _fma32(p[x + np.uint64(1)], g1, acc)
    acc = _fma32(p[x + np.uint64(2)], g2, acc)
    acc = _fma32(p[x + np.uint64(3)], g3, acc)
    acc = _fma32(p[x + np.uint64(4)], g4, acc)
    acc = _fma32(p[x + np.uint64(5)], g5, acc)
    acc = _fma32(p[x + np.uint64(6)], g6, acc)
    return _fma32(p[x + np.uint64(7)], g7, acc)


@njit(cache=True)
def _row_pass(pu, pv, g, ou, ov, c0, c1, fused):
    """Row pass of the Gaussian ``g`` for columns ``c0`` .. ``c1 - 1`` of one row: ``ou``,
    ``ov`` (W,) from the padded rows of products ``pu``, ``pv`` (W + len(g) - 1,); ``fused``:
    one rounding per tap (see ``_ROW_FUSED_LANES``), else a product and a sum. (Unsigned
    indices: no wraparound test, no views; the loops over columns vectorise.)"""
    if c1 <= c0:
        return
    for c in range(c0, c1):
        ou[np.uint64(c)] = 0.0
        ov[np.uint64(c)] = 0.0
    j = 0
    if fused:
        # eight taps per sweep, still summed in order (each column's sum is one chain of
        # fused multiply-adds): one load and store of the sums per eight taps
        while j + 8 <= g.size:
            g0, g1, g2, g3 = g[j], g[j + 1], g[j + 2], g[j + 3]
            g4, g5, g6, g7 = g[j + 4], g[j + 5], g[j + 6], g[j + 7]
            for c in range(c0, c1):
                q = np.uint64(c)
                x = np.uint64(c + j)
                ou[q] = _fma8(pu, x, g0, g1, g2, g3, g4, g5, g6, g7, ou[q])
                ov[q] = _fma8(pv, x, g0, g1, g2, g3, g4, g5, g6, g7, ov[q])
            j += 8
    while j < g.size:
        gj = g[j]
        if fused:
            for c in range(c0, c1):
                q = np.uint64(c)
                x = np.uint64(c + j)
                ou[q] = _fma32(pu[x], gj, ou[q])
                ov[q] = _fma32(pv[x], gj, ov[q])
        else:
            for c in range(c0, c1):
                q = np.uint64(c)
                x = np.uint64(c + j)
                ou[q] = ou[q] + pu[x] * gj
                ov[q] = ov[q] + pv[x] * gj
        j += 1


@njit(cache=True)
def _column_pass(ru, rv, g, m, c, h, fused):
    """Column pass of the Gaussian ``g`` at row ``m``, column ``c`` of an ``h``-row image from
    the row pass's rows ``ru``, ``rv`` (rows, W), kept in a ring (image row q in ring row
    q mod rows) that holds rows m - len(g) // 2 .. m + len(g) // 2 (reflected at the image
    border); ``fused`` as in :func:`_row_pass`. Returns J_uu, J_uv (float32)."""
    nr = ru.shape[0]
    rk = g.size // 2
    sm = m % nr
    su = ru[sm, c] * g[rk]
    sv = rv[sm, c] * g[rk]
    for j in range(1, rk + 1):
        a = reflect101(m + j, h) % nr
        b = reflect101(m - j, h) % nr
        gj = g[rk + j]
        if fused:
            su = _fma32(ru[a, c] + ru[b, c], gj, su)
            sv = _fma32(rv[a, c] + rv[b, c], gj, sv)
        else:
            su = su + (ru[a, c] + ru[b, c]) * gj
            sv = sv + (rv[a, c] + rv[b, c]) * gj
    return su, sv


@njit(cache=True)
def _column_points(ru, rv, g, sm, pc, pf, su, sv, n):
    """:func:`_column_pass` at the columns ``pc[:n]`` (uint64) of a row m whose rows
    m - len(g) // 2 .. m + len(g) // 2 all lie in the image (m in ring row ``sm``), into
    ``su``, ``sv``; ``pf``: fused (see :func:`_row_pass`) at each. The points advance
    together, one tap at a time: independent sums, no wait on each other's roundings."""
    nr, w = ru.shape
    fu = ru.ravel()
    fv = rv.ravel()
    rk = g.size // 2
    gc = g[rk]
    om = np.uint64(sm * w)
    all_fused = True
    for p in range(n):
        all_fused &= pf[p]
        su[p] = fu[om + pc[p]] * gc
        sv[p] = fv[om + pc[p]] * gc
    a = sm
    b = sm
    for j in range(1, rk + 1):
        a = a + 1 if a + 1 < nr else 0  # the ring rows of m + j and m - j
        b = b - 1 if b > 0 else nr - 1
        gj = g[rk + j]
        oa = np.uint64(a * w)
        ob = np.uint64(b * w)
        if all_fused:
            for p in range(n):
                su[p] = _fma32(fu[oa + pc[p]] + fu[ob + pc[p]], gj, su[p])
                sv[p] = _fma32(fv[oa + pc[p]] + fv[ob + pc[p]], gj, sv[p])
            continue
        for p in range(n):
            xu = fu[oa + pc[p]] + fu[ob + pc[p]]
            xv = fv[oa + pc[p]] + fv[ob + pc[p]]
            if pf[p]:
                su[p] = _fma32(xu, gj, su[p])
                sv[p] = _fma32(xv, gj, sv[p])
            else:
                su[p] = su[p] + xu * gj
                sv[p] = sv[p] + xv * gj


@njit(cache=True)
def _sobel_row(hp, r, gur, gvr):
    """Row ``r`` of cv2.Sobel's 3x3 derivatives of an integer image ``hp`` (H, W) along u and
    v (cv2.BORDER_REFLECT_101), as float32 into ``gur``, ``gvr`` (W,): sums of integers below
    2^24, exact in float32 in any order (so the loop runs in float32 lanes, not Numba's int64
    ones)."""
    h, w = hp.shape
    ra = hp[reflect101(r - 1, h)]
    rb = hp[r]
    rc = hp[reflect101(r + 1, h)]
    two = np.float32(2.0)
    # shifted 1-D views, indices from 0: the loop vectorises
    al, am, ar = ra[: w - 2], ra[1 : w - 1], ra[2:]
    bl, br = rb[: w - 2], rb[2:]
    cl, cm, cr = rc[: w - 2], rc[1 : w - 1], rc[2:]
    ou = gur[1 : w - 1]
    ov = gvr[1 : w - 1]
    for q in range(w - 2):
        a0, a1, a2 = np.float32(al[q]), np.float32(am[q]), np.float32(ar[q])
        b0, b2 = np.float32(bl[q]), np.float32(br[q])
        c0, c1, c2 = np.float32(cl[q]), np.float32(cm[q]), np.float32(cr[q])
        ou[q] = (a2 - a0) + two * (b2 - b0) + (c2 - c0)
        ov[q] = (c0 + two * c1 + c2) - (a0 + two * a1 + a2)
    for c in (0, w - 1):  # the reflected borders
        cl = reflect101(c - 1, w)
        cr = reflect101(c + 1, w)
        a0, a1, a2 = np.float32(ra[cl]), np.float32(ra[c]), np.float32(ra[cr])
        b0, b2 = np.float32(rb[cl]), np.float32(rb[cr])
        c0, c1, c2 = np.float32(rc[cl]), np.float32(rc[c]), np.float32(rc[cr])
        gur[c] = (a2 - a0) + two * (b2 - b0) + (c2 - c0)
        gvr[c] = (c0 + two * c1 + c2) - (a0 + two * a1 + a2)


@njit(cache=True)
def _tensor_at(hp, gu, gv, g, mids, cols):
    """J_uu and J_uv (K,) float32 of :func:`_structure_tensor` of ``hp`` (H, W) at the pixels
    (``mids``, ``cols``) (K,), from the Sobel derivatives ``gu``, ``gv`` (H, W) float32 (or,
    if they are (0, 0), those of an integer ``hp``, made row by row) and the Gaussian ``g``
    (odd length, cv2.BORDER_REFLECT_101), with OpenCV's float32 arithmetic (see
    ``_ROW_FUSED_LANES``). One pass down the rows: the row pass only on the column blocks
    whose rows some point's column pass reads, kept for the last len(g) rows; the column pass
    of a point as soon as its last row is made."""
    h, w = hp.shape
    rk = g.size // 2
    bs = _TENSOR_BLOCK
    nb = (w + bs - 1) // bs
    nr = min(2 * rk + 1, h)
    own = gu.shape[0] == 0
    gub = np.empty(w, np.float32)
    gvb = np.empty(w, np.float32)
    # rows r of column block b that some point reads: a difference array summed down the rows
    # (reflected rows near the borders fall inside mid - rk .. mid + rk, clamped); the points
    # by the row that completes their column (counting sort)
    diff = np.zeros((h + 1, nb), np.int32)
    first = np.zeros(h + 1, np.intp)
    for i in range(mids.size):
        b = cols[i] // bs
        diff[max(mids[i] - rk, 0), b] += 1
        diff[min(mids[i] + rk, h - 1) + 1, b] -= 1
        first[min(mids[i] + rk, h - 1) + 1] += 1
    for r in range(h):
        first[r + 1] += first[r]
    order = np.empty(mids.size, np.intp)
    fill = first[:h].copy()
    for i in range(mids.size):
        last = min(mids[i] + rk, h - 1)
        order[fill[last]] = i
        fill[last] += 1
    cnt = np.zeros(nb, np.int32)
    pad = w + 2 * rk
    pu = np.empty(pad, np.float32)
    pv = np.empty(pad, np.float32)
    ru = np.empty((nr, w), np.float32)
    rv = np.empty((nr, w), np.float32)
    most = 0  # the most points of one row
    for r in range(h):
        most = max(most, first[r + 1] - first[r])
    pi = np.empty(most, np.intp)
    pc = np.empty(most, np.uint64)
    pf = np.empty(most, np.bool_)
    ju = np.empty(most, np.float32)
    jv = np.empty(most, np.float32)
    row_fused = _ROW_FUSED_LANES * (w // _ROW_FUSED_LANES)
    col_fused = _COL_FUSED_LANES * (w // _COL_FUSED_LANES)
    juu = np.empty(mids.size, np.float32)
    juv = np.empty(mids.size, np.float32)
    for r in range(h):
        any_block = False
        for b in range(nb):
            cnt[b] += diff[r, b]
            if cnt[b] > 0:
                any_block = True
        if any_block:
            if own:
                _sobel_row(hp, r, gub, gvb)
                gur = gub
                gvr = gvb
            else:
                gur = gu[r]
                gvr = gv[r]
            our = ru[r % nr]
            ovr = rv[r % nr]
            if w == 1:  # not filtered along a single column
                our[0] = gur[0] * gur[0]
                ovr[0] = gur[0] * gvr[0]
            else:
                du = pu[rk : rk + w]  # 1-D views from 0: the loop vectorises
                dv = pv[rk : rk + w]
                for q in range(w):
                    du[q] = gur[q] * gur[q]
                    dv[q] = gur[q] * gvr[q]
                for q in range(rk):  # the reflected borders
                    for d in (q, pad - 1 - q):
                        pu[d] = pu[rk + reflect101(d - rk, w)]
                        pv[d] = pv[rk + reflect101(d - rk, w)]
                b = 0
                while b < nb:
                    if cnt[b] <= 0:
                        b += 1
                        continue
                    e = b
                    while e < nb and cnt[e] > 0:
                        e += 1
                    c0 = b * bs
                    c1 = min(e * bs, w)
                    _row_pass(pu, pv, g, our, ovr, c0, min(c1, row_fused), True)
                    _row_pass(pu, pv, g, our, ovr, max(c0, row_fused), c1, False)
                    b = e
        if first[r] == first[r + 1]:
            continue
        if h == 1:  # not filtered along a single row
            for k in range(first[r], first[r + 1]):
                juu[order[k]] = ru[0, cols[order[k]]]
                juv[order[k]] = rv[0, cols[order[k]]]
            continue
        # the points of row m = r - rk whose rows all lie in the image together, the others
        # (near the top or bottom border) one by one
        m = r - rk
        n = 0
        for k in range(first[r], first[r + 1]):
            i = order[k]
            if m - rk >= 0 and mids[i] == m:
                pi[n] = i
                pc[n] = np.uint64(cols[i])
                pf[n] = cols[i] < col_fused
                n += 1
            else:
                juu[i], juv[i] = _column_pass(ru, rv, g, mids[i], cols[i], h, cols[i] < col_fused)
        if n:
            _column_points(ru, rv, g, m % nr, pc, pf, ju, jv, n)
            for p in range(n):
                juu[pi[p]] = ju[p]
                juv[pi[p]] = jv[p]
    return juu, juv


def _gaussian_taps(sigma: float) -> NDArray[np.float32]:
    """The Gaussian (float32, odd length) that cv2.GaussianBlur uses on float32 data."""
    return cv2.getGaussianKernel(round(sigma * 8 + 1) | 1, sigma, cv2.CV_32F).ravel()


@functools.cache
def _blur_is_opencvs() -> bool:
    """Whether :func:`_tensor_at` gives cv2.GaussianBlur's values bit for bit here (OpenCV's
    arithmetic as described at ``_ROW_FUSED_LANES``), on small random images whose widths
    reach every kind of column. Checked once per process."""
    rng = np.random.default_rng(0)
    for h, w, sigma in ((23, 45, 2.5), (31, 21, 4.5), (9, 1, 1.5)):
        x = rng.normal(0.0, 300.0, (h, w)).astype(np.float32)
        mids, cols = (a.ravel() for a in np.indices((h, w)))
        # gu^2 = x^2 and gu gv = x * 1 with gu = x and gv = 1
        juu, juv = _tensor_at(x, x, np.ones_like(x), _gaussian_taps(sigma), mids, cols)
        for got, p in ((juu, x * x), (juv, x)):
            if not np.array_equal(got, cv2.GaussianBlur(p, (0, 0), sigma).ravel()):
                return False
    return True


def _slopes_at(hp: NDArray, sigma: float, mids: NDArray, cols: NDArray) -> F32:
    """:func:`stripe_slope` of ``hp`` (uint8, uint16 or float32) at the pixels (``mids``,
    ``cols``) (K,): (K,) float32, the values of the whole image's structure tensor there."""
    if mids.size == 0:
        return np.empty(0, np.float32)
    if _blur_is_opencvs():
        if hp.dtype == np.float32:  # float sums: OpenCV's own order
            gu = cv2.Sobel(hp, cv2.CV_32F, 1, 0, ksize=3)
            gv = cv2.Sobel(hp, cv2.CV_32F, 0, 1, ksize=3)
        else:
            gu = gv = np.empty((0, 0), np.float32)
        juu, juv = _tensor_at(hp, gu, gv, _gaussian_taps(sigma), mids, cols)
    else:  # another OpenCV build: its own blur, over the whole image
        tu, tv = _structure_tensor(hp, sigma)
        juu, juv = tu[mids, cols], tv[mids, cols]
    s = -juv / np.maximum(juu, np.float32(1e-6))
    return np.clip(s, np.float32(-1.0), np.float32(1.0))


#: :func:`lean_map` reads the stripes' direction on the image decimated this many times.
LEAN_DECIMATION = 4
#: ... where the structure there is at least this coherent (1: one direction, 0: none).
_LEAN_COHERENCE = 0.5


def lean_map(hp: NDArray, sigma: float, decimation: int = LEAN_DECIMATION) -> F32:
    """The stripes' direction, deg from the vertical (positive leaning right going down), on
    the image decimated D = ``decimation`` times (default :data:`LEAN_DECIMATION`):
    (H // D, W // D) float32, NaN where the image has no one direction (an isolated dot, blank
    background).

    The structure tensor of ``hp`` integrated over a Gaussian of ``sigma`` px, on the image
    averaged over blocks of D x D px: the direction is smooth over a few stripe widths, and it
    only chooses among lines 15 deg apart
    (:func:`~multislit.stripes.openings.follow_stripe_opening`). Where the tensor's coherence
    ((l1 - l2) / (l1 + l2) of its eigenvalues) is below :data:`_LEAN_COHERENCE`, NaN. Pixel
    (r, c) of the image lies in cell (r // D, c // D) (the last cells take the remainder).

    Parameters
    ----------
    hp : (H, W) highpass image (uint8, uint16 or float32)
    sigma : float, px, the integration scale (:func:`slope_sigma`)
    decimation : int, D, px; the decimated image must resolve the stripes, or the direction
        comes out too upright, the more so the closer they are: of stripes leaning 17.5
        degrees, 20, 12 and 6.5 px apart along the rows, D = 4 reads 14, 9 and -15 degrees,
        D = 2 reads 15, 15 and 12
    """
    h, w = hp.shape
    f = int(decimation)
    if h < 2 * f or w < 2 * f:
        return np.full((max(h // f, 1), max(w // f, 1)), np.nan, np.float32)
    small = cv2.resize(hp, (w // f, h // f), interpolation=cv2.INTER_AREA).astype(np.float32)
    gu = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3)
    s = max(sigma / f, 0.5)
    juu = cv2.GaussianBlur(cv2.multiply(gu, gu), (0, 0), s)
    jvv = cv2.GaussianBlur(cv2.multiply(gv, gv), (0, 0), s)
    juv2 = cv2.GaussianBlur(cv2.multiply(gu, gv, scale=2.0), (0, 0), s)
    # the gradients lie across the stripe, at half the angle of (J_uu - J_vv, 2 J_uv) from the
    # u axis; a stripe f(u - s v) has gradients along (1, -s): it leans atan(s), minus that
    mag, phase = cv2.cartToPolar(cv2.subtract(juu, jvv), juv2, angleInDegrees=True)
    theta = phase * np.float32(0.5)  # [0, 180)
    ang = np.where(theta > 90.0, np.float32(180.0) - theta, -theta)  # [-90, 90)
    incoherent = mag < cv2.add(juu, jvv) * np.float32(_LEAN_COHERENCE) + np.float32(1e-12)
    ang[incoherent] = np.nan
    return ang
