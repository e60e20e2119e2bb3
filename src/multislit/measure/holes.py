"""Hole measurement on a flat plate (the paper's section 6.2.3 and Table 1).

The paper measures the diameters of holes (100, 50 and 30 mm at about 0.9 m) in a flat board
from the points where the projected slits break at the hole's edge, by circle estimation.

* :func:`measure_holes` -- from one image: scans it (:func:`~multislit.reconstruct.
  scan_image_for_holes`), fits the plate's plane, finds the hole edges in the image and
  measures each hole.
* :func:`measure_holes_from_points` -- the same from the points of a scan only (e.g. read
  from a PLY): the edges are placed from the points (geometric edges), less accurately.
* :func:`~multislit.measure.fit_holes` -- edge points grouped per hole, one circle per hole.

Units: mm, target frame. Planes are (4,) ``[nx, ny, nz, d]`` with ``n . X + d = 0``.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.calibrate import Calibration
from multislit.errors import MeasurementError
from multislit.geometry import fit_plane_robust
from multislit.identify import ReferenceSet
from multislit.measure.edges import HoleEdges, hole_edges_from_profiles, subpixel_edges
from multislit.measure.hole_fit import HoleResult, fit_holes
from multislit.reconstruct import ScanOptions, ScanResult, scan_image_for_holes
from multislit.reconstruct.options import as_scan_options
from multislit.stripes import as_image, resolve_channel
from multislit.summaries import Summarised

F64 = NDArray[np.float64]

__all__ = ["HoleMeasurement", "measure_holes", "measure_holes_from_points"]

_MIN_SCAN_POINTS = 10  # fewer points in a scan: no hole measurement
_ON_PLATE_MM = 1.0  # points this close to the plate's plane are on it, mm
_LINK_SLIT_SPACINGS = 1.6  # edge grouping distance, in slit spacings on the plate
_DEFAULT_SLIT_SPACING_MM = 20.0  # used when no row is seen by two neighbouring slits


# --------------------------------------------------------------------------- scans
#: A measurement's summary lists at most this many holes; the rest are counted by reason.
_SUMMARY_HOLES = 8


@dataclass(frozen=True, eq=False, repr=False)
class HoleMeasurement(Summarised):
    """Holes measured in one scan.

    Attributes
    ----------
    plane : (4,) float64, the plate's plane (n.X + d = 0, mm), robust fit of the points
    plane_rms : float, mm, RMS distance of the plane's inliers
    holes : list of HoleResult (measurable or not, with the reason)
    edges : the HoleEdges used
    method : 'subpixel' (edges located in the image) or 'geometric' (from the points only)
    rejected_edges : int
        Gap ends whose stripe does not fade out in the image (not a hole's rim: stripe pieces
        missing from the points, e.g. unidentified); subpixel only.
    isolated_gaps : int
        Edge groups left out: in geometric mode those of one slit (a gap in one slit cannot be
        told from a missing stripe piece), in subpixel mode those without both edges of any
        gap (plate borders, shadows).
    scan : ScanResult or None
        The scan the holes were measured in.
    """

    plane: F64
    plane_rms: float
    holes: list[HoleResult]
    edges: HoleEdges
    method: str
    rejected_edges: int = 0
    isolated_gaps: int = 0
    scan: ScanResult | None = field(default=None, repr=False)

    @property
    def measurable(self) -> list[HoleResult]:
        """The holes with a diameter."""
        return [h for h in self.holes if h.measurable]

    def summary(self) -> str:
        """The plate and a line per hole, the measurable ones first (what ``print`` shows);
        beyond :data:`_SUMMARY_HOLES` lines the rest, all not measurable, are counted by
        reason."""
        name = self.scan.name if self.scan is not None and self.scan.name else "scan"
        lines = [
            f"{name}: plate plane RMS {self.plane_rms:.3f} mm, {len(self.edges)} edge points "
            f"({self.method}), {len(self.measurable)} measurable hole(s) of {len(self.holes)}"
        ]
        order = sorted(range(len(self.holes)), key=lambda i: not self.holes[i].measurable)
        shown = order[:_SUMMARY_HOLES] if len(order) > _SUMMARY_HOLES + 1 else order
        lines += [f"  hole {i + 1}: {self.holes[i].summary()}" for i in shown]
        rest = [self.holes[i] for i in order[len(shown) :]]
        if rest:
            why = Counter(h.reason.split(", need")[0] for h in rest)
            lines.append(
                f"  {len(rest)} more, not measurable: "
                + "; ".join(f"{n} {r}" for r, n in why.most_common())
            )
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """The measurement as JSON-ready values (not the edges' arrays, not the scan)."""
        return {
            "method": self.method,
            "plane": [float(x) for x in self.plane],
            "plane_rms_mm": float(self.plane_rms),
            "edge_points": len(self.edges),
            "rejected_edges": int(self.rejected_edges),
            "isolated_gaps": int(self.isolated_gaps),
            "holes": [h.to_dict() for h in self.holes],
        }


def _slit_spacing_mm(result: ScanResult, on: NDArray[np.bool_]) -> float:
    """Typical distance (mm) between neighbouring slits on the plate, from rows seen in both."""
    row = np.round(result.v[on]).astype(np.int64)
    sl = result.slit[on]
    p = result.points[on]
    key = sl * 100_000 + row
    order = np.argsort(key)
    key, p = key[order], p[order]
    nxt = np.searchsorted(key, key + 100_000)
    ok = nxt < len(key)
    ok[ok] &= key[nxt[ok]] == key[ok] + 100_000
    if not ok.any():
        return _DEFAULT_SLIT_SPACING_MM
    return float(np.median(np.linalg.norm(p[nxt[ok]] - p[ok], axis=1)))


def _plate_plane(result: ScanResult, plane: ArrayLike | None) -> tuple[F64, F64, float]:
    """The plate's plane (given, or a robust fit), the points' distances to it and its RMS."""
    if result.num_points < _MIN_SCAN_POINTS:
        raise MeasurementError(
            f"{result.name or 'scan'}: {result.num_points} points; too few to measure holes"
        )
    if plane is None:
        pl, inl = fit_plane_robust(result.points)
    else:
        pl = np.asarray(plane, dtype=float)
        pl = pl / np.linalg.norm(pl[:3])
        inl = np.abs(result.points @ pl[:3] + pl[3]) < _ON_PLATE_MM
    dist = result.points @ pl[:3] + pl[3]
    plane_rms = float(np.sqrt(np.mean(dist[inl] ** 2))) if inl.any() else float("nan")
    return pl, dist, plane_rms


def _drop_isolated(
    holes: list[HoleResult], edges: HoleEdges, subpixel: bool
) -> tuple[list[HoleResult], int]:
    """The holes without the edge groups that are not holes, and how many were dropped."""
    isolated = 0
    kept = []
    for h in holes:
        if h.measurable:
            kept.append(h)
            continue
        g = edges.gap[h.indices]
        complete = np.unique(g, return_counts=True)[1].max() >= 2 if len(g) else False
        # geometric: a gap in one slit cannot be told from a missing stripe piece;
        # subpixel: a lone edge without its partner is a plate border or a shadow, not a hole
        if (not subpixel and (h.n_slits or 0) <= 1) or (subpixel and not complete):
            isolated += 1
        else:
            kept.append(h)
    return kept, isolated


def _measure_scan(
    result: ScanResult,
    plane: ArrayLike | None,
    image: ArrayLike | None,
    calibration: Calibration | None,
    *,
    min_slits: int,
    min_points: int,
    min_arc_deg: float,
    min_gap_px: float,
    search_px: float,
) -> HoleMeasurement:
    """Holes of one scan: subpixel edges with ``image`` and ``calibration``, else geometric."""
    pl, dist, plane_rms = _plate_plane(result, plane)
    subpixel = image is not None
    if subpixel and (calibration is None or calibration.slit_planes is None):
        raise MeasurementError(
            "sub-pixel hole edges need the calibration (camera and slit planes) with the image"
        )
    e = hole_edges_from_profiles(
        result.points,
        result.slit,
        result.v,
        pl,
        min_gap=min_gap_px,
        edge_offset=0.0 if subpixel else 0.5,
    )
    rejected = 0
    if subpixel and len(e):
        assert calibration is not None
        edges, rejected = subpixel_edges(
            e, result.points, result.v, pl, image, calibration, search_px
        )
    else:
        edges = HoleEdges.geometric(e)
    holes = (
        fit_holes(
            edges.points,
            pl,
            min_points=min_points,
            min_slits=min_slits,
            slit=edges.slit,
            gap=edges.gap,
            min_arc_deg=min_arc_deg,
            link_distance=_LINK_SLIT_SPACINGS
            * _slit_spacing_mm(result, np.abs(dist) <= _ON_PLATE_MM),
        )
        if len(edges)
        else []
    )
    holes, isolated = _drop_isolated(holes, edges, subpixel)
    method = "subpixel" if subpixel else "geometric"
    return HoleMeasurement(pl, plane_rms, holes, edges, method, rejected, isolated, result)


def measure_holes(
    image: ArrayLike,
    reference: ReferenceSet,
    calibration: Calibration,
    options: ScanOptions | None = None,
    *,
    plane: ArrayLike | None = None,
    min_slits: int = 3,
    min_points: int = 5,
    min_arc_deg: float = 180.0,
    min_gap_px: float = 3.0,
    search_px: float = 12.0,
    name: str = "",
) -> HoleMeasurement:
    """Measure the holes in a flat plate from one image (paper section 6.2.3, Table 1).

    1. The image is scanned for hole measurement
       (:func:`~multislit.reconstruct.scan_image_for_holes`).
    2. The plate's plane: a robust fit of the points
       (:func:`~multislit.geometry.fit_plane_robust`), unless ``plane`` is given.
    3. Per slit, points ordered along v: where the stripe leaves the plate and comes back
       (:func:`~multislit.measure.hole_edges_from_profiles`).
    4. Each edge is located in the image where the stripe's intensity falls to half the
       plate's level (:func:`~multislit.measure.locate_edge_subpixel`); its 3D point is the
       point of the line (slit plane x plate plane) nearest to that pixel's line of sight.
       Gap ends where the stripe does not fade out are rejected (missing stripe pieces, not
       rims).
    5. Edge points grouped per hole and a circle fitted per hole (:func:`fit_holes`).

    Parameters
    ----------
    image : (H, W) grayscale or (H, W, 3) RGB, uint8/uint16, the scan image, of the
        calibrated size
    reference : the prepared :class:`~multislit.identify.ReferenceSet`
    calibration : the rig's :class:`~multislit.calibrate.Calibration` with slit planes
    options : :class:`~multislit.reconstruct.ScanOptions`, optional
        The scan's options: the extraction's (the colour plane, the photo mode, ...) and the
        identification's; the edges are measured on the extraction's centres (no
        refinement). Default ``ScanOptions()``.
    plane : (4,) float64, optional
        The plate's plane (``n . X + d = 0``, mm). Default: fitted to the points.
    min_slits : int
        A hole crossed by fewer slits is not measurable. Default 3.
    min_points : int
        A hole with fewer edge points is not measurable. Default 5.
    min_arc_deg : float, deg
        A hole whose edges cover a smaller arc is not measurable. Default 180.
    min_gap_px : float, px
        A stripe missing for at least this many rows (nothing in between) is a gap. Default 3.
    search_px : float, px
        How far beyond the last point (rows) an edge is searched in the image. Default 12.
    name : str
        A name for messages. Default ''.

    Returns
    -------
    HoleMeasurement, with the scan it was measured in.

    Raises
    ------
    CalibrationError, MeasurementError
        Image, reference and calibration do not fit together, or too few points.
    """
    opts = as_scan_options(options)
    image = as_image(image, channel=resolve_channel(image, opts.extraction.channel))
    result = scan_image_for_holes(image, reference, calibration, opts, name=name)
    return _measure_scan(
        result,
        plane,
        image,
        calibration,
        min_slits=min_slits,
        min_points=min_points,
        min_arc_deg=min_arc_deg,
        min_gap_px=min_gap_px,
        search_px=search_px,
    )


def measure_holes_from_points(
    scan: ScanResult,
    *,
    plane: ArrayLike | None = None,
    min_slits: int = 3,
    min_points: int = 5,
    min_arc_deg: float = 180.0,
    min_gap_px: float = 3.0,
) -> HoleMeasurement:
    """Measure the holes in a flat plate from a scan's points only (geometric edges).

    As :func:`measure_holes` without the image: each edge is placed half a row beyond the
    last point on the plate, and edge groups of a single slit are left out (a gap in one slit
    cannot be told from a missing stripe piece). Less accurate than :func:`measure_holes`:
    the rows left unidentified at stripe ends make holes come out too large.

    Parameters
    ----------
    scan : ScanResult
        The points with their image row ``v`` and slit (e.g. ``ScanResult.from_ply``).
    plane, min_slits, min_points, min_arc_deg, min_gap_px
        As :func:`measure_holes`.

    Returns
    -------
    HoleMeasurement with ``method == 'geometric'``.

    Raises
    ------
    MeasurementError
        Too few points.
    """
    return _measure_scan(
        scan,
        plane,
        None,
        None,
        min_slits=min_slits,
        min_points=min_points,
        min_arc_deg=min_arc_deg,
        min_gap_px=min_gap_px,
        search_px=0.0,
    )
