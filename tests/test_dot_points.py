"""The dots identified by the dots' geometry, measured as 3D points, against the truth."""

from __future__ import annotations

import numpy as np
import pytest

import multislit as ms
from multislit.errors import MultislitError
from multislit.reconstruct import RefineOptions, ScanOptions


@pytest.fixture(scope="module")
def scan(small_calibrated, small_capture):
    cap = ms.Capture.open(small_capture)
    img = cap.image(small_capture / "scans" / "steps.png")
    options = ScanOptions(refinement=RefineOptions(dot_points=True))
    return ms.scan_image(img, small_calibrated.reference, small_calibrated.calibration, options)


def _truth_errors(small_capture, points, u, v):
    truth = np.load(small_capture / "truth" / "steps.npz")
    h, w = truth["slit"].shape
    r = np.clip(np.rint(v).astype(int), 0, h - 1)
    c = np.clip(np.rint(u).astype(int), 0, w - 1)
    err = np.linalg.norm(points - truth["xyz"][r, c].astype(float), axis=1)
    return err[np.isfinite(err)]


def test_dots_are_measured_about_as_well_as_the_stripes(scan, small_capture):
    """The dot points lie on the surface about as close as the stripe points (both against the
    truth at the nearest pixel, which a tilted surface makes a few tenths of a mm off: at half
    size 0.67 mm median for the dots, 0.48 mm for the stripes), and hardly any is a wrong
    pairing of a dot and a ray (a wrong pairing lands tens of mm off: 0.23 % of the dots are
    more than 20 mm off, 0.28 % of the stripe points; 1.05 % of the dots are more than 5 mm
    off, where a dot by an edge takes the other surface's true point at its pixel)."""
    dots = scan.dots
    assert dots is not None and len(dots) > 0.05 * scan.num_points, (len(dots), scan.num_points)
    d = _truth_errors(small_capture, dots.points, dots.u, dots.v)
    s = _truth_errors(small_capture, scan.points, scan.u, scan.v)
    assert np.median(d) < 1.0 and np.median(d) < 1.6 * np.median(s), (np.median(d), np.median(s))
    assert np.mean(d > 20.0) < 0.005 and np.mean(d > 5.0) < 0.02, (
        np.mean(d > 20.0),
        np.mean(d > 5.0),
    )


def test_the_ply_marks_the_dot_points(scan, tmp_path):
    path = scan.write_ply(tmp_path / "steps.ply")
    d = ms.read_ply(path)
    assert d["dot"].dtype == np.uint8
    assert int(d["dot"].sum()) == len(scan.dots) and len(d["x"]) == scan.num_points + len(scan.dots)
    assert not d["dot"][: scan.num_points].any()
    assert "dot points" in scan.summary() and scan.to_dict()["dot_points"] == len(scan.dots)


def test_without_the_option_there_are_no_dot_points(small_calibrated, small_capture):
    cap = ms.Capture.open(small_capture)
    img = cap.image(small_capture / "scans" / "steps.png")
    res = ms.scan_image(img, small_calibrated.reference, small_calibrated.calibration)
    assert res.dots is None and "dot points" not in res.summary()


@pytest.mark.parametrize("bad", [np.array([0, 2, 1]), np.array([0.5, 1, 0])])
def test_a_dot_column_must_be_true_or_false(tmp_path, bad):
    with pytest.raises(MultislitError, match="dot must hold"):
        ms.write_ply(tmp_path / "x.ply", np.zeros((3, 3)), dot=bad)


def test_dot_points_option_is_validated():
    with pytest.raises(MultislitError, match="refinement.dot_points"):
        RefineOptions(dot_points="yes")
