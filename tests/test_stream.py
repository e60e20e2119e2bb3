"""Frame sources, `multislit stream` and `multislit batch`: images, videos, cameras, OUT folders."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from multislit.app.cli import main
from multislit.app.stream import INDEX_FILE, FrameResult, FrameWriter, run_frames
from multislit.errors import CaptureError, MeasurementError
from multislit.io import read_ply
from multislit.io import sources as sources_mod
from multislit.io.sources import open_source


def _pattern(seed: int, shape=(48, 64), dtype=np.uint8) -> np.ndarray:
    hi = 255 if dtype == np.uint8 else 65535
    return np.random.default_rng(seed).integers(0, hi, shape, endpoint=True).astype(dtype)


def _result(k: int, ms: float = 1.0) -> FrameResult:
    """A made-up frame result with k points."""
    pts = np.arange(3 * k, dtype=float).reshape(k, 3)
    return FrameResult(
        pts,
        np.arange(k, dtype=float),
        np.arange(k, dtype=float),
        np.arange(k, dtype=np.int64),
        np.full(k, 0.5),
        k,
        ms,
    )


def _index(out: Path) -> list[dict]:
    return [json.loads(s) for s in (out / INDEX_FILE).read_text().splitlines()]


# --------------------------------------------------------------------------- sources
def test_folder_of_png_tiff_jpeg_in_name_order(tmp_path: Path):
    a8, b16 = _pattern(1), _pattern(2, dtype=np.uint16)
    colour = np.zeros((48, 64, 3), np.uint8)
    colour[:, :, 2] = 200  # red (OpenCV's order is BGR)
    colour[:, :, 1] = 30
    cv2.imwrite(str(tmp_path / "a.png"), a8)
    cv2.imwrite(str(tmp_path / "b.tif"), b16)
    cv2.imwrite(str(tmp_path / "c.jpg"), colour)
    (tmp_path / "notes.txt").write_text("not an image")
    with open_source(tmp_path) as src:
        frames = list(src.frames())
    assert [f.source for f in frames] == ["a.png", "b.tif", "c.jpg"]
    assert [f.index for f in frames] == [0, 1, 2]
    assert not src.live and src.dropped == 0
    assert np.array_equal(frames[0].image, a8)
    assert frames[1].image.dtype == np.uint16 and np.array_equal(frames[1].image, b16)
    # a colour frame becomes its red channel, not luminance (~0.3 R + 0.6 G)
    assert frames[2].image.shape == (48, 64)
    assert abs(float(frames[2].image.mean()) - 200) < 3


def test_glob_and_every(tmp_path: Path):
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"f{i}.tif"), _pattern(i))
    cv2.imwrite(str(tmp_path / "other.png"), _pattern(9))
    with open_source(str(tmp_path / "*.tif"), every=2) as src:
        frames = list(src.frames())
    assert [f.source for f in frames] == ["f0.tif", "f2.tif", "f4.tif"]
    assert np.array_equal(frames[1].image, _pattern(2))


def test_colour_channel_choice(tmp_path: Path):
    bgr = np.stack([_pattern(1), _pattern(2), _pattern(3)], axis=2)
    cv2.imwrite(str(tmp_path / "c.png"), bgr)
    got = {}
    for ch in ("red", "green", "blue", "luma"):
        with open_source(tmp_path, channel=ch) as src:
            got[ch] = next(src.frames()).image
    assert np.array_equal(got["blue"], bgr[:, :, 0])
    assert np.array_equal(got["green"], bgr[:, :, 1])
    assert np.array_equal(got["red"], bgr[:, :, 2])
    # luma: ITU-R 601 weights, as OpenCV's (which rounds in fixed point: 1 DN apart at most)
    luma = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)
    assert got["luma"].dtype == np.uint8 and np.abs(got["luma"].astype(int) - luma).max() <= 1


@pytest.mark.parametrize("codec, suffix", [("FFV1", ".avi"), ("MJPG", ".avi")])
def test_video_file_frames(tmp_path: Path, codec: str, suffix: str):
    path = tmp_path / f"clip{suffix}"
    frames_in = [np.kron(_pattern(i, (12, 16)), np.ones((8, 8), np.uint8)) for i in range(4)]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 10, (128, 96))
    assert vw.isOpened()
    for f in frames_in:
        vw.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    vw.release()
    with open_source(path, channel="luma") as src:
        frames = list(src.frames())
    assert [f.source for f in frames] == [f"clip{suffix}#{i}" for i in range(4)]
    for got, want in zip(frames, frames_in, strict=True):
        assert got.image.shape == (96, 128) and got.image.dtype == np.uint8
        err = np.abs(got.image.astype(int) - want).mean()
        if codec == "FFV1":
            assert err == 0  # lossless
        else:
            assert err < 8  # JPEG-compressed blocks


def test_bad_sources_one_clear_error(tmp_path: Path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad.avi").write_bytes(b"not a video at all")
    cases = {
        str(tmp_path / "nothing"): "no such file or folder",
        str(tmp_path / "empty"): "has no",
        str(tmp_path / "*.png"): "matches no files",
        str(tmp_path / "bad.avi"): "OpenCV can read",
        "camera:x": "camera number",
    }
    for spec, words in cases.items():
        with pytest.raises(CaptureError, match=words) as exc:
            open_source(spec)
        assert "\n" not in str(exc.value) and "SOURCE" in str(exc.value)
    with pytest.raises(CaptureError, match="channel"):
        open_source(tmp_path, channel="purple")
    with pytest.raises(CaptureError, match="every"):
        open_source(tmp_path, every=0)


class _FakeCapture:
    """A stand-in for cv2.VideoCapture: a camera delivering numbered frames every period s."""

    period = 0.004
    present = True
    reads = 0

    def __init__(self, index):
        self.index = index
        self.n = 0

    def isOpened(self):
        return self.present

    def read(self):
        time.sleep(self.period)
        type(self).reads += 1
        self.n += 1
        img = np.full((24, 32, 3), 0, np.uint8)
        img[0, 0, 2] = self.n % 256  # the frame's number, in the red channel
        img[0, 1, 2] = self.n // 256
        return True, img

    def release(self):
        pass


def _number(image: np.ndarray) -> int:
    return int(image[0, 0]) + 256 * int(image[0, 1])


def test_camera_by_fake_videocapture_drops_when_busy(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(sources_mod.cv2, "VideoCapture", _FakeCapture)
    _FakeCapture.reads = 0

    class SlowRunner:
        capacity = 1

        def submit(self, image, name):
            # the camera keeps delivering while a frame is scanned
            reads = _FakeCapture.reads
            time.sleep(0.05)
            assert _FakeCapture.reads > reads + 3, "the camera was blocked"
            return _number(image)

        def done(self, h):
            return True

        def result(self, h):
            return _result(1)

        def close(self):
            pass

    with open_source("camera:0") as src:
        assert src.live
        writer = FrameWriter(tmp_path / "out")
        s = run_frames(src, writer, SlowRunner(), image_size=(32, 24), max_frames=5)
        writer.close()
    assert s.frames == 5 and s.skipped == 0
    assert s.dropped >= 20  # ~12 frames arrive during each 50 ms scan
    lines = _index(tmp_path / "out")
    assert [d["frame"] for d in lines] == list(range(5))
    assert all(d["source"].endswith("Z") and "T" in d["source"] for d in lines)  # capture times


def test_camera_frames_are_the_newest(monkeypatch):
    monkeypatch.setattr(sources_mod.cv2, "VideoCapture", _FakeCapture)
    with open_source("camera:1") as src:
        it = src.frames()
        a = _number(next(it).image)
        time.sleep(0.1)
        b = _number(next(it).image)
        dropped = src.dropped
    assert b - a > 5 and dropped >= b - a - 2


def test_absent_camera(monkeypatch):
    class Absent(_FakeCapture):
        present = False

    monkeypatch.setattr(sources_mod.cv2, "VideoCapture", Absent)
    with pytest.raises(CaptureError, match="no camera 4"):
        open_source("camera:4")


def _emulation_or_skip(monkeypatch):
    pylon = pytest.importorskip("pypylon.pylon", reason="pypylon (multislit[basler]) not installed")
    monkeypatch.setenv("PYLON_CAMEMU", "1")
    if not pylon.TlFactory.GetInstance().EnumerateDevices():
        pytest.skip("pylon's camera emulation shows no camera with PYLON_CAMEMU=1")
    return pylon


@pytest.mark.slow
def test_basler_emulation_replays_files(tmp_path: Path, monkeypatch):
    _emulation_or_skip(monkeypatch)
    pics = [_pattern(i, (48, 64)) for i in range(3)]
    for i, p in enumerate(pics):
        cv2.imwrite(str(tmp_path / f"p{i}.png"), p)
    feats = [
        ("ImageFilename", str(tmp_path)),
        ("ImageFileMode", "On"),
        ("TestImageSelector", "Off"),
    ]
    with open_source("basler:", image_size=(64, 48), features=feats) as src:
        assert src.live
        it = src.frames()
        got = [next(it) for _ in range(4)]
    for fr in got:
        assert fr.image.shape == (48, 64)
        assert any(np.array_equal(fr.image, p) for p in pics), "not one of the replayed files"
    with pytest.raises(CaptureError, match="no Basler camera with serial number"):
        open_source("basler:nosuchserial")
    with pytest.raises(CaptureError, match="no feature"):
        open_source("basler:", features=[("NoSuchFeature", "1")])


# --------------------------------------------------------------------------- the loop
class _ThreadRunner:
    """Frames finish out of order: later frames are quicker."""

    def __init__(self, delays):
        self.capacity = 3
        self.pool = ThreadPoolExecutor(3)
        self.delays = iter(delays)

    def submit(self, image, name):
        d = next(self.delays)
        return self.pool.submit(lambda: (time.sleep(d), _result(_number(image)))[1])

    def done(self, h):
        return h.done()

    def result(self, h):
        return h.result()

    def close(self):
        self.pool.shutdown()


def _numbered_folder(folder: Path, n: int, size=(32, 24)) -> None:
    folder.mkdir()
    for i in range(n):
        img = np.zeros((size[1], size[0]), np.uint8)
        img[0, 0] = i + 1
        cv2.imwrite(str(folder / f"img{i:02d}.png"), img)


def test_frames_written_in_order_when_they_finish_out_of_order(tmp_path: Path):
    _numbered_folder(tmp_path / "in", 6)
    runner = _ThreadRunner([0.12, 0.08, 0.01, 0.1, 0.02, 0.0])
    with open_source(tmp_path / "in") as src:
        writer = FrameWriter(tmp_path / "out")
        s = run_frames(src, writer, runner, image_size=(32, 24))
        writer.close()
    runner.close()
    lines = _index(tmp_path / "out")
    assert s.frames == 6
    assert [d["source"] for d in lines] == [f"img{i:02d}.png" for i in range(6)]
    assert [d["points"] for d in lines] == [1, 2, 3, 4, 5, 6]
    for d in lines:  # each PLY holds its own frame's points
        ply = read_ply(tmp_path / "out" / f"frame_{d['frame']:06d}.ply")
        assert len(ply["x"]) == d["points"]
        assert set(ply) == {"x", "y", "z", "u", "v", "slit", "confidence"}


class _SwallowingRunner:
    """Scans inline; Ctrl-C arrives while the second frame's result is fetched, inside a
    finaliser-like ``except`` that swallows it (as a Dask future's ``__del__`` does)."""

    capacity = 1

    def __init__(self) -> None:
        self.results = 0

    def submit(self, image, name):
        return _number(image)

    def done(self, h):
        return True

    def result(self, h):
        self.results += 1
        if self.results == 2:
            try:
                signal.raise_signal(signal.SIGINT)
            except KeyboardInterrupt:
                pass
        return _result(h)

    def close(self):
        pass


@pytest.fixture
def ctrl_c_reaches_python():
    """Ctrl-C (SIGINT) handled by Python's default handler during the test, whatever the test
    process inherited: a process started in the background by a shell without job control
    ignores SIGINT, and a run then leaves it ignored (as it should)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.mark.usefixtures("ctrl_c_reaches_python")
def test_ctrl_c_swallowed_where_it_lands_still_stops_the_run(tmp_path: Path):
    _numbered_folder(tmp_path / "in", 6)
    runner = _SwallowingRunner()
    with open_source(tmp_path / "in") as src:
        writer = FrameWriter(tmp_path / "out")
        with pytest.raises(KeyboardInterrupt):
            run_frames(src, writer, runner, image_size=(32, 24))
        writer.close()
    # stopped after the frame during which it came, that frame written whole
    assert runner.results == 2
    assert [d["points"] for d in _index(tmp_path / "out")] == [1, 2]
    # the run's own handler is gone: Ctrl-C outside a run raises where it lands again
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)


def test_bad_frames_skipped_and_counted_or_stop(tmp_path: Path):
    _numbered_folder(tmp_path / "in", 3)
    cv2.imwrite(str(tmp_path / "in" / "img01b.png"), np.zeros((10, 10), np.uint8))  # wrong size
    (tmp_path / "in" / "img01c.png").write_bytes(b"broken")  # unreadable
    runner = _ThreadRunner([0.0] * 5)
    with open_source(tmp_path / "in") as src:
        writer = FrameWriter(tmp_path / "out")
        s = run_frames(src, writer, runner, image_size=(32, 24))
        writer.close()
    assert (s.frames, s.skipped) == (3, 2)
    assert [d["source"] for d in _index(tmp_path / "out")] == [
        "img00.png",
        "img01.png",
        "img02.png",
    ]
    with open_source(tmp_path / "in") as src:
        writer = FrameWriter(tmp_path / "out2")
        with pytest.raises(MeasurementError, match=r"img01b.png is 10x10 px .* 32x24"):
            run_frames(
                src, writer, _ThreadRunner([0.0] * 5), image_size=(32, 24), on_bad_frame="stop"
            )
        writer.close()
    assert len(_index(tmp_path / "out2")) == 2  # the frames before it are whole


def test_writer_refuses_a_folder_with_frames(tmp_path: Path):
    w = FrameWriter(tmp_path / "out")
    w.write("a", _result(2))
    w.write("b", _result(2))
    w.close()
    with pytest.raises(MeasurementError, match="already holds frames"):
        FrameWriter(tmp_path / "out")
    (tmp_path / "out" / ".frame_000001.ply.x1y2.tmp").write_bytes(b"ply\n")  # a killed write
    w = FrameWriter(tmp_path / "out", overwrite=True)
    w.write("c", _result(3))  # the old frames and index go with the first new frame
    w.close()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
        [INDEX_FILE, "frame_000000.ply"]
    )
    assert [d["source"] for d in _index(tmp_path / "out")] == ["c"]
    with pytest.raises(MeasurementError, match="closed"):
        w.write("d", _result(1))
    (tmp_path / "file").write_text("x")
    with pytest.raises(MeasurementError, match="is a file"):
        FrameWriter(tmp_path / "file")


# --------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def frames_dir(calibrated: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four frames: holes, steps, holes, steps."""
    d = tmp_path_factory.mktemp("frames")
    for i, name in enumerate(["holes", "steps", "holes", "steps"]):
        shutil.copy(calibrated / "scans" / f"{name}.png", d / f"f{i}_{name}.png")
    return d


@pytest.fixture(scope="module")
def serial_out(calibrated: Path, frames_dir: Path, tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("serial") / "out"
    assert main(["stream", str(calibrated), str(frames_dir), "-o", str(out)]) == 0
    return out


def _same_out(a: Path, b: Path) -> None:
    pa, pb = sorted(p.name for p in a.glob("*.ply")), sorted(p.name for p in b.glob("*.ply"))
    assert pa == pb and pa
    for name in pa:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    strip = [{k: v for k, v in d.items() if k != "ms"} for d in _index(a)]
    assert strip == [{k: v for k, v in d.items() if k != "ms"} for d in _index(b)]


@pytest.mark.slow
def test_stream_gives_the_points_of_scan(calibrated: Path, serial_out: Path, tmp_path: Path):
    assert main(["scan", str(calibrated), "-o", str(tmp_path / "scan")]) == 0
    lines = _index(serial_out)
    assert [d["source"] for d in lines] == [
        "f0_holes.png",
        "f1_steps.png",
        "f2_holes.png",
        "f3_steps.png",
    ]
    for d in lines:
        name = d["source"].split("_")[1][:-4]
        got = read_ply(serial_out / f"frame_{d['frame']:06d}.ply")
        want = read_ply(tmp_path / "scan" / f"{name}.ply")
        assert list(got) == list(want)
        for k in want:
            assert np.array_equal(got[k], want[k]), k
        assert d["points"] == len(want["x"]) > 1000 and d["slits"] >= 20 and d["ms"] > 0


@pytest.mark.slow
def test_stream_writes_the_dot_points_as_scan_does(calibrated, frames_dir, tmp_path, capsys):
    """--dot-points: each frame's PLY holds the scan's points and its dots' (dot = 1)."""
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(frames_dir / "f1_steps.png", one / "f1_steps.png")
    out, scan = tmp_path / "out", tmp_path / "scan"
    assert main(["stream", str(calibrated), str(one), "-o", str(out), "--dot-points"]) == 0
    assert main(["scan", str(calibrated), "-o", str(scan), "--dot-points"]) == 0
    got, want = read_ply(out / "frame_000000.ply"), read_ply(scan / "steps.ply")
    assert list(got) == list(want) and "dot" in got and 0 < int(got["dot"].sum()) < len(got["x"])
    for k in want:
        assert np.array_equal(got[k], want[k]), k
    # the hole measurement takes no dot points
    with pytest.raises(SystemExit) as exc:
        main(["holes", str(calibrated), "--dot-points"])
    assert exc.value.code == 2 and "--dot-points" in capsys.readouterr().err


@pytest.mark.slow
def test_two_workers_write_the_serial_files_in_order(calibrated, frames_dir, serial_out, tmp_path):
    out = tmp_path / "out"
    assert main(["stream", str(calibrated), str(frames_dir), "-o", str(out), "--workers", "2"]) == 0
    _same_out(serial_out, out)


@pytest.mark.slow
def test_dask_local_cluster_equals_serial(calibrated, frames_dir, serial_out, tmp_path):
    from multislit.app.batch import batch
    from multislit.reconstruct import ScanOptions

    s = batch(calibrated, frames_dir, tmp_path / "out", workers=2, processes=False)
    assert s.frames == 4
    _same_out(serial_out, tmp_path / "out")
    photo = ScanOptions().with_extraction(reject_texture=True)  # the options reach the cluster
    batch(calibrated, frames_dir, tmp_path / "photo", workers=2, processes=False, options=photo)
    run = json.loads((tmp_path / "photo" / "run.json").read_text())
    assert run["command"] == "batch" and ScanOptions.from_dict(run["options"]) == photo
    got = [len(read_ply(p)["x"]) for p in sorted((tmp_path / "photo").glob("*.ply"))]
    assert got != [len(read_ply(p)["x"]) for p in sorted(serial_out.glob("*.ply"))]


@pytest.mark.slow
def test_dask_frames_alike_all_scanned(calibrated, tmp_path):
    """Equal frames (a static or dark scene) each keep their own data on the cluster: one
    finished frame does not release what a later, equal one still needs."""
    from multislit.app.batch import batch

    frames = tmp_path / "frames"
    frames.mkdir()
    dark = np.zeros(cv2.imread(str(calibrated / "scans" / "holes.png"), 0).shape, np.uint8)
    for i in range(60):
        cv2.imwrite(str(frames / f"f{i:03d}.png"), dark)
    with pytest.raises(MeasurementError, match="60 written without points"):
        batch(calibrated, frames, tmp_path / "out", workers=2)  # dark: no frame gives points
    assert [d["frame"] for d in _index(tmp_path / "out")] == list(range(60))


@pytest.mark.slow
def test_lossless_video_gives_the_same_points(calibrated, frames_dir, serial_out, tmp_path):
    imgs = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted(frames_dir.glob("*.png"))]
    h, w = imgs[0].shape
    for codec in ("FFV1", "MJPG"):
        path = tmp_path / f"{codec}.avi"
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 10, (w, h))
        for im in imgs[:2]:
            vw.write(cv2.cvtColor(im, cv2.COLOR_GRAY2BGR))
        vw.release()
        out = tmp_path / codec
        assert main(["stream", str(calibrated), str(path), "-o", str(out)]) == 0
        lines = _index(out)
        assert [d["source"] for d in lines] == [f"{codec}.avi#0", f"{codec}.avi#1"]
        for d in lines:
            got = read_ply(out / f"frame_{d['frame']:06d}.ply")
            want = read_ply(serial_out / f"frame_{d['frame']:06d}.ply")
            if codec == "FFV1":
                for k in want:
                    assert np.array_equal(got[k], want[k])
            else:  # JPEG-compressed: close to the same points
                assert abs(len(got["x"]) - len(want["x"])) < 0.1 * len(want["x"])


@pytest.mark.slow
def test_stream_cli_bad_input(calibrated: Path, frames_dir: Path, tmp_path: Path, capsys):
    code = main(["stream", str(calibrated), str(tmp_path / "none"), "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "no such file or folder" in err and len(err.strip().splitlines()) == 1
    code = main(["stream", str(calibrated), "camera:7", "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "no camera 7" in err and len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad"
    bad.mkdir()
    shutil.copy(frames_dir / "f0_holes.png", bad / "a.png")
    cv2.imwrite(str(bad / "b.png"), np.zeros((100, 120), np.uint8))
    code = main(
        ["stream", str(calibrated), str(bad), "-o", str(tmp_path / "o1"), "--on-bad-frame", "stop"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "b.png is 120x100 px" in err
    assert main(["stream", str(calibrated), str(bad), "-o", str(tmp_path / "o2")]) == 0
    out = capsys.readouterr().out
    assert "1 frame(s)" in out and "1 skipped" in out


@pytest.mark.slow
def test_killed_stream_leaves_whole_frames(calibrated: Path, tmp_path: Path):
    many = tmp_path / "many"
    many.mkdir()
    for i in range(12):
        shutil.copy(calibrated / "scans" / "holes.png", many / f"f{i:02d}.png")
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "multislit.app.cli",
            "stream",
            str(calibrated),
            str(many),
            "-o",
            str(out),
        ],
        stderr=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        env=env,
    )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if (out / INDEX_FILE).exists() and len(_index(out)) >= 2:
            break
        time.sleep(0.05)
    time.sleep(0.3)  # somewhere inside the next frame
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    lines = _index(out)  # every line parses
    assert 2 <= len(lines) < 12
    assert [d["frame"] for d in lines] == list(range(len(lines)))
    plys = sorted(p.name for p in out.glob("frame_*.ply"))
    assert plys[: len(lines)] == [f"frame_{i:06d}.ply" for i in range(len(lines))]
    assert len(plys) <= len(lines) + 1  # at most the frame written, not yet indexed
    for name in plys:
        assert len(read_ply(out / name)["x"]) > 1000  # whole files only


@pytest.mark.slow
def test_basler_emulation_whole_path(
    calibrated: Path, serial_out: Path, tmp_path: Path, monkeypatch
):
    _emulation_or_skip(monkeypatch)
    replay = tmp_path / "replay"
    replay.mkdir()
    shutil.copy(calibrated / "scans" / "holes.png", replay / "a.png")
    shutil.copy(calibrated / "scans" / "steps.png", replay / "b.png")
    out = tmp_path / "out"
    argv = ["stream", str(calibrated), "basler:", "-o", str(out), "--max-frames", "2"]
    argv += ["--pylon", f"ImageFilename={replay}", "--pylon", "ImageFileMode=On"]
    argv += ["--pylon", "TestImageSelector=Off"]
    assert main(argv) == 0
    lines = _index(out)
    assert len(lines) == 2
    wants = [read_ply(serial_out / f"frame_{i:06d}.ply") for i in (0, 1)]  # holes, steps
    for d in lines:
        got = read_ply(out / f"frame_{d['frame']:06d}.ply")
        assert any(all(np.array_equal(got[k], w[k]) for k in w) for w in wants)


def test_threads_left_running_none():
    # the live sources' grabber threads end with their source
    assert not [t for t in threading.enumerate() if t.name.startswith("grab ")]


@pytest.mark.slow
def test_batch_unreachable_scheduler(calibrated, frames_dir, tmp_path, capsys, monkeypatch):
    from multislit.app import batch as batch_mod

    monkeypatch.setattr(batch_mod, "_CONNECT_TIMEOUT_S", 1)
    argv = ["batch", str(calibrated), str(frames_dir), "-o", str(tmp_path / "o")]
    code = main([*argv, "--dask", "tcp://127.0.0.1:9"])
    err = capsys.readouterr().err
    assert code == 2 and "cannot reach the Dask scheduler" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_prior_keeps_the_slits_of_the_full_search(calibrated, frames_dir, tmp_path, capsys):
    """With ``--prior`` (the template identification) each frame is checked against the
    previous frame's slits first: no point gets another slit than the single-image scan gives
    it, and almost none is lost. The identification by the dots' geometry takes no prior."""
    base = ["stream", str(calibrated), str(frames_dir), "--method", "template"]
    full, out = tmp_path / "full", tmp_path / "prior"
    assert main([*base, "-o", str(full)]) == 0
    assert main([*base, "-o", str(out), "--prior"]) == 0
    for a, b in zip(sorted(full.glob("*.ply")), sorted(out.glob("*.ply")), strict=True):
        want, got = read_ply(a), read_ply(b)
        kw = np.round(want["v"]) * 1e5 + np.round(want["u"], 2)
        kg = np.round(got["v"]) * 1e5 + np.round(got["u"], 2)
        common, iw, ig = np.intersect1d(kw, kg, return_indices=True)
        assert np.array_equal(want["slit"][iw], got["slit"][ig]), a.name
        assert len(common) >= 0.99 * len(kw), a.name
    assert main([*base, "-o", str(tmp_path / "o"), "--prior", "--workers", "2"]) == 2
    capsys.readouterr()
    argv = ["stream", str(calibrated), str(frames_dir), "-o", str(tmp_path / "g"), "--prior"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--method template" in err, err
    assert not (tmp_path / "g").exists()


def test_live_camera_of_the_wrong_size_stops(tmp_path: Path, monkeypatch):
    """A camera that delivers only frames of another size than the calibration's: the run
    stops with the reason instead of skipping frames for ever."""
    from multislit.app import stream as stream_mod

    monkeypatch.setattr(sources_mod.cv2, "VideoCapture", _FakeCapture)  # 32x24 frames
    monkeypatch.setattr(stream_mod, "_LIVE_BAD_FRAMES_S", 0.5, raising=False)
    outcome = []

    def run():
        with open_source("camera:0") as src:
            writer = FrameWriter(tmp_path / "out")
            try:
                run_frames(src, writer, _ThreadRunner([0.0] * 9), image_size=(64, 48))
            except MeasurementError as exc:
                outcome.append(str(exc))
            finally:
                writer.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout=20)
    assert not t.is_alive(), "the run skips wrong-size frames for ever"
    assert outcome and "no usable frame for 0 s" in outcome[0]
    assert "32x24 px but the calibration is for 64x48 px" in outcome[0]
    assert not (tmp_path / "out").exists()


def test_non_ascii_source_names_in_the_frames(tmp_path: Path):
    w = FrameWriter(tmp_path / "out")
    w.write("café_ü.png", _result(2))
    w.close()
    assert _index(tmp_path / "out")[0]["source"] == "café_ü.png"
    assert b"caf\\xe9_\\xfc.png" in (tmp_path / "out" / "frame_000000.ply").read_bytes()[:300]


@pytest.mark.slow
def test_pictures_and_run_record(
    calibrated: Path, frames_dir: Path, serial_out: Path, tmp_path: Path
):
    """``--pictures`` writes each frame's picture beside its PLY (stream, two workers, and
    scan); ``run.json`` says how the run was made; the view finds the calibration there."""
    from multislit.app.index import RUN_FILE
    from multislit.app.view import find_calibration

    out = tmp_path / "out"
    argv = ["stream", str(calibrated), str(frames_dir), "-o", str(out), "--pictures"]
    argv += ["--reject-texture", "--channel", "auto"]  # the scan's options reach the workers
    assert main([*argv, "--workers", "2", "--max-frames", "2"]) == 0
    for i in range(2):
        pic = cv2.imread(str(out / f"frame_{i:06d}.png"))
        assert pic.shape == (512, 640, 3)
        magenta = np.all(pic == (255, 0, 255), axis=2).sum()
        coloured = (pic.max(axis=2).astype(int) - pic.min(axis=2) > 60).sum()
        assert coloured > 2 * magenta > 0  # the points by slit, and the centres left out
    run = json.loads((out / RUN_FILE).read_text())
    assert run["command"] == "stream" and run["format"] == "multislit-run/1"
    assert run["capture"] == str(calibrated.resolve())
    assert run["calibration"] == str((calibrated / "calibration.json").resolve())
    assert run["source"] == str(frames_dir) and run["settings"]["channel"] == "auto"
    assert run["options"]["extraction"]["reject_texture"] is True
    assert run["options"]["extraction"]["channel"] == "auto"
    assert find_calibration(out) == calibrated.resolve() / "calibration.json"
    photo, plain = read_ply(out / "frame_000000.ply"), read_ply(serial_out / "frame_000000.ply")
    assert len(photo["x"]) > 1000 and len(photo["x"]) != len(plain["x"])  # the photo mode's
    pts = tmp_path / "pts"
    assert main(["scan", str(calibrated), "-o", str(pts), "--pictures"]) == 0
    assert sorted(p.name for p in pts.iterdir()) == sorted(
        ["holes.ply", "holes.png", "steps.ply", "steps.png"]
    )
