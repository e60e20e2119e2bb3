"""Scanning: one image -> identified slit points -> 3D points (paper section 3, Fig. 24).

:func:`scan_image` runs slit identification (:func:`~multislit.identify.identify`) on one
image and triangulates every identified stripe-centre point with the calibrated camera and the
plane of its slit (:func:`~multislit.reconstruct.triangulate`). :func:`scan_capture` does
that for the scans of a capture folder, preparing the reference set once.
:func:`scan_image_for_holes` is the scan hole measurement works on.

Units: mm in the target frame, px in the image.
"""

from __future__ import annotations

import json
import math
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.calibrate import Calibration
from multislit.errors import CalibrationError, MeasurementError
from multislit.identify import (
    TEMPLATE_BACKGROUND,
    Identification,
    ReferenceSet,
    RigGeometry,
    capture_reference,
    identify,
    rig_geometry,
)
from multislit.identify.segments import group_order
from multislit.io import Capture, write_ply
from multislit.io.paths import as_path
from multislit.reconstruct.options import ScanOptions, as_scan_options
from multislit.reconstruct.triangulation import compile_kernels as compile_triangulation
from multislit.reconstruct.triangulation import triangulate
from multislit.stripes import as_image, extract_slits, refine_centres, resolve_channel
from multislit.stripes.dots import centre_dots
from multislit.summaries import Summarised

F64 = NDArray[np.float64]
Progress = Callable[[int, int, str], None]

__all__ = [
    "ScanResult",
    "DotPoints",
    "measure_dots",
    "rig_of",
    "scan_image",
    "scan_image_for_holes",
    "faded_ends",
    "compile_kernels",
    "scan_capture",
    "load_capture_calibration",
    "capture_reference",
    "CALIBRATION_FILE",
]

#: The calibration file name inside a capture folder (written by ``multislit calibrate``).
CALIBRATION_FILE = "calibration.json"

#: A dot whose line of sight passes farther than this many pixels' width (at its range) from
#: its ray is left out of the dot points.
_MAX_RAY_GAP_PX = 1.5

#: A scan whose identification labels fewer of its stripe centres than this fraction is not
#: taken as a scan of the rig's slits (its points are dropped, with a message).
_MIN_IDENTIFIED_FRACTION = 0.2

#: At either end of an identified piece, the points whose stripe is fainter than this share of
#: the piece's bright part (its peaks' 90th percentile) are left out: there the stripe fades
#: where the light grazes the surface towards a limb, and its centre lies off the slit's plane,
#: outward (on the simulated spheres by 0.2-1.6 mm on average, where the piece's other points
#: lie within 0.1 mm).
_FADED_SHARE = 0.3


@dataclass(frozen=True, eq=False)
class DotPoints:
    """The identified dots measured: each where its line of sight crosses its dot's ray.

    Attributes
    ----------
    points : (M, 3) float64, mm, target frame
    u, v : (M,) float64, px, the dots' centres
    slit : (M,) int64, the slit of the stripe piece whose dots they are
    confidence : (M,) float64, that piece's confidence
    ray_gap_mm : (M,) float64, mm, how far the line of sight passes from the dot's ray
    """

    points: F64
    u: F64
    v: F64
    slit: NDArray[np.int64]
    confidence: F64
    ray_gap_mm: F64

    def __len__(self) -> int:
        return len(self.points)


def measure_dots(ident: Identification, calibration: Calibration, rig: RigGeometry) -> DotPoints:
    """The 3D points of the dots an identification by the dots' geometry identified.

    Each dot is first centred as the calibration centres the reference boards' dots: a spot
    on the image's sharp response, fitted beside the spots around it
    (:func:`~multislit.stripes.dots.centre_dots`); a dot without a spot of its own keeps the
    centre it was found at. Its 3D point is the midpoint of the shortest segment between its
    line of sight and its ray (a dot whose two lines pass farther apart than
    :data:`_MAX_RAY_GAP_PX` px's width at its range is left out: a wrong pairing)."""
    d = ident.dots
    if d is None or len(d) == 0:
        e = np.zeros(0)
        return DotPoints(np.zeros((0, 3)), e, e.copy(), np.zeros(0, np.int64), e.copy(), e.copy())
    u, v = _centred_dots(ident, rig.dots.spot_sigma_px)
    cam = calibration.camera
    o, r = cam.rays(np.stack([u, v], axis=1))
    src = rig.dots.source
    dd = rig.dots.directions[d.dot]
    w0 = o - src
    b = np.einsum("ij,ij->i", r, dd)
    e1 = np.einsum("ij,ij->i", r, w0)
    e2 = np.einsum("ij,ij->i", dd, w0)
    den = np.maximum(1.0 - b * b, 1e-12)
    s1 = (b * e2 - e1) / den
    s2 = (e2 - b * e1) / den
    p1 = o + s1[:, None] * r
    p2 = src + s2[:, None] * dd
    gap = np.linalg.norm(p1 - p2, axis=1)
    f = float(np.sqrt(rig.camera.fx * rig.camera.fy))
    ok = (s1 > 0) & (gap <= _MAX_RAY_GAP_PX * s1 / f)
    return DotPoints(0.5 * (p1 + p2)[ok], u[ok], v[ok], d.slit[ok], d.confidence[ok], gap[ok])


def _centred_dots(ident: Identification, spot_sigma_px: float) -> tuple[F64, F64]:
    """(M,) px each: the identified dots (``ident.dots``) centred as spots of ``spot_sigma_px``
    px (NaN: fitted on the frame) on the extraction's sharp response
    (:func:`~multislit.stripes.dots.centre_dots`; the centres they were found at without an
    extraction)."""
    d = ident.dots
    if ident.extraction is None:
        return d.u, d.v
    u, v, _ = centre_dots(ident.extraction, d.u, d.v, d.angle, spot_sigma_px)
    return u, v


@dataclass(frozen=True, eq=False, repr=False)
class ScanResult(Summarised):
    """The 3D points of one image: its identified points that triangulate.

    Attributes
    ----------
    name : str
        The image's name (file stem) or ''.
    points : (K, 3) float64, mm, target frame
    u : (K,) float64, px
        Stripe centre column of each point (the refined centre when the scan refines them).
    index : (K,) intp
        Row of each point in :attr:`identification`.
    identification : Identification
        The slit identification of all stripe-centre points (identified or not); from a PLY,
        the file's points with their v, slit and confidence.
    num_invalid : int
        Identified points that did not triangulate (no plane, grazing ray).
    num_faded : int
        Identified points left out where their piece's stripe fades at its ends
        (:func:`faded_ends`: a limb, where the centre lies off the slit's plane).
    num_refined : int
        Points whose centre was refined; the others keep the extraction's centre.
    seconds : float, s
        Time to identify and triangulate.
    image_size : (W, H) px
    options : the :class:`~multislit.reconstruct.ScanOptions` the scan used (None: read from
        a PLY)
    dots : the identified dots measured (:class:`DotPoints`; with the refinement's
        ``dot_points``), or None

    The per-point arrays ``v``, ``slit``, ``confidence``, ``peak``, ``width`` and ``segment``
    and the counts are properties read from :attr:`identification`.
    """

    name: str
    points: F64
    u: F64
    index: NDArray[np.intp]
    identification: Identification
    num_invalid: int = 0
    num_faded: int = 0
    num_refined: int = 0
    seconds: float = 0.0
    image_size: tuple[int, int] = (0, 0)
    options: ScanOptions | None = None
    dots: DotPoints | None = None

    @property
    def v(self) -> F64:
        """(K,) float64, px, stripe centre row of each point."""
        return self.identification.v[self.index].astype(np.float64)

    @property
    def slit(self) -> NDArray[np.int64]:
        """(K,) int64, slit number 0..N-1 of each point."""
        return self.identification.slit[self.index].astype(np.int64)

    @property
    def confidence(self) -> F64:
        """(K,) float64, 0..1, identification confidence of each point's segment."""
        return self.identification.confidence[self.index].astype(np.float64)

    @property
    def peak(self) -> F64:
        """(K,) float64, DN above background, stripe peak height of each point."""
        return self.identification.peak[self.index].astype(np.float64)

    @property
    def width(self) -> F64:
        """(K,) float64, px, stripe width at each point."""
        return self.identification.width[self.index].astype(np.float64)

    @property
    def segment(self) -> NDArray[np.int64]:
        """(K,) int64, segment id of each point (-1: none)."""
        return self.identification.segment[self.index].astype(np.int64)

    @property
    def num_points(self) -> int:
        """K, the points."""
        return len(self.points)

    @property
    def num_centres(self) -> int:
        """Stripe-centre points found in the image (identified or not)."""
        return len(self.identification.u)

    @property
    def num_slits_found(self) -> int:
        """Distinct slits among the points."""
        return int(np.unique(self.slit).size)

    @property
    def num_segments(self) -> int:
        """Stripe segments found."""
        return int(self.identification.num_segments)

    @property
    def num_segments_identified(self) -> int:
        """Segments given a slit number."""
        return int(self.identification.num_identified)

    @property
    def dropped(self) -> dict[str, int]:
        """Reason -> number of segments dropped by the identification."""
        return dict(self.identification.dropped)

    @property
    def message(self) -> str:
        """'' or a note (e.g. no slits found)."""
        return self.identification.message

    @property
    def num_dropped(self) -> int:
        """Segments dropped by the identification, all reasons."""
        return int(sum(self.dropped.values()))

    @property
    def sources(self) -> dict[str, int]:
        """Pieces per source of their label (the identification by the dots' geometry: left
        out, by its dots, by its neighbours); empty for the template method."""
        p = self.identification.pieces
        return {} if p is None else p.counts()

    def summary(self) -> str:
        """One line: points (and dot points), slits found, segments identified and by what,
        dropped segments, time."""
        reasons = ", ".join(f"{k} {v}" for k, v in self.dropped.items() if v)
        src = self.sources
        by = (
            f" ({src['its dots']} by their dots, {src['its neighbours']} by their neighbours)"
            if src
            else ""
        )
        dots = f" + {len(self.dots)} dot points" if self.dots is not None else ""
        line = (
            f"{self.name or 'image'}: {self.num_points} points{dots}, {self.num_slits_found} "
            f"slits, {self.num_segments_identified}/{self.num_segments} segments identified{by}, "
            f"{self.num_dropped} dropped{f' ({reasons})' if reasons else ''}, "
            f"{self.seconds:.2f} s"
        )
        if self.message:
            line += f" -- {self.message}"
        return line

    def to_dict(self) -> dict[str, Any]:
        """The counts (not the arrays) as JSON-ready values."""
        return {
            "name": self.name,
            "points": self.num_points,
            "centres": self.num_centres,
            "slits_found": self.num_slits_found,
            "segments": self.num_segments,
            "segments_identified": self.num_segments_identified,
            "identified_by": self.sources,
            "dropped": {k: int(v) for k, v in self.dropped.items()},
            "dot_points": len(self.dots) if self.dots is not None else None,
            "invalid": self.num_invalid,
            "faded": self.num_faded,
            "refined": self.num_refined,
            "seconds": round(float(self.seconds), 4),
            "message": self.message,
            "options": self.options.to_dict() if self.options is not None else None,
        }

    @classmethod
    def from_ply(cls, path: str | Path) -> ScanResult:
        """Read a PLY written by :meth:`write_ply` (needs x y z, v and slit; u optional).

        The points with a slit number (>= 0) are kept; peak, width and segment are unknown
        (NaN, NaN, -1).
        """
        from multislit.io import read_ply

        d = read_ply(path)
        missing = [k for k in ("x", "y", "z", "v", "slit") if k not in d]
        if missing:
            raise MeasurementError(
                f"{path}: the PLY has no {', '.join(missing)} propert(ies); hole measurement "
                "needs the image row v and the slit of each point (write it with 'multislit scan')"
            )
        n = len(d["x"])
        pts = np.stack([d["x"], d["y"], d["z"]], axis=1).astype(np.float64)
        slit = d["slit"].astype(np.int64)
        keep = slit >= 0
        bad = [k for k in ("x", "y", "z", "v") if not np.all(np.isfinite(d[k][keep]))]
        if bad:
            raise MeasurementError(
                f"{path}: the PLY has NaN or infinite {'/'.join(bad)} values on identified "
                "points; scan the image again (multislit scan)"
            )
        nan = np.full(n, np.nan)

        def col(k: str) -> F64:
            return d[k].astype(np.float64) if k in d else nan

        ident = Identification(
            u=col("u"),
            v=col("v"),
            slit=slit,
            confidence=col("confidence"),
            segment=np.full(n, -1, np.int64),
            peak=nan,
            width=nan,
            num_segments=0,
            num_identified=0,
        )
        return cls(
            name=Path(path).stem,
            points=pts[keep],
            u=col("u")[keep],
            index=np.flatnonzero(keep),
            identification=ident,
        )

    def ply_columns(self) -> tuple[F64, dict[str, NDArray]]:
        """The points as written to a PLY: (M, 3) float64 mm, and the per-point columns
        ``u``, ``v`` (px), ``slit``, ``confidence`` and, with the identified dots
        (:attr:`dots`), ``dot`` (bool, True for a dot's point, after the stripes' points)."""
        cols: dict[str, NDArray] = {
            "u": self.u,
            "v": self.v,
            "slit": self.slit,
            "confidence": self.confidence,
        }
        if self.dots is None:
            return self.points, cols
        d = self.dots
        cols = {k: np.r_[c, getattr(d, k)] for k, c in cols.items()}
        cols["dot"] = np.r_[np.zeros(len(self.points), bool), np.ones(len(d), bool)]
        return np.concatenate([self.points, d.points]), cols

    def write_ply(self, path: str | Path, comment: str | None = None) -> Path:
        """Write the points as binary little-endian PLY (x y z u v slit confidence, and dot
        with the identified dots); the header's comments hold ``comment`` and the scan's
        options (``options {...}``, JSON)."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        lines = [] if comment is None else [comment]
        if self.options is not None:
            lines.append("options " + json.dumps(self.options.to_dict(), separators=(",", ":")))
        points, cols = self.ply_columns()
        write_ply(p, points, **cols, binary=True, comment=lines)
        return p


def _check_scan_inputs(
    image: ArrayLike, reference: ReferenceSet, calibration: Calibration
) -> tuple[tuple[int, int], F64]:
    """The image size (W, H) and the slit planes (N, 4), after checking that image, reference
    and calibration belong together."""
    if not isinstance(reference, ReferenceSet):
        raise MeasurementError(
            f"reference must be a ReferenceSet (from capture_reference(capture) or "
            f"prepare_reference(images, num_slits)), got {type(reference).__name__}"
        )
    if not isinstance(calibration, Calibration):
        raise CalibrationError(
            f"calibration must be a Calibration (e.g. Calibration.load(path)), got "
            f"{type(calibration).__name__}"
        )
    img = as_image(image)
    size = (int(img.shape[1]), int(img.shape[0]))
    calibration.check_image_size(size)
    if calibration.slit_planes is None:
        raise CalibrationError(
            "the calibration has no slit planes (projector calibration); recalibrate with the "
            "slits image (multislit calibrate)"
        )
    planes = calibration.slit_planes.planes
    n_ref = int(reference.curves.shape[1])
    if len(planes) != n_ref:
        raise CalibrationError(
            f"the calibration has {len(planes)} slit planes but the reference images show "
            f"{n_ref} slits; calibration and reference must come from the same rig"
        )
    if tuple(reference.image_size) != size:
        raise MeasurementError(
            f"image is {size[0]}x{size[1]} px but the reference was prepared for "
            f"{reference.image_size[0]}x{reference.image_size[1]} px"
        )
    return size, planes


_RIGS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def rig_of(calibration: Calibration) -> RigGeometry:
    """The calibrated rig as identification by the dots' geometry reads it (camera, slit
    planes, dot projector), prepared once per calibration and kept.

    Raises
    ------
    CalibrationError
        The calibration has no refined camera, no slit planes or no dot projector.
    """
    rig = _RIGS.get(calibration)
    if rig is None:
        if calibration.dot_projector is None or calibration.refined is None:
            raise CalibrationError(
                "the calibration has no dot projector (the identification by the dots' geometry "
                "needs it): recalibrate with the reference images (multislit calibrate), or "
                "identify by templates (method 'template')"
            )
        if calibration.slit_planes is None:
            raise CalibrationError("the calibration has no slit planes; recalibrate")
        rig = rig_geometry(
            calibration.refined, calibration.slit_planes.planes, calibration.dot_projector
        )
        _RIGS[calibration] = rig
    return rig


def _not_a_scan(ident: Identification) -> str:
    """Why the identification does not describe a scan of this rig's slits, or ''.

    Most stripe centres of a scan of the rig's slits are identified (58-99 % on the simulator's
    scenes at half size and on five zoo rigs); an image without them (lasers off, mirrored,
    rotated) has 0.7-5 % identified, and those are chance matches.
    """
    n = len(ident.slit)
    k = int(np.count_nonzero(ident.slit >= 0))
    if n == 0 or k >= _MIN_IDENTIFIED_FRACTION * n:
        return ident.message
    return (
        f"no slit identified: only {k} of {n} stripe centres ({100 * k / n:.1f} %) match the "
        "reference; is it a scan of this rig with the lasers on, not mirrored or rotated? "
        "(no points kept)"
    )


def _scan(
    image: ArrayLike,
    reference: ReferenceSet,
    calibration: Calibration,
    *,
    options: ScanOptions | None,
    name: str,
    refine: bool = True,
    previous: ScanResult | None = None,
    for_holes: bool = False,
) -> ScanResult:
    """Identify, optionally refine the centres, and triangulate (see :func:`scan_image`);
    ``refine`` False leaves the centres as extracted whatever the options say; ``for_holes``
    keeps the pieces' faded ends (:func:`faded_ends`: the hole edges are sought from the
    pieces' last points)."""
    opts = as_scan_options(options)
    if previous is not None and not isinstance(previous, ScanResult):
        raise MeasurementError(
            f"previous must be the ScanResult of the previous frame, got {type(previous).__name__}"
        )
    ex_opts = opts.extraction
    image = np.ascontiguousarray(as_image(image, channel=resolve_channel(image, ex_opts.channel)))
    size, planes = _check_scan_inputs(image, reference, calibration)
    prior = None
    if previous is not None and opts.identification.method != "template":
        raise MeasurementError(
            "previous: the previous frame is a prior for the template identification only "
            "(ScanOptions(identification=IdentifyOptions(method='template')))"
        )
    if previous is not None:
        if len(previous.points) and tuple(previous.image_size) == tuple(size):
            prior = previous.identification  # a frame that was no scan is no prior
    id_opts = opts.identification
    rig = rig_of(calibration) if id_opts.method == "geometry" else None
    t0 = time.perf_counter()
    # the template method matches the frame's dots against the boards': extracted alike
    background = TEMPLATE_BACKGROUND if id_opts.method == "template" else "opening"
    extraction = extract_slits(
        image,
        reference.stripe_width_px,
        reference.dot_size_px,
        **ex_opts.kwargs(),
        background=background,
    )
    ident = identify(
        image,
        reference,
        rig,
        options=id_opts,
        extraction=extraction,
        previous=prior,
        match_dots=opts.refinement.dot_points,
    )
    m = ident.slit >= 0
    problem = _not_a_scan(ident)
    if problem:
        ident = replace(ident, message=problem)
        m = np.zeros(len(ident.slit), bool)
    u = ident.u
    refined = np.zeros(len(u), bool)
    ex = ident.extraction
    refine = refine and opts.refinement.refine_centres
    if refine and m.any() and ex is not None and np.isfinite(ex.stripe_width_px):
        # all points, so that a neighbouring stripe is seen even where it is not identified;
        # the points found along their columns (stripes leaning towards the horizontal) keep
        # their first centre: the refinement fits along the rows
        seg = np.where(ex.by_column, -1, ident.segment)
        u, refined = refine_centres(
            image,
            ident.u,
            ident.v,
            seg,
            ex.stripe_width_px,
            ex.dot_size_px,
            noise_sigma=ex.noise_sigma,
        )
    faded = m & faded_ends(ident, 0.0 if for_holes else _FADED_SHARE)
    m &= ~faded
    uv = np.stack([u[m], ident.v[m]], axis=1)
    pts, valid = triangulate(
        calibration.camera, planes, uv, ident.slit[m], min_angle_deg=opts.refinement.min_angle_deg
    )
    idx = np.flatnonzero(m)[valid]
    dots = None
    if opts.refinement.dot_points and rig is not None and not problem:
        dots = measure_dots(ident, calibration, rig)
    seconds = time.perf_counter() - t0
    return ScanResult(
        name=name,
        points=pts[valid],
        u=u[idx].astype(np.float64),
        index=idx,
        identification=ident,
        num_invalid=int(np.count_nonzero(~valid)),
        num_faded=int(np.count_nonzero(faded)),
        num_refined=int(np.count_nonzero(refined[idx])),
        seconds=seconds,
        image_size=size,
        options=opts,
        dots=dots,
    )


def faded_ends(ident: Identification, share: float = _FADED_SHARE) -> NDArray[np.bool_]:
    """(K,) bool: the identified points at either end of their piece (``ident.segment`` and
    slit; along the rows, or the columns for the points found along them) whose peak is below
    ``share`` (default :data:`_FADED_SHARE`) times the 90th percentile of the piece's peaks, up
    to the first that is not: what :func:`scan_image` leaves out."""
    k = len(ident.slit)
    out = np.zeros(k, bool)
    seg = np.where(ident.slit >= 0, ident.segment, -1).astype(np.int64)
    if share <= 0 or not np.any(seg >= 0):
        return out
    ex = ident.extraction
    along = ident.v if ex is None else np.where(ex.by_column, ident.u, ident.v)
    order = group_order(seg)
    start = np.flatnonzero(np.r_[True, seg[order][1:] != seg[order][:-1], True])
    _faded_kernel(
        order,
        start,
        np.asarray(ident.slit, np.int64),
        np.asarray(along, np.float64),
        np.asarray(ident.peak, np.float64),
        float(share),
        out,
    )
    return out


#: Along the stripe, px: a piece's points are ordered by slit times this plus their position.
_SLIT_STRIDE = 1e6


@njit(cache=True)
def _faded_kernel(order, start, slit, along, peak, share, out):
    """:func:`faded_ends` on the points ``order`` grouped by segment (group g holds
    ``order[start[g]:start[g+1]]``): in each group the pieces of one slit, along the stripe."""
    for g in range(len(start) - 1):
        idx = order[start[g] : start[g + 1]]
        key = np.empty(idx.size)
        for i in range(idx.size):
            key[i] = slit[idx[i]] * _SLIT_STRIDE + along[idx[i]]
        a = idx[np.argsort(key, kind="mergesort")]
        lo = 0
        while lo < a.size:
            hi = lo + 1
            while hi < a.size and slit[a[hi]] == slit[a[lo]]:
                hi += 1
            n = hi - lo
            level = np.sort(peak[a[lo:hi]])[int(math.floor(0.9 * (n - 1)))]
            i = lo
            while i < hi and peak[a[i]] < share * level:
                out[a[i]] = True
                i += 1
            j = hi - 1
            while j >= i and peak[a[j]] < share * level:
                out[a[j]] = True
                j -= 1
            lo = hi


def compile_kernels() -> None:
    """Compile the stage's Numba kernels now (the triangulation's, :func:`faded_ends`'),
    or load them from Numba's disk cache; :func:`multislit.compile_kernels` calls this with
    the other stages' warm-ups."""
    compile_triangulation()
    _faded_kernel(
        np.arange(4, dtype=np.intp),
        np.array([0, 4], np.int64),
        np.zeros(4, np.int64),
        np.arange(4.0),
        np.array([1.0, 9.0, 9.0, 1.0]),
        0.3,
        np.zeros(4, bool),
    )


def scan_image(
    image: ArrayLike,
    reference: ReferenceSet,
    calibration: Calibration,
    options: ScanOptions | None = None,
    *,
    name: str = "",
    previous: ScanResult | None = None,
) -> ScanResult:
    """Measure the 3D points of one image.

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) RGB, uint8/uint16, a scan (lasers on), of the
        calibrated size
    reference : the prepared :class:`~multislit.identify.ReferenceSet`
    calibration : the rig's :class:`~multislit.calibrate.Calibration` with slit planes
    options : :class:`~multislit.reconstruct.ScanOptions`, optional
        The extraction's (colour plane, photo mode, ...), the identification's (the method:
        by the dots' geometry, the default, which needs a calibration with a dot projector;
        or by templates) and the refinement's options (re-centring the identified points, the
        least angle between a line of sight and a slit plane). Default: ``ScanOptions()``.
    name : str
        A name for messages and the summary. Default ''.
    previous : ScanResult
        The result of the previous frame of a sequence (the same rig, frames in order): with
        the template method its slit labels are a prior that the identification checks
        instead of searching every slit (see
        :func:`~multislit.identify.identify_template`'s ``previous``); a frame that gave no
        points is not used. The geometry method takes no prior (an error). Default None: the
        full search (single images).

    Returns
    -------
    ScanResult with the identified points that triangulate (and the options used). An image
    without slits, or one in which fewer than a fifth of the stripe centres are identified
    (lasers off, mirrored, another rig), gives an empty result whose ``message`` says so.

    Raises
    ------
    CalibrationError
        ``calibration`` is not a :class:`~multislit.calibrate.Calibration`, the image size
        differs from the calibration's, or the calibration has no slit planes or a different
        number of slits than the reference, or (identifying by the dots' geometry) no dot
        projector.
    MeasurementError
        ``reference`` is not a :class:`~multislit.identify.ReferenceSet`, or was prepared for
        another image size, ``previous`` is not a :class:`ScanResult`, or ``options`` is not
        a ScanOptions.
    """
    return _scan(
        image,
        reference,
        calibration,
        options=options,
        name=name,
        previous=previous,
    )


def scan_image_for_holes(
    image: ArrayLike,
    reference: ReferenceSet,
    calibration: Calibration,
    options: ScanOptions | None = None,
    *,
    name: str = "",
) -> ScanResult:
    """The scan hole measurement works on: :func:`scan_image` on the extraction's centres
    (no refinement, whatever ``options`` say), the pieces' faded ends kept (the hole edges are
    sought beyond the pieces' last points).

    Parameters and errors as :func:`scan_image`.
    """
    return _scan(
        image,
        reference,
        calibration,
        options=options,
        name=name,
        refine=False,
        for_holes=True,
    )


def load_capture_calibration(capture: Capture, path: str | Path | None = None) -> Calibration:
    """The capture's calibration (``<capture>/calibration.json`` or ``path``), checked.

    Raises
    ------
    CalibrationError
        The file is missing (with the hint to run ``multislit calibrate``), malformed, or made
        for another image size than the capture's.
    """
    p = (
        as_path(path, "calibration", error=CalibrationError)
        if path is not None
        else capture.root / CALIBRATION_FILE
    )
    if not p.is_file():
        raise CalibrationError(
            f"calibration file not found: {p}; run 'multislit calibrate {capture.root}' first"
            + ("" if path is None else " or fix the --calibration path")
        )
    cal = Calibration.load(p)
    try:
        cal.check_image_size(capture.image_size)
    except CalibrationError as exc:
        raise CalibrationError(f"{p}: {exc}") from None
    return cal


def scan_capture(
    capture: Capture | str | Path,
    calibration: Calibration | str | Path | None = None,
    reference: ReferenceSet | None = None,
    images: Sequence[str | Path] | None = None,
    progress: Progress | None = None,
    options: ScanOptions | None = None,
) -> dict[str, ScanResult]:
    """Scan the images of a capture folder.

    Parameters
    ----------
    capture : an opened :class:`~multislit.io.Capture` or its folder
    calibration : a Calibration, a calibration JSON path, or None for the capture's
        ``calibration.json`` (missing: an error asking to run ``multislit calibrate``)
    reference : a prepared reference set; None prepares it once from the capture's
        reference images
    images : image paths to scan (default: the capture's ``scans/*.png``)
    progress : called as ``progress(i, n, name)`` before each image and with ``i == n`` at
        the end
    options : :class:`~multislit.reconstruct.ScanOptions`, optional
        The scan's options (:func:`scan_image`); colour images are read in the extraction's
        channel, else the capture's ``laser_channel``. Default ``ScanOptions()``.

    Returns
    -------
    dict image name (file stem) -> ScanResult, in the order scanned

    Raises
    ------
    CaptureError, CalibrationError, MeasurementError
        No scans, a missing or mismatched calibration, images of the wrong size.
    """
    opts = as_scan_options(options)
    cap = capture if isinstance(capture, Capture) else Capture.open(capture, require_target=False)
    paths = [Path(p) for p in images] if images is not None else list(cap.scans)
    if not paths:
        raise MeasurementError(
            f"no scans to measure: {cap.root / 'scans'} has no *.png images (or give one image)"
        )
    if isinstance(calibration, Calibration):
        cal = calibration
        try:
            cal.check_image_size(cap.image_size)
        except CalibrationError as exc:
            raise CalibrationError(f"calibration does not fit the capture: {exc}") from None
    else:
        cal = load_capture_calibration(cap, calibration)
    ref = reference if reference is not None else capture_reference(cap)
    out: dict[str, ScanResult] = {}
    names = [p.stem for p in paths]
    if len(set(names)) != len(names):
        raise MeasurementError(f"image names must be unique, got {names}")
    for i, (path, nm) in enumerate(zip(paths, names, strict=True)):
        if progress:
            progress(i, len(paths), nm)
        img = cap.image(path, channel=opts.extraction.channel)
        out[nm] = scan_image(img, ref, cal, opts, name=nm)
    if progress:
        progress(len(paths), len(paths), "done")
    return out
