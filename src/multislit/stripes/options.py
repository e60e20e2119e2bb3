"""The stripe extraction's options a user decides: one frozen, validated value.

:class:`ExtractionOptions` holds what :func:`~multislit.stripes.extract_slits` takes from a
user (the colour plane, the photo mode, the sub-pixel method, the detection threshold, the
shortest segment); the scan's options (:class:`~multislit.reconstruct.ScanOptions`) carry it
from the command line and an options file to every scan. Internal thresholds stay private
constants of their modules.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

from multislit.stripes.centres import CENTRE_METHODS, DEFAULT_K_SIGMA
from multislit.stripes.chains import DEFAULT_MIN_LENGTH
from multislit.stripes.validation import CHANNEL_CHOICES, SlitExtractionError

__all__ = ["ExtractionOptions", "check_fields"]


def check_fields(cls: type, d: Any, where: str, error: type[ValueError]) -> dict[str, Any]:
    """``d`` as keyword arguments of the dataclass ``cls``: a dict whose keys are its fields
    (unknown keys named in one ``error`` line, with the known ones)."""
    if not isinstance(d, dict):
        raise error(f"{where} must be a JSON object of options, got {type(d).__name__}")
    names = [f.name for f in fields(cls)]
    unknown = [k for k in d if k not in names]
    if unknown:
        raise error(
            f"{where}: unknown option(s) {', '.join(map(repr, unknown))}; the options are "
            f"{', '.join(names)}"
        )
    return dict(d)


def _real(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


@dataclass(frozen=True)
class ExtractionOptions:
    """How the stripes are extracted (:func:`~multislit.stripes.extract_slits`).

    Attributes
    ----------
    channel : {'auto', 'red', 'green', 'blue', 'luma'} or None
        The plane of colour images. ``"auto"``: in each image the plane in which the stripes
        stand out most above their background, clipped planes avoided. None (default): the
        capture's ``laser_channel`` (rig.json) where there is a capture, else ``"auto"``.
    reject_texture : bool
        The photo mode: only centres that look like a laser line (for photos of a line on a
        checkerboard, a turntable, a textured object). Default False.
    method : {'gaussian', 'parabolic', 'centroid', 'steger'}
        The sub-pixel centre of each row's stripe. Default ``"gaussian"``.
    k_sigma : float, noise sigmas
        Detection threshold: a stripe's peak stands this many noise sigmas above the
        background (the noise is at least one quantisation step of the data), or the stripe
        integrated along itself (the ridge response) stands 0.75 times as many sigmas of its
        own noise above it. Default 8.
    min_length : int, rows
        The fewest centre points of a kept segment (twice as many for a stripe found along
        the columns). Default 10.
    leaning : bool
        Find the stripes that lean towards the horizontal too, along the image's columns (the
        tops of boxes; :mod:`~multislit.stripes.ridges`). Default True; False finds the
        stripes up to about 56 degrees from the vertical only, in less time.

    Raises
    ------
    SlitExtractionError
        (a ``ValueError``) naming the option, for a value of the wrong type or out of range.
    """

    channel: str | None = None
    reject_texture: bool = False
    method: str = CENTRE_METHODS[0]
    k_sigma: float = DEFAULT_K_SIGMA
    min_length: int = DEFAULT_MIN_LENGTH
    leaning: bool = True

    def __post_init__(self) -> None:
        where = "extraction"
        if self.channel is not None and self.channel not in CHANNEL_CHOICES:
            raise SlitExtractionError(
                f"{where}.channel must be one of {', '.join(CHANNEL_CHOICES)}, got {self.channel!r}"
            )
        if not isinstance(self.reject_texture, bool):
            raise SlitExtractionError(
                f"{where}.reject_texture must be true or false, got {self.reject_texture!r}"
            )
        if self.method not in CENTRE_METHODS:
            raise SlitExtractionError(
                f"{where}.method must be one of {', '.join(CENTRE_METHODS)}, got {self.method!r}"
            )
        if not _real(self.k_sigma) or not math.isfinite(self.k_sigma) or self.k_sigma <= 0:
            raise SlitExtractionError(
                f"{where}.k_sigma must be a positive number of noise sigmas, got {self.k_sigma!r}"
            )
        object.__setattr__(self, "k_sigma", float(self.k_sigma))
        if isinstance(self.min_length, bool) or not isinstance(self.min_length, int):
            raise SlitExtractionError(
                f"{where}.min_length must be an integer number of rows, got {self.min_length!r}"
            )
        if self.min_length < 1:
            raise SlitExtractionError(f"{where}.min_length must be >= 1, got {self.min_length}")
        if not isinstance(self.leaning, bool):
            raise SlitExtractionError(
                f"{where}.leaning must be true or false, got {self.leaning!r}"
            )

    def kwargs(self, channel: str | None = None) -> dict[str, Any]:
        """The keyword arguments of :func:`~multislit.stripes.extract_slits`; ``channel``
        stands in where :attr:`channel` is None."""
        d = asdict(self)
        d["channel"] = self.channel if self.channel is not None else channel
        return d

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON values."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any, where: str = "extraction") -> ExtractionOptions:
        """The options of a JSON object (missing keys keep their defaults)."""
        return cls(**check_fields(cls, d, where, SlitExtractionError))
