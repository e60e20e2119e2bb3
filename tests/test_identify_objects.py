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
    return object_metrics(ident, truth["slit"], truth["object"])


def test_the_scene_has_objects_and_a_backdrop(metrics):
    assert metrics["object"]["centres"] > 1000
    assert metrics["backdrop"]["centres"] > 1000


def test_the_backdrop_is_covered_and_right(metrics):
    b = metrics["backdrop"]
    assert b["coverage"] >= 0.90, b
    assert b["wrong_confident"] <= 0.001, b


@pytest.mark.xfail(
    strict=True,
    reason="goal not met: on this rig the objects' stripe pixels are about 68 % covered and "
    "2.5 % of their points wrong by the dots' geometry (63 % and 1.25 %, 0.17 % with "
    "confidence >= 0.5, by templates)",
)
def test_the_objects_meet_the_goals(metrics):
    o = metrics["object"]
    assert o["coverage"] >= 0.90, o
    assert o["wrong_confident"] <= 0.001, o
    assert o["wrong"] <= 0.002, o
