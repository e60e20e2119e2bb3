"""The rig calibration and its ``multislit-calibration/1`` JSON file.

:class:`Calibration` holds the camera (the paper's DLT matrix and the refined pinhole camera
with distortion), the projector (the paper's 2x4 matrix and our per-slit planes) and the
markers' residuals, and reads and writes them as JSON.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from multislit.calibrate.projector import ProjectorMatrix
from multislit.calibrate.slit_planes import SlitPlanes
from multislit.errors import CalibrationError, MultislitError
from multislit.geometry import MatrixCamera, PinholeCamera, camera_from_dict
from multislit.geometry.camera import F64
from multislit.geometry.dots import DotProjector
from multislit.io import json_safe, parse_json, read_json, write_text_atomic
from multislit.io.paths import as_path
from multislit.summaries import Summarised

#: The schema name of the calibration JSON.
SCHEMA = "multislit-calibration/1"


@dataclass(frozen=True, eq=False, repr=False)
class Calibration(Summarised):
    """A complete rig calibration (``multislit-calibration/1``).

    Attributes
    ----------
    image_size : (W, H) int, px
    dlt : MatrixCamera, the paper's camera matrix C
    refined : PinholeCamera with distortion, or None
    projector : ProjectorMatrix (the paper's 2x4 model), or None
    slit_planes : SlitPlanes (our per-slit model), or None
    camera_rms_px : float, px, reprojection RMS of :attr:`camera` on the markers
    dlt_rms_px : float, px, reprojection RMS of the DLT on the markers
    marker_ids : tuple of str, (M,), markers used
    marker_residuals_px : (M,) float64, px, reprojection distance of :attr:`camera` per marker
    dot_projector : DotProjector (the dot source and one ray per dot), or None
    """

    image_size: tuple[int, int]
    dlt: MatrixCamera
    refined: PinholeCamera | None = None
    projector: ProjectorMatrix | None = None
    slit_planes: SlitPlanes | None = None
    camera_rms_px: float = float("nan")
    dlt_rms_px: float = float("nan")
    marker_ids: tuple[str, ...] = ()
    marker_residuals_px: F64 = field(default_factory=lambda: np.zeros(0))
    dot_projector: DotProjector | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "image_size", (int(self.image_size[0]), int(self.image_size[1])))
        object.__setattr__(self, "marker_ids", tuple(str(i) for i in self.marker_ids))
        r = np.asarray(self.marker_residuals_px, dtype=float).reshape(-1)
        if len(r) != len(self.marker_ids):
            raise CalibrationError(
                f"marker_residuals_px has {len(r)} values but marker_ids has {len(self.marker_ids)}"
            )
        object.__setattr__(self, "marker_residuals_px", r)

    @property
    def camera(self) -> PinholeCamera | MatrixCamera:
        """The refined camera if present, else the DLT camera."""
        return self.refined if self.refined is not None else self.dlt

    def summary(self) -> str:
        """One line: image size, camera model and residual, slit planes."""
        w, h = self.image_size
        model = "pinhole with distortion" if self.refined is not None else "DLT matrix"
        planes = "no slit planes"
        if self.slit_planes is not None:
            p = self.slit_planes.planes
            ok = np.isfinite(p).all(axis=1)
            rms = self.slit_rms_mm[ok]
            median = f", RMS median {np.median(rms):.4f} mm" if rms.size else ""
            planes = f"{int(ok.sum())} of {len(p)} slit planes{median}"
        return (
            f"{w}x{h} px, camera {model} (RMS {self.camera_rms_px:.3f} px on "
            f"{len(self.marker_ids)} markers), {planes}"
        )

    @property
    def slit_rms_mm(self) -> F64:
        """(K,) float64, mm, per-slit plane RMS (empty without slit planes)."""
        return np.zeros(0) if self.slit_planes is None else self.slit_planes.rms_mm

    def check_image_size(self, size: tuple[int, int]) -> None:
        """Raise :class:`CalibrationError` if ``size`` (W, H) differs from the calibration's."""
        w, h = int(size[0]), int(size[1])
        if (w, h) != self.image_size:
            raise CalibrationError(
                f"the images are {w}x{h} px but the calibration was made for "
                f"{self.image_size[0]}x{self.image_size[1]} px; recalibrate with this camera "
                "setting or use images of the calibrated size"
            )

    def to_dict(self) -> dict[str, Any]:
        """The calibration as plain JSON values (NaN as None)."""
        return {
            "schema": SCHEMA,
            "units": {"length": "mm", "image": "px", "angle": "rad"},
            "image_size": list(self.image_size),
            "camera_dlt": self.dlt.to_dict(),
            "camera_refined": None if self.refined is None else self.refined.to_dict(),
            "projector_matrix": None if self.projector is None else self.projector.to_dict(),
            "slit_planes": None if self.slit_planes is None else self.slit_planes.to_dict(),
            "dot_projector": None if self.dot_projector is None else self.dot_projector.to_dict(),
            "residuals": {
                "camera_rms_px": json_safe(float(self.camera_rms_px)),
                "dlt_rms_px": json_safe(float(self.dlt_rms_px)),
                "markers_px": {
                    i: json_safe(float(r))
                    for i, r in zip(self.marker_ids, self.marker_residuals_px, strict=True)
                },
            },
        }

    def to_json(self) -> str:
        """The calibration as ``multislit-calibration/1`` JSON text."""
        return json.dumps(self.to_dict(), indent=1, allow_nan=False)

    @classmethod
    def from_dict(cls, d: Any) -> Calibration:
        """Read :meth:`to_dict`'s output; :class:`CalibrationError` naming the bad key if malformed.

        Every number is checked (finite, of the right shape); slit planes must have unit
        normals (rows of null for slits without a plane) and at least one slit a plane.
        """
        if not isinstance(d, dict):
            raise CalibrationError("calibration JSON must be an object")
        schema = d.get("schema")
        if schema != SCHEMA:
            raise CalibrationError(
                f"calibration schema is {_short(schema)}; this version reads {SCHEMA!r} "
                "(recalibrate, or convert the file)"
            )
        size = _image_size(_get(d, "image_size", "image_size"), "image_size")
        dlt_d = _get(d, "camera_dlt", "camera_dlt")
        _check_camera_dict(dlt_d, "matrix", "camera_dlt")
        ref = d.get("camera_refined")
        if ref is not None:
            _check_camera_dict(ref, "pinhole", "camera_refined")
        pm = d.get("projector_matrix")
        if pm is not None:
            if not isinstance(pm, dict):
                raise CalibrationError("projector_matrix must be an object or null")
            _numbers(_get(pm, "P", "projector_matrix.P"), "projector_matrix.P", (2, 4))
            _numbers(
                _get(pm, "xp_values", "projector_matrix.xp_values"),
                "projector_matrix.xp_values",
                (-1,),
            )
        sp = d.get("slit_planes")
        if sp is not None:
            _check_slit_planes(sp)
        dots = d.get("dot_projector")
        dot_projector = None if dots is None else DotProjector.from_dict(dots)
        res = d.get("residuals")
        if res is None:
            res = {}
        if not isinstance(res, dict):
            raise CalibrationError("residuals must be an object")
        markers = res.get("markers_px")
        if markers is None:
            markers = {}
        if not isinstance(markers, dict):
            raise CalibrationError("residuals.markers_px must be an object (marker id -> px)")
        rms = {k: _number(res.get(k), f"residuals.{k}", null=True) for k in _RMS_KEYS}
        mres = [
            _number(v, f"residuals.markers_px[{_short(k)}]", null=True) for k, v in markers.items()
        ]
        try:
            return cls(
                image_size=size,
                dlt=camera_from_dict(dlt_d),
                refined=None if ref is None else camera_from_dict(ref),
                projector=None if pm is None else ProjectorMatrix.from_dict(pm),
                slit_planes=None if sp is None else SlitPlanes.from_dict(sp),
                camera_rms_px=rms["camera_rms_px"],
                dlt_rms_px=rms["dlt_rms_px"],
                marker_ids=tuple(markers),
                marker_residuals_px=np.array(mres, dtype=float),
                dot_projector=dot_projector,
            )
        except CalibrationError:
            raise
        except MultislitError as exc:
            raise CalibrationError(f"malformed calibration: {exc}") from None
        except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
            raise CalibrationError(f"malformed calibration: missing or bad {exc!r}") from None

    @classmethod
    def from_json(cls, s: str | bytes) -> Calibration:
        """Read :meth:`to_json`'s output (text, or UTF-8 bytes); :class:`CalibrationError` if
        malformed."""
        return cls.from_dict(parse_json(s, where="calibration", error=CalibrationError))

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON, whole or not at all (folders are created).

        Returns the path.
        """
        return write_text_atomic(path, self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration JSON file written by :meth:`save`."""
        p = as_path(path, "calibration file", error=CalibrationError)
        if not p.is_file():
            raise CalibrationError(
                f"calibration file not found: {p}; run the calibration first or fix the path"
            )
        d = read_json(p, what="calibration file", error=CalibrationError)
        try:
            return cls.from_dict(d)
        except CalibrationError as exc:
            raise CalibrationError(f"{p}: {exc}") from None


# --------------------------------------------------------------------------- reading checks
#: The residual keys of the file, px.
_RMS_KEYS = ("camera_rms_px", "dlt_rms_px")

#: A slit plane's normal may differ from unit length by this much (the file stores float64).
_UNIT_TOLERANCE = 1e-6

#: Largest component of a camera's rotation vector, rad (a rotation needs at most pi).
_MAX_RVEC = 100.0

#: Largest image side, px.
_MAX_IMAGE_SIDE = 100_000


def _short(v: Any, limit: int = 60) -> str:
    """``repr(v)`` cut to ``limit`` characters, for messages."""
    r = repr(v)
    return r if len(r) <= limit else r[: limit - 3] + "..."


def _get(d: dict[str, Any], key: str, where: str) -> Any:
    if key not in d:
        raise CalibrationError(f"malformed calibration: missing {where!r}")
    return d[key]


def _number(v: Any, where: str, *, null: bool = False) -> float:
    """``v`` as a finite float (None -> NaN if ``null``), else :class:`CalibrationError`."""
    if v is None and null:
        return float("nan")
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise CalibrationError(
            f"{where} must be a number{' or null' if null else ''}, got {_short(v)}"
        )
    try:
        x = float(v)
    except OverflowError:
        x = float("inf")
    if not math.isfinite(x):
        raise CalibrationError(f"{where} must be finite, got {_short(v)}")
    return x


def _numbers(v: Any, where: str, shape: tuple[int, ...], *, null: bool = False) -> F64:
    """A nested list of finite numbers of ``shape`` (-1: any length) as float64.

    With ``null``, None entries become NaN.
    """
    if len(shape) == 0:
        return np.array(_number(v, where, null=null))
    if not isinstance(v, list) or (shape[0] >= 0 and len(v) != shape[0]):
        n = "a list" if shape[0] < 0 else f"a list of {shape[0]}"
        raise CalibrationError(f"{where} must be {n} (shape {shape}), got {_short(v)}")
    rows = [_numbers(x, f"{where}[{i}]", shape[1:], null=null) for i, x in enumerate(v)]
    return np.array(rows, dtype=float).reshape((len(v), *shape[1:]))


def _image_size(v: Any, where: str) -> tuple[int, int]:
    if (
        not isinstance(v, list)
        or len(v) != 2
        or not all(
            isinstance(x, int) and not isinstance(x, bool) and 0 < x <= _MAX_IMAGE_SIDE for x in v
        )
    ):
        raise CalibrationError(f"{where} must be [W, H] in px, got {_short(v)}")
    return int(v[0]), int(v[1])


def _check_camera_dict(c: Any, model: str, where: str) -> None:
    """Check a camera's JSON before it is built: its model, numbers and image size."""
    if not isinstance(c, dict):
        raise CalibrationError(f"{where} must be an object")
    if c.get("model") != model:
        raise CalibrationError(
            f"{where} must be a {model!r} camera, got model {_short(c.get('model'))}"
        )
    _image_size(c.get("image_size"), f"{where}.image_size")
    if model == "matrix":
        C = _numbers(_get(c, "C", f"{where}.C"), f"{where}.C", (3, 4))
        with np.errstate(all="ignore"):
            det = np.linalg.det(C[:, :3])
        if not abs(det) >= 1e-300:
            raise CalibrationError(f"{where}.C is degenerate (its left 3x3 block is singular)")
        return
    for k in ("fx", "fy"):
        if _number(_get(c, k, f"{where}.{k}"), f"{where}.{k}") <= 0:
            raise CalibrationError(f"{where}.{k} must be positive, got {c[k]!r}")
    for k in ("cx", "cy"):
        _number(_get(c, k, f"{where}.{k}"), f"{where}.{k}")
    for k in ("rvec", "tvec"):
        if k in c:
            _numbers(c[k], f"{where}.{k}", (3,))
    if "rvec" in c and not np.all(np.abs(np.asarray(c["rvec"], dtype=float)) <= _MAX_RVEC):
        raise CalibrationError(
            f"{where}.rvec must be a rotation vector (radians, each within +-{_MAX_RVEC:g}), "
            f"got {_short(c['rvec'])}"
        )
    if "dist" in c:
        _numbers(c["dist"], f"{where}.dist", (-1,))


def _check_slit_planes(sp: Any) -> None:
    """Check the ``slit_planes`` JSON: unit normals or null rows, at least one plane, and the
    per-slit arrays of the same length."""
    where = "slit_planes"
    if not isinstance(sp, dict):
        raise CalibrationError(f"{where} must be an object or null")
    planes = _numbers(_get(sp, "planes", f"{where}.planes"), f"{where}.planes", (-1, 4), null=True)
    k = len(planes)
    finite = np.isfinite(planes)
    partial = np.flatnonzero(finite.any(axis=1) & ~finite.all(axis=1))
    if len(partial):
        raise CalibrationError(
            f"{where}.planes[{partial[0]}] mixes numbers and nulls; a slit without a plane has "
            "a row of four nulls"
        )
    valid = finite.all(axis=1)
    if not valid.any():
        raise CalibrationError(
            f"{where}: no slit has a plane ({k} rows of nulls); recalibrate (multislit calibrate)"
        )
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(planes[valid, :3], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _UNIT_TOLERANCE)
    if len(bad):
        j = int(np.flatnonzero(valid)[bad[0]])
        raise CalibrationError(
            f"{where}.planes[{j}] has a normal of length {norms[bad[0]]:.6g}; slit planes are "
            "n.X + d = 0 with |n| = 1 (recalibrate, or divide the row by |n|)"
        )
    _numbers(_get(sp, "rms_mm", f"{where}.rms_mm"), f"{where}.rms_mm", (k,), null=True)
    counts = _get(sp, "counts", f"{where}.counts")
    if (
        not isinstance(counts, list)
        or len(counts) != k
        or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in counts)
    ):
        raise CalibrationError(f"{where}.counts must be {k} non-negative integers")
    for key in ("axis_point", "axis_direction"):
        if sp.get(key) is not None:
            a = _numbers(sp[key], f"{where}.{key}", (3,))
            with np.errstate(over="ignore"):
                n = np.linalg.norm(a)
            if key == "axis_direction" and not abs(n - 1.0) <= _UNIT_TOLERANCE:
                raise CalibrationError(f"{where}.axis_direction must be a unit vector")
    excluded = sp.get("excluded", [])
    if not isinstance(excluded, list) or not all(
        isinstance(e, list) and len(e) == 2 and _slit_number(e[0], k) and isinstance(e[1], str)
        for e in excluded
    ):
        raise CalibrationError(f"{where}.excluded must be a list of [slit, reason]")
    from_axis = sp.get("from_axis", [])
    if not isinstance(from_axis, list) or not all(_slit_number(j, k) for j in from_axis):
        raise CalibrationError(f"{where}.from_axis must be a list of slit numbers 0..{k - 1}")


def _slit_number(j: Any, k: int) -> bool:
    return isinstance(j, int) and not isinstance(j, bool) and 0 <= j < k
