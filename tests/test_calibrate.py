"""Capture-level calibration (multislit.calibrate) and `multislit calibrate` on simulated captures."""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from multislit.app.cli import main
from multislit.calibrate import Calibration, calibrate_capture, format_report, pipeline
from multislit.calibrate.camera import rms
from multislit.calibrate.capture_camera import camera_from_capture
from multislit.calibrate.slit_points import auto_slit_points, points_on_faces, transfer_labels
from multislit.errors import CalibrationError, CaptureError
from multislit.geometry import camera_from_dict
from multislit.io import Capture
from multislit.reconstruct import triangulate
from multislit.stripes import extract_slits


# --------------------------------------------------------------------------- helpers
def truth_labels(capture: Path):
    """Test-only labels (u, v, slit) of the calibration image's stripe centres: the true slit at
    each extracted centre's rounded pixel."""
    cap = Capture.open(capture)
    image = cap.image(cap.slits_image)
    slit = np.load(Path(capture) / "truth" / "slits.npz")["slit"]
    ex = extract_slits(image)
    iu = np.clip(np.round(ex.u).astype(int), 0, image.shape[1] - 1)
    iv = np.clip(np.round(ex.v).astype(int), 0, image.shape[0] - 1)
    return ex.u, ex.v, slit[iv, iu]


def truth(capture: Path):
    m = json.loads((capture / "truth" / "models.json").read_text())
    return camera_from_dict(m["camera"]), np.array(m["projector"]["planes"])


def copy_capture(src: Path, dst: Path, edit=None) -> Path:
    """A copy of the capture without scans/truth; ``edit(target_dict)`` changes target.json."""
    dst.mkdir(parents=True)
    for name in ("rig.json", "target.json"):
        shutil.copy(src / name, dst / name)
    for sub in ("calibration", "reference"):
        shutil.copytree(src / sub, dst / sub)
    if edit is not None:
        t = json.loads((dst / "target.json").read_text())
        edit(t)
        (dst / "target.json").write_text(json.dumps(t))
    return dst


def slits_on_two_faces(capture: Path, min_pixels: int = 20) -> np.ndarray:
    """(N,) bool: slits whose stripe crosses >= 2 target faces in calibration/slits.png (truth).

    A slit seen on one flat face gives a line, which does not determine its plane by itself.
    """
    tr = np.load(capture / "truth" / "slits.npz")
    faces = json.loads((capture / "target.json").read_text())["faces"]
    n = json.loads((capture / "rig.json").read_text())["num_slits"]
    vv, uu = np.nonzero(tr["slit"] >= 0)
    X = tr["xyz"][vv, uu].astype(float)
    k = tr["slit"][vv, uu]
    out = np.zeros(n, bool)
    counts = np.zeros((n, len(faces)), int)
    for j, f in enumerate(faces):
        on = np.abs(X @ np.array(f["plane"][:3]) + f["plane"][3]) < 0.5
        counts[:, j] = np.bincount(k[on], minlength=n)[:n]
    out[:] = (counts >= min_pixels).sum(axis=1) >= 2
    return out


def scan_truth_points(capture: Path, camera, planes, scan: str = "holes"):
    """True 3D points on the true slit planes (from a scan's truth), and their exact pixels."""
    tr = np.load(capture / "truth" / f"{scan}.npz")
    vv, uu = np.nonzero(tr["slit"] >= 0)
    X = tr["xyz"][vv, uu].astype(float)
    k = tr["slit"][vv, uu].astype(np.intp)
    X = X - (np.einsum("ij,ij->i", X, planes[k, :3]) + planes[k, 3])[:, None] * planes[k, :3]
    sel = np.arange(0, len(X), 7)  # thin for speed
    return X[sel], camera.project(X[sel]), k[sel]


def truth_triangulation(capture: Path, cal: Calibration):
    """Triangulate true points (exact pixels, true slits) with ``cal``.

    Returns the share of points valid where the calibration has the slit's plane, and the
    errors (mm) of those points against the truth.
    """
    true_cam, true_planes = truth(capture)
    X, uv, k = scan_truth_points(capture, true_cam, true_planes)
    Y, ok = triangulate(cal.camera, cal.slit_planes.planes, uv, k)
    cal_ok = cal.slit_planes.valid[k]
    ok_share = ok[cal_ok].mean()
    ok &= cal_ok
    return ok_share, np.linalg.norm(Y[ok] - X[ok], axis=1)


@pytest.fixture(scope="module")
def hand_result(small_capture):
    """The hand readings alone (the target's faces; no reference boards)."""
    return calibrate_capture(small_capture, source="hand", references=False)


@pytest.fixture(scope="module")
def auto_result(small_capture):
    """The automatic points with true labels alone (the target's faces; no reference boards)."""
    return calibrate_capture(
        small_capture, source="auto", labels=truth_labels(small_capture), references=False
    )


# --------------------------------------------------------------------------- camera
def test_camera_from_capture(small_capture, hand_result):
    det, refined, res = (
        hand_result.camera.detection,
        hand_result.camera.refined,
        hand_result.camera.residuals,
    )
    assert det.found.all() and len(res.ids) == len(det.ids) >= 12
    # the linear DLT cannot model the lens distortion; the refined model must
    assert res.refined_rms_px <= 0.1 and res.refined_rms_px < res.dlt_rms_px
    true_cam, _ = truth(small_capture)
    xyz = Capture.open(small_capture).target.marker_xyz
    err = np.linalg.norm(refined.project(xyz) - true_cam.project(xyz), axis=1)
    assert err.max() <= 0.15, err


@pytest.mark.slow
def test_camera_is_right_over_the_whole_target(small_capture):
    """The refined camera agrees with the true one over the target faces, not only at markers
    (markers spread over the image pin the distortion down; straight stripes must not spoil it)."""
    true_cam, _ = truth(small_capture)
    cap = Capture.open(small_capture)
    w, h = cap.image_size
    uu, vv = np.meshgrid(np.linspace(0, w - 1, 32), np.linspace(0, h - 1, 26))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    xyz, face = points_on_faces(true_cam, uv, cap.target.faces)
    ok = face >= 0
    assert ok.sum() > 200
    for stripes in (False, True):
        cam = camera_from_capture(cap, use_stripes=stripes).refined
        err = np.linalg.norm(cam.project(xyz[ok]) - uv[ok], axis=1)
        assert rms(err) < 0.1 and err.max() < 0.3, (stripes, rms(err), err.max())


# --------------------------------------------------------------------------- projector
def test_hand_readings_planes(small_capture, hand_result):
    sp = hand_result.calibration.slit_planes
    assert hand_result.source == "hand"
    # every slit clearly seen on two faces gets a plane; one seen on a single face is left out
    must, may = slits_on_two_faces(small_capture, 60), slits_on_two_faces(small_capture, 1)
    assert np.all(sp.valid[must]) and not np.any(sp.valid & ~may)
    assert np.nanmedian(sp.rms_mm) <= 0.05
    # the paper's single 2x4 matrix cannot follow the grating's planes: larger error
    pm = hand_result.projector.projector_rms_mm
    assert np.nanmedian(pm) > 5 * np.nanmedian(sp.rms_mm)
    _, true_planes = truth(small_capture)
    cosang = np.abs(np.sum(sp.planes[:, :3] * true_planes[:, :3], axis=1))
    assert np.nanmax(np.degrees(np.arccos(np.clip(cosang[sp.valid], 0, 1)))) < 0.05


@pytest.mark.slow
def test_auto_points_with_true_labels(small_capture, auto_result):
    r = auto_result
    assert r.source == "auto" and len(r.points) > 3000
    sp = r.calibration.slit_planes
    must = slits_on_two_faces(small_capture, 60)
    assert np.all(sp.valid[must]), r.projector.excluded
    # slits that reach only one face (a line each) get the plane through the common axis
    assert len(sp.from_axis) >= 2 and not must[list(sp.from_axis)].any(), sp.from_axis
    assert np.all(np.isfinite(sp.rms_mm[list(sp.from_axis)]))
    assert sum(f"slit {j} is seen along one line only" in n for n in r.notes for j in sp.from_axis)
    # residuals of single stripe centres (~0.1 px at 1.1 mm/px on the half-size rig), measured
    # 0.082 mm median, 0.110 max with the centres re-centred by refine_centres (0.152 and
    # 0.204 mm with the extraction's centres)
    assert np.nanmedian(sp.rms_mm) <= 0.11
    assert np.nanmax(sp.rms_mm) <= 0.15
    steps = dict(r.points.steps)
    assert steps["labelled"] <= steps["in linked segments"]


@pytest.mark.slow
@pytest.mark.xfail(
    reason="goal 0.05 mm per slit, met at full size; the half-size rig's stripe centres give "
    "about 0.075 mm (median)"
)
def test_auto_points_plane_rms_goal(auto_result):
    assert np.nanmedian(auto_result.calibration.slit_planes.rms_mm) <= 0.05


def per_slit_triangulation(capture: Path, cal: Calibration, scan: str = "holes") -> np.ndarray:
    """(K,) RMS error (mm) of true points triangulated with ``cal``, per slit (NaN: none)."""
    true_cam, true_planes = truth(capture)
    X, uv, k = scan_truth_points(capture, true_cam, true_planes, scan)
    Y, ok = triangulate(cal.camera, cal.slit_planes.planes, uv, k)
    err = np.linalg.norm(Y - X, axis=1)
    return np.array([rms(err[ok & (k == j)]) for j in range(len(true_planes))])


@pytest.mark.slow
def test_one_face_slits_triangulate_like_the_others(small_capture, auto_result):
    """Planes through the common axis and a slit's line on one face, checked against truth."""
    sp = auto_result.calibration.slit_planes
    axis = list(sp.from_axis)
    own = sp.valid.copy()
    own[axis] = False
    assert axis and own.sum() >= 15
    _, true_planes = truth(small_capture)
    cosang = np.abs(np.sum(sp.planes[:, :3] * true_planes[:, :3], axis=1))
    ang = 1e3 * np.arccos(np.clip(cosang, 0, 1))  # mrad
    for scan in ("holes", "steps"):
        err = per_slit_triangulation(small_capture, auto_result.calibration, scan)
        assert np.all(np.isfinite(err[axis])), (scan, err)
        # measured (half size): holes 0.26 and 0.36 mm against 0.03..0.24 mm for the others,
        # steps 1.2 and 0.56 mm against 0.07..0.51 (extraction's centres: holes 0.34 and 0.68
        # against 0.05..0.51, steps 1.9 and 1.1 against 0.09..0.88); a plane a slit off is
        # ~10 mm wrong. On the full-size rig they are within the others' range (0.019 and
        # 0.038 mm, others 0.015..0.061, before refine_centres)
        assert np.max(err[axis]) <= 2.5 * np.nanmax(err[own]), (scan, err)
    # the half-size planes are up to ~1.5 mrad off (2.5 mrad with the extraction's centres):
    # all turn with the axis, these as their neighbours
    for j in axis:
        nb = [i for i in (j - 2, j - 1, j + 1, j + 2) if 0 <= i < len(own) and own[i]]
        assert ang[j] <= 1.3 * max(ang[nb]) + 0.2, (j, ang)


@pytest.mark.parametrize("which", ["hand", pytest.param("auto", marks=pytest.mark.slow)])
def test_triangulation_against_truth(small_capture, request, which):
    res = request.getfixturevalue(f"{which}_result")
    ok_share, err = truth_triangulation(small_capture, res.calibration)
    assert ok_share > 0.99
    # measured on this capture: hand 0.082 mm (0.068 mm without slit 23, whose plane now comes
    # from the axis: the error grows towards that end for all slits), auto (true labels)
    # 0.143 mm RMS with the centres re-centred by refine_centres (0.246 mm without): the
    # half-size auto planes are up to ~1.5 mrad off (stripe-centre noise and bias, ~0.1 px at
    # ~1.1 mm/px)
    assert rms(err) < (0.1 if which == "hand" else 0.2)


@pytest.mark.slow
def test_refined_centres_are_nearer_the_true_planes(small_capture):
    """The automatic points (default: re-centred by refine_centres) lie nearer to the true slit
    planes than those from the extraction's centres, with the same labels."""
    cap = Capture.open(small_capture)
    cam = camera_from_capture(cap).refined
    _, planes = truth(small_capture)
    assert inspect.signature(auto_slit_points).parameters["refine"].default is True  # on by default
    labels = truth_labels(small_capture)
    dist = {}
    for name, kw in (("extraction", {"refine": False}), ("refined", {})):
        pts = auto_slit_points(cap, cam, labels, **kw)
        k = pts.slit
        dist[name] = np.abs(np.einsum("ij,ij->i", pts.xyz, planes[k, :3]) + planes[k, 3])
        assert len(pts) > 6000 and dict(pts.steps)["labelled"] > 10000
    a, b = dist["extraction"], dist["refined"]
    # measured: median 0.092 -> 0.051 mm, 90th percentile 0.27 -> 0.16 mm, RMS of the points
    # within 0.5 mm 0.154 -> 0.101 mm (98.2 -> 99.7 % of the points)
    assert np.median(b) <= 0.07 and np.median(b) < 0.7 * np.median(a), (np.median(a), np.median(b))
    assert np.percentile(b, 90) < 0.75 * np.percentile(a, 90)
    assert rms(b[b < 0.5]) < 0.8 * rms(a[a < 0.5])


@pytest.mark.xfail(
    reason="goal 0.05 mm RMS; the hand readings give about 0.08 mm on the half-size rig"
)
def test_triangulation_goal(small_capture, hand_result):
    _, err = truth_triangulation(small_capture, hand_result.calibration)
    assert rms(err) <= 0.05


@pytest.mark.slow
def test_mislabelled_points_do_not_ruin_planes(small_capture, auto_result):
    rng = np.random.default_rng(1)

    u, v, s = truth_labels(small_capture)
    s = s.copy()
    flip = (s >= 0) & (s < 24) & (rng.random(len(s)) < 0.08)
    s[flip] += 1
    r = calibrate_capture(small_capture, source="auto", labels=(u, v, s), references=False)
    assert r.projector.dropped.sum() > 0.5 * 0.08 * len(r.points)
    good = auto_result.calibration.slit_planes.planes
    got = r.calibration.slit_planes.planes
    got = got * np.sign(np.sum(got[:, :3] * good[:, :3], axis=1))[:, None]  # same orientation
    X = auto_result.points.xyz
    k = auto_result.points.slit
    d = np.einsum("ij,ij->i", X, got[k, :3]) + got[k, 3]
    d0 = np.einsum("ij,ij->i", X, good[k, :3]) + good[k, 3]
    assert rms(d - d0) < 0.05


@pytest.mark.slow
def test_slit_without_points_is_reported_not_guessed(small_capture, auto_result):
    auto_valid = int(auto_result.calibration.slit_planes.valid.sum())

    u, v, s = truth_labels(small_capture)
    s = s.copy()
    s[s == 7] = -1
    r = calibrate_capture(small_capture, source="auto", labels=(u, v, s), references=False)
    assert not r.calibration.slit_planes.valid[7]
    assert r.calibration.slit_planes.valid.sum() == auto_valid - 1
    assert any(re.search(r"slit\(s\) \[[^\]]*\b7\b", n) for n in r.notes), r.notes


def test_transfer_labels():
    lab = transfer_labels(
        [10.0, 30.0, 10.0], [5, 5, 6], [1, 2, 3], [11.0, 29.0, 20.0, 10.2], [5, 5, 5, 6]
    )
    assert lab.tolist() == [1, 2, -1, 3]


# --------------------------------------------------------------------------- bad input
def test_five_markers(small_capture, tmp_path):
    cap = copy_capture(small_capture, tmp_path / "c", lambda t: t.update(markers=t["markers"][:5]))
    with pytest.raises(CalibrationError, match=r"found 5 of 5 markers.*needs >= 6"):
        calibrate_capture(cap, source="hand")


def test_markers_on_one_face(small_capture, tmp_path):
    def one_face(t):
        f = t["faces"][0]
        n, d = np.array(f["plane"][:3]), f["plane"][3]
        t["markers"] = [m for m in t["markers"] if abs(n @ np.array(m["xyz"]) + d) < 0.5]

    cap = copy_capture(small_capture, tmp_path / "c", one_face)
    with pytest.raises(CalibrationError, match=r"all lie on one plane \(face F1\)"):
        calibrate_capture(cap, source="hand")


@pytest.mark.slow
def test_marker_hint_off_image_is_skipped(small_capture, tmp_path):
    def off(t):
        t["markers"][0]["uv_hint"] = [-50.0, 20.0]

    cap = copy_capture(small_capture, tmp_path / "c", off)
    r = calibrate_capture(cap, source="hand")
    mid = json.loads((cap / "target.json").read_text())["markers"][0]["id"]
    assert mid in r.camera.rejected and "off the image" in r.camera.rejected[mid]
    assert mid not in r.calibration.marker_ids
    assert r.calibration.camera_rms_px <= 0.1


def test_missing_marker_image(small_capture, tmp_path):
    cap = copy_capture(small_capture, tmp_path / "c")
    (cap / "calibration" / "markers.png").unlink()
    with pytest.raises(CalibrationError, match=r"missing marker image: .*markers\.png"):
        calibrate_capture(cap, source="hand")


def test_unknown_slit_number_in_hand_readings(small_capture, tmp_path):
    def bad(t):
        t["slit_points"][3]["slit"] = 99

    cap = copy_capture(small_capture, tmp_path / "c", bad)
    with pytest.raises(CaptureError, match=r"slit_points\[3\]\.slit is 99, but the rig has slits"):
        calibrate_capture(cap, source="hand")


# --------------------------------------------------------------------------- CLI and file
@pytest.mark.slow
def test_cli_calibrate_round_trip(small_capture, tmp_path, capsys):
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(small_capture), "-o", str(out), "--source", "hand"]) == 0
    text = capsys.readouterr().out
    n_markers = len(Capture.open(small_capture).target.markers)
    assert f"markers: {n_markers} of {n_markers} used" in text
    # every slit is on the reference boards: every slit gets a plane, its origin listed
    n_planes = int(re.search(r"slit planes: (\d+) of 25", text).group(1))
    assert n_planes == 25
    assert re.search(r"slits? [\d-]+: .*reference boards, RMS", text), text
    assert "projector matrix" in text and "hand readings" in text
    cal = Calibration.load(out)
    rep = json.loads(out.read_text())["report"]
    assert rep["source"] == "hand" and rep["camera"]["refined_rms_px"] <= 0.1
    assert cal.slit_planes.valid.sum() == n_planes and cal.refined is not None
    scan = Capture.open(small_capture).scans[0]
    h, w = Capture.open(small_capture).image(scan).shape
    cal.check_image_size((w, h))
    with pytest.raises(CalibrationError, match="recalibrate"):
        cal.check_image_size((w * 2, h * 2))


def test_cli_errors_are_messages(small_capture, tmp_path, capsys):
    assert main(["calibrate", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert "capture folder not found" in err and "Traceback" not in err
    cap = copy_capture(small_capture, tmp_path / "c", lambda t: t.update(markers=t["markers"][:5]))
    assert main(["calibrate", str(cap), "--source", "hand"]) == 2
    err = capsys.readouterr().err
    assert "multislit calibrate: error: found 5 of 5 markers" in err and "Traceback" not in err


def few_labels(capture: Path):
    """Labels of only two slits (as identification on a hard target might give)."""
    u, v, s = truth_labels(capture)
    s = s.copy()
    s[~np.isin(s, [5, 12])] = -1
    return u, v, s


@pytest.mark.slow
def test_unsupported_automatic_planes_fall_back_to_hand_readings(small_capture):
    r = calibrate_capture(small_capture, source="auto", labels=few_labels(small_capture))
    assert r.source == "hand"
    assert any("automatic projector calibration failed" in n for n in r.notes), r.notes
    assert r.calibration.slit_planes.valid.sum() >= 10


@pytest.mark.slow
def test_unsupported_automatic_planes_without_hand_readings_is_an_error(small_capture, tmp_path):
    cap = copy_capture(small_capture, tmp_path / "c", lambda t: t.pop("slit_points"))
    with pytest.raises(
        CalibrationError, match="automatic projector calibration failed.*hand readings"
    ):
        calibrate_capture(cap, source="auto", labels=few_labels(small_capture))


@pytest.mark.slow
def test_reference_without_an_epipole_labels_no_stripes(small_capture, tmp_path, monkeypatch):
    """Reference images whose dots cannot be followed between them (no epipole) give the
    labels no anchors: the calibration says so and falls back to the hand readings, or stops
    with one clear error without them."""
    real = pipeline._reference

    def no_epipole(cap, notes):
        return dataclasses.replace(real(cap, notes), epipole_problem="2 matched dots")

    monkeypatch.setattr(pipeline, "_reference", no_epipole)
    r = calibrate_capture(small_capture)
    assert r.source == "hand"
    note = [n for n in r.notes if "automatic projector calibration failed" in n]
    assert note and "could not be followed between them: 2 matched dots" in note[0], r.notes
    cap = copy_capture(small_capture, tmp_path / "c", lambda t: t.pop("slit_points"))
    with pytest.raises(CalibrationError, match="cannot be labelled.*--source hand"):
        calibrate_capture(cap)


# --------------------------------------------------------------------------- reference boards
@pytest.fixture(scope="module")
def boards_result(small_capture):
    """The automatic points with true labels and the reference boards (the default)."""
    return calibrate_capture(small_capture, source="auto", labels=truth_labels(small_capture))


@pytest.mark.slow
def test_reference_boards_give_every_slit_a_plane(small_capture, auto_result, boards_result):
    target_only = auto_result.calibration.slit_planes
    sp = boards_result.calibration.slit_planes
    assert sp.valid.all() and not sp.from_axis, (sp.excluded, sp.from_axis)
    own = target_only.valid.copy()
    own[list(target_only.from_axis)] = False
    origin = boards_result.origin
    assert len(origin) == sp.num_slits
    # one adjustment: each slit's plane is fitted to all its observations, on the target's
    # faces and on the boards; the slits the target misses (none, or one line: slits 0, 23
    # and 24 here) from the boards alone
    on_target = boards_result.bundle.slit_sources["target stripes"] > 0
    assert all(origin[j] == "target faces + reference boards" for j in np.flatnonzero(on_target))
    assert all(origin[j] == "reference boards" for j in np.flatnonzero(~on_target)), origin
    assert (~own).sum() >= 2 and not np.any(on_target & ~target_only.valid)
    per_slit = boards_result.report()["slit_planes"]["per_slit"]
    assert [x["origin"] for x in per_slit] == list(origin)
    text = "\n".join(format_report(boards_result))
    assert "slits 1-23: target faces + reference boards" in text, text
    # the boards stand as simulated (fronto-parallel, at their true distances); measured: normals
    # within 2.2e-4 rad, offsets within 0.03 mm
    m = json.loads((small_capture / "truth" / "models.json").read_text())
    names = [Path(n).stem for n in boards_result.bundle.result.images[3:]]
    true = np.array([m["reference_planes"][n] for n in names])
    fitted = boards_result.bundle.board_planes * np.sign(boards_result.bundle.board_planes[:, 2:3])
    assert np.all(np.abs(fitted[:, :2]) < 1e-3) and np.all(np.abs(fitted[:, 3] - true[:, 3]) < 0.2)
    assert_boards_keep_accuracy(small_capture, auto_result, boards_result, own)


def assert_boards_keep_accuracy(capture, before_result, after_result, own) -> None:
    """The slits the target determines triangulate as before; the boards' slits nearly as well.

    Measured (half size, true pixels of the holes / steps scans): the boards' slits (at the
    image's edges, where the target's planes are already the worst and the camera's error is
    largest) are up to 1.9 (automatic points) and 2.03 (hand readings) times the worst of
    the target's slits, slit 24 the worst (0.51 mm automatic, 0.38 mm hand).
    """
    for scan in ("holes", "steps"):
        before = per_slit_triangulation(capture, before_result.calibration, scan)
        after = per_slit_triangulation(capture, after_result.calibration, scan)
        worst = np.nanmax(before[own])
        assert np.nanmax(after[own]) <= 1.25 * worst, (scan, before, after)
        assert np.nanmax(after[~own]) <= 2.5 * worst, (scan, before, after)


@pytest.mark.slow
def test_hand_readings_with_reference_boards(small_capture, hand_result):
    r = calibrate_capture(small_capture, source="hand")
    sp = r.calibration.slit_planes
    assert sp.valid.all() and r.boards is not None
    own = hand_result.calibration.slit_planes.valid.copy()
    own[list(hand_result.calibration.slit_planes.from_axis)] = False
    read = r.bundle.slit_sources["hand readings"] > 0
    assert [("hand readings" in o) for o in r.origin] == read.tolist(), r.origin
    assert all("reference boards" in o for o in r.origin), r.origin
    assert_boards_keep_accuracy(small_capture, hand_result, r, own)


def lose_slit(monkeypatch, slit: int) -> None:
    """Make the reference boards' fit end without a plane for ``slit`` (as if its points failed)."""
    import multislit.calibrate.pipeline as pipeline

    real = pipeline.fit_with_boards

    def fit_without(*args, **kwargs):
        bf = real(*args, **kwargs)
        sp = bf.fit.slit_planes
        planes = sp.planes.copy()
        planes[slit] = np.nan
        why = ((slit, "only 2 point(s), need >= 20"),)
        sp2 = dataclasses.replace(sp, planes=planes, excluded=why)
        fit = dataclasses.replace(bf.fit, slit_planes=sp2, excluded=why)
        return dataclasses.replace(bf, fit=fit)

    monkeypatch.setattr(pipeline, "fit_with_boards", fit_without)


@pytest.mark.slow
def test_slit_on_the_boards_without_a_plane_is_an_error(small_capture, monkeypatch):
    """A slit the references show that ends without a plane stops the calibration, named."""
    lose_slit(monkeypatch, 0)  # the first slit: the common axis model cannot place it either
    with pytest.raises(
        CalibrationError, match=r"slit\(s\) \[0\] are seen on the reference boards.*need >= 20"
    ):
        calibrate_capture(small_capture, source="hand")


@pytest.mark.slow
def test_slit_seen_along_one_line_gets_the_plane_through_the_axis(
    small_capture, tmp_path, monkeypatch
):
    """A slit whose points give no plane of their own (here: its fit fails, it has no hand
    readings and the boards show it on one board only, one line) between slits with planes:
    the common axis model places it between its neighbours to start, and the adjustment fits
    it through the common axis and its line on the board."""
    import multislit.calibrate.pipeline as pipeline

    lose_slit(monkeypatch, 4)
    real = pipeline.reference_stripes

    def without_slit_4(*args, **kwargs):
        rs = real(*args, **kwargs)
        keep = [(s != 4) | (r == 0) for r, s in enumerate(rs.slit)]
        return dataclasses.replace(
            rs,
            uv=[u[k] for u, k in zip(rs.uv, keep, strict=True)],
            slit=[s[k] for s, k in zip(rs.slit, keep, strict=True)],
        )

    monkeypatch.setattr(pipeline, "reference_stripes", without_slit_4)

    def drop_readings(t):
        t["slit_points"] = [p for p in t["slit_points"] if p["slit"] != 4]

    cap = copy_capture(small_capture, tmp_path / "cap", drop_readings)
    r = calibrate_capture(cap, source="hand")
    sp = r.calibration.slit_planes
    assert sp.valid.all() and r.origin[4] == "reference boards", r.origin
    assert r.bundle.kind == "common axis" and r.bundle.slit_item[4] >= 0
    assert r.bundle.slit_sources["board stripes"][4] > 0
    assert any(n.startswith("slit 4 gave no plane from its points") for n in r.notes), r.notes
    shutil.copytree(small_capture / "truth", cap / "truth")
    err = per_slit_triangulation(cap, r.calibration)
    # a plane a slit off would be ~10 mm wrong
    assert err[4] <= 2 * np.nanmedian(err), err
