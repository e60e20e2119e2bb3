"""Shared fixtures: small simulated scenes, built once per test session."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from multislit.sim import RigSpec, SimulatedRig


@pytest.fixture(scope="session")
def small_spec() -> RigSpec:
    """The default rig at half resolution (640x512): stripes and dots keep their pixel widths."""
    return RigSpec().scaled(0.5)


@pytest.fixture(scope="session")
def clean_spec(small_spec: RigSpec) -> RigSpec:
    """Half-size rig without noise or speckle and with a 16-bit sensor: for geometry checks."""
    return replace(
        small_spec,
        sensor=replace(small_spec.sensor, noise=False, speckle_contrast=0.0, bit_depth=16),
    )


@pytest.fixture(scope="session")
def small_rig(small_spec: RigSpec) -> SimulatedRig:
    return SimulatedRig.build(small_spec)


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory: pytest.TempPathFactory, small_spec: RigSpec) -> Path:
    """A complete half-size simulated capture: holes plate and steps, seed 3."""
    from multislit.sim import simulate_capture

    out = tmp_path_factory.mktemp("capture") / "cap"
    return simulate_capture(out, ["holes", "steps"], small_spec, seed=3)


@pytest.fixture(scope="session")
def calibrated(small_capture: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the small capture (holes, steps) with its calibration (hand readings); tests
    write their outputs elsewhere."""
    import shutil

    from multislit.calibrate import calibrate_capture, write_calibration

    cap = tmp_path_factory.mktemp("calibrated") / "cap"
    shutil.copytree(small_capture, cap)
    write_calibration(calibrate_capture(cap, source="hand"), cap / "calibration.json")
    return cap


@pytest.fixture(scope="session")
def small_calibrated(small_capture: Path):
    """``calibrate_capture(small_capture)``: camera, slit planes and dot projector (a few s)."""
    from multislit.calibrate import calibrate_capture

    return calibrate_capture(small_capture)


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def scenes_capture(tmp_path_factory: pytest.TempPathFactory, small_spec: RigSpec) -> Path:
    """Half-size capture with the identification scenes (25 slits), seed 11."""
    from multislit.sim import simulate_capture

    out = tmp_path_factory.mktemp("scenes") / "cap"
    return simulate_capture(
        out, ["holes", "spheres", "steps", "freeform", "textured"], small_spec, seed=11
    )


def _reference(capture: Path):
    from multislit.identify import prepare_reference
    from multislit.io import Capture

    cap = Capture.open(capture)
    return prepare_reference(
        [cap.image(p) for p in cap.references], cap.num_slits, [p.stem for p in cap.references]
    )


@pytest.fixture(scope="session")
def scenes_reference(scenes_capture: Path):
    return _reference(scenes_capture)


@pytest.fixture(scope="session")
def dense_scenes_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Full-size capture with the identification scenes on the 49-slit rig, seed 11.

    Full size, not half: at half size the stripes keep their width but lie half as far apart
    (as dense as 98 slits). About a minute to build: for slow tests only.
    """
    from multislit.sim import dense_rig, simulate_capture

    out = tmp_path_factory.mktemp("dense_scenes") / "cap"
    return simulate_capture(
        out, ["holes", "spheres", "steps", "freeform", "textured"], dense_rig(), seed=11
    )


@pytest.fixture(scope="session")
def dense_scenes_reference(dense_scenes_capture: Path):
    return _reference(dense_scenes_capture)


@pytest.fixture(scope="session")
def zoo_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A zoo rig and scene (seed 1, a tuning seed) at 640x480, 29 slits: spheres, a rod and boxes
    in front of a wall. About 12 s to simulate."""
    from multislit.sim import simulate_zoo_capture

    out = tmp_path_factory.mktemp("zoo") / "cap"
    return simulate_zoo_capture(out, 1, scenes=1, max_size=(640, 512))
