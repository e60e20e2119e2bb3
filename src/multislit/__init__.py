"""multislit: single-shot 3D measurement with multiple slits and random dots."""

__version__ = "0.1.0"
