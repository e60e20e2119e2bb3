"""The bundle adjustment (multislit.calibrate.bundle) against ground truth.

Synthetic observations (no rendering: the half-size rig's true camera, slit planes, target and
boards, with Gaussian noise) check the adjustment itself; the simulated half-size capture checks
the whole calibration.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from multislit.calibrate import bundle as B
from multislit.calibrate import calibrate_capture, format_report
from multislit.calibrate.camera import calibrate_dlt, refine_camera, rms
from multislit.calibrate.edges import fold_points, target_folds
from multislit.calibrate.slit_points import points_on_faces
from multislit.errors import CalibrationError
from multislit.geometry import PinholeCamera, camera_from_dict, intersect_rays_planes
from multislit.io import Capture, Face
from multislit.reconstruct import triangulate
from multislit.sim.scene import standard_object

BOARDS = (780.0, 900.0, 1020.0)


# --------------------------------------------------------------------------- synthetic rig
def _faces() -> tuple[list[Face], np.ndarray, np.ndarray]:
    _, markers, faces = standard_object()
    fl = [Face(f["id"], tuple(f["plane"]), np.asarray(f["polygon"], float)) for f in faces]
    planes = np.array([f["plane"] for f in faces], float)
    planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    return fl, planes, np.array([m["xyz"] for m in markers], float)


def _line_points(cam: PinholeCamera, pa: np.ndarray, pb: np.ndarray, step_px: float = 2.0):
    """Pixels (N, 2) of the line where planes ``pa`` and ``pb`` meet, every ~``step_px`` rows,
    inside the image."""
    P, D = B.plane_lines(pa[None], pb[None])
    s = np.linspace(-1500, 1500, 3001)  # 1 mm apart: about a pixel at the boards
    X = P[0] + s[:, None] * D[0]
    uv = cam.project(X)
    w, h = cam.image_size
    ok = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > 2) & (uv[:, 0] < w - 3)
    ok &= (uv[:, 1] > 2) & (uv[:, 1] < h - 3)
    uv, X = uv[ok], X[ok]
    if not len(uv):
        return uv, X
    keep = np.unique(np.round(uv[:, 1] / step_px), return_index=True)[1]
    return uv[keep], X[keep]


def synthetic_observations(
    rig, rng: np.random.Generator, marker_px=0.02, stripe_px=0.05, board_shift=None
) -> tuple[B.CaptureObservations, dict]:
    """Observations of the half-size rig: markers, stripes on the target's faces and on three
    boards, with Gaussian noise (px); ``board_shift`` = (board, slit offset) mislabels a board."""
    cam = rig.camera
    planes = rig.projector.planes()
    faces, face_planes, marker_xyz = _faces()
    muv = cam.project(marker_xyz) + rng.normal(0, marker_px, (len(marker_xyz), 2))
    t_uv, t_slit, t_face = [], [], []
    for k in range(len(planes)):
        for f in range(len(faces)):
            uv, _ = _line_points(cam, planes[k], face_planes[f])
            if not len(uv):
                continue
            _, hit = points_on_faces(cam, uv, faces)
            uv = uv[hit == f]
            t_uv.append(uv)
            t_slit += [k] * len(uv)
            t_face += [f] * len(uv)
    t_uv = np.concatenate(t_uv)
    t_uv[:, 0] += rng.normal(0, stripe_px, len(t_uv))
    boards = np.array([[0.0, 0.0, 1.0, -(1000.0 - d)] for d in BOARDS])
    b_uv, b_slit = [], []
    for b in range(len(boards)):
        uvs, ss = [], []
        for k in range(len(planes)):
            uv, _ = _line_points(cam, planes[k], boards[b])
            uvs.append(uv)
            ss += [k] * len(uv)
        uv = np.concatenate(uvs)
        uv[:, 0] += rng.normal(0, stripe_px, len(uv))
        s = np.array(ss, np.intp)
        if board_shift is not None and board_shift[0] == b:
            s = np.clip(s + board_shift[1], 0, len(planes) - 1)
        b_uv.append(uv)
        b_slit.append(s)
    e3, e2, ei = np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.intp)
    obs = B.CaptureObservations(
        image_size=cam.image_size,
        marker_xyz=marker_xyz,
        marker_uv=muv,
        faces=face_planes,
        target_uv=t_uv,
        target_slit=np.array(t_slit, np.intp),
        target_face=np.array(t_face, np.intp),
        readings_xyz=e3,
        readings_slit=ei,
        readings_uv=e2,
        board_uv=tuple(b_uv),
        board_slit=tuple(b_slit),
        names=("markers.png", "slits.png", "target.json", "ref_0780", "ref_0900", "ref_1020"),
    )
    return obs, {"planes": planes, "boards": boards}


def start_values(obs: B.CaptureObservations, truth: dict, rng: np.random.Generator):
    """A start as the pipeline has one: the camera from the markers alone (k1, k2, p1, p2), the
    planes and boards a little off."""
    dlt, _ = calibrate_dlt(obs.marker_xyz, obs.marker_uv, obs.image_size)
    cam, _ = refine_camera(obs.marker_xyz, obs.marker_uv, dlt)
    planes = truth["planes"].copy()
    planes[:, 3] += rng.normal(0, 0.5, len(planes))
    boards = truth["boards"].copy()
    boards[:, 3] += rng.normal(0, 3.0, len(boards))
    return cam, planes, boards


def board_points(rig, step: int = 23) -> np.ndarray:
    """True 3D points (N, 3) mm on the three boards, over the whole image."""
    cam = rig.camera
    w, h = cam.image_size
    uu, vv = np.meshgrid(np.arange(0, w, step), np.arange(0, h, step))
    uv = np.stack([uu.ravel(), vv.ravel()], 1).astype(float)
    o, d = cam.rays(uv)
    out = []
    for dist in BOARDS:
        X, _ = intersect_rays_planes(o, d, np.array([0.0, 0.0, 1.0, -(1000.0 - dist)]))
        out.append(X)
    return np.concatenate(out)


@pytest.fixture(scope="module")
def synthetic(small_rig):
    rng = np.random.default_rng(7)
    obs, truth = synthetic_observations(small_rig, rng)
    cam, planes, boards = start_values(obs, truth, rng)
    return obs, truth, B.adjust_capture(obs, cam, planes, boards), cam


# --------------------------------------------------------------------------- the machinery
def test_line_residuals_vanish_on_the_line(small_rig):
    cam = small_rig.camera
    planes = small_rig.projector.planes()
    board = np.array([0.0, 0.0, 1.0, -100.0])  # the middle reference board
    for k in (0, 12, 24):
        uv, _ = _line_points(cam, planes[k], board, step_px=7.0)
        P, D = B.plane_lines(planes[k][None], board[None])
        r = B.line_residuals(
            B.camera_vector(cam), np.repeat(P, len(uv), 0), np.repeat(D, len(uv), 0), uv
        )
        assert np.abs(r).max() < 1e-6
        # a point 0.3 px to the right of the line is 0.3 px (times the line's slant) off
        r = B.line_residuals(
            B.camera_vector(cam), np.repeat(P, len(uv), 0), np.repeat(D, len(uv), 0), uv + [0.3, 0]
        )
        assert np.all(np.abs(np.abs(r) - 0.3) < 0.02)


def test_jacobian_matches_central_differences(small_rig):
    rng = np.random.default_rng(3)
    obs, truth = synthetic_observations(small_rig, rng)
    cam, planes, boards = start_values(obs, truth, rng)
    model, _ = B.axis_planes_model(cam, planes, boards)
    item = np.arange(len(planes))
    blocks = B._capture_blocks(obs, item, np.arange(len(boards)), model.slit_deps)
    rows = [np.arange(0, len(b), 17) for b in blocks]
    prob = B._Problem(model, blocks, rows, [1.0] * len(blocks))
    x = B.Layout(model.blocks).pack({b.name: b.x0 for b in model.blocks})
    J = prob.jac(x)
    for col in (0, 3, 6, 9, 11, 16, 20, 30):
        h = 1e-5 * max(1.0, abs(x[col]))
        xp, xm = x.copy(), x.copy()
        xp[col] += h
        xm[col] -= h
        num = (prob.fun(xp) - prob.fun(xm)) / (2 * h)
        assert np.allclose(J[:, col], num, rtol=1e-3, atol=1e-4 * np.abs(num).max()), col


@pytest.mark.slow
def test_synthetic_capture_recovers_the_truth(small_rig, synthetic):
    """Noise 0.02 px on 48 markers, 0.05 px on the stripe centres: every camera parameter lies
    within its standard errors of the truth, the camera reprojects true points of the three
    boards (the whole image at three depths) better than the markers alone (measured 0.031
    against 0.042 px RMS: the markers' noise sets the camera's pose and focal length), the
    planes give true points to < 0.05 mm, the noise levels are found, and the true model is
    kept (common axis, no k3)."""
    obs, truth, bundle, start = synthetic
    res = bundle.result
    assert res.converged and bundle.kind == "common axis"
    assert not bundle.tests["k3"]["added"] and not bundle.tests["free planes"]["added"]
    X = board_points(small_rig)
    uv = small_rig.camera.project(X)
    err = np.linalg.norm(bundle.camera.project(X) - uv, axis=1)
    err0 = np.linalg.norm(start.project(X) - uv, axis=1)
    assert rms(err) < 0.05 and rms(err) < rms(err0), (rms(err), rms(err0))
    Xs, k = [], []
    for j, plane in enumerate(truth["planes"]):
        for board in truth["boards"]:
            Xs.append(_line_points(small_rig.camera, plane, board, step_px=9.0)[1])
            k += [j] * len(Xs[-1])
    Xs, k = np.concatenate(Xs), np.array(k)
    Y, ok = triangulate(bundle.camera, bundle.slit_planes, small_rig.camera.project(Xs), k)
    tri = rms(np.linalg.norm(Y[ok] - Xs[ok], axis=1))
    assert ok.all() and tri < 0.05, tri  # measured 0.036 mm
    tv = B.camera_vector(small_rig.camera)
    for i, name in enumerate(B.CAMERA_PARAMS[:14]):
        z = (res.geometry["camera"][i] - tv[i]) / res.std_error(f"camera.{name}")
        assert abs(z) < 4.5, (name, z)
    stats = res.per_source()
    assert abs(stats["markers"]["sigma"] / 0.02 - 1) < 0.4  # 96 residuals: a rough estimate
    # the boards' centres are averaged in bins of consecutive rows: noise 0.05 / sqrt(bin size)
    sizes = [np.ceil(np.bincount(s)[np.bincount(s) > 0] / B.MAX_PER_LINE) for s in obs.board_slit]
    expected = 0.05 / np.sqrt(np.mean(np.concatenate(sizes)))
    assert abs(stats["board stripes"]["sigma"] / expected - 1) < 0.2, expected
    assert set(stats["board stripes"]["regions"]) == set(B.REGIONS)
    assert not bundle.problems


@pytest.mark.slow
def test_predicted_uncertainty_matches_the_errors(small_rig, synthetic):
    """The predicted 3D error of triangulated points (from the parameters' covariance) is the
    size of the actual errors, largest at the near and far boards."""
    obs, truth, bundle, _ = synthetic
    u = bundle.uncertainty
    assert [x["board"] for x in u] == ["ref_0780", "ref_0900", "ref_1020"]
    med = [x["median_mm"] for x in u]
    assert med[1] < med[0] and med[1] < med[2] and 0.0005 < min(med) and max(med) < 0.05
    assert all(x["p95_mm"] >= x["median_mm"] for x in u)


@pytest.mark.slow
def test_planes_off_a_common_axis_are_fitted_free(small_rig):
    """A projector whose slit planes do not share one axis (slit 12's plane turned 0.3 degrees
    about the line where it meets the middle board's plane's normal through the image centre)
    is fitted with free planes: the score test rejects the common axis, and the plane is found."""
    rng = np.random.default_rng(11)
    rig = replace(small_rig)  # the truth below is changed through the observations only
    obs, truth = synthetic_observations(rig, rng)
    planes = truth["planes"].copy()
    p0 = B.plane_lines(planes[12][None], truth["boards"][1][None])[0][0]  # on the middle board
    a = np.radians(0.3)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    planes[12, :3] = turn @ planes[12, :3]
    planes[12, 3] = -planes[12, :3] @ p0
    # re-observe slit 12 on its moved plane
    cam = rig.camera
    _, face_planes, _ = _faces()
    faces, _, _ = _faces()
    t_keep = obs.target_slit != 12
    add_uv, add_face = [], []
    for f in range(len(face_planes)):
        uv, _ = _line_points(cam, planes[12], face_planes[f])
        if len(uv):
            _, hit = points_on_faces(cam, uv, faces)
            add_uv.append(uv[hit == f])
            add_face += [f] * int((hit == f).sum())
    b_uv, b_slit = [], []
    for b, board in enumerate(truth["boards"]):
        keep = obs.board_slit[b] != 12
        uv, _ = _line_points(cam, planes[12], board)
        b_uv.append(np.concatenate([obs.board_uv[b][keep], uv]))
        b_slit.append(np.concatenate([obs.board_slit[b][keep], np.full(len(uv), 12)]))
    obs = replace(
        obs,
        target_uv=np.concatenate([obs.target_uv[t_keep], *add_uv]),
        target_slit=np.concatenate([obs.target_slit[t_keep], np.full(len(add_face), 12)]),
        target_face=np.concatenate([obs.target_face[t_keep], np.array(add_face, np.intp)]),
        board_uv=tuple(b_uv),
        board_slit=tuple(b_slit),
    )
    cam0, start, boards = start_values(obs, {**truth, "planes": planes}, rng)
    bundle = B.adjust_capture(obs, cam0, start, boards)
    assert bundle.tests["free planes"]["added"] and bundle.kind == "free", bundle.tests
    n = bundle.slit_planes[12, :3] * np.sign(bundle.slit_planes[12, :3] @ planes[12, :3])
    assert np.degrees(np.arccos(min(1.0, n @ planes[12, :3]))) < 0.05
    assert abs(bundle.slit_planes[12, :3] @ p0 + bundle.slit_planes[12, 3]) < 0.05


@pytest.mark.slow
def test_mislabelled_board_is_named(small_rig):
    """A reference board whose slits are numbered one off does not fit the others: the fit it
    pulls leaves other boards off too, but without it the others fit, and it is named
    (measured: its stripes 0.46 px off as whole stripes, 14.9 times their scatter)."""
    rng = np.random.default_rng(5)
    obs, truth = synthetic_observations(small_rig, rng, board_shift=(2, 1))
    cam, planes, boards = start_values(obs, truth, rng)
    bundle = B.adjust_capture(obs, cam, planes, boards)
    assert bundle.problems and bundle.problems[0].startswith("ref_1020"), bundle.problems


@pytest.mark.slow
def test_moved_target_is_named(small_rig):
    """The target moved 3 mm between the markers image and the slits image: its stripes do not
    fit the markers; the adjustment says which image to retake (measured: whole stripes 0.53
    px off, 9.0 times their scatter; 1 mm gives 0.17 px, 4.2 times)."""
    rng = np.random.default_rng(5)
    obs, truth = synthetic_observations(small_rig, rng)
    moved = obs.marker_xyz + [3.0, 0.0, 0.0]
    obs = replace(obs, marker_uv=small_rig.camera.project(moved))
    cam, planes, boards = start_values(obs, truth, rng)
    bundle = B.adjust_capture(obs, cam, planes, boards)
    assert len(bundle.problems) == 1 and "slits.png" in bundle.problems[0], bundle.problems
    assert "did the target move" in bundle.problems[0]


def test_camera_alone_on_heikkila_data():
    """The adjustment's camera model on real data (Heikkila's 3D rig, 491 points): 0.072 px
    RMS (the data's README: 0.073 px with k1, k2, p1, p2)."""
    from .test_calibration import HEIKKILA

    if not HEIKKILA.is_file():
        pytest.skip(f"real calibration data not found at {HEIKKILA}")
    d = np.loadtxt(HEIKKILA, delimiter=",", skiprows=1)
    X, uv = d[:, :3], d[:, 3:]
    dlt, _ = calibrate_dlt(X, uv, (768, 576))
    start, _ = refine_camera(X, uv, dlt, distortion=False)
    res = B.adjust(B.camera_model(start), [B.marker_block(X, uv, 0)], ["points.csv"], (768, 576))
    err = np.linalg.norm(res.camera.project(X) - uv, axis=1)
    assert res.converged and rms(err) <= 0.073, rms(err)
    assert res.camera.dist[0] < -0.1 and np.isfinite(res.std_error("camera.k3"))


def test_target_folds_are_where_the_faces_meet():
    faces, _, _ = _faces()
    folds = target_folds(faces)
    assert [f[0] for f in folds] == ["F1/F2", "F1/F3", "F2/F3"]
    for _, a, b in folds:  # every fold lies on both faces' planes
        for f in faces:
            pl = np.asarray(f.plane)
            if f.id in _:
                assert abs(pl[:3] @ a + pl[3]) < 1e-6 and abs(pl[:3] @ b + pl[3]) < 1e-6


@pytest.mark.slow
def test_folds_found_in_the_markers_image(small_capture):
    """The folds of the half-size capture's target, found near where the markers' camera puts
    them, lie on the true folds' images: measured 0.12-0.26 px RMS per fold, means within
    0.08 px."""
    cap = Capture.open(small_capture)
    m = json.loads((small_capture / "truth" / "models.json").read_text())
    true_cam = camera_from_dict(m["camera"])
    start, _ = refine_camera(
        cap.target.marker_xyz, true_cam.project(cap.target.marker_xyz) + 0.3, None
    )
    fp = fold_points(cap.image(cap.markers_image), start, cap.target.faces)
    assert fp.names == ("F1/F2", "F1/F3", "F2/F3") and len(fp) > 60
    r = B.line_residuals(B.camera_vector(true_cam), fp.P[fp.fold], fp.D[fp.fold], fp.uv)
    for k in range(len(fp.names)):
        rk = r[fp.fold == k]
        assert len(rk) >= 10 and rms(rk) < 0.35 and abs(rk.mean()) < 0.12, (k, rms(rk))


# --------------------------------------------------------------------------- a capture
@pytest.fixture(scope="module")
def capture_result(small_capture):
    return calibrate_capture(small_capture)


@pytest.mark.slow
def test_capture_camera_over_the_whole_image(small_capture, capture_result):
    """The half-size capture (640x512, 48 markers): true 3D points of the three reference
    boards reproject within 0.03 px RMS over the whole image, corners included (measured
    0.018 px, corners 0.023 px)."""
    m = json.loads((small_capture / "truth" / "models.json").read_text())
    true_cam = camera_from_dict(m["camera"])
    errs, uvs = [], []
    for f in sorted((small_capture / "truth").glob("ref_*.npz")):
        xyz = np.load(f)["xyz"][::6, ::6].reshape(-1, 3).astype(float)
        xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
        uv = true_cam.project(xyz)
        errs.append(np.linalg.norm(capture_result.calibration.camera.project(xyz) - uv, axis=1))
        uvs.append(uv)
    e, uv = np.concatenate(errs), np.concatenate(uvs)
    w, h = true_cam.image_size
    corner = ((uv[:, 0] < w / 3) | (uv[:, 0] > 2 * w / 3)) & (
        (uv[:, 1] < h / 3) | (uv[:, 1] > 2 * h / 3)
    )
    assert rms(e) < 0.03 and rms(e[corner]) < 0.035, (rms(e), rms(e[corner]))


@pytest.mark.slow
def test_capture_triangulation_against_truth(small_capture, capture_result):
    """True stripe pixels of both scans triangulate within the depth that 0.03 px of image
    error makes on this 640x512 rig, times 1.2 (measured on the holes scene: 0.053 mm against
    0.071 mm; `benchmarks/bench_calibration.py --half`)"""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_calibration import depth_of_pixels, truth_errors

    for scan in ("holes", "steps"):
        tol = depth_of_pixels(small_capture, scan)
        _, err = truth_errors(small_capture, capture_result.calibration, scan)
        assert rms(err) < 1.2 * tol, (scan, rms(err), tol)


@pytest.mark.slow
def test_capture_report_has_residuals_per_source_and_region(capture_result):
    r = capture_result.report()["bundle"]
    assert set(r["sources"]) == {"markers", "target folds", "target stripes", "board stripes"}
    for v in r["sources"].values():
        assert v["kept"] > 0.9 * v["count"] and len(v["regions"]) >= 5
    assert set(r["images"]) >= {"calibration/markers.png", "calibration/slits.png"}
    assert r["camera"]["fx"][1] > 0 and len(r["uncertainty"]) == 3
    text = "\n".join(format_report(capture_result))
    for what in ("bundle adjustment:", "by region:", "+-", "predicted 3D error"):
        assert what in text, text


@pytest.mark.slow
def test_capture_with_a_foreign_reference_image_is_an_error(small_capture, tmp_path):
    """A reference image from another set-up (here: the board image flipped left-right, so
    every slit lies where another should) stops the calibration, naming the image."""
    from multislit.io import write_image

    from .test_calibrate import copy_capture

    cap = copy_capture(small_capture, tmp_path / "cap")
    ref = sorted((cap / "reference").glob("*.png"))[1]
    img = Capture.open(cap).image(ref)
    write_image(ref, np.ascontiguousarray(img[:, ::-1]))
    with pytest.raises(CalibrationError, match=ref.name):
        calibrate_capture(cap)
