"""Path arguments: the one check of a file or folder argument, and of an output folder.

:func:`as_path` turns a path argument into a :class:`~pathlib.Path` or says in one line what
is wrong with it (not a path, empty, a NUL character); :func:`check_output_dir` refuses an
output folder that cannot be made before any work starts; :func:`is_regular_file` tells a
file from a device, a FIFO or a folder, so that no reader waits on a pipe or reads a device
without end.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from multislit.errors import MultislitError

__all__ = ["as_path", "check_output_dir", "is_regular_file", "ascii_line"]


def as_path(value: object, name: str, *, error: type[MultislitError] = MultislitError) -> Path:
    """``value`` as a Path, checked.

    Parameters
    ----------
    value : str or os.PathLike
    name : what the argument is, for the message (e.g. ``"path"``, ``"-o"``, ``"SOURCE"``)
    error : the exception raised; default MultislitError

    Raises
    ------
    error
        ``value`` is not a str or path-like object, is empty (which would mean the current
        folder) or holds a NUL character.
    """
    if isinstance(value, bytes):
        value = os.fsdecode(value)
    if not isinstance(value, str | os.PathLike):
        raise error(f"{name} must be a path (str or os.PathLike), got {type(value).__name__}")
    text = os.fspath(value)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if text == "":
        raise error(f"{name} is empty; give a file or folder name ('.' for the current folder)")
    if "\0" in text:
        raise error(f"{name} {text!r} contains a NUL character")
    return Path(text)


def check_output_dir(path: str | os.PathLike[str], option: str) -> Path:
    """Refuse an output folder that is a file or cannot be created (nothing is created here).

    Returns the folder as a Path; raises :class:`~multislit.errors.MultislitError` naming
    ``option`` (e.g. ``"-o"``).
    """
    p = as_path(path, option)
    if p.exists() and not p.is_dir():
        raise MultislitError(f"{option} {p} is a file, not a folder; give a folder")
    parent = p
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise MultislitError(f"{option} {p}: cannot create a folder under {parent}, a file")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise MultislitError(f"{option} {p}: cannot write in {parent} (permission denied)")
    return p


def is_regular_file(path: Path) -> bool:
    """True if ``path`` is a regular file (following links), not a folder, device or FIFO."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False


def ascii_line(text: str) -> str:
    """``text`` on one line in ASCII: non-ASCII characters (and undecodable file-name bytes)
    as backslash escapes, line breaks as spaces (for PLY headers, which are ASCII)."""
    one = " ".join(str(text).splitlines())
    return one.encode("ascii", "backslashreplace").decode("ascii")
