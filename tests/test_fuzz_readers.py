"""Fuzz tests of the file readers: rig.json / target.json (``Capture.open``), the calibration
file (``Calibration.load``), PLY files (``read_ply``) and the index of an OUT folder
(``frames.jsonl``, :func:`multislit.app.index.read_index`).

Hypothesis damages valid files (truncation, changed bytes, non-UTF-8 bytes, repeated or cut
spans, JSON values of any type in place of the file's, ASCII PLY values out of range) and
shrinks a failure to its smallest case. Each reader must either give a correct result or
raise a one-line ``MultislitError``: never another exception and never a warning.
"""

from __future__ import annotations

import json
import math
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from multislit.app.index import read_index
from multislit.app.stream import FrameResult, FrameWriter
from multislit.calibrate import Calibration
from multislit.errors import MultislitError
from multislit.io import Capture, read_ply, write_ply
from tests.test_calibration import _calibration

#: JSON values of every type, edge numbers and nesting: what replaces a value of a file.
_JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
    | st.sampled_from(["", "1e3", "\udc80", "x"]),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=12,
)

#: Tokens that replace a value of an ASCII PLY.
_PLY_TOKENS = st.sampled_from(
    [b"1e300", b"-1e39", b"nan", b"inf", b"-1", b"2.5", b"99999999999", b"x", b""]
) | st.binary(max_size=6)

#: Byte sequences that are not UTF-8.
_NOT_UTF8 = st.sampled_from([b"\xff", b"\xfe", b"\xc3", b"\x80", b"\xed\xa0\x80", b"\xc0\xaf"])


@st.composite
def damaged_bytes(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` damaged one of five ways: truncated, bytes changed, non-UTF-8 bytes inserted,
    a span repeated or a span cut out."""
    n = len(data)
    kind = draw(st.sampled_from(["truncate", "change", "insert", "repeat", "cut"]))
    if kind == "truncate":
        return data[: draw(st.integers(0, n - 1))]
    if kind == "change":
        b = bytearray(data)
        for i, x in draw(
            st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=5)
        ):
            b[i] = x
        return bytes(b)
    i = draw(st.integers(0, n))
    if kind == "insert":
        return data[:i] + draw(_NOT_UTF8 | st.binary(min_size=1, max_size=4)) + data[i:]
    if kind == "repeat":
        j = min(n, i + draw(st.integers(1, 40)))
        return data[:i] + data[i:j] * 2 + data[i:]
    j = draw(st.integers(i, n))
    return data[:i] + data[j:]


def _slots(o: object, parent: object, key: object, out: list[tuple[object, object]]) -> None:
    """Append (parent, key) of ``o`` and of every value inside it to ``out``."""
    out.append((parent, key))
    if isinstance(o, dict):
        for k, v in o.items():
            _slots(v, o, k, out)
    elif isinstance(o, list):
        for k, v in enumerate(o):
            _slots(v, o, k, out)


@st.composite
def damaged_json(draw: st.DrawFn, data: bytes) -> bytes:
    """JSON ``data`` with 1-3 values replaced by values of any type, or keys deleted."""
    obj = json.loads(data)
    for _ in range(draw(st.integers(1, 3))):
        slots: list[tuple[object, object]] = []
        _slots(obj, None, None, slots)
        parent, key = draw(st.sampled_from(slots))
        if parent is None:
            obj = draw(_JSON)
        elif isinstance(parent, dict) and draw(st.booleans()) and draw(st.booleans()):
            del parent[key]
        else:
            parent[key] = draw(_JSON)  # type: ignore[index]
    return json.dumps(obj).encode("utf-8", "surrogatepass")


@st.composite
def damaged_ply_values(draw: st.DrawFn, data: bytes) -> bytes:
    """An ASCII PLY with a few values replaced by odd tokens."""
    head, sep, body = data.partition(b"end_header\n")
    tokens = body.split(b" ")
    for _ in range(draw(st.integers(1, 3))):
        tokens[draw(st.integers(0, len(tokens) - 1))] = draw(_PLY_TOKENS)
    return head + sep + b" ".join(tokens)


def _outcome(read: Callable[[], object], check: Callable[[object], None]) -> str | None:
    """None if ``read`` gives a result that passes ``check`` or raises a one-line
    MultislitError; else what went wrong (exception type, message and where)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            result = read()
        except MultislitError as exc:
            msg = str(exc)
            return None if msg and "\n" not in msg else f"message not one line: {msg!r}"
        except Exception as exc:  # noqa: BLE001 - any other exception is the failure
            where = traceback.extract_tb(exc.__traceback__)[-1]
            return f"{type(exc).__name__}: {exc} (at {where.filename}:{where.lineno})"
    try:
        check(result)
    except AssertionError as exc:
        return f"wrong result: {exc}"
    return None


# --------------------------------------------------------------------------- the readers
@pytest.fixture(scope="module")
def originals(small_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """Valid files to damage: rig.json, target.json, a calibration, binary and ASCII PLY, an
    OUT folder's index."""
    tmp = tmp_path_factory.mktemp("fuzz_originals")
    rng = np.random.default_rng(3)
    n = 40
    cols = dict(
        u=rng.uniform(0, 640, n),
        v=rng.uniform(0, 512, n),
        slit=rng.integers(-1, 25, n),
        confidence=rng.random(n),
    )
    pts = rng.normal(0, 100, (n, 3))
    write_ply(tmp / "b.ply", pts, **cols)
    write_ply(tmp / "a.ply", pts, **cols, binary=False)
    w = FrameWriter(tmp / "out")
    for i, k in enumerate((3, 0, 5)):
        res = FrameResult(pts[:k], pts[:k, 0], pts[:k, 1], np.zeros(k, np.int64),
                          np.ones(k), 1, 12.5, "" if k else "no slits found in the image")  # fmt: skip
        w.write(f"img{i}.png", res)
    w.close()
    return {
        "rig": (small_capture / "rig.json").read_bytes(),
        "target": (small_capture / "target.json").read_bytes(),
        "calibration": _calibration().to_json().encode(),
        "binary_ply": (tmp / "b.ply").read_bytes(),
        "ascii_ply": (tmp / "a.ply").read_bytes(),
        "index": (tmp / "out" / "frames.jsonl").read_bytes(),
    }


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder for the damaged files, with a capture folder's reference images (listed by
    ``Capture.open``, not read)."""
    tmp = tmp_path_factory.mktemp("fuzz")
    (tmp / "cap" / "reference").mkdir(parents=True)
    for name in ("a.png", "b.png"):
        (tmp / "cap" / "reference" / name).write_bytes(b"")
    return tmp


def _check_capture(cap: object) -> None:
    assert isinstance(cap, Capture)
    w, h = cap.image_size
    assert isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0
    assert isinstance(cap.num_slits, int) and cap.num_slits >= 1
    if cap.target is not None:
        assert np.isfinite(cap.target.marker_xyz).all()
        for f in cap.target.faces:
            assert math.isclose(float(np.linalg.norm(f.plane[:3])), 1.0, rel_tol=1e-9)
        assert all(0 <= s.slit < cap.num_slits for s in cap.target.slit_points)


def _check_calibration(cal: object) -> None:
    assert isinstance(cal, Calibration)
    assert np.isfinite(cal.dlt.C).all()
    if cal.slit_planes is not None:
        p = cal.slit_planes.planes
        ok = np.isfinite(p).all(axis=1)
        assert ok.any() and np.allclose(np.linalg.norm(p[ok, :3], axis=1), 1.0, atol=1e-6)
    # what was read can be written and read back unchanged
    assert Calibration.from_json(cal.to_json()).to_json() == cal.to_json()


def _check_ply(d: object) -> None:
    assert isinstance(d, dict) and d
    assert len({len(v) for v in d.values()}) == 1, {k: len(v) for k, v in d.items()}


def _check_index(lines: object) -> None:
    assert isinstance(lines, list)
    for d in lines:
        assert isinstance(d, dict)
        assert isinstance(d["frame"], int) and not isinstance(d["frame"], bool)
        assert d["frame"] >= 0 and isinstance(d["source"], str)


#: The readers fuzzed, by the original file they read.
READERS = ("rig", "target", "calibration", "binary_ply", "ascii_ply", "index")


def _damaged(key: str, data: bytes) -> st.SearchStrategy[bytes]:
    """How the file ``key`` is damaged: its bytes, and its values by their own syntax."""
    if key == "ascii_ply":
        return damaged_bytes(data) | damaged_ply_values(data)
    if key == "binary_ply":
        return damaged_bytes(data)
    if key == "index":
        lines = data.splitlines(keepends=True)
        return damaged_bytes(data) | st.builds(
            lambda i, line: b"".join(lines[:i]) + line + b"".join(lines[i + 1 :]),
            st.integers(0, len(lines) - 1),
            damaged_json(lines[0]).map(lambda b: b + b"\n"),
        )
    return damaged_bytes(data) | damaged_json(data)


def _read(key: str, data: bytes, originals: dict[str, bytes], tmp: Path) -> str | None:
    """None if the reader of ``key`` reads ``data`` right or refuses it in one line; else
    what went wrong."""
    if key in ("rig", "target"):
        cap = tmp / "cap"
        (cap / "rig.json").write_bytes(data if key == "rig" else originals["rig"])
        (cap / "target.json").write_bytes(data if key == "target" else originals["target"])
        return _outcome(lambda: Capture.open(cap), _check_capture)
    if key == "calibration":
        (tmp / "calibration.json").write_bytes(data)
        return _outcome(lambda: Calibration.load(tmp / "calibration.json"), _check_calibration)
    if key == "index":
        (tmp / "frames.jsonl").write_bytes(data)
        return _outcome(lambda: read_index(tmp / "frames.jsonl"), _check_index)
    (tmp / "points.ply").write_bytes(data)
    return _outcome(lambda: read_ply(tmp / "points.ply"), _check_ply)


_FUZZ = settings(
    deadline=None,
    derandomize=True,  # the same cases on every run: the suite stays deterministic
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _fuzz_one(originals: dict[str, bytes], workdir: Path, key: str, data: st.DataObject) -> None:
    """One damaged file through the reader of ``key``."""
    damaged = data.draw(_damaged(key, originals[key]), label="file")
    why = _read(key, damaged, originals, workdir)
    assert why is None, why


def test_originals_are_read(originals, workdir):
    """The undamaged files give correct results (so the fuzzing starts from valid input)."""
    for key in READERS:
        assert _read(key, originals[key], originals, workdir) is None, key
    assert len(read_ply(workdir / "points.ply")["x"]) == 40
    assert [d["points"] for d in read_index(workdir / "frames.jsonl")] == [3, 0, 5]


@pytest.mark.parametrize("key", READERS)
@settings(_FUZZ, max_examples=60)
@given(data=st.data())
def test_fuzz_readers_quick(originals, workdir, key, data):
    """60 damaged files per reader."""
    _fuzz_one(originals, workdir, key, data)


@pytest.mark.slow
@pytest.mark.parametrize("key", READERS)
@settings(_FUZZ, max_examples=400)
@given(data=st.data())
def test_fuzz_readers_long(originals, workdir, key, data):
    """400 damaged files per reader, other cases."""
    _fuzz_one(originals, workdir, key, data)


@pytest.mark.parametrize(
    "text, match",
    [
        (b"\xff\xfe{}", "not UTF-8 text"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"schema": ' + b"9" * 5000 + b"}", "unreadable JSON value"),
        (b'{"schema": "multislit-calibration/1"', "not valid JSON"),
        (b"", "not valid JSON"),
    ],
)
def test_unreadable_json_is_one_line(tmp_path, text, match):
    """Each way a JSON file can be unreadable, for every JSON reader, is one clear line."""
    p = tmp_path / "f.json"
    p.write_bytes(text)
    cap = tmp_path / "cap"
    (cap / "reference").mkdir(parents=True)
    (cap / "rig.json").write_bytes(text)
    for read in (lambda: Calibration.load(p), lambda: Capture.open(cap)):
        with pytest.raises(MultislitError, match=match) as exc:
            read()
        assert "\n" not in str(exc.value) and str(p.parent) in str(exc.value)
