"""JSON and file writing shared by every module that saves results.

:func:`json_safe` turns a result (dicts, lists, NumPy scalars, NaN) into plain JSON values;
:func:`write_text_atomic` and :func:`write_json` write a file whole or not at all (a temporary
file in the same folder, then a rename), so an interrupted write never leaves a truncated file
in place of a good one.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["json_safe", "write_text_atomic", "write_bytes_atomic", "write_json"]


def json_safe(x: Any) -> Any:
    """``x`` with NaN and infinities as None, NumPy scalars as Python numbers, tuples as lists.

    Dicts and lists are converted recursively; other values are returned unchanged.
    """
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_safe(v) for v in x]
    return x


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all; create the folder if needed.

    The bytes go to a temporary file beside ``path``, which is then renamed over it.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` whole or not at all; see :func:`write_bytes_atomic`."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike[str], obj: Any, *, indent: int | None = 1) -> Path:
    """Write ``json_safe(obj)`` as JSON to ``path``, whole or not at all.

    Parameters
    ----------
    path : the file to write (its folder is created if needed)
    obj : dicts, lists, numbers and strings; NaN becomes null
    indent : JSON indentation (None: one line). Default 1.
    """
    return write_text_atomic(path, json.dumps(json_safe(obj), indent=indent) + "\n")
