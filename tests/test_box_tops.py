"""Box tops: stripes leaning 72-80 degrees from the vertical, found, identified and measured
on a calibrated half-size capture (the scene ``box_tops``)."""

from __future__ import annotations

import numpy as np
import pytest

from multislit.calibrate import calibrate_capture
from multislit.identify import identify
from multislit.io import Capture
from multislit.reconstruct import rig_of, scan_image
from multislit.sim import object_metrics, simulate_capture
from multislit.sim.evaluate import _centres_in, _near_centres
from multislit.sim.scene import make_scene

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def box_tops(tmp_path_factory, small_spec):
    """The capture, its calibration, the identification of the scan, its truth and the tops'
    pixels."""
    out = simulate_capture(
        tmp_path_factory.mktemp("box_tops") / "cap", ["box_tops"], small_spec, seed=5
    )
    cap = Capture.open(out)
    res = calibrate_capture(cap)
    img = cap.image(cap.scans[0])
    ident = identify(img, res.reference, rig_of(res.calibration))
    truth = np.load(out / "truth" / "box_tops.npz")
    scene = make_scene("box_tops")
    names = [p.name for p in scene.primitives]
    xyz = truth["xyz"].reshape(-1, 3)
    tops = {}
    for t in scene.info["tops"]:
        i = names.index(t["name"])
        on = np.isfinite(xyz[:, 0]) & (truth["obj"].reshape(-1) == i)
        n = np.zeros_like(xyz)
        n[on] = scene.primitives[i].normal(xyz[on].astype(float))
        tops[t["name"]] = ((n @ np.asarray(t["normal"])) > 0.9).reshape(truth["slit"].shape)
    return img, res, ident, truth, scene, tops


def test_the_stripes_on_the_tops_are_found(box_tops):
    _, _, ident, truth, _, tops = box_tops
    ex = ident.extraction
    top = tops["box_flat"] | tops["box_turned"]
    h, w = top.shape
    lk = ex.segment >= 0
    near = _near_centres(ex.u[lk], ex.v[lk], _centres_in(truth["slit"], top), h, w)
    assert np.mean([len(i) > 0 for i in near]) >= 0.85


def test_what_is_labelled_on_the_tops_is_right_and_the_rest_stays(box_tops):
    _, _, ident, truth, _, tops = box_tops
    top = tops["box_flat"] | tops["box_turned"]
    m = object_metrics(ident, truth["slit"], top)
    on, off = m["object"], m["backdrop"]
    # what the dots label on the tops: a part of them (measured 74.9 % of the tops' stripe
    # pixels, 0.28 % of the points there wrong; the goals are in the strict xfail below)
    assert on["coverage"] >= 0.65, on
    assert on["wrong"] <= 0.01, on
    # the rest of the scene (the boxes' fronts, the wall) as without the tops
    assert off["coverage"] >= 0.95 and off["wrong"] <= 0.001, off


@pytest.mark.xfail(
    strict=True,
    reason="goal not met: the stripes on the tops are found (94 % of their true centres) but "
    "the dots' geometry labels 74.9 % of their stripe pixels (78 % of the flat box's top, 71 % "
    "of the turned box's), 0.28 % of its points there wrong: the projector meets the tops at a "
    "grazing angle, where a window's own dots say little for its slit",
)
def test_the_tops_are_measured_with_the_right_slit(box_tops):
    _, _, ident, truth, _, tops = box_tops
    m = object_metrics(ident, truth["slit"], tops["box_flat"] | tops["box_turned"])
    assert m["object"]["coverage"] >= 0.90, m["object"]
    assert m["object"]["wrong"] <= 0.002, m["object"]


def test_the_tops_points_lie_on_the_tops(box_tops):
    img, res, ident, _, scene, _ = box_tops
    scan = scan_image(img, res.reference, res.calibration)
    col = scan.identification.extraction.by_column[scan.index]
    # the points found along the columns keep their first centre
    assert col.sum() >= 300
    assert np.array_equal(scan.u[col], scan.identification.u[scan.index][col])
    names = [p.name for p in scene.primitives]
    measured = 0
    for t in scene.info["tops"]:
        box = scene.primitives[names.index(t["name"])]
        local = (scan.points - box.c) @ box.A.T
        d = local[:, 1] - box.h[1]  # mm above the top's plane
        on = (np.abs(local[:, 0]) < box.h[0]) & (np.abs(local[:, 2]) < box.h[2])
        on &= (np.abs(d) < 5.0) & col
        if on.any():  # the top turned away gets few labels (the strict xfail above)
            assert np.sqrt(np.mean(d[on] ** 2)) <= 0.2, t["name"]
            assert np.percentile(np.abs(d[on]), 95) <= 0.3, t["name"]
        measured += on.sum()
    assert measured >= 100
