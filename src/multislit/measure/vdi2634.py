"""Acceptance metrics of optical 3D measuring systems after VDI/VDE 2634 part 2.

The guideline characterises an area-scanning system by a few measurements of calibrated
artefacts:

* probing error form ``PF`` (:func:`probing_error_form`): the range of the radial distances of
  the points measured on a sphere to their least squares sphere (radius free);
* probing error size ``PS`` (:func:`probing_error_size`): the fitted minus the calibrated
  diameter of that sphere;
* sphere-spacing error ``SD`` (:func:`sphere_spacing_error`): the distance between the
  fitted centres of the two spheres of a ball bar minus the calibrated distance;
* flatness measurement error ``F`` (:func:`flatness_error`): the range of the signed
  distances of the points measured on a flat to their least squares plane.

The guideline allows up to 0.3 % of the points to be left out before the ranges are taken
(``exclude``). :func:`markdown_table` and :class:`AcceptanceRow` format results for
``benchmarks/RESULTS.md``.

Units: mm. Points are (N, 3) float arrays in any Cartesian frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry import finite_points, fit_plane, fit_sphere

F64 = NDArray[np.float64]

__all__ = [
    "AcceptanceRow",
    "acceptance_table",
    "flatness_error",
    "markdown_table",
    "probing_error_form",
    "probing_error_size",
    "sphere_spacing_error",
]

MAX_EXCLUDE = 0.5  # the guideline itself allows 0.003; larger values are for diagnostics only


def _points(a: ArrayLike, name: str, minimum: int) -> F64:
    p = finite_points(a, 3, name)
    if len(p) < minimum:
        raise MeasurementError(f"{name}: need >= {minimum} points, got {len(p)}")
    return p


def _check_exclude(exclude: float) -> float:
    e = float(exclude)
    if not (np.isfinite(e) and 0.0 <= e < MAX_EXCLUDE):
        raise MeasurementError(f"exclude must be a fraction in [0, {MAX_EXCLUDE}), got {exclude}")
    return e


def _kept(residuals: F64, exclude: float) -> F64:
    """The residuals without the ``exclude`` fraction of largest magnitude (at least 1 kept)."""
    n_drop = int(np.floor(_check_exclude(exclude) * len(residuals)))
    if n_drop == 0:
        return residuals
    order = np.argsort(np.abs(residuals))
    return residuals[order[: len(residuals) - n_drop]]


def _range(residuals: F64) -> float:
    return float(residuals.max() - residuals.min())


def probing_error_form(points: ArrayLike, exclude: float = 0.0) -> float:
    """Probing error form PF: range of the radial residuals to the least squares sphere.

    Parameters
    ----------
    points : (N, 3) float64, mm, measured on one sphere, N >= 4
    exclude : float
        Fraction of the points with the largest residuals left out of the range (the guideline
        allows 0.003).

    Returns
    -------
    PF : float, mm, >= 0
    """
    return _range(_kept(fit_sphere(points).residuals, exclude))


def probing_error_size(points: ArrayLike, true_diameter: float) -> float:
    """Probing error size PS: fitted minus calibrated sphere diameter.

    Parameters
    ----------
    points : (N, 3) float64, mm, measured on one sphere, N >= 4
    true_diameter : float, mm, > 0

    Returns
    -------
    PS : float, mm (signed)
    """
    d = float(true_diameter)
    if not (np.isfinite(d) and d > 0):
        raise MeasurementError(f"true_diameter must be a positive length, got {true_diameter}")
    return fit_sphere(points).diameter - d


def sphere_spacing_error(points_a: ArrayLike, points_b: ArrayLike, true_distance: float) -> float:
    """Sphere-spacing error SD: distance of the fitted centres minus the calibrated distance.

    Parameters
    ----------
    points_a, points_b : (N, 3) float64, mm, measured on the two spheres, N >= 4 each
    true_distance : float, mm, > 0

    Returns
    -------
    SD : float, mm (signed)
    """
    d = float(true_distance)
    if not (np.isfinite(d) and d > 0):
        raise MeasurementError(f"true_distance must be a positive length, got {true_distance}")
    ca = fit_sphere(points_a).centre
    cb = fit_sphere(points_b).centre
    return float(np.linalg.norm(ca - cb)) - d


# --------------------------------------------------------------------------- flats
def flatness_error(points: ArrayLike, exclude: float = 0.0) -> float:
    """Flatness measurement error F: range of the signed distances to the least squares plane.

    Parameters
    ----------
    points : (N, 3) float64, mm, measured on one flat, N >= 3, not collinear
    exclude : float
        Fraction of the points with the largest distances left out of the range.

    Returns
    -------
    F : float, mm, >= 0
    """
    p = _points(points, "points", 3)
    try:
        _, resid = fit_plane(p)
    except MultislitError as exc:
        raise MeasurementError(str(exc)) from exc
    return _range(_kept(resid, exclude))


# --------------------------------------------------------------------------- tables
def _cell(x: object, digits: int) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "nan" if not np.isfinite(x) else f"{float(x):.{digits}f}"
    return str(x).replace("|", "\\|").replace("\n", " ")


def markdown_table(
    headers: Sequence[str], rows: Sequence[Sequence[object]], digits: int = 3
) -> str:
    """A GitHub markdown table.

    Parameters
    ----------
    headers : column titles
    rows : one sequence per row, as long as ``headers``; floats are printed with ``digits``
        decimals, None as ``-``, bools as yes/no, anything else with ``str``
    digits : int, decimals of floats

    Returns
    -------
    str, lines joined by newlines, ending with a newline
    """
    h = [_cell(str(x), digits) for x in headers]
    if not h:
        raise MultislitError("markdown_table needs at least one column")
    lines = ["| " + " | ".join(h) + " |", "|" + "|".join(" --- " for _ in h) + "|"]
    for i, r in enumerate(rows):
        if len(r) != len(h):
            raise MultislitError(f"markdown_table: row {i} has {len(r)} cells, expected {len(h)}")
        lines.append("| " + " | ".join(_cell(x, digits) for x in r) + " |")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class AcceptanceRow:
    """One acceptance result.

    Attributes
    ----------
    label : str, what was measured (e.g. ``"sphere r=60, ours"``)
    quantity : str, ``"PF"``, ``"PS"``, ``"SD"`` or ``"F"`` (free text accepted)
    value_mm : float, mm
    n_points : int, points used
    limit_mm : float or None, the maximum permissible error (MPE), mm
    """

    label: str
    quantity: str
    value_mm: float
    n_points: int
    limit_mm: float | None = None

    @property
    def passed(self) -> bool | None:
        """|value| within the limit; None without a limit or for a NaN value."""
        if self.limit_mm is None or not np.isfinite(self.value_mm):
            return None
        return bool(abs(self.value_mm) <= self.limit_mm)


def acceptance_table(rows: Sequence[AcceptanceRow], digits: int = 3) -> str:
    """Markdown table of acceptance rows: measured, quantity, value (mm), points, MPE, pass."""
    return markdown_table(
        ["measured", "quantity", "value (mm)", "points", "MPE (mm)", "pass"],
        [[r.label, r.quantity, r.value_mm, r.n_points, r.limit_mm, r.passed] for r in rows],
        digits,
    )
