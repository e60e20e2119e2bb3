"""Fuzz tests of the three file readers: rig.json / target.json (``Capture.open``), the
calibration file (``Calibration.load``) and PLY files (``read_ply``).

A seeded generator damages valid files (truncation, byte flips, non-UTF-8 bytes, repeated or
cut spans, JSON values of the wrong type, ASCII PLY values out of range). Each reader must
either give a correct result or raise a one-line ``MultislitError``: never another exception
and never a warning.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from multislit.calibrate import Calibration
from multislit.errors import MultislitError
from multislit.io import Capture, read_ply, write_ply
from tests.test_calibration import _calibration

#: Values that replace a JSON value: every JSON type, edge numbers, nesting.
_ODD_VALUES: list = [
    None,
    True,
    False,
    0,
    -1,
    7,
    0.5,
    1e300,
    -1e300,
    float("nan"),
    float("inf"),
    2**70,
    "",
    "x",
    "1e3",
    "\udc80",
    [],
    {},
    [1, 2],
    [[1]],
    [None, None, None, None],
    {"a": 1},
    [[[[[[[[1]]]]]]]],
]

#: Tokens that replace a value of an ASCII PLY.
_ODD_TOKENS = [b"1e300", b"-1e39", b"nan", b"inf", b"-1", b"2.5", b"99999999999", b"x", b""]

#: Byte sequences that are not UTF-8.
_NOT_UTF8 = [b"\xff", b"\xfe", b"\xc3", b"\x80", b"\xed\xa0\x80", b"\xc0\xaf"]


def _mutate_bytes(rng: np.random.Generator, data: bytes) -> bytes:
    """``data`` damaged one of five ways."""
    b = bytearray(data)
    kind = int(rng.integers(5))
    if kind == 0:  # truncated
        return bytes(b[: int(rng.integers(len(b)))])
    if kind == 1:  # bytes flipped
        for _ in range(int(rng.integers(1, 6))):
            b[int(rng.integers(len(b)))] = int(rng.integers(256))
        return bytes(b)
    i = int(rng.integers(len(b) + 1))
    if kind == 2:  # non-UTF-8 bytes inserted
        return bytes(b[:i]) + _NOT_UTF8[int(rng.integers(len(_NOT_UTF8)))] + bytes(b[i:])
    if kind == 3:  # a span repeated
        return bytes(b[:i]) + bytes(b[i : i + int(rng.integers(1, 40))]) * 2 + bytes(b[i:])
    j = int(rng.integers(i, len(b) + 1))  # a span cut out
    return bytes(b[:i]) + bytes(b[j:])


def _mutate_json(rng: np.random.Generator, data: bytes) -> bytes:
    """``data`` (JSON) with 1-3 values replaced by values of other types, or keys deleted."""
    obj = json.loads(data)
    for _ in range(int(rng.integers(1, 4))):
        slots: list[tuple[object, object]] = []
        _slots(obj, None, None, slots)
        parent, key = slots[int(rng.integers(len(slots)))]
        value = copy.deepcopy(_ODD_VALUES[int(rng.integers(len(_ODD_VALUES)))])
        if parent is None:
            obj = value
        elif isinstance(parent, dict) and rng.random() < 0.2:
            del parent[key]
        else:
            parent[key] = value  # type: ignore[index]
    return json.dumps(obj).encode("utf-8", "surrogatepass")


def _slots(o: object, parent: object, key: object, out: list[tuple[object, object]]) -> None:
    """Append (parent, key) of ``o`` and of every value inside it to ``out``."""
    out.append((parent, key))
    if isinstance(o, dict):
        for k, v in o.items():
            _slots(v, o, k, out)
    elif isinstance(o, list):
        for k, v in enumerate(o):
            _slots(v, o, k, out)


def _mutate_ply_values(rng: np.random.Generator, data: bytes) -> bytes:
    """An ASCII PLY with a few values replaced by odd tokens."""
    head, sep, body = data.partition(b"end_header\n")
    tokens = body.split(b" ")
    for _ in range(int(rng.integers(1, 4))):
        tokens[int(rng.integers(len(tokens)))] = _ODD_TOKENS[int(rng.integers(len(_ODD_TOKENS)))]
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
    """Valid files to damage: rig.json, target.json, a calibration, binary and ASCII PLY."""
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
    return {
        "rig": (small_capture / "rig.json").read_bytes(),
        "target": (small_capture / "target.json").read_bytes(),
        "calibration": _calibration().to_json().encode(),
        "binary_ply": (tmp / "b.ply").read_bytes(),
        "ascii_ply": (tmp / "a.ply").read_bytes(),
    }


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


def _fuzz(originals: dict[str, bytes], tmp: Path, seed: int, cases: int) -> list[str]:
    """Run ``cases`` damaged files through each reader; the failures, one line each."""
    rng = np.random.default_rng(seed)
    cap = tmp / "cap"
    (cap / "reference").mkdir(parents=True)
    for name in ("a.png", "b.png"):  # Capture.open lists the reference images, not reads
        (cap / "reference" / name).write_bytes(b"")
    cal, ply = tmp / "calibration.json", tmp / "points.ply"
    failures = []

    def damaged(key: str) -> bytes:
        data = originals[key]
        if key.endswith("ply"):
            if key == "ascii_ply" and rng.random() < 0.4:
                return _mutate_ply_values(rng, data)
            return _mutate_bytes(rng, data)
        return _mutate_json(rng, data) if rng.random() < 0.5 else _mutate_bytes(rng, data)

    for case in range(cases):
        for key in ("rig", "target", "calibration", "binary_ply", "ascii_ply"):
            data = damaged(key)
            if key in ("rig", "target"):
                (cap / "rig.json").write_bytes(data if key == "rig" else originals["rig"])
                (cap / "target.json").write_bytes(data if key == "target" else originals["target"])
                why = _outcome(lambda: Capture.open(cap), _check_capture)
            elif key == "calibration":
                cal.write_bytes(data)
                why = _outcome(lambda: Calibration.load(cal), _check_calibration)
            else:
                ply.write_bytes(data)
                why = _outcome(lambda: read_ply(ply), _check_ply)
            if why:
                failures.append(f"seed {seed} case {case} {key}: {why}")
    return failures


def test_originals_are_read(originals, tmp_path):
    """The undamaged files give correct results (so the fuzzing starts from valid input)."""
    assert _fuzz(originals, tmp_path, seed=0, cases=0) == []
    cap = tmp_path / "cap"
    (cap / "rig.json").write_bytes(originals["rig"])
    (cap / "target.json").write_bytes(originals["target"])
    _check_capture(Capture.open(cap))
    (tmp_path / "c.json").write_bytes(originals["calibration"])
    _check_calibration(Calibration.load(tmp_path / "c.json"))
    for key in ("binary_ply", "ascii_ply"):
        (tmp_path / "p.ply").write_bytes(originals[key])
        assert len(read_ply(tmp_path / "p.ply")["x"]) == 40


def test_fuzz_readers_quick(originals, tmp_path):
    """60 damaged files per reader: 300 reads, 1-3 s."""
    failures = _fuzz(originals, tmp_path, seed=1, cases=60)
    assert not failures, f"{len(failures)} failures:\n" + "\n".join(failures[:20])


@pytest.mark.slow
def test_fuzz_readers_long(originals, tmp_path):
    """600 damaged files per reader (3000 reads), other seeds."""
    failures = []
    for seed in range(2, 4):
        shutil.rmtree(tmp_path / "cap", ignore_errors=True)
        failures += _fuzz(originals, tmp_path, seed=seed, cases=300)
    assert not failures, f"{len(failures)} failures:\n" + "\n".join(failures[:20])


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
