"""VDI/VDE 2634-2 metrics on synthetic points with known spheres and planes."""

import numpy as np
import pytest

from multislit.errors import MeasurementError, MultislitError
from multislit.geometry import fit_sphere
from multislit.measure import (
    AcceptanceRow,
    acceptance_table,
    flatness_error,
    markdown_table,
    probing_error_form,
    probing_error_size,
    sphere_spacing_error,
)


def sphere_points(rng, centre, radius, n, radial=None, cap_deg=180.0):
    """Points on a cap (half angle ``cap_deg`` about +z) of a sphere, radial offsets added."""
    cz = rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cz**2)
    u = np.stack([s * np.cos(phi), s * np.sin(phi), cz], axis=1)
    r = radius + (np.zeros(n) if radial is None else radial)
    return np.asarray(centre) + r[:, None] * u


def test_fit_sphere_exact_on_a_cap(rng):
    p = sphere_points(rng, (10.0, -20.0, 850.0), 25.0, 200, cap_deg=70)
    f = fit_sphere(p)
    np.testing.assert_allclose(f.centre, (10.0, -20.0, 850.0), atol=1e-8)
    assert f.radius == pytest.approx(25.0, abs=1e-9)
    assert f.diameter == pytest.approx(50.0, abs=1e-9)
    assert f.rms < 1e-9 and f.residuals.shape == (200,)


def test_fit_sphere_four_points():
    c, r = np.array([1.0, 2.0, 3.0]), 5.0
    u = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, -1, -1]], float)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    f = fit_sphere(c + r * u)
    np.testing.assert_allclose(f.centre, c, atol=1e-8)
    assert f.radius == pytest.approx(r, abs=1e-8)


def test_probing_errors_with_noise(rng):
    sigma = 0.05
    radial = rng.normal(0, sigma, 5000)
    p = sphere_points(rng, (0.0, 0.0, 900.0), 30.0, 5000, radial=radial, cap_deg=80)
    f = fit_sphere(p)
    assert f.rms == pytest.approx(sigma, rel=0.05)
    pf = probing_error_form(p)
    # PF is the range of the fitted residuals: close to the range of the added offsets
    assert pf == pytest.approx(np.ptp(radial), rel=0.05)
    assert pf == pytest.approx(np.ptp(f.residuals), rel=1e-12)
    assert abs(probing_error_size(p, 60.0)) < 0.01
    assert probing_error_size(p, 59.0) == pytest.approx(1.0, abs=0.01)


def test_probing_form_exclude_drops_the_worst_points(rng):
    p = sphere_points(rng, (0.0, 0.0, 0.0), 20.0, 1000, radial=rng.normal(0, 0.01, 1000))
    p[0] *= 1.05  # one point 1 mm out
    assert probing_error_form(p) > 0.9
    assert probing_error_form(p, exclude=0.003) < 0.1
    with pytest.raises(MeasurementError, match="exclude"):
        probing_error_form(p, exclude=0.7)


def test_sphere_spacing_error_exact(rng):
    a = np.array([-100.0, 10.0, 900.0])
    b = a + np.array([250.0, 80.0, -30.0])
    L = float(np.linalg.norm(b - a))
    pa = sphere_points(rng, a, 25.0, 300, cap_deg=75)
    pb = sphere_points(rng, b, 25.0, 300, cap_deg=75)
    assert sphere_spacing_error(pa, pb, L) == pytest.approx(0.0, abs=1e-8)
    assert sphere_spacing_error(pa, pb, L - 0.2) == pytest.approx(0.2, abs=1e-8)


def test_flatness(rng):
    n = np.array([0.2, -0.1, 1.0])
    n /= np.linalg.norm(n)
    e1 = np.cross(n, [0, 1, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    ab = rng.uniform(-200, 200, (4000, 2))
    h = rng.uniform(-0.1, 0.1, 4000)
    p = np.array([0, 0, 900.0]) + ab[:, :1] * e1 + ab[:, 1:] * e2 + h[:, None] * n
    assert flatness_error(p) == pytest.approx(0.2, abs=0.01)
    exact = np.array([0, 0, 900.0]) + ab[:, :1] * e1 + ab[:, 1:] * e2
    assert flatness_error(exact) < 1e-9


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((3, 3)) + np.eye(3), "need >= 4"),
        (np.c_[np.random.default_rng(0).normal(size=(50, 2)), np.zeros(50)], "coplanar"),
        (np.full((10, 3), np.nan), "finite"),
        (np.zeros((10, 2)), "shape"),
    ],
)
def test_fit_sphere_refuses_bad_points(points, match):
    with pytest.raises(MeasurementError, match=match):
        fit_sphere(points)


def test_bad_arguments():
    p = sphere_points(np.random.default_rng(1), (0, 0, 0), 10.0, 50)
    with pytest.raises(MeasurementError, match="true_diameter"):
        probing_error_size(p, 0.0)
    with pytest.raises(MeasurementError, match="true_distance"):
        sphere_spacing_error(p, p + 100, -1.0)
    with pytest.raises(MeasurementError, match="collinear"):
        flatness_error(np.outer(np.arange(10.0), [1, 2, 3]))
    with pytest.raises(MeasurementError, match="need >= 3"):
        flatness_error(np.eye(3)[:2])


def test_tables():
    rows = [
        AcceptanceRow("sphere r=30", "PF", 0.1234, 5000, 0.2),
        AcceptanceRow("sphere r=30", "PS", -0.3, 5000, 0.2),
        AcceptanceRow("plane", "F", float("nan"), 0),
    ]
    assert [r.passed for r in rows] == [True, False, None]
    t = acceptance_table(rows)
    lines = t.strip().splitlines()
    assert len(lines) == 5 and lines[0].startswith("| measured")
    assert "| sphere r=30 | PF | 0.123 | 5000 | 0.200 | yes |" in lines
    assert "| plane | F | nan | 0 | - | - |" in lines
    assert markdown_table(["a|b"], [["x|y"]]).splitlines()[2] == "| x\\|y |"
    with pytest.raises(MultislitError, match="row 0"):
        markdown_table(["a", "b"], [[1]])
