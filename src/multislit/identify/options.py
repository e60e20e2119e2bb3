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

__all__ = ["IdentifyOptions"]


@dataclass(frozen=True)
class IdentifyOptions:
    """How the slits are identified (:func:`~multislit.identify.identify`).

    Attributes
    ----------
    min_confidence : float, 0..1
        A segment whose dots give its best slit a confidence below this is not labelled by
        its dots alone. Default 0.30.

    Raises
    ------
    IdentificationError
        (a ``ValueError``) naming the option, for a value of the wrong type or out of range.
    """

    min_confidence: float = 0.30

    def __post_init__(self) -> None:
        x = self.min_confidence
        if isinstance(x, bool) or not isinstance(x, int | float) or not 0.0 <= x <= 1.0:
            raise IdentificationError(
                f"identification.min_confidence must be a number in [0, 1], got {x!r}"
            )
        if math.isnan(x):  # pragma: no cover - the range check catches NaN
            raise IdentificationError("identification.min_confidence is NaN")
        object.__setattr__(self, "min_confidence", float(x))

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON values."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any, where: str = "identification") -> IdentifyOptions:
        """The options of a JSON object (missing keys keep their defaults)."""
        return cls(**check_fields(cls, d, where, IdentificationError))
