"""Shared fixtures: small simulated scenes, built once per test session."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from multislit.sim.rig import RigSpec, SimulatedRig

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


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
    from multislit.sim.simulate import simulate_capture

    out = tmp_path_factory.mktemp("capture") / "cap"
    return simulate_capture(out, ["holes", "steps"], small_spec, seed=3)


@pytest.fixture()
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def identification_metrics(ident, truth_slit) -> dict:
    """Score an identification against the simulator's per-pixel truth.

    correct : share of output points whose slit is the true one at their pixel (or a neighbour
        in the row: a centre can round onto the stripe's edge pixel)
    wrong_confident : share of output points that are wrong and have confidence >= 0.5
    coverage : share of true stripe-centre pixels (the middle of each lit run of one slit in a
        row) that have an output point of that slit within 1.5 px in the same row
    """
    h, w = truth_slit.shape
    ok = ident.identified
    u, v, k = ident.u[ok], ident.v[ok], ident.slit[ok]
    r = np.clip(np.round(v).astype(int), 0, h - 1)
    cand = np.stack(
        [truth_slit[r, np.clip(np.round(u).astype(int) + d, 0, w - 1)] for d in (0, -1, 1)], 1
    )
    correct = (cand == k[:, None]).any(1)
    wrong = ~correct & (cand >= 0).any(1)
    hi = ident.confidence[ok] >= 0.5
    # true stripe-centre pixels: middle of each run of one slit label along a row
    pad = np.full((h, 1), -1, truth_slit.dtype)
    t = np.hstack([pad, truth_slit, pad])
    change = np.diff(t, axis=1) != 0
    rows, cols = np.nonzero(change)
    centres = []
    for row in np.unique(rows):
        b = cols[rows == row]
        for a, e in zip(b[:-1], b[1:], strict=True):
            lab = truth_slit[row, a]
            if lab >= 0 and e - a >= 2:
                centres.append((row, (a + e - 1) / 2, lab))
    got = 0
    pts: dict = {}
    for uu, vv, kk in zip(u, np.round(v).astype(int), k, strict=True):
        pts.setdefault((vv, kk), []).append(uu)
    for row, c, lab in centres:
        us = pts.get((row, lab))
        got += bool(us) and min(abs(x - c) for x in us) <= 1.5
    n = max(int(ok.sum()), 1)
    return {
        "points": int(ok.sum()),
        "correct": float(correct.sum() / n),
        "wrong_confident": float((wrong & hi).sum() / n),
        "coverage": got / max(len(centres), 1),
    }


@pytest.fixture(scope="session")
def scenes_capture(tmp_path_factory: pytest.TempPathFactory, small_spec: RigSpec) -> Path:
    """Half-size capture with the identification scenes (25 slits), seed 11."""
    from multislit.sim.simulate import simulate_capture

    out = tmp_path_factory.mktemp("scenes") / "cap"
    return simulate_capture(
        out, ["holes", "spheres", "steps", "freeform", "textured"], small_spec, seed=11
    )


@pytest.fixture(scope="session")
def scenes_reference(scenes_capture: Path):
    from multislit.capture import Capture
    from multislit.reference import prepare_reference

    cap = Capture.open(scenes_capture)
    return prepare_reference(
        [cap.image(p) for p in cap.references], cap.num_slits, [p.stem for p in cap.references]
    )
