import numpy as np
import pytest

from multislit.errors import MultislitError
from multislit.geometry import (
    CircleModel,
    LineModel,
    MatrixCamera,
    PinholeCamera,
    PlaneModel,
    camera_from_dict,
    check_plane,
    fit_plane,
    intersect_rays_planes,
    look_at,
    ransac,
    rotation_from_rvec,
    rvec_from_rotation,
)


@pytest.fixture()
def cam() -> PinholeCamera:
    return PinholeCamera(
        1800,
        1790,
        645,
        508,
        rvec=(0.1, -0.25, 0.03),
        tvec=(20, -10, 1000),
        dist=(-0.15, 0.08, 0.001, -0.0015),
    )


def test_projection_matches_opencv(cam, rng):
    import cv2

    X = rng.uniform(-300, 300, (200, 3))
    ref, _ = cv2.projectPoints(X, np.array(cam.rvec), np.array(cam.tvec), cam.K, np.array(cam.dist))
    assert np.abs(cam.project(X) - ref.reshape(-1, 2)).max() < 1e-9


def test_rays_pass_through_points(cam, rng):
    X = rng.uniform(-300, 300, (200, 3))
    o, d = cam.rays(cam.project(X))
    v = X - o
    dist = np.linalg.norm(v - np.einsum("ij,ij->i", v, d)[:, None] * d, axis=1)
    assert dist.max() < 1e-8
    assert np.all(np.einsum("ij,ij->i", v, d) > 0), "rays must point forward"


def test_undistort_inverts_distort(cam, rng):
    uv = rng.uniform([0, 0], [1280, 1024], (500, 2))
    und = cam.undistort_pixels(uv)
    nodist = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy)
    # re-distort through a ray in the camera frame
    xy = (und - [cam.cx, cam.cy]) / [cam.fx, cam.fy]
    back = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, dist=cam.dist).project(
        np.c_[xy, np.ones(len(xy))]
    )
    assert np.abs(back - uv).max() < 1e-8
    assert np.abs(nodist.undistort_pixels(uv) - uv).max() < 1e-12


def test_matrix_camera_agrees_with_pinhole(rng):
    cam = PinholeCamera(1500, 1500, 600, 500, rvec=(0.2, 0.1, -0.1), tvec=(5, 5, 900))
    mc = MatrixCamera(cam.matrix * 3.7)  # any positive scale
    X = rng.uniform(-200, 200, (50, 3))
    assert np.abs(mc.project(X) - cam.project(X)).max() < 1e-9
    assert np.allclose(mc.centre, cam.centre)
    o, d = mc.rays(cam.project(X))
    assert np.all(np.einsum("ij,ij->i", X - o, d) > 0)


def test_rotation_round_trip(rng):
    for _ in range(20):
        r = rng.normal(size=3)
        r *= rng.uniform(0, 3.1) / np.linalg.norm(r)
        R = rotation_from_rvec(r)
        assert np.allclose(R @ R.T, np.eye(3))
        assert np.allclose(rvec_from_rotation(R), r, atol=1e-9)


def test_look_at_orientation():
    R = look_at((0, 0, 1000), (0, 0, 0))
    # world up (+Y) appears as image up (-y), world +X as image right
    assert np.allclose(R @ [0, 1, 0], [0, -1, 0])
    assert np.allclose(R @ [1, 0, 0], [1, 0, 0])
    assert np.allclose(R @ [0, 0, -1], [0, 0, 1])


def test_json_round_trip(cam):
    c2 = camera_from_dict(cam.to_dict())
    X = np.array([[10.0, 20, 30]])
    assert np.allclose(c2.project(X), cam.project(X))
    m = MatrixCamera(cam.matrix)
    assert np.allclose(MatrixCamera.from_json(m.to_json()).C, m.C)
    with pytest.raises(MultislitError, match="unknown camera model"):
        camera_from_dict({"model": "fisheye"})


def test_fit_plane_and_errors(rng):
    n = np.array([0.2, -0.3, 0.93])
    n /= np.linalg.norm(n)
    pts = rng.uniform(-100, 100, (100, 3))
    pts -= np.outer(pts @ n - 50.0, n)
    plane, res = fit_plane(pts)
    assert abs(abs(plane[:3] @ n) - 1) < 1e-12 and np.abs(res).max() < 1e-9
    with pytest.raises(MultislitError, match="collinear"):
        fit_plane(np.outer(np.arange(5.0), [1, 2, 3]))
    with pytest.raises(MultislitError, match="points must have shape"):
        fit_plane(np.zeros((4, 2)))


def test_intersect_rays_rejects_grazing_rays():
    o = np.zeros((2, 3))
    d = np.array([[0, 0, 1.0], [1, 0, 1e-4]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts, t = intersect_rays_planes(o, d, np.array([0, 0, 1.0, -500]), min_cos=0.05)
    assert np.allclose(pts[0], [0, 0, 500]) and np.isnan(pts[1]).all()


def test_weighted_fit_plane(rng):
    pts = rng.uniform(-100, 100, (50, 3))
    pts[:, 2] = 0.1 * pts[:, 0] - 3.0
    w = rng.uniform(0.5, 2.0, 50)
    plane, res = fit_plane(pts, weights=w)
    np.testing.assert_allclose(abs(plane[:3] @ np.array([0.1, 0, -1]) / np.hypot(0.1, 1)), 1)
    assert np.abs(res).max() < 1e-9
    # a point with weight 0 does not pull the plane
    off = np.vstack([pts, [0.0, 0.0, 50.0]])
    p0, _ = fit_plane(off, weights=np.append(w, 0.0))
    np.testing.assert_allclose(p0 * np.sign(p0[2]), plane * np.sign(plane[2]), atol=1e-9)
    with pytest.raises(MultislitError, match="weights are 0"):
        fit_plane(pts, weights=np.zeros(50))
    with pytest.raises(MultislitError, match="weights must have shape"):
        fit_plane(pts, weights=np.ones(3))


def test_ransac_plane_line_circle(rng):
    # plane z = 0 with 30 % outliers: most inliers within the threshold
    pts = np.column_stack([rng.uniform(-50, 50, (200, 2)), rng.normal(0, 0.01, 200)])
    pts[:60, 2] += rng.uniform(5, 20, 60)
    tri = rng.integers(0, 200, size=(200, 3))
    best = ransac(PlaneModel(), pts, tri, threshold=0.1)
    assert best is not None and best.score >= 130 and not best.inliers[:60].any()
    assert abs(abs(best.params[2]) - 1) < 1e-3
    lmeds = ransac(PlaneModel(), pts, tri, block_elements=1000)  # least median, in blocks
    assert lmeds is not None and lmeds.inliers is None and lmeds.score < 0.05
    # group rule: candidates need inliers in two groups
    groups = (pts[:, 0] > 0).astype(np.int64)
    assert ransac(PlaneModel(), pts, tri, threshold=0.1, groups=groups).score >= 130
    # line along x with squared-distance residuals
    line = np.column_stack([np.linspace(0, 100, 50), np.zeros(50), np.zeros(50)])
    best = ransac(LineModel(min_length=1.0), line, rng.integers(0, 50, (20, 2)), threshold=1e-6)
    assert best.score == 50 and abs(abs(best.params[3]) - 1) < 1e-12
    # circle through triples; all samples degenerate -> None
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    circ = np.column_stack([3 + 5 * np.cos(t), 5 * np.sin(t)])
    best = ransac(CircleModel(), circ, [[0, 3, 6], [1, 1, 2]])
    np.testing.assert_allclose(best.params, [3, 0, 5], atol=1e-12)
    assert ransac(CircleModel(), circ, [[0, 0, 1]]) is None


def test_check_plane():
    np.testing.assert_allclose(check_plane([0, 0, 2, 4]), [0, 0, 1, 2])
    with pytest.raises(MultislitError, match="zero normal"):
        check_plane([0, 0, 0, 1])
    with pytest.raises(MultislitError, match="my_plane must be a finite"):
        check_plane([0, 0, 1], "my_plane")
