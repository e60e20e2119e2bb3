"""The rig calibration and its ``multislit-calibration/1`` JSON file.

:class:`Calibration` holds the camera (the paper's DLT matrix and the refined pinhole camera
with distortion), the projector (the paper's 2x4 matrix and our per-slit planes) and the
markers' residuals, and reads and writes them as JSON.

Units: mm in the world (target) frame, px in the image.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from multislit.calibrate.projector import ProjectorMatrix
from multislit.calibrate.slit_planes import SlitPlanes
from multislit.errors import CalibrationError, MultislitError
from multislit.geometry import MatrixCamera, PinholeCamera, camera_from_dict
from multislit.geometry.camera import F64
from multislit.io import json_safe, write_text_atomic

#: The schema name of the calibration JSON.
SCHEMA = "multislit-calibration/1"


@dataclass(frozen=True, eq=False)
class Calibration:
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
        """Read :meth:`to_dict`'s output; :class:`CalibrationError` if malformed."""
        if not isinstance(d, dict):
            raise CalibrationError("calibration JSON must be an object")
        schema = d.get("schema")
        if schema != SCHEMA:
            raise CalibrationError(
                f"calibration schema is {schema!r}; this version reads {SCHEMA!r} "
                "(recalibrate, or convert the file)"
            )
        try:
            dlt = camera_from_dict(d["camera_dlt"])
            if not isinstance(dlt, MatrixCamera):
                raise CalibrationError("camera_dlt must be a 'matrix' camera")
            ref = d.get("camera_refined")
            refined = None if ref is None else camera_from_dict(ref)
            if refined is not None and not isinstance(refined, PinholeCamera):
                raise CalibrationError("camera_refined must be a 'pinhole' camera")
            pm = d.get("projector_matrix")
            sp = d.get("slit_planes")
            res = d.get("residuals") or {}
            markers = res.get("markers_px") or {}

            def num(v: Any) -> float:
                return float("nan") if v is None else float(v)

            return cls(
                image_size=tuple(d["image_size"]),
                dlt=dlt,
                refined=refined,
                projector=None if pm is None else ProjectorMatrix.from_dict(pm),
                slit_planes=None if sp is None else SlitPlanes.from_dict(sp),
                camera_rms_px=num(res.get("camera_rms_px")),
                dlt_rms_px=num(res.get("dlt_rms_px")),
                marker_ids=tuple(markers),
                marker_residuals_px=np.array([num(v) for v in markers.values()]),
            )
        except MultislitError as exc:
            if isinstance(exc, CalibrationError):
                raise
            raise CalibrationError(f"malformed calibration: {exc}") from None
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise CalibrationError(f"malformed calibration: missing or bad {exc!r}") from None

    @classmethod
    def from_json(cls, s: str) -> Calibration:
        """Read :meth:`to_json`'s output; :class:`CalibrationError` if malformed."""
        try:
            d = json.loads(s)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"calibration is not valid JSON: {exc}") from None
        return cls.from_dict(d)

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON, whole or not at all (folders are created).

        Returns the path.
        """
        return write_text_atomic(path, self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration JSON file written by :meth:`save`."""
        p = Path(path)
        if not p.is_file():
            raise CalibrationError(
                f"calibration file not found: {p}; run the calibration first or fix the path"
            )
        try:
            return cls.from_json(p.read_text())
        except CalibrationError as exc:
            raise CalibrationError(f"{p}: {exc}") from None
