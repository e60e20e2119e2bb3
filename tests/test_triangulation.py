"""Tests of triangulation: the paper's V = Q^-1 F and rays intersected with slit planes."""

from __future__ import annotations

import numpy as np
import pytest

from multislit.calibrate import ProjectorMatrix, calibrate_dlt, fit_slit_planes
from multislit.errors import MultislitError
from multislit.geometry import MatrixCamera, PinholeCamera, look_at, rvec_from_rotation
from multislit.reconstruct import triangulate, triangulate_matrix


def make_camera(dist=(0.0, 0.0, 0.0, 0.0)) -> PinholeCamera:
    eye = np.array([0.0, 0.0, -1000.0])
    R = look_at(eye, (0.0, 0.0, 0.0))
    return PinholeCamera(
        1400.0, 1390.0, 640.0, 512.0, tuple(rvec_from_rotation(R)), tuple(-R @ eye), dist
    )


def slit_planes(k: int = 15) -> np.ndarray:
    """Planes through a vertical axis at x = 450 mm, z = -1000 mm, fanning over the scene."""
    ang = np.deg2rad(np.linspace(-12, 12, k))
    a = np.array([450.0, 0.0, -1000.0])
    base = np.array([-450.0, 0.0, 1000.0]) / np.hypot(450, 1000)  # axis -> origin
    along = np.cos(ang)[:, None] * base + np.sin(ang)[:, None] * np.cross([0, 1.0, 0], base)
    n = np.cross(along, [0.0, 1.0, 0.0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.c_[n, -n @ a]


def points_on(planes: np.ndarray, rng: np.random.Generator, per: int = 50):
    s = np.repeat(np.arange(len(planes)), per)
    y = rng.uniform(-200, 200, len(s))
    z = rng.uniform(-150, 200, len(s))
    n = planes[s, :3]
    # solve n.X + d = 0 for x given y, z
    x = -(n[:, 1] * y + n[:, 2] * z + planes[s, 3]) / n[:, 0]
    return np.c_[x, y, z], s


def test_triangulate_round_trip_pinhole_with_distortion():
    rng = np.random.default_rng(0)
    cam = make_camera(dist=(-0.15, 0.08, 5e-4, -2e-4))
    planes = slit_planes()
    X, s = points_on(planes, rng)
    uv = cam.project(X)
    pts, valid = triangulate(cam, planes, uv, s)
    assert valid.all()
    assert np.abs(pts - X).max() < 1e-6


def test_triangulate_matrix_round_trip():
    rng = np.random.default_rng(1)
    cam = make_camera()
    # a projector pencil: plane of X_p is (P0 - X_p P1).[X, 1] = 0
    P = np.array([[1.0, 0.0, 0.3, -300.0], [0.002, 0.0, 0.0, 1.0]])
    k = 12
    pm = ProjectorMatrix(P, np.arange(k, dtype=float))
    planes = pm.planes()
    X, s = points_on(planes, rng, per=30)
    uv = cam.project(X)
    V, valid = triangulate_matrix(cam.matrix, P, uv, s.astype(float))
    assert valid.all()
    assert np.abs(V - X).max() < 1e-6
    # the general path with the same model agrees
    pts, valid2 = triangulate(MatrixCamera(cam.matrix), planes, uv, s)
    assert valid2.all()
    assert np.abs(pts - X).max() < 1e-6
    # and the calibrated DLT camera (any scale / sign of C) gives the same points
    dlt, _ = calibrate_dlt(X, uv)
    V2, _ = triangulate_matrix(-7.0 * dlt.C, P, uv, s.astype(float))
    assert np.abs(V2 - X).max() < 1e-6


def test_triangulate_matrix_rejects_parallel_and_nan():
    cam = make_camera()
    # a plane containing the camera centre (0, 0, -1000): every ray lies in it
    P = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    uv = np.array([[640.0, 512.0], [700.0, 500.0], [100.0, 100.0]])
    V, valid = triangulate_matrix(cam.matrix, P, uv, [0.0, np.nan, 5.0])
    assert valid.tolist() == [False, False, True]
    assert np.all(np.isnan(V[:2])) and np.all(np.isfinite(V[2]))
    with pytest.raises(MultislitError, match="xp has 2 values"):
        triangulate_matrix(cam.matrix, P, uv, [0.0, 1.0])
    with pytest.raises(MultislitError, match=r"P must be a finite \(2, 4\)"):
        triangulate_matrix(cam.matrix, P[:1], uv, [0.0, 1.0, 2.0])


def test_triangulate_rejects_grazing_unknown_and_missing_planes():
    cam = make_camera()
    planes = slit_planes(5)
    # slit 4's plane contains the camera centre: all its rays are parallel to it
    c = cam.centre
    n = np.array([1.0, 0.0, 0.0])
    planes[4] = np.r_[n, -n @ c]
    planes[2] = np.nan  # slit without calibration
    uv = np.array([[600.0, 500.0]] * 5)
    pts, valid = triangulate(cam, planes, uv, np.array([0, 2, 4, -1, 1]))
    assert valid.tolist() == [True, False, False, False, True]
    assert np.all(np.isnan(pts[~valid]))
    with pytest.raises(MultislitError, match=r"slit has values outside 0..4 \(e.g. 5"):
        triangulate(cam, planes, uv, np.array([0, 1, 5, 0, 0]))
    with pytest.raises(MultislitError, match="slit must be integer"):
        triangulate(cam, planes, uv, np.zeros(5))


def test_fitted_slit_planes_triangulate_to_the_surface():
    rng = np.random.default_rng(2)
    cam = make_camera(dist=(-0.1, 0.0, 0.0, 0.0))
    planes = slit_planes(9)
    X, s = points_on(planes, rng, per=40)
    sp = fit_slit_planes(X + rng.normal(0, 0.01, X.shape), s, 9)
    Y, s2 = points_on(planes, rng, per=20)
    pts, valid = triangulate(cam, sp.planes, cam.project(Y), s2)
    assert valid.all()
    assert np.sqrt(np.mean(np.sum((pts - Y) ** 2, axis=1))) < 0.1
