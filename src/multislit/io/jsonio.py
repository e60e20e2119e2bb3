"""JSON and file writing shared by every module that saves results.

:func:`json_safe` turns a result (dicts, lists, NumPy scalars, NaN) into plain JSON values;
:func:`write_text_atomic` and :func:`write_json` write a file whole or not at all (a temporary
file in the same folder, then a rename), so an interrupted write never leaves a truncated file
in place of a good one. :func:`read_json` reads a JSON file and turns every way it can be
unreadable (missing, not UTF-8, not JSON, nested too deeply) into one
:class:`~multislit.errors.MultislitError` line naming the file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from multislit.errors import MultislitError
from multislit.io.paths import as_path

__all__ = [
    "json_safe",
    "write_text_atomic",
    "write_bytes_atomic",
    "write_json",
    "read_json",
    "parse_json",
]


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


def _umask() -> int:
    """The process's umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all; create the folder if needed.

    The bytes go to a temporary file beside ``path``, which is then renamed over it. The file
    gets the permissions a plain ``open`` would give it (0666 less the umask).
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
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


def read_json(
    path: str | os.PathLike[str],
    *,
    what: str = "JSON file",
    error: type[MultislitError] = MultislitError,
) -> Any:
    """The parsed content of the JSON file ``path``.

    Parameters
    ----------
    path : the file to read
    what : str
        What the file is, for messages (e.g. ``"rig description"``). Default ``"JSON file"``.
    error : subclass of MultislitError
        The exception raised when the file cannot be read. Default MultislitError.

    Returns
    -------
    The JSON value (dicts, lists, str, int, float, bool, None); ``NaN`` and ``Infinity``
    literals are read as floats.

    Raises
    ------
    error
        One line naming the file: missing, unreadable, not UTF-8 text (with the byte offset),
        not valid JSON (with line and column), or nested or sized beyond what the JSON reader
        accepts.
    """
    p = as_path(path, what, error=error)
    if not p.is_file():
        raise error(f"{what} not found: {p}" if not p.exists() else f"{what} {p} is not a file")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise error(f"cannot read {what} {p}: {exc.strerror or exc}") from None
    return parse_json(data, where=f"{what} {p}", error=error)


def parse_json(
    data: bytes | str, *, where: str = "JSON text", error: type[MultislitError] = MultislitError
) -> Any:
    """Parse JSON ``data`` (UTF-8 bytes or text); see :func:`read_json` for the errors.

    ``where`` names the data in messages (default ``"JSON text"``).
    """
    if isinstance(data, bytes | bytearray):
        try:
            data = bytes(data).decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise error(
                f"{where} is not UTF-8 text (byte {exc.start}: 0x{exc.object[exc.start]:02x}); "
                "save it as UTF-8"
            ) from None
    try:
        return json.loads(data)
    except json.JSONDecodeError as exc:
        raise error(f"{where} is not valid JSON: {exc}") from None
    except RecursionError:
        raise error(f"{where}: JSON nested too deeply") from None
    except ValueError as exc:  # e.g. an integer with more digits than Python converts
        raise error(f"{where}: unreadable JSON value ({exc})") from None
