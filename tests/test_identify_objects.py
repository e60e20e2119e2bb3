"""Identification on the objects apart from the wall behind them (a zoo rig and scene)."""

from __future__ import annotations

import numpy as np
import pytest

from multislit.calibrate import calibrate_capture
from multislit.identify import IdentifyOptions, identify
from multislit.io import Capture
from multislit.reconstruct import rig_of
from multislit.sim import object_metrics

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", params=["geometry", "template"])
def metrics(zoo_capture, request):
    cap = Capture.open(zoo_capture)
    res = calibrate_capture(cap)
    truth = np.load(zoo_capture / "truth" / "zoo0.npz")
    options = IdentifyOptions(method=request.param)
    ident = identify(
        cap.image(cap.scans[0]), res.reference, rig_of(res.calibration), options=options
    )
    return request.param, object_metrics(ident, truth["slit"], truth["object"])


def test_the_scene_has_objects_and_a_backdrop(metrics):
    _, m = metrics
    assert m["object"]["centres"] > 1000
    assert m["backdrop"]["centres"] > 1000


#: The backdrop's bars per method (coverage at least, wrong with confidence >= 0.5 at most).
#: Measured on this scene: the template matching covers 89.4 % with 0.14 % confidently wrong;
#: the dots' geometry 98.4 % with 0.02 %.
BACKDROP_BARS = {"geometry": (0.90, 0.001), "template": (0.85, 0.005)}


def test_the_backdrop_is_covered_and_right(metrics):
    method, m = metrics
    b = m["backdrop"]
    coverage, wrong = BACKDROP_BARS[method]
    assert b["coverage"] >= coverage, b
    assert b["wrong_confident"] <= wrong, b


def test_the_dots_geometry_measures_most_of_the_objects(metrics):
    """Measured on this scene: the objects' stripe pixels 73.9 % covered by the dots' geometry,
    0.31 % of their points wrong (all with confidence >= 0.99); the bars leave room for the
    run-to-run spread. The template matching: 54.3 % covered, 1.70 % wrong (0.42 % with
    confidence >= 0.5)."""
    method, m = metrics
    o = m["object"]
    if method == "geometry":
        assert o["coverage"] >= 0.68, o
        assert o["wrong"] <= 0.01, o
    else:
        assert o["coverage"] >= 0.45, o
        assert o["wrong_confident"] <= 0.005, o


@pytest.mark.xfail(
    strict=True,
    reason="goal not met: on this rig the objects' stripe pixels are 73.9 % covered and 0.31 % "
    "of their points wrong by the dots' geometry (54.3 % and 1.70 %, 0.42 % with confidence "
    ">= 0.5, by templates)",
)
def test_the_objects_meet_the_goals(metrics):
    o = metrics[1]["object"]
    assert o["coverage"] >= 0.90, o
    assert o["wrong_confident"] <= 0.001, o
    assert o["wrong"] <= 0.002, o
