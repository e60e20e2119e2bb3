"""PLY writer and strict reader: round trips, interoperability with plyfile, malformed files."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from multislit.errors import MultislitError
from multislit.io import read_ply, write_ply


def _cloud(n: int = 50, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts = rng.normal([0, 0, 900], [100, 80, 20], size=(n, 3))
    uv = rng.uniform(0, 1280, size=(n, 2))
    slit = rng.integers(-1, 40, size=n)
    conf = rng.uniform(0, 1, size=n)
    return pts, uv, slit, conf


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip(tmp_path, binary):
    pts, uv, slit, conf = _cloud()
    path = tmp_path / "c.ply"
    write_ply(
        path, pts, u=uv[:, 0], v=uv[:, 1], slit=slit, confidence=conf, binary=binary, comment="hi"
    )
    d = read_ply(path)
    assert list(d) == ["x", "y", "z", "u", "v", "slit", "confidence"]
    for name, want in [
        ("x", pts[:, 0]),
        ("y", pts[:, 1]),
        ("z", pts[:, 2]),
        ("u", uv[:, 0]),
        ("v", uv[:, 1]),
        ("confidence", conf),
    ]:
        assert d[name].dtype == np.float32
        np.testing.assert_array_equal(d[name], want.astype(np.float32))
    assert d["slit"].dtype == np.int32
    np.testing.assert_array_equal(d["slit"], slit)
    head = path.read_bytes()[:300]
    assert head.startswith(b"ply\n")
    assert (b"binary_little_endian" in head) == binary
    assert b"comment multislit" in head and b"comment hi\n" in head


@pytest.mark.parametrize("binary", [True, False])
def test_plyfile_reads_our_files(tmp_path, binary):
    pts, uv, slit, conf = _cloud(seed=1)
    path = tmp_path / "c.ply"
    write_ply(path, pts, u=uv[:, 0], v=uv[:, 1], slit=slit, confidence=conf, binary=binary)
    ply = PlyData.read(str(path))
    assert ply.text == (not binary)
    v = ply["vertex"]
    assert v.count == len(pts)
    ours = read_ply(path)
    for name in ("x", "y", "z", "u", "v", "slit", "confidence"):
        assert v[name].dtype.kind == ours[name].dtype.kind
        assert v[name].dtype.itemsize == ours[name].dtype.itemsize
        np.testing.assert_array_equal(v[name], ours[name])


@pytest.mark.parametrize("binary", [True, False])
def test_zero_points(tmp_path, binary):
    path = tmp_path / "empty.ply"
    write_ply(path, np.zeros((0, 3)), slit=np.zeros(0, int), binary=binary)
    d = read_ply(path)
    assert set(d) == {"x", "y", "z", "slit"}
    assert all(len(a) == 0 for a in d.values())
    assert d["slit"].dtype == np.int32
    assert PlyData.read(str(path))["vertex"].count == 0


def test_points_only(tmp_path):
    path = tmp_path / "p.ply"
    write_ply(path, [[1.0, 2.0, 3.0]])
    d = read_ply(path)
    assert list(d) == ["x", "y", "z"]
    assert d["z"][0] == 3.0


@pytest.mark.parametrize(
    "text",
    [
        "binary_big_endian",
        "binary_little_endian",
        "ascii",
    ],
)
def test_reads_plyfile_files_all_types(tmp_path, text):
    # every scalar type, a face element with a list property after the vertex element
    types = ["i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"]
    n = 7
    rng = np.random.default_rng(2)
    order = ">" if text == "binary_big_endian" else "<"
    vert = np.empty(n, dtype=[(f"p{t}", order + t) for t in types])
    for t in types:
        info = np.iinfo(t) if t[0] in "iu" else None
        vert[f"p{t}"] = (
            rng.integers(info.min, info.max, size=n, endpoint=True)
            if info
            else rng.normal(size=n) * 1e3
        )
    faces = np.empty(2, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([2, 3, 4], "i4")]
    el = [PlyElement.describe(vert, "vertex"), PlyElement.describe(faces, "face")]
    path = tmp_path / "t.ply"
    PlyData(el, text=text == "ascii", byte_order=order).write(str(path))
    d = read_ply(path)
    for t in types:
        assert d[f"p{t}"].dtype == np.dtype(t)
        np.testing.assert_array_equal(d[f"p{t}"], vert[f"p{t}"])


def test_element_before_vertex_is_skipped(tmp_path):
    for binary in (True, False):
        extra = np.zeros(3, dtype=[("a", "<f8"), ("b", "u1")])
        vert = np.array([(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)], dtype=[(c, "<f4") for c in "xyz"])
        el = [PlyElement.describe(extra, "camera"), PlyElement.describe(vert, "vertex")]
        path = tmp_path / "b.ply"
        PlyData(el, text=not binary).write(str(path))
        np.testing.assert_array_equal(read_ply(path)["y"], [2.0, 5.0])


HEADER = "ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty int s\nend_header\n"


def _write(tmp_path, data: bytes):
    path = tmp_path / "bad.ply"
    path.write_bytes(data)
    return path


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"plx\nformat ascii 1.0\nend_header\n", "not a PLY file"),
        (b"", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "end_header"),
        (b"ply\nformat ascii 2.0\nelement vertex 0\nproperty float x\nend_header\n", "format"),
        (b"ply\nformat weird 1.0\nelement vertex 0\nproperty float x\nend_header\n", "format"),
        (b"ply\nelement vertex 0\nproperty float x\nend_header\n", "format"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty flot x\nend_header\n", "flot"),
        (b"ply\nformat ascii 1.0\nelement vertex -2\nproperty float x\nend_header\n", "count"),
        (b"ply\nformat ascii 1.0\nelement vertex two\nproperty float x\nend_header\n", "count"),
        (b"ply\nformat ascii 1.0\nproperty float x\nelement vertex 0\nend_header\n", "before"),
        (b"ply\nformat ascii 1.0\nelement vertex 0\nfoo bar\nend_header\n", "keyword"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float x\n"
            b"end_header\n",
            "twice",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar int idx\n"
            b"end_header\n3 1 2 3\n",
            "list properties",
        ),
        (b"ply\nformat ascii 1.0\nelement face 0\nproperty float x\nend_header\n", "no 'vertex'"),
        (HEADER.format(fmt="ascii", n=3).encode() + b"1.5 2\n2.5 3\n", "truncated"),
        (HEADER.format(fmt="ascii", n=2).encode() + b"1.5 2\n2.5\n", "line 2 has 1 values"),
        (HEADER.format(fmt="ascii", n=1).encode() + b"1.5 2.5\n", "not int32"),
        (HEADER.format(fmt="ascii", n=1).encode() + b"1.5 abc\n", "non-numeric"),
        (HEADER.format(fmt="ascii", n=1).encode() + b"1.5 2\n7 7\n", "after the last"),
        (HEADER.format(fmt="binary_little_endian", n=3).encode() + b"\0" * 23, "truncated"),
        (HEADER.format(fmt="binary_little_endian", n=1).encode() + b"\0" * 9, "unexpected data"),
    ],
)
def test_malformed(tmp_path, data, match):
    with pytest.raises(MultislitError, match=match):
        read_ply(_write(tmp_path, data))


def test_missing_file(tmp_path):
    with pytest.raises(MultislitError, match="cannot read"):
        read_ply(tmp_path / "nope.ply")


def test_write_validation(tmp_path):
    path = tmp_path / "w.ply"
    with pytest.raises(MultislitError, match="points"):
        write_ply(path, np.zeros((3, 2)))
    with pytest.raises(MultislitError, match="finite"):
        write_ply(path, [[0, 0, np.nan]])
    with pytest.raises(MultislitError, match="u must have shape"):
        write_ply(path, np.zeros((3, 3)), u=np.zeros(2))
    with pytest.raises(MultislitError, match="slit"):
        write_ply(path, np.zeros((2, 3)), slit=[0.5, 1])
    with pytest.raises(MultislitError, match="int32"):
        write_ply(path, np.zeros((1, 3)), slit=np.array([2**40]))
    with pytest.raises(MultislitError, match="single line"):
        write_ply(path, np.zeros((1, 3)), comment="a\nb")
    with pytest.raises(MultislitError, match="cannot write"):
        write_ply(tmp_path / "no" / "dir.ply", np.zeros((1, 3)))


def test_written_files_get_the_usual_permissions(tmp_path):
    """Atomic writes go through a private temporary file; the result is not left private."""
    import os

    from multislit.io import write_text_atomic

    mask = os.umask(0o022)
    try:
        p = write_text_atomic(tmp_path / "a.txt", "x")
    finally:
        os.umask(mask)
    assert (p.stat().st_mode & 0o777) == 0o644
