"""PLY point clouds: a writer for measured points and a strict reader of our own.

The writer stores one ``vertex`` element with the properties ``x y z`` (float32, mm, target
frame) and, when given, ``u v`` (float32, px), ``slit`` (int32, slit number, -1 = unidentified)
and ``confidence`` (float32), binary little-endian by default or ASCII.

The reader follows the PLY specification (http://paulbourke.net/dataformats/ply/): the three
formats ``ascii``, ``binary_little_endian`` and ``binary_big_endian``, the scalar types
``char uchar short ushort int uint float double`` and their aliases ``int8 uint8 int16 uint16
int32 uint32 float32 float64``. It returns the ``vertex`` element's scalar properties; elements
before ``vertex`` are skipped, elements after it are not read. Anything malformed (bad magic,
unknown keyword or type, list properties on ``vertex``, truncated or excess data, values that
do not fit the declared type) raises :class:`~multislit.errors.MultislitError` naming the file
and the problem.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from multislit import __version__
from multislit.errors import MultislitError
from multislit.geometry import as_points
from multislit.io.jsonio import write_bytes_atomic
from multislit.io.paths import as_path, ascii_line, is_regular_file

__all__ = ["write_ply", "read_ply", "PLY_SCALAR_TYPES"]

#: PLY scalar type name -> NumPy dtype character code (without byte order).
PLY_SCALAR_TYPES: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}

_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER_BYTES = 1 << 20


# --------------------------------------------------------------------------- writing
def _column(a: ArrayLike | None, n: int, name: str) -> NDArray | None:
    if a is None:
        return None
    arr = np.asarray(a)
    if arr.shape != (n,):
        raise MultislitError(f"{name} must have shape ({n},) like points, got {arr.shape}")
    return arr


def write_ply(
    path: str | os.PathLike[str],
    points: ArrayLike,
    *,
    u: ArrayLike | None = None,
    v: ArrayLike | None = None,
    slit: ArrayLike | None = None,
    confidence: ArrayLike | None = None,
    dot: ArrayLike | None = None,
    binary: bool = True,
    comment: str | Sequence[str] | None = None,
) -> None:
    """Write measured points as a PLY file.

    Parameters
    ----------
    path : str or path-like
        Output file in an existing folder (replaced whole, or left as it was if the write
        fails).
    points : (N, 3) float64, mm, target frame
        Must be finite. N may be 0.
    u, v : (N,) float, px, optional
        Image position of each point (written as float32).
    slit : (N,) int, optional
        Slit number of each point (-1 = unidentified), written as int32.
    confidence : (N,) float, optional
        Per-point confidence, written as float32.
    dot : (N,) bool, optional
        True for a point measured on an identified dot rather than on a stripe (written as
        uchar 1 / 0).
    binary : bool
        ``True`` (default): ``binary_little_endian``; ``False``: ``ascii``.
    comment : str or sequence of str, optional
        Extra single-line comments for the header; characters outside ASCII (a PLY header
        is ASCII) are written as backslash escapes (``\\xe9``).

    Raises
    ------
    MultislitError
        Bad shapes, non-finite points, non-integer or out-of-range slit numbers, a comment
        that is not a str or has a line break, a path that is not one, or the file cannot be
        written.
    """
    path = as_path(path, "path")
    extra = [comment] if isinstance(comment, str) else comment
    if extra is None:
        extra = []
    if not isinstance(extra, list | tuple) or not all(isinstance(c, str) for c in extra):
        raise MultislitError(
            f"comment must be a str or a list of str, got {type(comment).__name__}"
        )
    p = as_points(points, 3, "points")
    n = len(p)
    if not np.all(np.isfinite(p)):
        raise MultislitError("points must be finite (drop NaN/inf points before writing)")
    columns: list[tuple[str, str, NDArray]] = [
        ("x", "f4", p[:, 0]),
        ("y", "f4", p[:, 1]),
        ("z", "f4", p[:, 2]),
    ]
    for name, arr in (("u", u), ("v", v)):
        col = _column(arr, n, name)
        if col is not None:
            columns.append((name, "f4", col.astype(np.float64)))
    s = _column(slit, n, "slit")
    if s is not None:
        if s.dtype.kind == "f":
            if not np.all(np.isfinite(s)) or np.any(s != np.round(s)):
                raise MultislitError("slit must hold integer slit numbers")
        elif s.dtype.kind not in "iub":
            raise MultislitError(f"slit must hold integer slit numbers, got dtype {s.dtype}")
        info = np.iinfo(np.int32)
        if n and (s.min() < info.min or s.max() > info.max):
            raise MultislitError("slit numbers must fit in int32")
        columns.append(("slit", "i4", s.astype(np.int64)))
    c = _column(confidence, n, "confidence")
    if c is not None:
        columns.append(("confidence", "f4", c.astype(np.float64)))
    d = _column(dot, n, "dot")
    if d is not None:
        if d.dtype.kind not in "biu" or (n and not np.isin(d, (0, 1)).all()):
            raise MultislitError("dot must hold True/False (1/0) per point")
        columns.append(("dot", "u1", d.astype(np.int64)))

    comments = [f"multislit {__version__}: x y z mm target frame, u v px"]
    for line in extra:
        if "\n" in line or "\r" in line:
            raise MultislitError("comment must be a single line")
        comments.append(ascii_line(line))

    fmt = "binary_little_endian" if binary else "ascii"
    header = ["ply", f"format {fmt} 1.0"]
    header += [f"comment {c}" for c in comments]
    header.append(f"element vertex {n}")
    type_names = {"f4": "float", "i4": "int", "u1": "uchar"}
    header += [f"property {type_names[t]} {name}" for name, t, _ in columns]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode("ascii", errors="strict")

    data = [head]
    if binary:
        rec = np.empty(n, dtype=[(name, "<" + t) for name, t, _ in columns])
        for name, _, col in columns:
            rec[name] = col
        data.append(rec.tobytes())
    elif n:
        table = np.stack([col.astype(t).astype(np.float64) for _, t, col in columns], 1)
        # 9 significant digits round-trip float32 exactly; int32 is exact in float64
        fmts = ["%.9g" if t == "f4" else "%d" for _, t, _ in columns]
        buf = io.StringIO()
        np.savetxt(buf, table, fmt=fmts, delimiter=" ", newline="\n")
        data.append(buf.getvalue().encode("ascii"))
    try:
        if not Path(path).parent.is_dir():
            raise FileNotFoundError(f"no folder {os.fspath(Path(path).parent)!r}")
        write_bytes_atomic(path, b"".join(data))
    except OSError as exc:
        raise MultislitError(f"cannot write PLY file {os.fspath(path)!r}: {exc}") from exc


# --------------------------------------------------------------------------- reading
@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: tuple[tuple[str, str], ...]  # (name, dtype code) for scalars
    lists: tuple[str, ...]  # names of list properties


def _parse_header(text: str, where: str) -> tuple[str, list[_Element]]:
    lines = text.split("\n")
    if lines[0] != "ply":
        raise MultislitError(f"{where}: not a PLY file (first line must be 'ply')")
    fmt: str | None = None
    elements: list[dict] = []
    for lineno, raw in enumerate(lines[1:], start=2):
        words = raw.split()
        if not words:
            raise MultislitError(f"{where}: empty header line {lineno}")
        key = words[0]
        if key in ("comment", "obj_info"):
            continue
        if key == "format":
            if fmt is not None:
                raise MultislitError(f"{where}: second 'format' line at header line {lineno}")
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise MultislitError(
                    f"{where}: bad format line {raw!r} (expected 'format ascii|"
                    "binary_little_endian|binary_big_endian 1.0')"
                )
            fmt = words[1]
            continue
        if fmt is None:
            raise MultislitError(f"{where}: the 'format' line must come right after 'ply'")
        if key == "element":
            if len(words) != 3:
                raise MultislitError(f"{where}: bad element line {raw!r}")
            try:
                count = int(words[2])
            except ValueError:
                count = -1
            if count < 0:
                raise MultislitError(f"{where}: bad element count in {raw!r}")
            if any(e["name"] == words[1] for e in elements):
                raise MultislitError(f"{where}: element {words[1]!r} declared twice")
            elements.append({"name": words[1], "count": count, "props": [], "lists": []})
        elif key == "property":
            if not elements:
                raise MultislitError(f"{where}: property before any element: {raw!r}")
            el = elements[-1]
            if len(words) >= 2 and words[1] == "list":
                if (
                    len(words) != 5
                    or words[2] not in PLY_SCALAR_TYPES
                    or words[3] not in PLY_SCALAR_TYPES
                ):
                    raise MultislitError(f"{where}: bad list property line {raw!r}")
                name = words[4]
                el["lists"].append((name, words[2], words[3]))
            else:
                if len(words) != 3:
                    raise MultislitError(f"{where}: bad property line {raw!r}")
                if words[1] not in PLY_SCALAR_TYPES:
                    raise MultislitError(
                        f"{where}: unknown property type {words[1]!r} in {raw!r}; expected one "
                        f"of {', '.join(sorted(PLY_SCALAR_TYPES))}"
                    )
                name = words[2]
                el["props"].append((name, PLY_SCALAR_TYPES[words[1]]))
            names = [p[0] for p in el["props"]] + [p[0] for p in el["lists"]]
            if names.count(name) > 1:
                raise MultislitError(
                    f"{where}: property {name!r} declared twice in element {el['name']!r}"
                )
        else:
            raise MultislitError(f"{where}: unknown header keyword {key!r} on line {lineno}")
    if fmt is None:
        raise MultislitError(f"{where}: the header has no 'format' line")
    out = []
    for e in elements:
        out.append(
            _Element(e["name"], e["count"], tuple(e["props"]), tuple(n for n, *_ in e["lists"]))
        )
    return fmt, out


def read_ply(path: str | os.PathLike[str]) -> dict[str, NDArray]:
    """Read the ``vertex`` element of a PLY file.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    dict[str, ndarray]
        Property name -> (N,) array in the declared type (native byte order), in header order,
        e.g. ``x y z`` float32 mm for files from :func:`write_ply`. N may be 0.

    Raises
    ------
    MultislitError
        Missing or unreadable file, a path that is not a regular file (a folder, device or
        FIFO), bad magic, malformed header, no ``vertex`` element, list properties on
        ``vertex``, truncated or excess data, or values not of the declared type.
    """
    path = as_path(path, "path")
    where = f"PLY file {os.fspath(path)!r}"
    if path.exists() and not is_regular_file(path):
        raise MultislitError(f"{where} is not a regular file (a folder, device or pipe)")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise MultislitError(f"cannot read {where}: {exc}") from exc
    if not data.startswith(b"ply\n") and not data.startswith(b"ply\r\n"):
        raise MultislitError(f"{where}: not a PLY file (it must start with the line 'ply')")
    crlf = data.startswith(b"ply\r\n")
    eol = b"\r\n" if crlf else b"\n"
    marker = eol + b"end_header" + eol
    pos = data.find(marker, 0, _MAX_HEADER_BYTES)
    if pos < 0:
        raise MultislitError(f"{where}: no 'end_header' line (truncated or not a PLY header)")
    body_start = pos + len(marker)
    try:
        text = data[:pos].decode("ascii")
    except UnicodeDecodeError as exc:
        raise MultislitError(f"{where}: the header is not ASCII text") from exc
    if crlf:
        text = text.replace("\r\n", "\n")
    fmt, elements = _parse_header(text, where)

    idx = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if idx is None:
        raise MultislitError(f"{where}: no 'vertex' element")
    vertex = elements[idx]
    if vertex.lists:
        raise MultislitError(
            f"{where}: list properties on 'vertex' are not supported ({', '.join(vertex.lists)})"
        )
    if not vertex.properties:
        raise MultislitError(f"{where}: the 'vertex' element has no properties")
    before = elements[:idx]
    is_last = idx == len(elements) - 1
    body = data[body_start:]

    if fmt == "ascii":
        return _read_ascii(body, before, vertex, is_last, where)
    return _read_binary(body, _FORMATS[fmt], before, vertex, is_last, where)


def _read_binary(
    body: bytes, order: str, before: list[_Element], vertex: _Element, is_last: bool, where: str
) -> dict[str, NDArray]:
    offset = 0
    for e in before:
        if e.lists:
            raise MultislitError(
                f"{where}: cannot skip element {e.name!r} with list properties before 'vertex'"
            )
        offset += e.count * np.dtype([(n, order + t) for n, t in e.properties]).itemsize
    dt = np.dtype([(n, order + t) for n, t in vertex.properties])
    need = offset + vertex.count * dt.itemsize
    if len(body) < need:
        raise MultislitError(
            f"{where}: truncated data: {vertex.count} vertices need {need} bytes after the "
            f"header, found {len(body)}"
        )
    if is_last and len(body) > need:
        raise MultislitError(
            f"{where}: {len(body) - need} bytes of unexpected data after the last element"
        )
    rec = np.frombuffer(body, dtype=dt, count=vertex.count, offset=offset)
    return {n: rec[n].astype(np.dtype(t)) for n, t in vertex.properties}


def _read_ascii(
    body: bytes, before: list[_Element], vertex: _Element, is_last: bool, where: str
) -> dict[str, NDArray]:
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError as exc:
        raise MultislitError(f"{where}: ASCII PLY data contains non-ASCII bytes") from exc
    lines = text.replace("\r\n", "\n").split("\n")
    if lines and lines[-1] == "":
        lines.pop()  # the final newline
    skip = sum(e.count for e in before)
    n, k = vertex.count, len(vertex.properties)
    if len(lines) < skip + n:
        raise MultislitError(
            f"{where}: truncated data: expected {skip + n} data lines, found {len(lines)}"
        )
    rows = lines[skip : skip + n]
    if is_last and any(s.strip() for s in lines[skip + n :]):
        raise MultislitError(f"{where}: unexpected data lines after the last element")
    if n == 0:
        return {name: np.zeros(0, np.dtype(t)) for name, t in vertex.properties}
    tokens = "\n".join(rows).split()
    counts = np.fromiter((len(r.split()) for r in rows), dtype=np.int64, count=n)
    bad = np.flatnonzero(counts != k)
    if bad.size:
        i = int(bad[0])
        raise MultislitError(
            f"{where}: vertex line {i + 1} has {counts[i]} values, expected {k} ({rows[i]!r})"
        )
    try:
        table = np.array(tokens, dtype=np.float64).reshape(n, k)
    except ValueError as exc:
        raise MultislitError(f"{where}: non-numeric vertex value ({exc})") from exc
    out: dict[str, NDArray] = {}
    for j, (name, t) in enumerate(vertex.properties):
        col = table[:, j]
        dtype = np.dtype(t)
        if dtype.kind in "iu":
            info = np.iinfo(dtype)
            if (
                not np.all(np.isfinite(col))
                or np.any(col != np.round(col))
                or col.min() < info.min
                or col.max() > info.max
            ):
                raise MultislitError(
                    f"{where}: property {name!r} declared {dtype.name} holds values that are not "
                    f"{dtype.name} integers"
                )
        elif np.any(np.abs(col[np.isfinite(col)]) > np.finfo(dtype).max):
            raise MultislitError(
                f"{where}: property {name!r} declared {dtype.name} holds values beyond its range "
                f"(+-{np.finfo(dtype).max:.4g})"
            )
        out[name] = col.astype(dtype)
    return out
