"""Hole measurement (paper section 6.2.3, Table 1) on synthetic data with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry import (
    CircleFit,
    fit_circle,
    fit_plane_robust,
    from_plane_coords,
    plane_basis,
    project_to_plane,
)
from multislit.measure import fit_holes, hole_edges_from_profiles

NOISE = 0.05  # mm, per coordinate


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


# the plate: tilted 25 deg and 15 deg, about 0.9 m from the system
R = _rot("y", 25) @ _rot("x", -15)
O, E1, E2, N = np.array([10.0, -20.0, 900.0]), R[:, 0], R[:, 1], R[:, 2]
PLANE = np.append(N, -N @ O)


def to3d(q: np.ndarray) -> np.ndarray:
    """Plate coordinates (M, 2) mm -> target frame (M, 3) mm."""
    q = np.atleast_2d(q)
    return O + q[:, :1] * E1 + q[:, 1:] * E2


def crossings(centre, diameter, spacing, phase, first_slit=0):
    """Where slit lines x = phase + k * spacing (plate coordinates) cut a circle.

    Returns points (M, 2), slit numbers (M,), gap ids (M,): two points per crossing slit.
    """
    r = diameter / 2
    k = np.arange(np.floor((centre[0] - r - phase) / spacing), (centre[0] + r - phase) / spacing)
    xs = phase + k * spacing
    keep = np.abs(xs - centre[0]) < r
    xs, k = xs[keep], k[keep].astype(int)
    h = np.sqrt(r * r - (xs - centre[0]) ** 2)
    q = np.column_stack([np.concatenate([xs, xs]), np.concatenate([centre[1] - h, centre[1] + h])])
    gap = np.concatenate([np.arange(len(xs)), np.arange(len(xs))])
    return q, np.concatenate([k, k]) + 1000 + first_slit, gap


HOLES = [((-100.0, 5.0), 100.0), ((20.0, -5.0), 50.0), ((100.0, 10.0), 30.0)]


# --------------------------------------------------------------------------- plane basis
def test_plane_basis_and_projection_round_trip():
    origin, e1, e2 = plane_basis(PLANE * 3.0)  # any normal length
    np.testing.assert_allclose(origin @ N + PLANE[3], 0, atol=1e-9)
    np.testing.assert_allclose(
        [e1 @ e1, e2 @ e2, e1 @ e2, e1 @ N, e2 @ N], [1, 1, 0, 0, 0], atol=1e-12
    )
    np.testing.assert_allclose(np.cross(e1, e2), N, atol=1e-12)
    q = np.random.default_rng(0).uniform(-200, 200, (20, 2))
    p = from_plane_coords(q, PLANE)
    np.testing.assert_allclose(p @ N + PLANE[3], 0, atol=1e-9)
    np.testing.assert_allclose(project_to_plane(p, PLANE), q, atol=1e-9)
    # distances in the plane are preserved
    np.testing.assert_allclose(
        np.linalg.norm(p[1:] - p[:-1], axis=1), np.linalg.norm(q[1:] - q[:-1], axis=1)
    )
    # a point off the plane projects orthogonally
    np.testing.assert_allclose(project_to_plane(p[:1] + 7 * N, PLANE), q[:1], atol=1e-9)


def test_plane_basis_normal_along_x():
    origin, e1, e2 = plane_basis([1.0, 0, 0, -5])
    np.testing.assert_allclose(origin, [5, 0, 0])
    assert abs(e1 @ [1, 0, 0]) < 1e-12 and abs(e2 @ [1, 0, 0]) < 1e-12


# --------------------------------------------------------------------------- robust plane
def _plate_cloud(n, outlier_fraction, rng):
    q = rng.uniform(-150, 150, (n, 2))
    p = to3d(q) + rng.normal(0, NOISE, (n, 3))
    m = int(outlier_fraction * n)
    bad = rng.choice(n, m, replace=False)
    # outliers: walls behind the holes, reflections: 1..60 mm off the plane, either side
    off = rng.uniform(1, 60, m) * rng.choice([-1, 1], m)
    p[bad] += off[:, None] * N
    truth = np.ones(n, bool)
    truth[bad] = False
    return p, truth


def _angle_deg(a, b):
    return np.degrees(np.arccos(min(1.0, abs(a[:3] @ b[:3]))))


@pytest.mark.parametrize("threshold", [None, 0.25])
def test_fit_plane_robust_30_percent_outliers(threshold):
    rng = np.random.default_rng(3)
    p, truth = _plate_cloud(3000, 0.30, rng)
    plane, inliers = fit_plane_robust(p, threshold_mm=threshold, rng=np.random.default_rng(1))
    assert _angle_deg(plane, PLANE) < 0.1
    np.testing.assert_allclose(np.linalg.norm(plane[:3]), 1.0)
    # offset: the truth's point O lies on the fitted plane within the noise
    assert abs(plane[:3] @ O + plane[3]) < 0.02
    assert np.all(inliers[truth] | (np.abs(p[truth] @ N + PLANE[3]) > 0.15))
    assert not np.any(inliers[~truth])
    assert inliers.sum() > 0.99 * truth.sum()


def test_fit_plane_robust_default_rng_is_reproducible_and_exact_data():
    rng = np.random.default_rng(4)
    p = to3d(rng.uniform(-50, 50, (100, 2)))
    a, ia = fit_plane_robust(p)
    b, ib = fit_plane_robust(p)
    np.testing.assert_array_equal(a, b)
    assert ia.all()
    assert _angle_deg(a, PLANE) < 1e-6


def test_fit_plane_robust_errors():
    with pytest.raises(MeasurementError, match=">= 3 points"):
        fit_plane_robust(np.zeros((2, 3)))
    with pytest.raises(MeasurementError, match="collinear"):
        fit_plane_robust(np.outer(np.arange(10.0), [1, 2, 3]))
    with pytest.raises(MeasurementError, match="points"):
        fit_plane_robust(np.zeros((5, 2)))
    with pytest.raises(MeasurementError, match="finite"):
        fit_plane_robust([[0, 0, 0], [1, 0, 0], [0, 1, np.nan]])
    with pytest.raises(MeasurementError, match="threshold_mm"):
        fit_plane_robust(np.eye(3), threshold_mm=-1)


# --------------------------------------------------------------------------- circle fit
def test_fit_circle_exact_and_fields():
    t = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    q = np.column_stack([3 + 12 * np.cos(t), -4 + 12 * np.sin(t)])
    for robust in (True, False):
        fit = fit_circle(q, robust=robust)
        assert isinstance(fit, CircleFit)
        np.testing.assert_allclose(fit.centre, [3, -4], atol=1e-9)
        assert fit.radius == pytest.approx(12, abs=1e-9)
        assert fit.diameter == pytest.approx(24, abs=1e-9)
        assert fit.rms < 1e-9 and fit.n_points == fit.n_inliers == 7
        assert fit.arc_deg == pytest.approx(360 - 360 / 7)
        d = fit.to_dict()
        assert d["n_inliers"] == 7 and len(d["centre"]) == 2


def test_fit_circle_three_points():
    fit = fit_circle([[1, 0], [0, 1], [-1, 0]])
    np.testing.assert_allclose(fit.centre, [0, 0], atol=1e-12)
    assert fit.radius == pytest.approx(1)
    assert np.isnan(fit.radius_std)


def test_fit_circle_errors():
    with pytest.raises(MeasurementError, match=">= 3 points, got 2"):
        fit_circle([[0, 0], [1, 1]])
    with pytest.raises(MeasurementError, match="collinear"):
        fit_circle([[0, 0], [1, 1], [2, 2], [3, 3], [4, 4], [5, 5]])
    with pytest.raises(MeasurementError, match="points2d"):
        fit_circle(np.zeros((4, 3)))
    with pytest.raises(MultislitError, match="finite"):
        fit_circle([[0, 0], [1, 1], [np.inf, 2]])


def _hole_points(centre, diameter, spacing, rng, outliers=0.0):
    """Edge points of one hole; ``outliers`` adds that fraction of spurious edge points
    1..8 mm off the circle (they get gap -1 and the slit of a random crossing)."""
    q, slit, gap = crossings(centre, diameter, spacing, rng.uniform(0, spacing))
    p = to3d(q) + rng.normal(0, NOISE, (len(q), 3))
    m = int(np.ceil(outliers * len(q)))
    ang = rng.uniform(0, 2 * np.pi, m)
    rad = diameter / 2 + rng.uniform(1, 8, m) * rng.choice([-1, 1], m)
    qb = np.asarray(centre) + rad[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    p = np.vstack([p, to3d(qb)])
    slit = np.concatenate([slit, rng.choice(slit, m)])
    gap = np.concatenate([gap, np.full(m, -1)])
    bad = np.arange(len(p)) >= len(q)
    return p, slit, gap, bad


# spacing per hole: within the brief's 8..20 mm, dense enough for >= 4 slits on every hole
SPACING = {100.0: 12.0, 50.0: 8.0, 30.0: 8.0}


@pytest.mark.parametrize(("centre", "diameter"), HOLES)
def test_fit_circle_known_holes(centre, diameter):
    rng = np.random.default_rng(int(diameter))
    p, slit, _, _ = _hole_points(centre, diameter, SPACING[diameter], rng)
    fit = fit_circle(project_to_plane(p, PLANE))
    c3 = from_plane_coords(fit.centre, PLANE)[0]
    assert abs(fit.diameter - diameter) < 0.05
    assert np.linalg.norm(c3 - to3d(np.array(centre))[0]) < 0.1
    assert fit.rms < 3 * NOISE


@pytest.mark.parametrize(("centre", "diameter"), HOLES)
def test_diameter_error_statistics(centre, diameter):
    """Over many random slit phases and noise draws: unbiased, RMS error < 0.05 mm."""
    rng = np.random.default_rng(10 + int(diameter))
    err, cerr, std = [], [], []
    for _ in range(60):
        p, *_ = _hole_points(centre, diameter, SPACING[diameter], rng)
        fit = fit_circle(project_to_plane(p, PLANE))
        err.append(fit.diameter - diameter)
        cerr.append(np.linalg.norm(from_plane_coords(fit.centre, PLANE)[0] - to3d(centre)[0]))
        std.append(2 * fit.radius_std)
    err = np.array(err)
    assert np.sqrt(np.mean(err**2)) < 0.05
    assert abs(err.mean()) < 0.015
    assert np.sqrt(np.mean(np.square(cerr))) < 0.1
    # the reported uncertainty is realistic (within a factor 1.5 of the actual scatter)
    assert 1 / 1.5 < np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(np.square(std))) < 1.5


@pytest.mark.parametrize(("centre", "diameter"), HOLES)
def test_fit_circle_robust_to_10_percent_outliers(centre, diameter):
    # the same edge points as test_fit_circle_known_holes, plus 10 % spurious ones
    rng = np.random.default_rng(int(diameter))
    p, _, _, bad = _hole_points(centre, diameter, SPACING[diameter], rng, outliers=0.10)
    assert bad.any()
    q = project_to_plane(p, PLANE)
    fit = fit_circle(q)
    np.testing.assert_array_equal(fit.inliers, ~bad)
    clean = fit_circle(q[~bad], robust=False)
    np.testing.assert_allclose(fit.centre, clean.centre, atol=1e-9)
    assert fit.radius == pytest.approx(clean.radius, abs=1e-9)
    assert abs(fit.diameter - diameter) < 0.05
    assert np.linalg.norm(from_plane_coords(fit.centre, PLANE)[0] - to3d(centre)[0]) < 0.1
    plain = fit_circle(q, robust=False)
    assert abs(plain.diameter - diameter) > 0.1  # the outliers do spoil a plain fit


# --------------------------------------------------------------------------- fit_holes
def _three_holes(rng, spacing=8.0):
    phase = rng.uniform(0, spacing)
    pts, slits, gaps = [], [], []
    for c, d in HOLES:
        q, s, g = crossings(c, d, spacing, phase)
        pts.append(to3d(q) + rng.normal(0, NOISE, (len(q), 3)))
        slits.append(s)
        gaps.append(g + sum(len(x) for x in gaps))
    return np.concatenate(pts), np.concatenate(slits), np.concatenate(gaps)


@pytest.mark.parametrize("with_gap", [True, False])
def test_measure_holes_separates_three_holes(with_gap):
    rng = np.random.default_rng(5)
    p, slit, gap = _three_holes(rng)
    order = rng.permutation(len(p))  # input order must not matter
    p, slit, gap = p[order], slit[order], gap[order]
    holes = fit_holes(p, PLANE, slit=slit, gap=gap if with_gap else None)
    assert len(holes) == 3
    for h, (c, d) in zip(holes, HOLES, strict=True):  # ordered along e1
        assert h.measurable, h.reason
        assert abs(h.diameter - d) < 0.05
        assert np.linalg.norm(h.centre - to3d(c)[0]) < 0.1
        assert h.n_slits == len(np.unique(slit[h.indices]))
        assert h.n_points == h.n_inliers == len(h.indices)
        assert h.rms < 3 * NOISE and h.arc_deg > 180
        d = h.to_dict()
        assert d["measurable"] and d["reason"] == "" and len(d["centre"]) == 3
    assert sorted(np.concatenate([h.indices for h in holes]).tolist()) == list(range(len(p)))


def test_hole_crossed_by_one_slit_is_not_measurable():
    rng = np.random.default_rng(6)
    p, slit, gap = _three_holes(rng)
    # one more small hole, crossed by a single slit only
    q, s, g = crossings((200.0, 0.0), 20.0, 40.0, 3.0, first_slit=99)
    assert len(q) == 2
    p = np.vstack([p, to3d(q)])
    slit = np.concatenate([slit, s])
    holes = fit_holes(p, PLANE, slit=slit)
    assert len(holes) == 4
    last = holes[-1]
    assert not last.measurable and last.n_slits == 1 and "1 slit" in last.reason
    assert np.isnan(last.diameter) and last.n_points == 2
    np.testing.assert_allclose(last.centre, to3d(q).mean(axis=0))
    assert last.to_dict()["diameter"] is None
    # without slit labels the point count says it
    holes = fit_holes(p, PLANE)
    assert not holes[-1].measurable and "2 edge point" in holes[-1].reason
    assert holes[-1].n_slits is None


def test_hole_seen_on_one_side_only_is_not_measurable():
    # three slits, all right of the centre: 6 points covering < 180 deg of the circle
    q, slit, _ = crossings((0.0, 0.0), 30.0, 4.0, 1.0)
    keep = q[:, 0] > 0.5
    q, slit = q[keep], slit[keep]
    assert len(np.unique(slit)) >= 3 and len(q) >= 6
    (hole,) = fit_holes(to3d(q), PLANE, slit=slit, link_distance=40.0)
    assert not hole.measurable and "deg of the circle" in hole.reason
    (hole,) = fit_holes(to3d(q), PLANE, slit=slit, link_distance=40.0, min_arc_deg=90)
    assert hole.measurable and hole.diameter == pytest.approx(30.0, abs=1e-6)


def test_measure_holes_with_outliers():
    rng = np.random.default_rng(7)
    p, slit, gap, bad = _hole_points((0.0, 0.0), 100.0, 10.0, rng, outliers=0.10)
    (hole,) = fit_holes(p, PLANE, slit=slit, gap=gap)
    assert hole.measurable
    assert hole.n_inliers == hole.n_points - bad.sum()
    assert abs(hole.diameter - 100) < 0.05


def test_measure_holes_validation():
    assert fit_holes(np.zeros((0, 3)), PLANE) == []
    with pytest.raises(MeasurementError, match="plane"):
        fit_holes(np.zeros((3, 3)), [0, 0, 0, 1])
    with pytest.raises(MeasurementError, match="slit must have shape"):
        fit_holes(np.zeros((3, 3)), PLANE, slit=[1, 2])
    with pytest.raises(MeasurementError, match="min_points"):
        fit_holes(np.zeros((3, 3)), PLANE, min_points=2)


# --------------------------------------------------------------------------- profiles
STEP = 0.5  # mm between samples along a slit


def _profiles(rng, noise=0.0, centre=(5.0, -3.0), diameter=50.0, spacing=6.0):
    """Vertical slits across a plate with one hole; inside the hole half the slits land on a
    wall 40 mm behind the plate, the others vanish. t = sample number (like image v, px)."""
    r = diameter / 2
    xs = centre[0] - 40 + spacing * np.arange(int(80 / spacing) + 1) + rng.uniform(0, spacing)
    pts, slit, t, truth = [], [], [], []
    for k, x in enumerate(xs):  # building the synthetic scene only
        y0 = rng.uniform(0, STEP)
        y = -90 + y0 + STEP * np.arange(int(180 / STEP))
        inside = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 < r * r
        p = to3d(np.column_stack([np.full_like(y, x), y]))
        p[inside] -= 40 * N
        keep = ~inside if k % 2 else np.ones(len(y), bool)
        pts.append(p[keep] + rng.normal(0, noise, (keep.sum(), 3)))
        slit.append(np.full(keep.sum(), k))
        t.append((y[keep] + 90) / STEP)
        if abs(x - centre[0]) < r:
            h = np.sqrt(r * r - (x - centre[0]) ** 2)
            truth.append([(x, centre[1] - h), (x, centre[1] + h)])
        else:
            truth.append([])
    return np.concatenate(pts), np.concatenate(slit), np.concatenate(t), truth


def _edge_errors(edges, truth):
    err = []
    for i in range(len(edges)):
        true = to3d(np.array(truth[edges.slit[i]][(edges.side[i] + 1) // 2]))[0]
        err.append(np.linalg.norm(edges.points[i] - true))
    return np.array(err)


@pytest.mark.parametrize("offset", [0.0, 0.5])
def test_hole_edges_from_profiles_within_sampling_step(offset):
    rng = np.random.default_rng(8)
    p, slit, t, truth = _profiles(rng)
    order = rng.permutation(len(p))
    edges = hole_edges_from_profiles(p[order], slit[order], t[order], PLANE, edge_offset=offset)
    crossing = [k for k, tr in enumerate(truth) if tr]
    assert len(edges) == 2 * len(crossing)
    assert sorted(set(edges.slit.tolist())) == crossing
    np.testing.assert_array_equal(edges.gap, np.repeat(np.arange(len(crossing)), 2))
    np.testing.assert_array_equal(edges.side, np.tile([-1, 1], len(crossing)))
    np.testing.assert_allclose(edges.points @ N + PLANE[3], 0, atol=1e-9)
    err = _edge_errors(edges, truth)
    # f = 0: the last on-plate sample, less than a step from the edge; f = 0.5: half a step
    assert err.max() <= (STEP if offset == 0 else STEP / 2) + 1e-9
    # the source rows are the last on-plate samples
    np.testing.assert_allclose(np.abs(p[order][edges.source] @ N + PLANE[3]), 0, atol=1e-9)


def test_hole_edges_exact_fractions_hook():
    rng = np.random.default_rng(9)
    p, slit, t, truth = _profiles(rng)
    # the exact sub-sample position, as an intensity-based locator would give it
    xq, yq = (p - O) @ E1, (p - O) @ E2  # plate coordinates
    h = np.sqrt(np.clip(25.0**2 - (xq - 5.0) ** 2, 0, None))
    edge_y = np.where(yq < -3.0, -3.0 - h, -3.0 + h)
    frac = np.clip(np.abs(edge_y - yq) / STEP, 0, 1)
    edges = hole_edges_from_profiles(p, slit, t, PLANE, edge_offset=frac)
    assert _edge_errors(edges, truth).max() < 1e-6
    calls = []

    def hook(source, side):
        calls.append((source, side))
        return frac[source]

    edges2 = hole_edges_from_profiles(p, slit, t, PLANE, edge_offset=hook)
    np.testing.assert_allclose(edges2.points, edges.points)
    assert len(calls) == 1 and set(calls[0][1].tolist()) == {-1, 1}


def test_hole_edges_noisy_then_measured():
    """The whole chain: noisy profiles -> edges -> fit_holes on the gap-labelled edges."""
    rng = np.random.default_rng(11)
    p, slit, t, truth = _profiles(rng, noise=NOISE)
    edges = hole_edges_from_profiles(p, slit, t, PLANE)
    assert len(edges) == 2 * sum(1 for tr in truth if tr)
    assert _edge_errors(edges, truth).max() < STEP / 2 + 4 * NOISE
    (hole,) = fit_holes(edges.points, PLANE, slit=edges.slit, gap=edges.gap)
    assert hole.measurable
    assert abs(hole.diameter - 50.0) < 0.15
    # the last on-plate samples (f = 0) lie outside the hole: the diameter comes out too large
    e0 = hole_edges_from_profiles(p, slit, t, PLANE, edge_offset=0.0)
    (h0,) = fit_holes(e0.points, PLANE, slit=e0.slit, gap=e0.gap)
    assert h0.diameter > hole.diameter + 0.2 * STEP


def test_hole_edges_no_gap_and_validation():
    y = np.arange(0, 50, STEP)
    p = to3d(np.column_stack([np.zeros_like(y), y]))
    e = hole_edges_from_profiles(p, np.zeros(len(y), int), y / STEP, PLANE)
    assert len(e) == 0 and e.points.shape == (0, 3)
    # a single missing sample is a gap by default; min_gap can ignore it
    drop = np.ones(len(y), bool)
    drop[40] = False
    e = hole_edges_from_profiles(p[drop], np.zeros(drop.sum(), int), y[drop] / STEP, PLANE)
    assert len(e) == 2
    e = hole_edges_from_profiles(
        p[drop], np.zeros(drop.sum(), int), y[drop] / STEP, PLANE, min_gap=2.5
    )
    assert len(e) == 0
    with pytest.raises(MeasurementError, match="t must"):
        hole_edges_from_profiles(p, np.zeros(len(y), int), y[:-1], PLANE)
    with pytest.raises(MeasurementError, match="slit must hold integer"):
        hole_edges_from_profiles(p, np.full(len(y), 0.5), y, PLANE)
    with pytest.raises(MeasurementError, match="edge_offset"):
        hole_edges_from_profiles(p[drop], np.zeros(drop.sum(), int), y[drop], PLANE, edge_offset=2)
