"""The identification's options a user decides: one frozen, validated value.

:class:`IdentifyOptions` travels in :class:`~multislit.reconstruct.ScanOptions` from the
command line and an options file to :func:`~multislit.identify.identify`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from multislit.errors import IdentificationError
from multislit.stripes.options import check_fields

__all__ = ["DEFAULT_MIN_CONFIDENCE", "METHODS", "IdentifyOptions"]

#: The identification methods: the dots' geometry (default), or the paper's template matching.
METHODS = ("geometry", "template")

#: Default ``min_confidence`` per method.
DEFAULT_MIN_CONFIDENCE = {"geometry": 0.98, "template": 0.30}


@dataclass(frozen=True)
class IdentifyOptions:
    """How the slits are identified (:func:`~multislit.identify.identify`).

    Attributes
    ----------
    method : str
        ``"geometry"`` (default): each piece of stripe is labelled by where the calibrated dot
        projector's rays must put the dots beside it under each slit, and by its neighbours
        (:mod:`~multislit.identify.geometric`); needs a calibration with a dot projector.
        ``"template"``: the paper's template matching of the dots with the reference images
        along the epipolar lines (:mod:`~multislit.identify.labelling`).
    min_confidence : float, 0..1, or None
        A piece is labelled when the confidence in its slit reaches this; None: the method's
        default (:data:`DEFAULT_MIN_CONFIDENCE`: 0.98 for geometry, where the confidence is
        the labelling's belief in the slit against every other slit; 0.30 for the template,
        where it is the margin of the dots' vote).
    depth_range : (near, far) or None
        mm, the camera depths (along its optical axis) a measured surface may have: slits that
        put a piece outside are ruled out (geometry only). None: 0.7 times the nearest and 1.35
        times the farthest reference board's depth.

    Raises
    ------
    IdentificationError
        (a ``ValueError``) naming the option, for a value of the wrong type or out of range.
    """

    method: str = "geometry"
    min_confidence: float | None = None
    depth_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise IdentificationError(
                f"identification.method must be one of {', '.join(METHODS)}, got {self.method!r}"
            )
        x = self.min_confidence
        if x is not None:
            if (
                isinstance(x, bool)
                or not isinstance(x, int | float)
                or not 0.0 <= x <= 1.0  # also NaN
            ):
                raise IdentificationError(
                    f"identification.min_confidence must be a number in [0, 1], got {x!r}"
                )
            object.__setattr__(self, "min_confidence", float(x))
        d = self.depth_range
        if d is not None:
            try:
                near, far = (float(v) for v in d)
                if isinstance(d, str | bytes):
                    raise TypeError
            except (TypeError, ValueError):
                raise IdentificationError(
                    f"identification.depth_range must be two depths [near, far] in mm, got {d!r}"
                ) from None
            if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
                raise IdentificationError(
                    f"identification.depth_range must be two depths 0 < near < far (mm), got {d!r}"
                )
            object.__setattr__(self, "depth_range", (near, far))

    @property
    def confidence(self) -> float:
        """The confidence required: ``min_confidence`` or the method's default."""
        if self.min_confidence is None:
            return DEFAULT_MIN_CONFIDENCE[self.method]
        return float(self.min_confidence)

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON values."""
        d = asdict(self)
        if self.depth_range is not None:
            d["depth_range"] = list(self.depth_range)
        return d

    @classmethod
    def from_dict(cls, d: Any, where: str = "identification") -> IdentifyOptions:
        """The options of a JSON object (missing keys keep their defaults)."""
        return cls(**check_fields(cls, d, where, IdentificationError))
