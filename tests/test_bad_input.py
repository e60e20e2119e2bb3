"""Bad input on the command line and in the library: one clear line (exit 2 on the command
line) or the right result; outputs written whole or not at all; inputs never overwritten."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from multislit.app.cli import main
from multislit.calibrate import Calibration, calibrate_capture, write_calibration
from multislit.calibrate.pipeline import _hand_reading_problem
from multislit.calibrate.slit_planes import SlitPlanes, fit_slit_planes
from multislit.calibrate.slit_points import SlitPointSet
from multislit.errors import (
    CalibrationError,
    CaptureError,
    MeasurementError,
    MultislitError,
    ReferenceImageError,
)
from multislit.geometry import MatrixCamera, PinholeCamera
from multislit.identify import prepare_reference
from multislit.io import Capture, read_image, read_ply, write_image, write_json, write_ply
from multislit.reconstruct import ScanResult, scan_image
from tests.test_calibration import _calibration, grating_planes, points_on_planes


def _cli(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _one_error_line(err: str, command: str) -> str:
    """The single error line the CLI printed (and nothing else on stderr)."""
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"multislit {command}: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.fixture()
def cap(small_capture: Path, tmp_path: Path) -> Path:
    """A copy of the small capture that a test may change."""
    dst = tmp_path / "cap"
    shutil.copytree(small_capture, dst, ignore=shutil.ignore_patterns("truth"))
    return dst


def _fake_calibration(size=(640, 512), num_slits: int = 25) -> Calibration:
    """A calibration of the right image size and slit count (its geometry is not the rig's):
    enough for checks that stop before triangulation."""
    cam = PinholeCamera(fx=900, fy=900, cx=320, cy=256, tvec=(0, 0, 1000), image_size=size)
    planes, _, _ = grating_planes(num_slits)
    sp = SlitPlanes(planes, np.zeros(num_slits), np.full(num_slits, 10))
    return Calibration(size, MatrixCamera(cam.matrix, image_size=size), refined=cam, slit_planes=sp)


# --------------------------------------------------------------------------- unreadable text
def test_non_utf8_rig_json(cap, capsys):
    (cap / "rig.json").write_bytes((cap / "rig.json").read_bytes().replace(b'"num', b'"\xffnum'))
    rc, _, err = _cli(capsys, "scan", cap)
    line = _one_error_line(err, "scan")
    assert rc == 2 and "rig.json is not UTF-8 text" in line and "save it as UTF-8" in line


def test_non_utf8_calibration_json(cap, capsys):
    bad = cap / "calibration.json"
    bad.write_bytes(b'{"schema": "multislit-calibration/1", "x": "\xe9"}')
    rc, _, err = _cli(capsys, "scan", cap)
    assert rc == 2 and "calibration.json is not UTF-8 text" in _one_error_line(err, "scan")
    with pytest.raises(CalibrationError, match="not UTF-8"):
        Calibration.from_json(bad.read_bytes())


def test_non_utf8_rig_file(tmp_path, capsys):
    rig = tmp_path / "rig.json"
    rig.write_bytes(b'{"slits": {"num_slits": 7}, "note": "\xff"}')
    rc, _, err = _cli(capsys, "simulate", tmp_path / "c", "--rig", rig)
    assert rc == 2 and "rig file" in _one_error_line(err, "simulate") and "UTF-8" in err
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize(
    "rig", ['{"camera": 5}', '{"slits": {"num_slits": "x"}}', '{"reference_distances": 5}']
)
def test_rig_file_with_wrong_types(tmp_path, capsys, rig):
    (tmp_path / "rig.json").write_text(rig)
    rc, _, err = _cli(capsys, "simulate", tmp_path / "c", "--rig", tmp_path / "rig.json")
    line = _one_error_line(err, "simulate")
    assert rc == 2 and "a value has the wrong type" in line and "multislit rig" in line


# --------------------------------------------------------------------------- output places
def test_outputs_under_a_file_or_on_a_file(cap, tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("keep")
    cases = [
        ("simulate", [f / "sub", "--scale", "0.1"], "cannot create a folder under"),
        ("demo", ["--out", f], "is a file, not a folder"),
        ("demo", ["--out", f / "sub"], "cannot create a folder under"),
        ("scan", [cap, "-o", f / "sub"], "cannot create a folder under"),
        ("scan", [cap, "-o", f], "is a file, not a folder"),
        ("calibrate", [cap, "-o", tmp_path], "is a folder"),
        ("calibrate", [cap, "-o", f / "sub" / "c.json"], "cannot create a folder under"),
    ]
    for command, args, message in cases:
        rc, _, err = _cli(capsys, command, *args)
        assert rc == 2 and message in _one_error_line(err, command), (command, args, err)
    assert f.read_text() == "keep"


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_output_folder_that_cannot_be_created(tmp_path, capsys):
    """/proc refuses new folders even to root: the failure is one line."""
    for command, args in (
        ("simulate", ["/proc/multislit-test", "--scale", "0.1"]),
        ("demo", ["--out", "/proc/multislit-test", "--scale", "0.2"]),
    ):
        rc, _, err = _cli(capsys, command, *args)
        line = _one_error_line(err, command)
        assert rc == 2 and line.endswith(": /proc/multislit-test"), line


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root may write anywhere")
def test_output_folder_without_permission(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        rc, _, err = _cli(capsys, "simulate", locked / "c", "--scale", "0.1")
        assert rc == 2 and "permission denied" in _one_error_line(err, "simulate")
    finally:
        locked.chmod(0o700)


def test_calibrate_refuses_to_overwrite_an_input(cap, tmp_path, capsys):
    scan = cap / "scans" / "holes.png"
    before = {p: p.read_bytes() for p in (scan, cap / "rig.json", cap / "target.json")}
    link = tmp_path / "link.png"
    link.symlink_to(scan)
    for out in (scan, cap / "rig.json", cap / "target.json", link, cap / "." / "scans/../rig.json"):
        rc, _, err = _cli(capsys, "calibrate", cap, "-o", out)
        line = _one_error_line(err, "calibrate")
        assert rc == 2 and "would overwrite an input" in line and "choose another -o" in line
    assert all(p.read_bytes() == b for p, b in before.items())


def test_scan_refuses_to_overwrite_an_input(cap, capsys):
    ply = cap / "points" / "holes.ply"
    ply.parent.mkdir()
    ply.write_bytes(b"my calibration, oddly named")
    rc, _, err = _cli(capsys, "scan", cap, "--calibration", ply)
    assert rc == 2 and f"would overwrite an input of the command ({ply})" in err
    assert ply.read_bytes() == b"my calibration, oddly named"


# --------------------------------------------------------------------------- numeric options
@pytest.mark.parametrize(
    "args, message",
    [
        (["--scale", "inf"], "--scale must be a finite positive number, got inf"),
        (["--scale", "nan"], "got nan"),
        (["--scale", "50"], "64000x51200 px camera (3276.8 Mpx, about 1160 GB"),
        (["--scale", "50"], "the limit is 16 Mpx"),
        (["--seed", "-1"], "--seed must be a non-negative integer, got -1"),
        (["--slits", "0"], "--slits must be a positive number of slits, got 0"),
        (["--slits", "-3"], "got -3"),
    ],
)
def test_simulate_numeric_options(tmp_path, capsys, args, message):
    rc, _, err = _cli(capsys, "simulate", tmp_path / "c", *args)
    assert rc == 2 and message in _one_error_line(err, "simulate")
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--seed", "-1"], "--seed must be a non-negative integer"),
        (["--scale", "inf"], "scale"),
        (["--scale", "50"], "scale"),
    ],
)
def test_demo_numeric_options(tmp_path, capsys, args, message):
    rc, _, err = _cli(capsys, "demo", "--out", tmp_path / "d", *args)
    assert rc == 2 and message in _one_error_line(err, "demo")


def test_simulate_slits_option_is_used(tmp_path, capsys):
    rc, out, _ = _cli(capsys, "simulate", tmp_path / "c", "--slits", "5", "--scale", "0.1")
    assert rc == 0 and "5 slits" in out
    assert Capture.open(tmp_path / "c").num_slits == 5


# --------------------------------------------------------------------------- atomic writes
def _fail_at_fsync(monkeypatch):
    """Make every atomic write fail after its bytes are in the temporary file (disk full)."""

    def fsync(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("multislit.io.jsonio.os.fsync", fsync)


def test_failed_writes_leave_the_old_file(tmp_path, monkeypatch):
    cal_path, ply_path, png_path = tmp_path / "c.json", tmp_path / "p.ply", tmp_path / "i.png"
    result = SimpleNamespace(calibration=_calibration(), report=lambda: {"source": "hand"})
    write_calibration(result, cal_path)
    write_ply(ply_path, np.ones((5, 3)))
    write_image(png_path, np.full((8, 8), 7, np.uint8))
    before = {p: p.read_bytes() for p in (cal_path, ply_path, png_path)}
    _fail_at_fsync(monkeypatch)
    with pytest.raises(CaptureError, match="No space left"):
        write_calibration(result, cal_path)
    with pytest.raises(MultislitError, match="cannot write PLY .*No space left"):
        write_ply(ply_path, np.zeros((500, 3)))
    with pytest.raises(CaptureError, match="cannot write image .*No space left"):
        write_image(png_path, np.zeros((64, 64), np.uint8))
    with pytest.raises(OSError):
        write_json(tmp_path / "new.json", {"a": 1})
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.json", "i.png", "p.ply"]
    Calibration.load(cal_path)  # still the whole, valid file


@pytest.fixture(scope="module")
def small_reference(small_capture: Path):
    """The small capture's prepared reference."""
    from multislit.identify import capture_reference

    return capture_reference(Capture.open(small_capture))


def test_failed_reference_save_leaves_the_old_file(small_reference, tmp_path, monkeypatch):
    reference = small_reference
    p = tmp_path / "ref.npz"
    reference.save(tmp_path / "ref")  # the suffix is added
    before = p.read_bytes()
    _fail_at_fsync(monkeypatch)
    with pytest.raises(OSError, match="No space left"):
        reference.save(p)
    assert p.read_bytes() == before and [q.name for q in tmp_path.iterdir()] == ["ref.npz"]


def test_cli_write_failure_is_one_line(cap, capsys, monkeypatch):
    """A failing disk during 'calibrate' is an error line, and the old calibration stays."""
    import multislit.calibrate as calibrate_pkg

    old = _fake_calibration()
    old.save(cap / "calibration.json")
    before = (cap / "calibration.json").read_bytes()
    fake = SimpleNamespace(calibration=_calibration(), report=lambda: {})
    monkeypatch.setattr(calibrate_pkg, "calibrate_capture", lambda *a, **k: fake)
    monkeypatch.setattr(calibrate_pkg, "format_report", lambda r: [])
    _fail_at_fsync(monkeypatch)
    rc, _, err = _cli(capsys, "calibrate", cap)
    assert rc == 2 and "No space left on device" in _one_error_line(err, "calibrate")
    assert (cap / "calibration.json").read_bytes() == before


# --------------------------------------------------------------------------- library arguments
def test_scan_image_needs_a_reference_and_a_calibration(tmp_path):
    img = np.zeros((512, 640), np.uint8)
    cal = _fake_calibration()
    with pytest.raises(MeasurementError, match="reference must be a ReferenceSet .* got NoneType"):
        scan_image(img, None, cal)
    with pytest.raises(MeasurementError, match="got PosixPath|got WindowsPath"):
        scan_image(img, tmp_path / "reference", cal)
    ref = SimpleNamespace(curves=np.zeros((2, 25, 3)))  # looks like one, is not one
    with pytest.raises(MeasurementError, match="got SimpleNamespace"):
        scan_image(img, ref, cal)
    with pytest.raises(MeasurementError, match="previous must be the ScanResult .* got str"):
        scan_image(img, ref, cal, previous="frame_000001.ply")


@pytest.mark.parametrize(
    "images, match",
    [
        (np.zeros(100), r"got an array of shape \(100,\)"),
        ([np.zeros(100), np.zeros(100)], r"'ref0' must be a 2-D .* got shape \(100,\)"),
        ("ref.png", "got str"),
        (None, "got NoneType"),
        ([None, None], "'ref0' must be"),
    ],
)
def test_prepare_reference_bad_images(images, match):
    with pytest.raises(ReferenceImageError, match=match):
        prepare_reference(images, 25)


# --------------------------------------------------------------------------- PLY values
def test_ascii_ply_value_beyond_float32_is_an_error_without_warnings(tmp_path, recwarn):
    p = tmp_path / "w.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n1e300 0 0\n1 1 1\n"
    )
    with pytest.raises(MultislitError, match=r"'x' declared float32 holds values beyond"):
        read_ply(p)
    assert not recwarn.list


def test_ply_with_non_finite_points_is_refused(tmp_path, recwarn):
    p = tmp_path / "n.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty float v\nproperty int slit\nend_header\n"
        "nan 0 0 1 3\n1 1 1 2 4\n"
    )
    assert np.isnan(read_ply(p)["x"][0])  # the file is valid PLY ...
    with pytest.raises(MeasurementError, match="NaN or infinite x values"):
        ScanResult.from_ply(p)  # ... but not a scan
    assert not recwarn.list


def test_broken_png_is_one_message_and_nothing_on_stderr(tmp_path, capfd):
    p = tmp_path / "broken.png"
    p.write_bytes(b"\x89PNG\r\n\x1a\nnot a png")
    with pytest.raises(CaptureError, match="not a valid PNG"):
        read_image(p)
    assert capfd.readouterr().err == ""  # OpenCV's own log line is silenced


# --------------------------------------------------------------------------- messages
def test_marker_far_away_is_named(cap):
    t = json.loads((cap / "target.json").read_text())
    t["markers"][2]["xyz"] = [1e300, 0, 0]
    (cap / "target.json").write_text(json.dumps(t))
    with pytest.raises(
        CaptureError, match=r"markers\[2\]\.xyz = \[1e\+300, 0, 0\] is out of range"
    ):
        Capture.open(cap)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (
            lambda d: d["camera_dlt"]["C"][1].__setitem__(2, None),
            r"camera_dlt\.C\[1\]\[2\] must be a number",
        ),
        (
            lambda d: d["camera_dlt"]["C"][0].__setitem__(0, float("nan")),
            r"C\[0\]\[0\] must be finite, got nan",
        ),
        (lambda d: d["camera_dlt"].__setitem__("C", [[1, 2, 3, 4]]), r"C must be a list of 3"),
        (
            lambda d: d["camera_refined"].__setitem__("fx", -5),
            r"camera_refined\.fx must be positive",
        ),
        (lambda d: d["camera_refined"].__setitem__("rvec", [1e300, 0, 0]), "rotation vector"),
        (lambda d: d.__setitem__("image_size", [640]), r"image_size must be \[W, H\]"),
        (
            lambda d: d["residuals"].__setitem__("markers_px", [1, 2]),
            "markers_px must be an object",
        ),
    ],
)
def test_calibration_messages_name_the_value(mutate, match):
    d = json.loads(_calibration().to_json())
    mutate(d)
    with pytest.raises(CalibrationError, match=match):
        Calibration.from_dict(d)


def test_slit_planes_must_have_unit_normals_and_one_plane(tmp_path):
    d = json.loads(_calibration().to_json())
    d["slit_planes"]["planes"][3] = [2 * x for x in d["slit_planes"]["planes"][3]]
    with pytest.raises(CalibrationError, match=r"planes\[3\] has a normal of length 2;"):
        Calibration.from_dict(d)
    d = json.loads(_calibration().to_json())
    d["slit_planes"]["planes"] = [[None] * 4 for _ in d["slit_planes"]["planes"]]
    p = tmp_path / "c.json"
    p.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match=f"{p}: slit_planes: no slit has a plane"):
        Calibration.load(p)
    d = json.loads(_calibration().to_json())
    d["slit_planes"]["planes"][0][1] = None
    with pytest.raises(CalibrationError, match="mixes numbers and nulls"):
        Calibration.from_dict(d)


# --------------------------------------------------------------------------- scans without slits
def test_scan_image_calibration_path_is_refused(small_capture, small_reference):
    img = np.zeros((512, 640), np.uint8)
    with pytest.raises(CalibrationError, match=r"Calibration \(e.g. Calibration.load\(path\)\)"):
        scan_image(img, small_reference, str(small_capture / "calibration.json"))


def test_scan_without_slits_keeps_no_points(small_capture, small_calibrated):
    cap = Capture.open(small_capture)
    cal, small_reference = small_calibrated.calibration, small_calibrated.reference
    off = scan_image(cap.image(cap.markers_image), small_reference, cal, name="off")
    assert off.num_points == 0 and "no slit identified" in off.message
    assert "lasers on" in off.summary()
    holes = cap.image(cap.scans[0])
    for img in (holes[:, ::-1], holes[::-1, ::-1]):  # mirrored, rotated half a turn
        res = scan_image(np.ascontiguousarray(img), small_reference, cal)
        assert res.num_points == 0 and "not mirrored or rotated" in res.message
    ok = scan_image(holes, small_reference, cal)
    assert ok.num_centres > 0 and ok.message == ""
    assert np.count_nonzero(ok.identification.slit >= 0) > 0.5 * ok.num_centres


@pytest.mark.slow
def test_cli_scan_without_slits_exits_2(cap, tmp_path, capsys, small_calibrated):
    small_calibrated.calibration.save(tmp_path / "cal.json")
    black = tmp_path / "black.png"
    cv2.imwrite(str(black), np.zeros((512, 640), np.uint8))
    for image, message in (
        (cap / "calibration" / "markers.png", "no slit identified"),
        (black, "no slits found in the image"),
    ):
        args = ["--image", image, "--calibration", tmp_path / "cal.json", "-o", tmp_path / "pts"]
        rc, _, err = _cli(capsys, "scan", cap, *args)
        line = _one_error_line(err, "scan")
        assert rc == 2 and "1 of 1 scan(s) gave no points (no PLY written)" in line
        assert message in line
    assert not (tmp_path / "pts" / "markers.ply").exists()


def test_cli_scan_without_a_dot_projector_says_what_to_do(cap, tmp_path, capsys):
    """A calibration without the dot projector: identification by the dots' geometry cannot
    run; one line says to recalibrate or use the templates, which then run."""
    _fake_calibration().save(tmp_path / "cal.json")
    args = ["--calibration", tmp_path / "cal.json", "-o", tmp_path / "pts"]
    rc, _, err = _cli(capsys, "scan", cap, *args)
    line = _one_error_line(err, "scan")
    assert rc == 2 and "no dot projector" in line and "template" in line
    rc, _, err = _cli(capsys, "scan", cap, *args, "--method", "template")
    assert "no dot projector" not in err


# --------------------------------------------------------------------------- holes from a PLY
def test_holes_from_a_ply_is_refused_with_the_command(cap, tmp_path, capsys):
    ply = cap / "points" / "holes.ply"
    ply.parent.mkdir()
    write_ply(ply, np.ones((3, 3)), v=np.ones(3), slit=np.zeros(3, int))
    rc, out, err = _cli(capsys, "holes", ply)
    line = _one_error_line(err, "holes")
    assert rc == 2 and out == ""
    assert f"multislit holes {cap} --image {cap / 'scans' / 'holes.png'}" in line
    other = tmp_path / "elsewhere.ply"
    shutil.copy(ply, other)
    rc, _, err = _cli(capsys, "holes", other)
    assert rc == 2 and "multislit holes CAPTURE --image CAPTURE/scans/NAME.png" in err


# --------------------------------------------------------------------------- hand readings
def _hand_points(labels: np.ndarray, X: np.ndarray) -> SlitPointSet:
    n = len(X)
    return SlitPointSet(X, labels, np.zeros((n, 2)), np.full(n, -1), "hand")


def test_hand_reading_off_by_one_is_named():
    rng = np.random.default_rng(4)
    planes, _, _ = grating_planes(15)
    X, s = points_on_planes(rng, planes, per_slit=4, noise=0.02)
    good = fit_slit_planes(X, s, 15).planes
    assert _hand_reading_problem(_hand_points(s, X), good) is None
    one = s.copy()
    one[np.flatnonzero(s == 6)[1]] = 7  # one reading of slit 6 numbered 7
    bad = _hand_reading_problem(_hand_points(one, X), fit_slit_planes(X, one, 15).planes)
    i = int(np.flatnonzero(s == 6)[1])
    assert bad is not None and "slit 7's readings lie" in bad
    assert f"slit_points[{i}] lies nearer slit 6's plane" in bad
    whole = s.copy()
    whole[s == 10] = 11  # every reading of slit 10 numbered 11
    bad = _hand_reading_problem(_hand_points(whole, X), fit_slit_planes(X, whole, 15).planes)
    assert (
        bad is not None and "slit 11's readings" in bad and "slit 10" not in bad.split(";")[0][:12]
    )


def _renumber(cap: Path, change) -> None:
    t = json.loads((cap / "target.json").read_text())
    change(t["slit_points"])
    (cap / "target.json").write_text(json.dumps(t))


@pytest.mark.slow
def test_cli_calibrate_hand_readings_off_by_one(cap, capsys):
    def slit_10_as_11(points):
        for p in points:
            if p["slit"] == 10:
                p["slit"] = 11

    _renumber(cap, slit_10_as_11)
    rc, out, err = _cli(capsys, "calibrate", cap, "--source", "hand")
    line = _one_error_line(err, "calibrate")
    assert rc == 2 and "slit 11's readings lie" in line and "lies nearer slit 10's plane" in line
    assert not (cap / "calibration.json").exists()


@pytest.mark.slow
def test_slits_image_without_the_target_is_refused(cap):
    """A flat board's image as calibration/slits.png: its points, put on the target's faces,
    give planes through the camera; the calibration falls back to the hand readings (and says
    so) or stops."""
    shutil.copy(cap / "reference" / "ref_0900.png", cap / "calibration" / "slits.png")
    res = calibrate_capture(cap)
    assert res.source == "hand"
    assert any("slits.png does not show the stripes on the target" in n for n in res.notes)
    _renumber(cap, lambda points: points.clear())
    with pytest.raises(CalibrationError, match="pass through the camera: lines of sight meet"):
        calibrate_capture(cap)
