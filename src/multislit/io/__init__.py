"""multislit.io."""

from multislit.io.capture import (
    FORMAT,
    MIN_REFERENCES,
    Capture,
    Face,
    Marker,
    SlitPoint,
    Target,
    laser_plane,
    read_image,
    write_image,
    write_rig_json,
)
from multislit.io.jsonio import (
    json_safe,
    parse_json,
    read_json,
    write_bytes_atomic,
    write_json,
    write_text_atomic,
)
from multislit.io.ply import (
    PLY_SCALAR_TYPES,
    read_ply,
    write_ply,
)

__all__ = [
    "json_safe",
    "parse_json",
    "read_json",
    "write_bytes_atomic",
    "write_json",
    "write_text_atomic",
    "FORMAT",
    "MIN_REFERENCES",
    "laser_plane",
    "read_image",
    "write_image",
    "Marker",
    "Face",
    "SlitPoint",
    "Target",
    "Capture",
    "write_rig_json",
    "PLY_SCALAR_TYPES",
    "write_ply",
    "read_ply",
]
