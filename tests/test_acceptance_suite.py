"""A small version of the accuracy suite (benchmarks/bench_accuracy.py) for CI.

Half-size rig (``RigSpec().scaled(0.5)``, 640x512), one calibration (hand readings) and one
reference set, three scans: a sphere (r = 60 mm at 900 mm), a ball bar (2 x r = 60 mm, 300 mm,
at 45 deg), a 360 x 260 mm plate tilted 25 deg. Bounds are loose (several times the measured
values, seed 0) but fail on a broken calibration, frame or identification.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from multislit.sim.rig import RigSpec

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_accuracy.py"


def _bench():
    if str(BENCH.parent) not in sys.path:
        sys.path.insert(0, str(BENCH.parent))  # the benchmark imports its sibling results.py
    spec = importlib.util.spec_from_file_location("bench_accuracy", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_accuracy", mod)  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def suite(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    b = _bench()
    # the suite's sphere at half size is crossed by too few identified slits for a sphere
    # fit (see benchmarks/RESULTS.md); the CI sphere is r = 80 mm (0.19 of the diagonal)
    scenes = [
        b.sphere_scene("sphere_900", (0.0, 0.0, 100.0), 80.0),
        b.bar_scene("bar_45deg", (1.0, 1.0, 0.0), radius=60.0),
        b.default_artefacts(full=False)[2],
    ]
    rig = b.prepare_rig(RigSpec().scaled(0.5), scenes, tmp_path_factory.mktemp("acc") / "c", 0)
    rows = {}
    for sc in scenes:
        for r in b.evaluate(b.scan(rig, sc.name), rig.scenes[sc.name]):
            rows[r["quantity"]] = r
    return rows


@pytest.mark.slow
def test_three_artefacts_measured(suite: dict[str, dict]) -> None:
    assert set(suite) == {"PS", "PF", "SD", "F"}


@pytest.mark.slow
def test_sphere_probing_errors(suite: dict[str, dict]) -> None:
    ps, pf = suite["PS"], suite["PF"]
    print(ps, pf)
    # measured (seed 0): 267 points, PS = 7.23 mm, PF = 5.46 mm (full size, r = 60: PS 0.7-3.8,
    # PF 2.8-3.6, see benchmarks/RESULTS.md); the fit from 3 identified slits is ill-conditioned
    assert ps["points"] >= 100
    assert np.isfinite(ps["value"]) and abs(ps["value"]) < 12.0
    assert 0.0 < pf["value"] < 12.0


@pytest.mark.slow
def test_ball_bar_spacing(suite: dict[str, dict]) -> None:
    sd = suite["SD"]
    print(sd)
    # measured (seed 0): 475 points, SD = +0.51 mm (full size, r = 40: -5.4..+0.4 mm)
    assert sd["points"] >= 80
    assert np.isfinite(sd["value"]) and abs(sd["value"]) < 8.0


@pytest.mark.slow
def test_plate_flatness(suite: dict[str, dict]) -> None:
    f = suite["F"]
    print(f)
    # measured (seed 0): 4885 points, F = 5.71 mm, 2.38 mm with 0.3 % left out, RMS 0.20 mm
    assert f["points"] >= 2000
    assert 0.0 < f["value"] < 12.0
    assert f["value_excl"] < 6.0
    assert f["value_excl"] <= f["value"]
