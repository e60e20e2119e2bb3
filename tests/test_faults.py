"""Faults found by trying the commands and the library the way users get them wrong: wrong
types, empty strings, odd file names, devices, truncated files, unreachable or silent
servers. Each gets one clear line (exit 2 on the command line) or the right result, never a
traceback, a hang or a silently wrong result."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

import multislit as ms
from multislit.app import batch as batch_mod
from multislit.app.cli import main
from multislit.app.index import read_index
from multislit.app.stream import FrameResult, FrameWriter, check_frame_options, max_workers
from multislit.errors import CaptureError, MeasurementError, MultislitError
from multislit.io import read_image
from multislit.io.sources import open_source
from multislit.reconstruct import RefineOptions, triangulate


def _cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _one_line(err: str, command: str) -> str:
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith(f"{command}: ")]
    assert len(lines) == 1 and lines[0].startswith(f"multislit {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


def _result(k: int) -> FrameResult:
    pts = np.arange(3.0 * k).reshape(k, 3)
    idx = np.arange(k, dtype=float)
    return FrameResult(pts, idx, idx, np.arange(k, dtype=np.int64), np.full(k, 0.5), k, 1.0)


# --------------------------------------------------------------------------- wrong types
@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: ms.read_ply(None), "path must be a path"),
        (lambda: ms.read_ply(3.5), "path must be a path"),
        (lambda: open_source(123), "SOURCE must be a path"),
        (lambda: ms.Capture.open(None), "capture folder must be a path"),
        (lambda: ms.calibrate_capture(5), "capture folder must be a path"),
        (lambda: ms.write_ply("x.ply", np.zeros((1, 3)), comment=123), "comment must be a str"),
        (lambda: ms.write_ply(None, np.zeros((1, 3))), "path must be a path"),
        (lambda: read_image(None), "image path must be a path"),
        (lambda: ms.Calibration.load(None), "calibration file must be a path"),
        (lambda: ms.read_ply(""), "path is empty"),
    ],
)
def test_wrong_types_are_one_line(call, match):
    with pytest.raises(MultislitError, match=match) as exc:
        call()
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize(
    "angle, match",
    [
        ("2", "must be a number of degrees, got str"),
        (float("nan"), "0 to less than 90"),
        (-5, "0 to less than 90"),
        (90, "0 to less than 90"),
        (True, "number of degrees"),
    ],
)
def test_min_angle_is_checked(angle, match):
    with pytest.raises(MultislitError, match=match):
        RefineOptions(min_angle_deg=angle)
    cam = ms.geometry.PinholeCamera(500, 500, 4, 4, tvec=(0, 0, 500))
    with pytest.raises(MultislitError, match=match):
        triangulate(cam, np.array([[1.0, 0, 0, 0]]), np.zeros((1, 2)), [0], min_angle_deg=angle)


_READ_DEVICE = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))  # a reader without end fails fast
import multislit as ms
try:
    ms.read_ply(sys.argv[1])
except ms.MultislitError as exc:
    print(exc)
"""


@pytest.mark.slow  # two fresh interpreters
def test_read_ply_of_a_device_or_fifo_is_refused_at_once(tmp_path):
    """/dev/zero would be read until memory runs out, a FIFO waited on for ever (each tried in
    a process of its own, with a memory limit and a timeout)."""
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    for path in ("/dev/zero", fifo):
        run = subprocess.run(
            [sys.executable, "-c", _READ_DEVICE, str(path)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 0 and "not a regular file" in run.stdout, run.stderr[-300:]


def test_non_ascii_comment_is_escaped_in_the_ascii_header(tmp_path):
    p = tmp_path / "é.ply"
    ms.write_ply(p, np.zeros((2, 3)), comment="scan of café.png")
    head = p.read_bytes().split(b"end_header")[0]
    assert b"comment scan of caf\\xe9.png" in head
    assert len(ms.read_ply(p)["x"]) == 2


# --------------------------------------------------------------------------- images, sources
def _jpeg(tmp_path: Path) -> bytes:
    img = (np.arange(64 * 48) % 251).reshape(48, 64).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def test_truncated_jpeg_is_a_bad_frame_not_a_grey_one(tmp_path):
    data = _jpeg(tmp_path)
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.jpg").write_bytes(data)
    (folder / "b.jpg").write_bytes(data[: len(data) // 2])
    (folder / "c.jpg").write_bytes(data + b"\x00" * 16)  # padding after the end: whole
    with open_source(folder) as src:
        frames = list(src.frames())
    assert frames[0].image is not None and frames[2].image is not None
    assert frames[1].image is None and "truncated JPEG" in frames[1].error
    with pytest.raises(CaptureError, match="truncated JPEG"):
        read_image(folder / "b.jpg")


def test_huge_camera_number_is_one_line():
    for spec in ("camera:99999999999999999999", "camera:-1", "camera:٣"):
        with pytest.raises(CaptureError, match="give the camera number") as exc:
            open_source(spec)
        assert "\n" not in str(exc.value)


def test_empty_strings_do_not_mean_the_current_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cv2.imwrite("a.png", np.zeros((8, 8), np.uint8))  # '' would read the current folder
    with pytest.raises(CaptureError, match="SOURCE is empty"):
        open_source("")
    for argv, what in (
        (["stream", "cap", "", "-o", "out"], "SOURCE is empty"),
        (["stream", "cap", ".", "-o", ""], "-o is empty"),
        (["batch", "cap", ".", "-o", "out", "--dask", ""], "give the scheduler's address"),
        (["scan", "cap", "-o", ""], "-o is empty"),
    ):
        (tmp_path / "cap").mkdir(exist_ok=True)
        rc, _, err = _cli(capsys, *argv)
        assert rc == 2 and what in _one_line(err, argv[0]), err


# --------------------------------------------------------------------------- stream, batch
def test_workers_have_an_upper_bound(capsys):
    with pytest.raises(MeasurementError, match="at most"):
        check_frame_options(max_workers() + 1, 1, None, "skip")
    check_frame_options(max_workers(), 1, None, "skip")
    for cmd in ("stream", "batch"):
        rc, _, err = _cli(capsys, cmd, "cap", "src", "-o", "out", "--workers", 10**12)
        assert rc == 2 and "--workers" in _one_line(err, cmd)


@pytest.mark.parametrize(
    "address, match",
    [
        ("tcp://127.0.0.1:abc", "port number"),
        ("foo://127.0.0.1:8786", "unknown scheme 'foo'"),
        ("tcp://127.0.0.1", "HOST:PORT"),
        ("tcp://127.0.0.1:99999", "port number"),
        ("tcp://:8786", "HOST:PORT"),
    ],
)
def test_malformed_dask_addresses(capsys, tmp_path, address, match):
    pytest.importorskip("distributed")
    rc, _, err = _cli(capsys, "batch", tmp_path, tmp_path, "-o", tmp_path / "o", "--dask", address)
    assert rc == 2 and match in _one_line(err, "batch")


def test_a_silent_scheduler_times_out(tmp_path, monkeypatch):
    """A server that accepts the connection and never answers: a Dask client alone waits for
    ever; the run stops after the connect timeout."""
    pytest.importorskip("distributed")
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    held = []
    threading.Thread(target=lambda: held.append(server.accept()), daemon=True).start()
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    monkeypatch.setattr(batch_mod, "_CONNECT_TIMEOUT_S", 1.0)
    monkeypatch.setattr(batch_mod, "load_capture_calibration", lambda cap, path: None)
    monkeypatch.setattr(batch_mod.Capture, "open", lambda *a, **k: _FakeCapture())
    outcome = []

    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "a.png"), np.zeros((8, 8), np.uint8))

    def run():
        try:
            batch_mod.batch("cap", frames, tmp_path / "out", address=address)
        except MultislitError as exc:
            outcome.append(str(exc))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout=20)
    server.close()
    assert not t.is_alive(), "batch still waits for the silent server"
    assert outcome and "no answer in 1 s" in outcome[0] and address in outcome[0]


class _FakeCapture:
    laser_channel = "red"
    image_size = (8, 8)
    root = Path("cap")


# --------------------------------------------------------------------------- OUT folders
def test_overwrite_removes_only_the_runs_own_files(tmp_path):
    out = tmp_path / "out"
    w = FrameWriter(out)
    w.write("a.png", _result(2))
    w.close()
    mine = ["frame_best.ply", "frame_notes.txt", "frame_1.ply", "my_frame_000000.ply"]
    for name in mine:
        (out / name).write_text("the user's own file")
    (out / ".frame_000001.ply.x1y2.tmp").write_bytes(b"ply\n")  # a killed write
    w = FrameWriter(out, overwrite=True)
    w.write("b.png", _result(3))
    w.close()
    for name in mine:
        assert (out / name).read_text() == "the user's own file", name
    assert not (out / ".frame_000001.ply.x1y2.tmp").exists()
    assert [d["source"] for d in read_index(out / "frames.jsonl")] == ["b.png"]
    assert len(ms.read_ply(out / "frame_000000.ply")["x"]) == 3


def test_a_failed_start_leaves_the_folder_as_it_was(tmp_path):
    out = tmp_path / "out"
    FrameWriter(out).close()  # no frame written: nothing made
    assert not out.exists()
    w = FrameWriter(out)
    w.write("a.png", _result(2))
    w.close()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    FrameWriter(out, overwrite=True).close()  # a run with --overwrite that failed at once
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    out2 = tmp_path / "out2"
    out2.mkdir()
    FrameWriter(out2).close()
    FrameWriter(out2).close()  # a second try needs no --overwrite
    assert list(out2.iterdir()) == []


def test_index_that_is_not_utf8_or_not_records(tmp_path):
    p = tmp_path / "frames.jsonl"
    for data, match in (
        (b'{"frame": 0, "source": "caf\xe9.png"}\n', "line 1 is not UTF-8"),
        (b'{"frame": 0}\n{"frame": -1}\n', "line 2 is not a frame record"),
        (b'{"frame": true}\n', "line 1 is not a frame record"),
        (b'{"frame": 0, "source": 5}\n', "'source' must be text"),
        (b"[1, 2]\n", "line 1 is not a frame record"),
        (b'{"frame": 0\n', "line 1 is not valid JSON"),
    ):
        p.write_bytes(data)
        with pytest.raises(MeasurementError, match=match) as exc:
            read_index(p)
        assert "\n" not in str(exc.value)
    p.write_bytes(b'{"frame": 0, "source": "a"}\n\n{"frame": 1, "points": 3}\n')
    assert read_index(p) == [
        {"frame": 0, "source": "a"},
        {"frame": 1, "points": 3, "source": ""},
    ]


def test_json_index_lines_keep_the_message_of_an_empty_frame(tmp_path):
    w = FrameWriter(tmp_path / "out")
    empty = FrameResult(*(_result(0).__dict__[k] for k in ("points", "u", "v", "slit")),
                        np.zeros(0), 0, 1.0, "no slits found in the image")  # fmt: skip
    w.write("a.png", empty)
    w.close()
    line = json.loads((tmp_path / "out" / "frames.jsonl").read_text())
    assert line["points"] == 0 and line["message"] == "no slits found in the image"
    assert math.isfinite(line["ms"])
