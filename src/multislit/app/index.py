"""The OUT folder of ``multislit stream`` and ``batch``: its file names and its index.

::

    OUT/frame_000000.ply   one PLY per frame
    OUT/frame_000000.png   its picture (with --pictures): the points on the frame
    OUT/frames.jsonl       one JSON object per line and frame: frame, source, points, slits,
                           ms, and message where the scan left a note (e.g. why no points)
    OUT/run.json           how the run was made (written by stream and batch)

:func:`read_index` is the strict reader of ``frames.jsonl``: any line that is not a frame
record (not UTF-8, not JSON, a frame number that is not a non-negative integer) is one
:class:`~multislit.errors.MeasurementError` line naming the file and the line.
"""

from __future__ import annotations

import os
from typing import Any

from multislit.errors import MeasurementError, MultislitError
from multislit.io import parse_json
from multislit.io.paths import as_path, is_regular_file

__all__ = ["INDEX_FILE", "RUN_FILE", "RUN_FORMAT", "frame_file", "picture_file", "read_index"]

#: The index of an OUT folder.
INDEX_FILE = "frames.jsonl"
#: How a run was made (options, capture, source), beside the index.
RUN_FILE = "run.json"
#: The format of ``run.json``.
RUN_FORMAT = "multislit-run/1"
#: The largest index read, bytes (about ten million frames).
_MAX_INDEX_BYTES = 2**30


def frame_file(frame: int) -> str:
    """The PLY file name of output frame ``frame``: ``frame_000000.ply``."""
    return f"frame_{frame:06d}.ply"


def picture_file(frame: int) -> str:
    """The picture's file name of output frame ``frame``: ``frame_000000.png``."""
    return f"frame_{frame:06d}.png"


def read_index(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The frame records of a ``frames.jsonl`` file, in file order.

    Returns
    -------
    list of dict, each with ``frame`` (int >= 0) and ``source`` (str, '' if absent) and the
    line's other keys as they are

    Raises
    ------
    MeasurementError
        A missing or unreadable file, or a line that is not a frame record (the line named).
    """
    p = as_path(path, "index", error=MeasurementError)
    if not is_regular_file(p):
        raise MeasurementError(f"{p}: not a file" if p.exists() else f"{p}: no such index file")
    if p.stat().st_size > _MAX_INDEX_BYTES:
        raise MeasurementError(f"{p}: larger than {_MAX_INDEX_BYTES >> 20} MB; not an index")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MeasurementError(f"cannot read {p}: {exc.strerror or exc}") from None
    out = []
    for n, line in enumerate(data.splitlines(), 1):
        if not line.strip():
            continue
        try:
            d = parse_json(line, where=f"{p} line {n}", error=MeasurementError)
        except MultislitError as exc:
            raise MeasurementError(str(exc)) from None
        frame = d.get("frame") if isinstance(d, dict) else None
        source = d.get("source", "") if isinstance(d, dict) else None
        if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
            raise MeasurementError(
                f"{p}: line {n} is not a frame record (no frame number >= 0: {line[:60]!r})"
            )
        if not isinstance(source, str):
            raise MeasurementError(f"{p}: line {n}: 'source' must be text, got {source!r:.60}")
        out.append({**d, "frame": frame, "source": source})
    return out
