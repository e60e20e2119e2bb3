"""Faults of ``multislit stream`` and ``batch`` end to end, in processes of their own: worker
processes that must end with their parent, Ctrl-C of a cluster, runs where no frame can be
used, file names beyond ASCII."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from multislit.app.cli import main
from multislit.app.index import INDEX_FILE
from multislit.io import read_ply


def _index(out: Path) -> list[dict]:
    return [json.loads(s) for s in (out / INDEX_FILE).read_text().splitlines()]


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _running(pid: int) -> bool:
    """The process exists and is not a zombie (an orphan's zombie waits for its reaper)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait_for_frames(out: Path, n: int, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if (out / INDEX_FILE).exists() and len(_index(out)) >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"no {n} frame(s) written in {timeout} s")


def _linked_frames(calibrated: Path, folder: Path, n: int) -> Path:
    folder.mkdir()
    for i in range(n):
        (folder / f"f{i:03d}.png").symlink_to(calibrated / "scans" / "holes.png")
    return folder


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_stream_workers_end_with_their_parent(calibrated: Path, tmp_path: Path, sig):
    """``kill -9`` or ``kill`` of ``stream --workers 2``: its worker processes end too."""
    many = _linked_frames(calibrated, tmp_path / "many", 200)
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "multislit.app.cli", "stream", str(calibrated), str(many)]
    proc = subprocess.Popen(
        [*argv, "-o", str(out), "--workers", "2"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _wait_for_frames(out, 1, proc)
        workers = [
            p
            for p in _children(proc.pid)
            if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()
        ]
        assert len(workers) == 2
        proc.send_signal(sig)
        proc.wait(timeout=60)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_running(p) for p in workers):
            time.sleep(0.1)
        left = [p for p in workers if _running(p)]
        for p in left:
            os.kill(p, signal.SIGKILL)
        assert not left, "worker processes outlived their parent"
        if sig == signal.SIGTERM:
            assert proc.returncode == 128 + signal.SIGTERM  # it ended itself, cleanly
    finally:
        if proc.poll() is None:
            proc.kill()
    lines = _index(out)
    assert [d["frame"] for d in lines] == list(range(len(lines)))  # whole frames only


@pytest.mark.slow
def test_ctrl_c_of_batch_is_one_line(calibrated: Path, tmp_path: Path):
    """Ctrl-C (SIGINT to the terminal's process group) during ``batch``: 'interrupted', exit
    130, and no traceback of the local cluster's worker processes."""
    pytest.importorskip("distributed")
    many = _linked_frames(calibrated, tmp_path / "many", 400)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "multislit.app.cli", "batch", str(calibrated), str(many)]
        + ["-o", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,  # a process group of its own, like a terminal's job
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        _wait_for_frames(out, 1, proc)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = err.decode(errors="replace")
    assert proc.returncode == 130 and "Traceback" not in text, text
    assert text.strip().splitlines()[-1] == "interrupted"


@pytest.mark.slow
def test_non_ascii_file_names_end_to_end(calibrated: Path, tmp_path: Path, capsys):
    folder = tmp_path / "bilder_ä"
    folder.mkdir()
    shutil.copy(calibrated / "scans" / "holes.png", folder / "café.png")
    assert main(["stream", str(calibrated), str(folder), "-o", str(tmp_path / "ö")]) == 0
    assert _index(tmp_path / "ö")[0]["source"] == "café.png"
    argv = ["scan", str(calibrated), "--image", str(folder / "café.png")]
    assert main([*argv, "-o", str(tmp_path / "pts")]) == 0
    assert "café.ply" in capsys.readouterr().out
    assert len(read_ply(tmp_path / "pts" / "café.ply")["x"]) > 1000


@pytest.mark.slow
def test_a_run_of_unusable_frames_exits_2_with_the_reason(calibrated: Path, tmp_path: Path, capsys):
    holes = cv2.imread(str(calibrated / "scans" / "holes.png"), cv2.IMREAD_UNCHANGED)
    cases = {
        "float": ("f.tif", np.full(holes.shape, np.nan, np.float32), "pixel type float32"),
        "int16": ("i.tif", holes.astype(np.int16), "pixel type int16"),
        "size": ("s.png", holes[:100, :120], "is 120x100 px but the calibration is for"),
        # a green laser read in the red channel: a dark frame
        "green": ("g.png", np.dstack([0 * holes, holes, 0 * holes]), "without points"),
    }
    for name, (file, img, why) in cases.items():
        folder = tmp_path / name
        folder.mkdir()
        assert cv2.imwrite(str(folder / file), img)
        out = tmp_path / f"out_{name}"
        argv = ["stream", str(calibrated), str(folder), "-o", str(out)]
        rc = main(argv + (["--channel", "red"] if name == "green" else []))
        err = capsys.readouterr().err
        last = err.strip().splitlines()[-1]
        assert rc == 2 and last.startswith("multislit stream: error: no frame of"), err
        assert why in last and "Traceback" not in err, (name, last)
    # the green laser's frame in its own channel gives points, also with the channel chosen
    # from the data (the default)
    for channel in ("green", "auto"):
        out = tmp_path / f"out_green_{channel}"
        argv = ["stream", str(calibrated), str(tmp_path / "green"), "-o", str(out)]
        assert main([*argv, "--channel", channel]) == 0
        assert _index(out)[0]["points"] > 1000
