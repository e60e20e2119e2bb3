"""Camera models and rays: the geometry every stage shares.

Conventions (the capture format's): units mm and px; pixel (u, v) with u right, v down and
(0, 0) the centre of the top-left pixel (OpenCV's convention). World frame = target frame.
The camera frame is OpenCV's: x right, y down, z forward; ``X_cam = R @ X_world + t``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from multislit.errors import MultislitError

F64 = NDArray[np.float64]


# --------------------------------------------------------------------------- validation
def as_points(a: ArrayLike, dim: int, name: str) -> F64:
    """Return ``a`` as a C-contiguous (N, dim) float64 array, or raise naming ``name``.

    A single point of shape (dim,) is accepted and returned as (1, dim).
    """
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise MultislitError(f"{name} must have shape (N, {dim}), got {np.shape(a)}")
    return np.ascontiguousarray(arr)


def rotation_from_rvec(rvec: ArrayLike) -> F64:
    """Rodrigues vector (3,) -> rotation matrix (3, 3)."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * (kx @ kx)


def rvec_from_rotation(R: ArrayLike) -> F64:
    """Rotation matrix (3, 3) -> Rodrigues vector (3,)."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    if theta < 1e-12:
        return np.zeros(3)
    if np.pi - theta < 1e-6:
        # near 180 degrees: axis from the symmetric part
        M = (R + np.eye(3)) / 2
        k = np.sqrt(np.clip(np.diag(M), 0, None))
        i = int(np.argmax(k))
        k = M[:, i] / np.sqrt(M[i, i])
        return k / np.linalg.norm(k) * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * np.sin(theta))
    return w * theta


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 1.0, 0.0)) -> F64:
    """Rotation R (world -> device) for a device at ``eye`` whose z axis points at ``target``.

    The device frame is OpenCV-like: z forward, y along ``up`` negated (down), x right; ``up``
    is a world direction (default +Y, the world's up).
    """
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    down = -np.asarray(up, float)
    x = np.cross(down, z)
    n = np.linalg.norm(x)
    if n < 1e-9:
        raise MultislitError("look_at: the up vector is parallel to the viewing direction")
    x /= n
    y = np.cross(z, x)
    return np.stack([x, y, z])


# --------------------------------------------------------------------------- cameras
class Camera(Protocol):
    """What triangulation and the simulator need of any camera model."""

    image_size: tuple[int, int]

    def project(self, points: ArrayLike) -> F64: ...

    def rays(self, uv: ArrayLike) -> tuple[F64, F64]: ...


def _coefficients(dist: F64) -> tuple[float, float, float, float, float]:
    """(k1, k2, p1, p2, k3) of a 4- or 5-coefficient OpenCV model."""
    k1, k2, p1, p2 = dist[:4]
    k3 = dist[4] if len(dist) > 4 else 0.0
    return k1, k2, p1, p2, k3


def _distort(xy: F64, dist: F64) -> F64:
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3)) if k3 else 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


#: Newton steps of the undistortion at most, and the step below which a point has converged.
UNDISTORT_ITERATIONS = 20
_UNDISTORT_TOL = 1e-14


@njit(cache=True, inline="always")
def undistort_point(xd, yd, k1, k2, p1, p2, k3, iterations):
    """One distorted normalised point (``xd``, ``yd``) -> undistorted (x, y): :func:`_distort`
    inverted by Newton's method, at most ``iterations`` steps, until a step is below
    :data:`_UNDISTORT_TOL` (exact to ~1e-12 for sane lenses). Compiled, for the kernels that
    undistort point by point."""
    x, y = xd, yd
    for _ in range(iterations):
        r2 = x * x + y * y
        if k3:
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            drad = 2 * k1 + 4 * k2 * r2 + 6 * k3 * r2 * r2  # d(radial)/d(r2) * 2
        else:
            radial = 1 + k1 * r2 + k2 * r2 * r2
            drad = 2 * k1 + 4 * k2 * r2
        ex = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
        ey = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
        j11 = radial + x * x * drad + 2 * p1 * y + 6 * p2 * x
        j12 = x * y * drad + 2 * p1 * x + 2 * p2 * y
        j22 = radial + y * y * drad + 6 * p1 * y + 2 * p2 * x
        det = j11 * j22 - j12 * j12
        dx = (j22 * ex - j12 * ey) / det
        dy = (-j12 * ex + j11 * ey) / det
        x -= dx
        y -= dy
        if max(abs(dx), abs(dy)) < _UNDISTORT_TOL:
            break
    return x, y


@njit(cache=True)
def _undistort_kernel(xyd, k1, k2, p1, p2, k3, iterations, out):
    """:func:`undistort_point` of each row of ``xyd`` (N, 2) into ``out`` (N, 2)."""
    for i in range(xyd.shape[0]):
        out[i, 0], out[i, 1] = undistort_point(xyd[i, 0], xyd[i, 1], k1, k2, p1, p2, k3, iterations)


@njit(cache=True, inline="always")
def line_of_sight(u, v, fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, R):
    """The unit direction (world frame) of the line of sight through pixel (``u``, ``v``) of a
    pinhole camera (intrinsics ``fx`` .. ``cy``, distortion ``k1`` .. ``k3``, undistorted by
    :func:`undistort_point` where ``distorted``; ``R`` (3, 3) world -> camera): R^T (x, y, 1),
    normalised. Compiled, for the kernels that work point by point."""
    x = (u - cx) / fx
    y = (v - cy) / fy
    if distorted:
        x, y = undistort_point(x, y, k1, k2, p1, p2, k3, UNDISTORT_ITERATIONS)
    d0 = x * R[0, 0] + y * R[1, 0] + R[2, 0]
    d1 = x * R[0, 1] + y * R[1, 1] + R[2, 1]
    d2 = x * R[0, 2] + y * R[1, 2] + R[2, 2]
    dl = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return d0 / dl, d1 / dl, d2 / dl


@njit(cache=True)
def _rays_kernel(uv, fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, R, out):
    """:func:`line_of_sight` of each row of ``uv`` (N, 2) px into ``out`` (N, 3)."""
    for i in range(uv.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = line_of_sight(
            uv[i, 0], uv[i, 1], fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, R
        )


def _undistort(xyd: F64, dist: F64, iterations: int = UNDISTORT_ITERATIONS) -> F64:
    """Invert :func:`_distort` (N, 2) -> (N, 2), point by point (:func:`undistort_point`)."""
    if not np.any(dist):
        return xyd.copy()
    k1, k2, p1, p2, k3 = (float(c) for c in _coefficients(dist))
    out = np.empty_like(xyd, dtype=np.float64)
    _undistort_kernel(
        np.ascontiguousarray(xyd, np.float64), k1, k2, p1, p2, k3, int(iterations), out
    )
    return out


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """Pinhole camera with OpenCV's radial (k1, k2, k3) and tangential (p1, p2) distortion.

    Parameters
    ----------
    fx, fy : float, px
        Focal lengths.
    cx, cy : float, px
        Principal point.
    rvec, tvec : (3,) float, rad / mm
        Pose, world -> camera: ``X_cam = R(rvec) @ X_world + tvec``.
    dist : (4,) or (5,) float
        (k1, k2, p1, p2) or OpenCV's 5-coefficient (k1, k2, p1, p2, k3), on normalised
        coordinates (``cv2.calibrateCamera``'s ``distCoeffs.ravel()``). A k3 of 0 is dropped,
        so a 5-coefficient model without k3 is stored, compared and written as 4.
    image_size : (W, H) int, px
    """

    fx: float
    fy: float
    cx: float
    cy: float
    rvec: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tvec: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    image_size: tuple[int, int] = (1280, 1024)
    _R: F64 = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "rvec", tuple(float(x) for x in self.rvec))
        object.__setattr__(self, "tvec", tuple(float(x) for x in self.tvec))
        dist = tuple(float(x) for x in np.ravel(np.asarray(self.dist, dtype=np.float64)))
        if len(dist) not in (4, 5) or not all(np.isfinite(dist)):
            raise MultislitError(
                f"dist must be 4 or 5 finite numbers, (k1, k2, p1, p2) or OpenCV's "
                f"(k1, k2, p1, p2, k3), got {self.dist}"
            )
        if len(dist) == 5 and dist[4] == 0.0:
            dist = dist[:4]
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))
        if not (self.fx > 0 and self.fy > 0):
            raise MultislitError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        object.__setattr__(self, "_R", rotation_from_rvec(self.rvec))

    # -- matrices
    @property
    def K(self) -> F64:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def R(self) -> F64:
        """(3, 3) rotation world -> camera."""
        return self._R.copy()

    @property
    def t(self) -> F64:
        """(3,) translation world -> camera, mm."""
        return np.array(self.tvec)

    @property
    def centre(self) -> F64:
        """(3,) camera centre in the world frame, mm."""
        return -self._R.T @ self.t

    @property
    def matrix(self) -> F64:
        """(3, 4) projection matrix K [R | t] of the distortion-free part (the DLT's C)."""
        return self.K @ np.hstack([self._R, self.t[:, None]])

    @property
    def dist_array(self) -> F64:
        return np.array(self.dist)

    # -- projection
    def to_camera(self, points: ArrayLike) -> F64:
        """World points (N, 3) mm -> camera-frame points (N, 3) mm."""
        p = as_points(points, 3, "points")
        return p @ self._R.T + self.t

    def project(self, points: ArrayLike) -> F64:
        """Project world points.

        Parameters
        ----------
        points : (N, 3) float64, mm, world frame

        Returns
        -------
        uv : (N, 2) float64, px. Points at or behind the camera give NaN.
        """
        pc = self.to_camera(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / z[:, None]
        xy[z <= 1e-9] = np.nan
        xyd = _distort(xy, self.dist_array)
        return np.stack([self.fx * xyd[:, 0] + self.cx, self.fy * xyd[:, 1] + self.cy], axis=1)

    def normalized(self, uv: ArrayLike) -> F64:
        """Pixels (N, 2) -> undistorted normalised image coordinates (N, 2) (x/z, y/z)."""
        p = as_points(uv, 2, "uv")
        xyd = np.stack([(p[:, 0] - self.cx) / self.fx, (p[:, 1] - self.cy) / self.fy], axis=1)
        return _undistort(xyd, self.dist_array)

    def undistort_pixels(self, uv: ArrayLike) -> F64:
        """Pixels (N, 2) -> pixels (N, 2) of the same camera without distortion."""
        xy = self.normalized(uv)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)

    def rays(self, uv: ArrayLike) -> tuple[F64, F64]:
        """Lines of sight through pixels.

        Parameters
        ----------
        uv : (N, 2) float64, px

        Returns
        -------
        origins : (N, 3) float64, mm, world frame (the camera centre)
        directions : (N, 3) float64, unit, world frame
        """
        p = as_points(uv, 2, "uv")
        dist = self.dist_array
        d = np.empty((len(p), 3))
        _rays_kernel(
            p, self.fx, self.fy, self.cx, self.cy, *(float(c) for c in _coefficients(dist)),
            bool(np.any(dist)), np.ascontiguousarray(self._R, np.float64), d,
        )  # fmt: skip
        return np.broadcast_to(self.centre, d.shape).copy(), d

    # -- serialisation
    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "pinhole",
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "rvec": list(self.rvec),
            "tvec": list(self.tvec),
            "dist": list(self.dist),
            "image_size": list(self.image_size),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PinholeCamera:
        try:
            return cls(
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                rvec=tuple(d.get("rvec", (0, 0, 0))),
                tvec=tuple(d.get("tvec", (0, 0, 0))),
                dist=tuple(d.get("dist", (0, 0, 0, 0))),
                image_size=tuple(d["image_size"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MultislitError(f"malformed pinhole camera: {exc!r}") from exc

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, s: str) -> PinholeCamera:
        return cls.from_dict(json.loads(s))


@dataclass(frozen=True, eq=False)
class MatrixCamera:
    """The paper's camera: a 3x4 projection matrix C (eq. 1), no distortion.

    Parameters
    ----------
    C : (3, 4) float64
        Maps homogeneous world points (mm) to homogeneous pixels, scaled so that points in
        front of the camera get a positive homogeneous coordinate H_c (as ``calibrate_dlt``
        returns it); the overall magnitude is free.
    image_size : (W, H) int, px
    """

    C: F64
    image_size: tuple[int, int] = (1280, 1024)

    def __post_init__(self) -> None:
        C = np.asarray(self.C, dtype=np.float64)
        if C.shape != (3, 4) or not np.all(np.isfinite(C)):
            raise MultislitError(f"C must be a finite (3, 4) matrix, got shape {C.shape}")
        if abs(np.linalg.det(C[:, :3])) < 1e-300:
            raise MultislitError("C is degenerate: its left 3x3 block is singular")
        object.__setattr__(self, "C", C)
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))

    @property
    def centre(self) -> F64:
        """(3,) camera centre in the world frame, mm (the right null vector of C)."""
        return -np.linalg.solve(self.C[:, :3], self.C[:, 3])

    def project(self, points: ArrayLike) -> F64:
        """World points (N, 3) mm -> pixels (N, 2) px."""
        p = as_points(points, 3, "points")
        h = p @ self.C[:, :3].T + self.C[:, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            return h[:, :2] / h[:, 2:3]

    def rays(self, uv: ArrayLike) -> tuple[F64, F64]:
        """Lines of sight through pixels (N, 2) px: origins (N, 3) mm and unit directions (N, 3)."""
        p = as_points(uv, 2, "uv")
        h = np.concatenate([p, np.ones((len(p), 1))], axis=1)
        # convention: C is scaled so that points in front of the camera have H_c > 0 (eq. 1);
        # then M^-1 (u, v, 1) points forward, whatever the handedness of the target frame
        d = np.linalg.solve(self.C[:, :3], h.T).T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.centre, d.shape).copy(), d

    def to_dict(self) -> dict[str, Any]:
        return {"model": "matrix", "C": self.C.tolist(), "image_size": list(self.image_size)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MatrixCamera:
        try:
            return cls(C=np.array(d["C"], dtype=float), image_size=tuple(d["image_size"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise MultislitError(f"malformed matrix camera: {exc!r}") from exc

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, s: str) -> MatrixCamera:
        return cls.from_dict(json.loads(s))


def camera_from_dict(d: dict[str, Any]) -> PinholeCamera | MatrixCamera:
    """Load either camera model from its ``to_dict`` form (by its ``model`` key)."""
    model = d.get("model")
    if model == "pinhole":
        return PinholeCamera.from_dict(d)
    if model == "matrix":
        return MatrixCamera.from_dict(d)
    raise MultislitError(f"unknown camera model {model!r} (expected 'pinhole' or 'matrix')")
