"""Planes: normalisation, ray intersection and 2D frames in a plane.

A plane is (4,) ``[nx, ny, nz, d]`` with ``n . X + d = 0``; several planes are (N, 4). Units mm.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry.camera import F64, as_points

__all__ = [
    "orthonormal_basis",
    "check_plane",
    "from_plane_coords",
    "intersect_rays_planes",
    "normalize_planes",
    "plane_basis",
    "project_to_plane",
]


def normalize_planes(planes: ArrayLike) -> F64:
    """Planes (N, 4) [nx, ny, nz, d] (n.X + d = 0) scaled to unit normals."""
    p = as_points(planes, 4, "planes")
    n = np.linalg.norm(p[:, :3], axis=1, keepdims=True)
    if np.any(n < 1e-12):
        raise MultislitError("planes must have non-zero normals")
    return p / n


def check_plane(plane: ArrayLike, name: str = "plane") -> F64:
    """One plane (4,) scaled to a unit normal, or MeasurementError naming ``name``.

    Parameters
    ----------
    plane : (4,) float64, ``n . X + d = 0``, finite, non-zero normal
    name : str
        The argument's name in the error message. Default ``"plane"``.
    """
    p = np.asarray(plane, dtype=np.float64)
    if p.shape != (4,) or not np.all(np.isfinite(p)):
        raise MeasurementError(f"{name} must be a finite (4,) [nx, ny, nz, d], got {p.shape}")
    n = np.linalg.norm(p[:3])
    if n < 1e-12:
        raise MeasurementError(f"{name} has a zero normal")
    return p / n


def intersect_rays_planes(
    origins: ArrayLike, directions: ArrayLike, planes: ArrayLike, min_cos: float = 0.0
) -> tuple[F64, F64]:
    """Intersect each ray with its own plane.

    Parameters
    ----------
    origins, directions : (N, 3) float64, mm / unit
    planes : (N, 4) float64, unit normals, n.X + d = 0 (or (4,) for one plane shared by all)
    min_cos : float
        Rays whose |cos| of the angle to the plane normal is below this are rejected (NaN).

    Returns
    -------
    points : (N, 3) float64, mm (NaN where rejected or behind the origin)
    t : (N,) float64, mm along the ray
    """
    o = as_points(origins, 3, "origins")
    d = as_points(directions, 3, "directions")
    pl = np.asarray(planes, dtype=np.float64)
    if pl.ndim == 1:
        pl = np.broadcast_to(pl, (len(o), 4))
    pl = as_points(pl, 4, "planes")
    n = pl[:, :3]
    denom = np.einsum("ij,ij->i", n, d)
    num = -(np.einsum("ij,ij->i", n, o) + pl[:, 3])
    dn = np.linalg.norm(d, axis=1) * np.linalg.norm(n, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
        bad = (np.abs(denom) <= min_cos * dn) | (denom == 0) | (t < 0)
    t = np.where(bad, np.nan, t)
    return o + t[:, None] * d, t


def plane_basis(plane: ArrayLike) -> tuple[F64, F64, F64]:
    """Orthonormal 2D frame in a plane.

    Parameters
    ----------
    plane : (4,) float64, ``n . X + d = 0`` (any normal length)

    Returns
    -------
    origin : (3,) float64, mm
        The foot of the perpendicular from the frame origin onto the plane.
    e1, e2 : (3,) float64, unit
        In-plane axes; (e1, e2, n) is right-handed. e1 is the world x axis projected into the
        plane (the y axis if the normal is within ~25 deg of x).
    """
    p = check_plane(plane)
    n = p[:3]
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return -p[3] * n, e1, e2


def project_to_plane(points: ArrayLike, plane: ArrayLike) -> F64:
    """3D points -> 2D coordinates in :func:`plane_basis` (orthogonal projection).

    Parameters
    ----------
    points : (N, 3) float64, mm, target frame
    plane : (4,) float64

    Returns
    -------
    coords : (N, 2) float64, mm, along (e1, e2) from the basis origin
    """
    p = as_points(points, 3, "points")
    origin, e1, e2 = plane_basis(plane)
    d = p - origin
    return np.stack([d @ e1, d @ e2], axis=1)


def from_plane_coords(coords: ArrayLike, plane: ArrayLike) -> F64:
    """2D coordinates in :func:`plane_basis` -> 3D points on the plane.

    Parameters
    ----------
    coords : (N, 2) float64, mm
    plane : (4,) float64

    Returns
    -------
    points : (N, 3) float64, mm, target frame
    """
    c = as_points(coords, 2, "coords")
    origin, e1, e2 = plane_basis(plane)
    return origin + c[:, :1] * e1 + c[:, 1:] * e2


def orthonormal_basis(normal: F64) -> tuple[F64, F64]:
    """Two unit vectors (3,) that with the unit vector ``normal`` (3,) form an orthonormal frame.

    The first is ``normal`` x the coordinate axis least aligned with it, the second
    ``normal`` x the first.
    """
    a = np.eye(3)[int(np.argmin(np.abs(normal)))]
    e1 = np.cross(normal, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)
