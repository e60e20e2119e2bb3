"""Tests of camera/projector calibration, marker detection and the Calibration file."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from multislit.calibrate import (
    Calibration,
    ProjectorMatrix,
    SlitPlanes,
    calibrate_dlt,
    fit_slit_planes,
)
from multislit.calibrate.camera import decompose_camera, refine_camera, rms
from multislit.calibrate.markers import find_marker_corners
from multislit.calibrate.model import SCHEMA
from multislit.calibrate.projector import fit_projector_matrix
from multislit.calibrate.slit_planes import axis_order_deviation, planes_between, slit_plane_rms
from multislit.calibrate.slit_points import points_on_faces
from multislit.errors import CalibrationError, MultislitError
from multislit.geometry import MatrixCamera, PinholeCamera, look_at, rvec_from_rotation
from multislit.io import Face

HEIKKILA = Path(__file__).resolve().parent / "data" / "heikkila-3d-rig" / "points.csv"


# --------------------------------------------------------------------------- synthetic rig
def make_camera(dist=(0.0, 0.0, 0.0, 0.0)) -> PinholeCamera:
    eye = np.array([420.0, -350.0, -900.0])
    R = look_at(eye, (120.0, 120.0, 120.0))
    return PinholeCamera(
        fx=1420.0,
        fy=1405.0,
        cx=652.0,
        cy=498.0,
        rvec=tuple(rvec_from_rotation(R)),
        tvec=tuple(-R @ eye),
        dist=dist,
        image_size=(1280, 1024),
    )


def markers_on_three_faces(rng: np.random.Generator, n: int = 20) -> np.ndarray:
    """n points on the faces x=0, y=0, z=0 of a 300 mm box corner (mm)."""
    pts = rng.uniform(20, 280, (n, 3))
    pts[np.arange(n), np.arange(n) % 3] = 0.0
    return pts


# --------------------------------------------------------------------------- DLT
def test_dlt_exact_recovers_matrix_and_parameters():
    rng = np.random.default_rng(0)
    cam = make_camera()
    X = markers_on_three_faces(rng, 30)
    uv = cam.project(X)
    dlt, res = calibrate_dlt(X, uv, cam.image_size)
    assert res.max() < 1e-6
    C_true = cam.matrix
    C = dlt.C / dlt.C[2, 3] * C_true[2, 3]
    np.testing.assert_allclose(C, C_true, rtol=1e-7, atol=1e-7 * np.abs(C_true).max())
    pin = decompose_camera(dlt)
    np.testing.assert_allclose([pin.fx, pin.fy, pin.cx, pin.cy], [1420, 1405, 652, 498], rtol=1e-7)
    np.testing.assert_allclose(pin.R, cam.R, atol=1e-9)
    np.testing.assert_allclose(pin.t, cam.t, rtol=1e-7, atol=1e-6)
    assert np.linalg.det(pin.R) == pytest.approx(1.0)
    np.testing.assert_allclose(pin.centre, cam.centre, atol=1e-5)


def test_decompose_handles_negated_matrix():
    cam = make_camera()
    pin = decompose_camera(-3.0 * cam.matrix)
    np.testing.assert_allclose(pin.R, cam.R, atol=1e-9)
    assert pin.fx > 0 and pin.fy > 0


def test_refine_on_distortion_free_data_keeps_dlt():
    rng = np.random.default_rng(1)
    cam = make_camera()
    X = markers_on_three_faces(rng, 30)
    uv = cam.project(X)
    dlt, _ = calibrate_dlt(X, uv, cam.image_size)
    ref, res = refine_camera(X, uv, dlt)
    assert res.max() < 1e-6
    assert np.abs(ref.dist).max() < 1e-7
    np.testing.assert_allclose(ref.project(X), dlt.project(X), atol=1e-6)
    np.testing.assert_allclose([ref.fx, ref.fy], [1420, 1405], rtol=1e-7)


def test_noisy_calibration_rms_matches_noise():
    rng = np.random.default_rng(2)
    cam = make_camera(dist=(-0.3, 0.1, 4e-4, -3e-4))
    X = markers_on_three_faces(rng, 20)
    sigma = 0.05
    uv = cam.project(X) + rng.normal(0, sigma, (20, 2))
    _, res_dlt = calibrate_dlt(X, uv, cam.image_size)
    ref, res = refine_camera(X, uv)
    # 40 equations, 14 parameters: expected RMS distance = sigma*sqrt(2*(40-14)/40)
    expected = sigma * np.sqrt(2 * 26 / 40)
    assert 0.5 * expected < rms(res) < 1.6 * expected
    assert rms(res_dlt) > 3 * rms(res)  # distortion the 3x4 matrix cannot model
    # check the model off the calibration points too
    Y = markers_on_three_faces(rng, 200)
    assert np.abs(ref.project(Y) - cam.project(Y)).max() < 0.5


def test_square_pixels_option():
    rng = np.random.default_rng(3)
    cam = PinholeCamera(1400, 1400, 640, 512, (0.1, -0.2, 0.05), (-100, -80, 900))
    X = markers_on_three_faces(rng, 25)
    ref, res = refine_camera(X, cam.project(X), square_pixels=True)
    assert ref.fx == ref.fy
    assert res.max() < 1e-5


@pytest.mark.parametrize(
    ("world", "image", "match"),
    [
        (np.zeros((5, 3)) + np.arange(5)[:, None], np.zeros((5, 2)), r"needs >= 6.*5 given"),
        (
            np.c_[np.random.default_rng(0).uniform(0, 100, (10, 2)), np.zeros(10)],
            np.random.default_rng(1).uniform(0, 100, (10, 2)),
            "coplanar: the DLT needs markers on at least two non-parallel faces",
        ),
    ],
)
def test_dlt_bad_input(world, image, match):
    with pytest.raises(CalibrationError, match=match):
        calibrate_dlt(world, image)


def test_dlt_nan_and_mismatched_input():
    rng = np.random.default_rng(4)
    cam = make_camera()
    X = markers_on_three_faces(rng, 12)
    uv = cam.project(X)
    uv[3, 0] = np.nan
    with pytest.raises(CalibrationError, match=r"image contains NaN.*rows \[3\]"):
        calibrate_dlt(X, uv)
    with pytest.raises(CalibrationError, match="corresponding pairs"):
        calibrate_dlt(X, uv[:10])
    with pytest.raises(MultislitError, match=r"world must have shape \(N, 3\)"):
        calibrate_dlt(X[:, :2], uv)


def test_dlt_degenerate_configurations():
    rng = np.random.default_rng(14)
    # 6 points on one line and 2 off it: not coplanar, but the matrix is not determined
    X = np.r_[np.linspace(0, 1, 6)[:, None] * [100, 50, 20.0], [[0, 100, 0], [50, 0, 100]]]
    with pytest.raises(CalibrationError, match="not unique"):
        calibrate_dlt(X, rng.uniform(0, 100, (8, 2)))
    with pytest.raises(CalibrationError, match="all points of image coincide"):
        calibrate_dlt(rng.uniform(0, 100, (8, 3)), np.ones((8, 2)))


# --------------------------------------------------------------------------- real data
@pytest.fixture(scope="module")
def heikkila():
    if not HEIKKILA.is_file():
        pytest.skip(f"real calibration data not found at {HEIKKILA}")
    first = HEIKKILA.read_text().splitlines()[0]
    skip = 0 if first[0].isdigit() or first[0] == "-" else 1  # the file has a header line
    d = np.loadtxt(HEIKKILA, delimiter=",", skiprows=skip)
    assert d.shape == (491, 5)
    return d[:, :3], d[:, 3:]


def test_heikkila_dlt_and_refinement(heikkila):
    X, uv = heikkila
    dlt, res = calibrate_dlt(X, uv, (768, 576))
    assert 0.90 < rms(res) < 1.02
    assert 2.4 < res.max() < 3.0
    ref, res2 = refine_camera(X, uv, dlt, distortion=True)
    assert rms(res2) <= 0.08
    assert ref.dist[0] < -0.1  # barrel distortion
    radial, res3 = refine_camera(X, uv, dlt, tangential=False)
    assert abs(rms(res3) - 0.073) < 0.003
    assert abs(rms(res3) - rms(res2)) < 0.002
    _, res4 = refine_camera(X, uv, dlt, distortion=False)
    assert rms(res4) > 0.9


# --------------------------------------------------------------------------- markers
def draw_marker(
    rng: np.random.Generator,
    size: tuple[int, int] = (96, 80),
    corner: tuple[float, float] | None = None,
    kind: str = "checker",
    scale: float = 12.0,
    blur: float = 0.7,
    noise: float = 2.0,
    supersample: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """A 2x2 checker (or an edge / blank patch) seen through a random homography.

    The drawing is rendered at ``supersample`` x resolution with cv2.warpPerspective (nearest
    samples of an analytic pattern), box-averaged to 1x, blurred and noised. Returns the uint8
    image and the true corner (px).
    """
    w, h = size
    c = np.array(corner) if corner is not None else np.array([w / 2, h / 2]) + rng.uniform(-3, 3, 2)
    ang = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    shear = np.array(
        [[1 + rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2)], [0, 1 + rng.uniform(-0.2, 0.2)]]
    )
    H = np.eye(3)
    H[:2, :2] = scale * rot @ shear
    H[:2, 2] = c
    H[2, :2] = rng.uniform(-0.04, 0.04, 2)
    # analytic pattern on a fine grid of the marker plane (units: squares), drawn high-res
    f = supersample
    n_src = 2048
    half = 2.0  # the drawing covers [-2, 2]^2 squares
    g = (np.arange(n_src) + 0.5) / n_src * 2 * half - half
    a, b = np.meshgrid(g, g)
    inside = (np.abs(a) < 1) & (np.abs(b) < 1)
    if kind == "checker":
        pat = np.where((a > 0) == (b > 0), 40.0, 210.0)
    elif kind == "edge":
        pat, inside = np.where(a > 0, 40.0, 210.0), np.ones_like(inside)
    else:
        pat = np.full(a.shape, 190.0)
    pat = np.where(inside, pat, 190.0).astype(np.float32)
    # src pixel (i, j) centre <-> marker-plane point; hi-res dst pixel centre <-> image px
    S = np.array(
        [
            [n_src / (2 * half), 0, n_src / 2 - 0.5],
            [0, n_src / (2 * half), n_src / 2 - 0.5],
            [0, 0, 1],
        ]
    )
    D = np.array([[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1]])
    M = D @ H @ np.linalg.inv(S)  # src px -> hi-res dst px
    hi = cv2.warpPerspective(pat, M, (w * f, h * f), flags=cv2.INTER_NEAREST, borderValue=190.0)
    img = cv2.resize(hi, (w, h), interpolation=cv2.INTER_AREA).astype(float)
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img += rng.normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), c


@pytest.mark.slow
def test_marker_corner_subpixel_accuracy():
    rng = np.random.default_rng(5)
    errs = []
    for _ in range(25):
        img, c = draw_marker(rng)
        det = find_marker_corners(img, c[None] + rng.uniform(-6, 6, 2), ["m"], search_radius=12)
        assert det.found[0], det.reasons
        assert det.reasons == ("",)
        errs.append(np.hypot(*(det.uv[0] - c)))
    assert max(errs) <= 0.05
    assert np.sqrt(np.mean(np.square(errs))) < 0.03


def test_marker_uint16_image():
    rng = np.random.default_rng(6)
    img, c = draw_marker(rng)
    det = find_marker_corners(img.astype(np.uint16) * 257, c[None] + 2.0)
    assert det.found[0]
    assert np.hypot(*(det.uv[0] - c)) < 0.05


def test_marker_rejects_blank_edge_and_off_image():
    rng = np.random.default_rng(7)
    blank, c = draw_marker(rng, kind="blank")
    edge, c2 = draw_marker(rng, kind="edge")
    good, c3 = draw_marker(rng)
    img = np.hstack([blank, edge, good])
    w = blank.shape[1]
    hints = np.array([c, c2 + [w, 0], c3 + [2 * w, 0] + 4, [-20.0, 30.0], [10.0, 500.0]])
    det = find_marker_corners(img, hints, ["blank", "edge", "good", "left", "below"])
    assert det.found.tolist() == [False, False, True, False, False]
    assert np.all(np.isnan(det.uv[~det.found]))
    assert np.hypot(*(det.uv[2] - c3 - [2 * w, 0])) < 0.05
    rej = det.rejected
    assert set(rej) == {"blank", "edge", "left", "below"}
    assert "edge" in rej["edge"] or "L-corner" in rej["edge"]
    assert "off the image" in rej["left"] and "off the image" in rej["below"]
    assert "not a checker corner" in rej["blank"] or "contrast" in rej["blank"]


def test_marker_bad_image_type():
    with pytest.raises(CalibrationError, match="uint8 or uint16"):
        find_marker_corners(np.zeros((20, 20), np.float32), [[10, 10]])


# --------------------------------------------------------------------------- projector
def grating_planes(num: int = 25, pitch_um: float = 30.0, wavelength_nm: float = 650.0):
    """Slit planes of a diffraction grating: sin(theta_m) = m lambda / pitch, one vertical axis.

    The axis is vertical (direction +y) through (450, 0, 0) mm; order 0 contains the origin.
    Returns planes (K, 4), the orders m (K,), and the axis point.
    """
    m = np.arange(num) - num // 2
    theta = np.arcsin(m * wavelength_nm * 1e-6 / (pitch_um * 1e-3))
    a = np.array([450.0, 0.0, 0.0])
    # order 0 plane contains the axis and the direction (-1, 0, 0): normal (0, 0, 1)
    n = np.stack([np.sin(theta), np.zeros(num), np.cos(theta)], axis=1)
    return np.c_[n, -n @ a], m, a


def points_on_planes(rng, planes, per_slit: int = 40, noise: float = 0.0):
    k = len(planes)
    s = np.repeat(np.arange(k), per_slit)
    n = planes[s, :3]
    a = np.array([450.0, 0.0, 0.0])
    inplane = np.cross(n, [0.0, 1.0, 0.0])  # horizontal direction in the plane, away from axis
    inplane *= np.sign(inplane[:, :1] * -1)  # towards -x (the target)
    r = rng.uniform(250, 650, len(s))
    y = rng.uniform(-150, 150, len(s))
    X = a + r[:, None] * inplane + y[:, None] * np.array([0.0, 1.0, 0.0])
    X += noise * rng.normal(size=(len(s), 1)) * n
    return X, s


def test_grating_paper_model_systematic_error_vs_slit_planes():
    rng = np.random.default_rng(8)
    planes_true, m, axis = grating_planes()
    X, s = points_on_planes(rng, planes_true, noise=0.0)
    np.testing.assert_allclose(slit_plane_rms(planes_true, X, s)[0], 0.0, atol=1e-9)
    noise = 0.02
    Xn = X + noise * rng.normal(size=X.shape)
    pm, res = ProjectorMatrix.fit(Xn, s, len(planes_true), xp_values=m.astype(float))
    paper_rms = slit_plane_rms(pm.planes(), X, s)[0]  # against noise-free points: systematic
    sp = fit_slit_planes(Xn, s, len(planes_true), common_axis=True)
    ours_rms = slit_plane_rms(sp.planes, X, s)[0]
    assert np.max(ours_rms) < 2 * noise
    assert np.median(sp.rms_mm) == pytest.approx(noise, rel=0.3)
    assert np.max(paper_rms) > 10 * np.max(ours_rms)
    assert rms(res) > 5 * noise
    # the common axis is recovered
    assert abs(abs(sp.axis_direction[1]) - 1) < 1e-6
    np.testing.assert_allclose(sp.axis_point, axis, atol=0.5)
    free = fit_slit_planes(Xn, s, len(planes_true), common_axis=False)
    assert np.max(slit_plane_rms(free.planes, X, s)[0]) < 3 * noise
    assert free.axis_point is None


def test_projector_matrix_exact_on_projective_pencil():
    # planes of a pencil with X_p a Moebius function of the angle: the 2x4 model is exact
    rng = np.random.default_rng(9)
    P_true = np.array([[0.0, 0.0, 1.0, 0.0], [0.01, 0.0, 0.0, -4.5]])
    k = 9
    pm_true = ProjectorMatrix(P_true, np.arange(k, dtype=float))
    planes = pm_true.planes()
    X, s = points_on_planes(rng, planes, per_slit=10)
    pm, res = ProjectorMatrix.fit(X, s, k)
    assert np.abs(res).max() < 1e-8
    assert np.max(slit_plane_rms(pm.planes(), X, s)[0]) < 1e-8
    P, res2 = fit_projector_matrix(X, s.astype(float))
    np.testing.assert_allclose(P / P[0, 2], pm.P / pm.P[0, 2], atol=1e-9)
    assert ProjectorMatrix.from_json(pm.to_json()).P.tolist() == pm.P.tolist()


def test_projector_bad_input():
    rng = np.random.default_rng(10)
    X = rng.uniform(0, 100, (7, 3))
    with pytest.raises(CalibrationError, match=r"needs >= 8 points.*7 given"):
        fit_projector_matrix(X, np.arange(7.0))
    with pytest.raises(CalibrationError, match="same X_p"):
        fit_projector_matrix(rng.uniform(0, 100, (10, 3)), np.ones(10))
    with pytest.raises(CalibrationError, match="slits has values outside 0..3"):
        fit_slit_planes(X, [0, 1, 2, 3, 4, 0, 1], 4)


def test_slit_planes_reports_short_and_collinear_slits():
    rng = np.random.default_rng(11)
    planes_true, _, _ = grating_planes(num=5)
    X, s = points_on_planes(rng, planes_true, per_slit=20)
    # slit 1: only 2 points; slit 3: collinear points (on a vertical line, in its plane)
    keep = (s != 1) | (np.arange(len(s)) % 20 < 2)
    X, s = X[keep].copy(), s[keep]
    line = s == 3
    X[line] = X[line][0] + np.linspace(0, 1, line.sum())[:, None] * [0.0, 100.0, 0.0]
    free = fit_slit_planes(X, s, 6, common_axis=False)
    assert dict(free.excluded).keys() == {1, 3}
    assert "2 point" in dict(free.excluded)[1] and "collinear" in dict(free.excluded)[3]
    assert free.valid.tolist() == [True, False, True, False, True, False]
    assert free.counts.tolist() == [20, 2, 20, 20, 20, 0]
    assert np.nanmax(free.rms_mm) < 1e-6 and free.from_axis == ()
    # with the common axis, the line and the axis span slit 3's plane
    sp = fit_slit_planes(X, s, 6)
    assert dict(sp.excluded).keys() == {1} and sp.from_axis == (3,)
    assert sp.valid.tolist() == [True, False, True, True, True, False]
    pl = sp.planes[3] * np.sign(sp.planes[3, :3] @ planes_true[3, :3])
    np.testing.assert_allclose(pl, planes_true[3], atol=1e-7)
    assert np.nanmax(sp.rms_mm) < 1e-6


def _angle_mrad(planes, truth_planes):
    c = np.abs(np.sum(planes[:, :3] * truth_planes[:, :3], axis=1))
    return 1e3 * np.arccos(np.clip(c, 0, 1))


def _on_line(rng, plane, axis, n, direction, noise):
    """n points along a 200 mm line in ``plane`` ~550 mm from the axis, noisy across the plane."""
    inplane = np.cross(plane[:3], [0.0, 1.0, 0.0])
    inplane *= -np.sign(inplane[0])
    p0 = axis + 550.0 * inplane
    d = np.asarray(direction, float) @ np.stack([inplane, [0.0, 1.0, 0.0]])
    d /= np.linalg.norm(d)
    t = np.linspace(-100, 100, n)[:, None]
    return p0 + t * d + noise * rng.normal(size=(n, 1)) * plane[:3]


def test_slits_seen_along_one_line_get_the_plane_through_the_axis():
    rng = np.random.default_rng(21)
    planes_true, _, axis = grating_planes(num=9)
    noise = 0.02
    X, s = points_on_planes(rng, planes_true, per_slit=60, noise=noise)
    # slits 0 and 3 on lines parallel to the axis (a vertical wall), slit 8 on a slanted line
    for j, direction in [(0, (0.0, 1.0)), (3, (0.0, 1.0)), (8, (1.0, 0.7))]:
        X[s == j] = _on_line(rng, planes_true[j], axis, 60, direction, noise)
    sp = fit_slit_planes(X, s, 9, min_width_mm=0.5)
    assert sp.from_axis == (0, 3, 8) and sp.excluded == ()
    ang = _angle_mrad(sp.planes, planes_true)
    # as accurate as the slits seen on two faces; their residuals are the noise
    assert ang[[0, 3, 8]].max() < max(0.2, 2 * np.delete(ang, [0, 3, 8]).max()), ang
    np.testing.assert_allclose(sp.rms_mm[[0, 3, 8]], noise, rtol=0.35)
    # without the common axis a line does not determine a plane
    free = fit_slit_planes(X, s, 9, common_axis=False, min_width_mm=0.5)
    assert dict(free.excluded).keys() == {0, 3, 8} and free.from_axis == ()
    assert all("one line" in r and "common_axis=False" in r for _, r in free.excluded)
    # the JSON keeps which planes come from the axis
    assert SlitPlanes.from_json(sp.to_json()).from_axis == (0, 3, 8)


@pytest.mark.slow
def test_line_slits_stay_excluded_when_the_axis_cannot_place_them():
    rng = np.random.default_rng(22)
    planes_true, _, axis = grating_planes(num=9)
    X, s = points_on_planes(rng, planes_true, per_slit=40, noise=0.02)
    # slit 3's points are those of slit 4's plane (mislabelled): one slit spacing off
    X[s == 3] = _on_line(rng, planes_true[4], axis, 40, (0.0, 1.0), 0.02)
    # slit 6's points run along the axis itself, 5 mm from it: no angle about the axis
    inplane = np.cross(planes_true[6, :3], [0.0, 1.0, 0.0])
    X[s == 6] = axis + 5.0 * inplane + np.linspace(-100, 100, 40)[:, None] * [0.0, 1.0, 0.0]
    # slit 7: two points only
    keep = (s != 7) | (np.arange(len(s)) % 40 < 2)
    X, s = X[keep], s[keep]
    sp = fit_slit_planes(X, s, 9, min_width_mm=0.5)
    why = dict(sp.excluded)
    assert sp.from_axis == () and why.keys() == {3, 6, 7}, why
    assert "mislabelled" in why[3] and "slit spacings" in why[3]
    assert "of the common axis" in why[6] and "undetermined" in why[6]
    assert "only 2 point(s)" in why[7]
    assert not sp.valid[[3, 6, 7]].any() and np.isnan(sp.rms_mm[[3, 6, 7]]).all()
    # an axis from two slits only is not trusted to place a line
    two = np.isin(s, [0, 1, 3])
    sp2 = fit_slit_planes(X[two], s[two], 9, min_width_mm=0.5)
    assert "fitted from only 2 slit(s)" in dict(sp2.excluded)[3], sp2.excluded
    with pytest.raises(CalibrationError, match="min_width_mm"):
        fit_slit_planes(X, s, 9, min_width_mm=-1.0)


def test_slit_plane_weights():
    rng = np.random.default_rng(23)
    planes_true, _, _ = grating_planes(num=7)
    X, s = points_on_planes(rng, planes_true, per_slit=40, noise=0.01)
    bad = np.arange(len(s)) % 10 == 0
    Xb = X.copy()
    Xb[bad] += 3.0 * planes_true[s[bad], :3]  # 3 mm off their planes
    plain = fit_slit_planes(Xb, s, 7)
    w = fit_slit_planes(Xb, s, 7, weights=np.where(bad, 0.0, 1.0))
    assert (
        _angle_mrad(w.planes, planes_true).max()
        < 0.5 * _angle_mrad(plain.planes, planes_true).max()
    )
    # the reported residual is the plain RMS of all points
    assert np.all(w.rms_mm > 0.5)
    with pytest.raises(CalibrationError, match="weights must be"):
        fit_slit_planes(X, s, 7, weights=np.ones(3))


# --------------------------------------------------------------------------- faces
def test_points_on_faces():
    cam = make_camera()
    faces = [
        Face("back", (0.0, 0.0, 1.0, 0.0), ((0, 0, 0), (300, 0, 0), (300, 300, 0), (0, 300, 0))),
        Face("side", (1.0, 0.0, 0.0, 0.0), ((0, 0, 0), (0, 300, 0), (0, 300, 300), (0, 0, 300))),
        Face("floor", (0.0, 1.0, 0.0, 0.0), ((0, 0, 0), (300, 0, 0), (300, 0, 300), (0, 0, 300))),
    ]
    rng = np.random.default_rng(12)
    X = markers_on_three_faces(rng, 30)
    outside = np.array([[600.0, 100.0, 0.0], [100.0, -200.0, 0.0]])  # on back plane, off polygon
    uv = cam.project(np.vstack([X, outside]))
    xyz, fi = points_on_faces(cam, uv, faces)
    assert np.all(fi[30:] == -1) and np.all(np.isnan(xyz[30:]))
    # each synthetic point is on face (index % 3) = side(x=0)->1, floor(y=0)->2, back(z=0)->0
    expected = np.array([1, 2, 0])[np.arange(30) % 3]
    # a point is visible unless another face is nearer along its ray: compare where it matches
    match = fi[:30] == expected
    assert match.mean() > 0.5
    np.testing.assert_allclose(xyz[:30][match], X[match], atol=1e-8)


# --------------------------------------------------------------------------- calibration file
def _calibration() -> Calibration:
    rng = np.random.default_rng(13)
    cam = make_camera(dist=(-0.1, 0.02, 0.0, 0.0))
    X = markers_on_three_faces(rng, 20)
    uv = cam.project(X)
    dlt, res_d = calibrate_dlt(X, uv, cam.image_size)
    ref, res = refine_camera(X, uv, dlt)
    planes, m, _ = grating_planes(num=7)
    Xs, s = points_on_planes(rng, planes, per_slit=10)
    s[s == 6] = 5  # slit 6 has no data
    sp = fit_slit_planes(Xs, s, 7)
    pm, _ = ProjectorMatrix.fit(Xs, s, 7)
    return Calibration(
        image_size=cam.image_size,
        dlt=dlt,
        refined=ref,
        projector=pm,
        slit_planes=sp,
        camera_rms_px=rms(res),
        dlt_rms_px=rms(res_d),
        marker_ids=tuple(f"M{i}" for i in range(20)),
        marker_residuals_px=res,
    )


def test_calibration_json_round_trip(tmp_path):
    cal = _calibration()
    assert cal.camera is cal.refined
    p = cal.save(tmp_path / "sub" / "calibration.json")
    d = json.loads(p.read_text())
    assert d["schema"] == SCHEMA and d["units"]["length"] == "mm"
    assert d["slit_planes"]["planes"][6] == [None, None, None, None]
    back = Calibration.load(p)
    assert back.image_size == cal.image_size
    np.testing.assert_allclose(back.dlt.C, cal.dlt.C)
    assert back.refined.to_dict() == cal.refined.to_dict()
    np.testing.assert_allclose(back.projector.P, cal.projector.P)
    np.testing.assert_array_equal(back.slit_planes.planes, cal.slit_planes.planes)
    np.testing.assert_array_equal(back.slit_rms_mm, cal.slit_rms_mm)
    assert back.slit_planes.excluded == cal.slit_planes.excluded
    assert back.marker_ids == cal.marker_ids
    np.testing.assert_allclose(back.marker_residuals_px, cal.marker_residuals_px)
    assert back.camera_rms_px == cal.camera_rms_px
    assert back.to_json() == cal.to_json()
    minimal = Calibration((1280, 1024), cal.dlt)
    assert isinstance(Calibration.from_json(minimal.to_json()).camera, MatrixCamera)


def test_calibration_errors(tmp_path):
    cal = _calibration()
    d = cal.to_dict()
    d["schema"] = "multislit-calibration/0"
    with pytest.raises(CalibrationError, match="schema is 'multislit-calibration/0'"):
        Calibration.from_dict(d)
    with pytest.raises(CalibrationError, match="calibration file not found"):
        Calibration.load(tmp_path / "nope.json")
    with pytest.raises(CalibrationError, match="images are 640x480 px .* 1280x1024 px"):
        cal.check_image_size((640, 480))
    cal.check_image_size((1280, 1024))
    d = cal.to_dict()
    del d["camera_dlt"]
    with pytest.raises(CalibrationError, match="malformed"):
        Calibration.from_dict(d)


def test_axis_model_checks_order_and_fills_in_between():
    rng = np.random.default_rng(5)
    planes_true, _, _ = grating_planes(num=15)
    X, s = points_on_planes(rng, planes_true, per_slit=60, noise=0.01)
    keep = ~np.isin(s, [0, 6])  # slit 0 at the end and slit 6 between planes: no points
    sp = fit_slit_planes(X[keep], s[keep], 15)
    dev = axis_order_deviation(sp)
    assert np.isnan(dev[[0, 6]]).all() and np.nanmax(np.abs(dev)) < 0.01, dev
    filled, which = planes_between(sp)
    assert which == (6,) and not filled.valid[0] and np.isnan(filled.rms_mm[6])
    assert _angle_mrad(filled.planes[[6]], planes_true[[6]])[0] < 0.05
    # a plane turned a third of a spacing (mislabelled points) stands out
    bad = sp.planes.copy()
    n = bad[9, :3]
    # turn about the axis (vertical, through (450, 0, 0))
    step = np.arcsin(650e-6 / 30e-3) / 3
    c, si = np.cos(step), np.sin(step)
    n2 = np.array([c * n[0] + si * n[2], n[1], -si * n[0] + c * n[2]])
    bad[9] = [*n2, -(n2 @ np.array([450.0, 0.0, 0.0]))]
    dev2 = axis_order_deviation(dataclasses.replace(sp, planes=bad))
    assert abs(dev2[9]) > 0.25 and np.nanmax(np.abs(np.delete(dev2, 9))) < 0.2, dev2
