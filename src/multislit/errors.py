"""Exceptions raised by multislit.

Every error the library raises on bad input derives from :class:`MultislitError` (a
:class:`ValueError`), so the CLI
can print its message and exit non-zero without a traceback.
"""


class MultislitError(ValueError):
    """Base class: bad input or a measurement that cannot be made. The message says what to fix."""


class CaptureError(MultislitError):
    """A capture folder (or one of its files) is missing, malformed or inconsistent."""


class CalibrationError(MultislitError):
    """Calibration cannot be computed from the given data (too few points, degenerate, ...)."""


class ReferenceImageError(MultislitError):
    """The reference images do not give a usable set of reference lines."""


class IdentificationError(MultislitError):
    """Slit identification cannot run on the given input."""


class MeasurementError(MultislitError):
    """A measurement (scan, hole fit, ...) cannot be made from the given data."""
