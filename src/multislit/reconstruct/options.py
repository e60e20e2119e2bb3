"""The scan's options: one frozen, validated value per stage, and :class:`ScanOptions` that
combines them.

::

    {"extraction": {"channel": "auto", "reject_texture": true},
     "identification": {"min_confidence": 0.3},
     "refinement": {"refine_centres": true, "min_angle_deg": 2.0}}

is an options file (``multislit scan|holes|stream|batch --options FILE.json``); keys left out
keep their defaults, unknown keys are refused. :func:`~multislit.scan_image`,
:func:`~multislit.scan_capture`, :func:`~multislit.measure_holes`, ``stream`` and ``batch``
take a :class:`ScanOptions`; what a run used is written into its output (``run.json``, the
PLY's header).
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from multislit.errors import MeasurementError, MultislitError
from multislit.identify.options import IdentifyOptions
from multislit.io import read_json
from multislit.reconstruct.triangulation import check_min_angle
from multislit.stripes.options import ExtractionOptions, check_fields

__all__ = ["RefineOptions", "ScanOptions"]


@dataclass(frozen=True)
class RefineOptions:
    """How the identified points become 3D points.

    Attributes
    ----------
    refine_centres : bool
        Re-centre the identified points for triangulation
        (:func:`~multislit.stripes.refine_centres`: Steger's centre on a smoothed
        background, fitted along the stripe); the slit numbers do not change. Default True.
    min_angle_deg : float, deg, 0 <= x < 90
        Lines of sight meeting a slit plane at a smaller angle are dropped. Default 2.0.
    dot_points : bool
        Also measure the dots the identification by the dots' geometry identified: each is
        where its line of sight crosses its dot's ray (:attr:`ScanResult.dots`), 3D points
        between the slits; written to the PLY after the stripe points, with ``dot`` = 1.
        Default False.

    Raises
    ------
    MeasurementError
        (a ``ValueError``) naming the option, for a value of the wrong type or out of range.
    """

    refine_centres: bool = True
    min_angle_deg: float = 2.0
    dot_points: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.dot_points, bool):
            raise MeasurementError(
                f"refinement.dot_points must be true or false, got {self.dot_points!r}"
            )
        if not isinstance(self.refine_centres, bool):
            raise MeasurementError(
                f"refinement.refine_centres must be true or false, got {self.refine_centres!r}"
            )
        try:
            angle = check_min_angle(self.min_angle_deg)
        except MultislitError as exc:
            raise MeasurementError(f"refinement.{exc}") from None
        object.__setattr__(self, "min_angle_deg", angle)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any, where: str = "refinement") -> RefineOptions:
        return cls(**check_fields(cls, d, where, MeasurementError))


@dataclass(frozen=True)
class ScanOptions:
    """Everything a user decides about a scan, stage by stage.

    Attributes
    ----------
    extraction : :class:`~multislit.stripes.ExtractionOptions` (channel, photo mode, ...)
    identification : :class:`~multislit.identify.IdentifyOptions`
    refinement : :class:`RefineOptions`
    """

    extraction: ExtractionOptions = field(default_factory=ExtractionOptions)
    identification: IdentifyOptions = field(default_factory=IdentifyOptions)
    refinement: RefineOptions = field(default_factory=RefineOptions)

    def __post_init__(self) -> None:
        for name, cls in (
            ("extraction", ExtractionOptions),
            ("identification", IdentifyOptions),
            ("refinement", RefineOptions),
        ):
            if not isinstance(getattr(self, name), cls):
                raise MeasurementError(
                    f"ScanOptions.{name} must be a {cls.__name__}, got "
                    f"{type(getattr(self, name)).__name__}"
                )

    def to_dict(self) -> dict[str, Any]:
        """The options as a JSON object (the form of an options file)."""
        return {
            "extraction": self.extraction.to_dict(),
            "identification": self.identification.to_dict(),
            "refinement": self.refinement.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Any, where: str = "options") -> ScanOptions:
        """The options of a JSON object like :meth:`to_dict`'s (missing keys: defaults)."""
        d = check_fields(cls, d, where, MeasurementError)
        return cls(
            extraction=ExtractionOptions.from_dict(d.get("extraction", {}), f"{where}: extraction"),
            identification=IdentifyOptions.from_dict(
                d.get("identification", {}), f"{where}: identification"
            ),
            refinement=RefineOptions.from_dict(d.get("refinement", {}), f"{where}: refinement"),
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ScanOptions:
        """The options of an options file (JSON, see the module's text)."""
        data = read_json(path, what="options file", error=MeasurementError)
        return cls.from_dict(data, where=f"options file {os.fspath(path)}")

    def with_extraction(self, **changes: Any) -> ScanOptions:
        """A copy with the extraction's options ``changes`` (validated)."""
        return replace(self, extraction=replace(self.extraction, **changes))


def as_scan_options(options: object) -> ScanOptions:
    """``options`` if it is a ScanOptions, the defaults if None; else one clear line."""
    if options is None:
        return ScanOptions()
    if not isinstance(options, ScanOptions):
        raise MeasurementError(
            f"options must be a ScanOptions (multislit.reconstruct.ScanOptions), got "
            f"{type(options).__name__}"
        )
    return options
