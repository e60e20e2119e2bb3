import hashlib
import json

import numpy as np
import pytest

from multislit.errors import MultislitError
from multislit.sim.rig import RigSpec
from multislit.sim.simulate import simulate_capture


def test_truth_is_saved_and_consistent(small_capture):
    models = json.loads((small_capture / "truth" / "models.json").read_text())
    planes = np.array(models["projector"]["planes"])
    assert planes.shape == (25, 4)
    t = np.load(small_capture / "truth" / "holes.npz")
    xyz, slit = t["xyz"], t["slit"]
    assert xyz.shape == (512, 640, 3) and slit.shape == (512, 640)
    # a pixel labelled slit k sees a point within 2 sigma (the stripe's core) of slit k's plane
    v, u = np.nonzero(slit >= 0)
    p = xyz[v, u].astype(float)
    d = np.abs(np.einsum("ij,ij->i", p, planes[slit[v, u], :3]) + planes[slit[v, u], 3])
    r = np.linalg.norm(p - np.array(models["projector"]["origin"]), axis=1)
    assert np.all(d <= 2 * models["projector"]["sigma"] * r * 1.01 + 0.01)
    # the seen points of the plate lie on the plate
    plane = np.array(models["scenes"]["holes"]["plane"])
    on = np.abs(xyz.reshape(-1, 3) @ plane[:3] + plane[3]) < 0.01
    assert on.sum() > 100000


def test_hand_readings_lie_on_their_slit_planes(small_capture):
    target = json.loads((small_capture / "target.json").read_text())
    models = json.loads((small_capture / "truth" / "models.json").read_text())
    planes = np.array(models["projector"]["planes"])
    sp = target["slit_points"]
    assert len(sp) >= 12
    k = np.array([s["slit"] for s in sp])
    xyz = np.array([s["xyz"] for s in sp])
    assert np.abs(np.einsum("ij,ij->i", xyz, planes[k, :3]) + planes[k, 3]).max() < 0.01


def _digest(folder):
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*.png")):
        h.update(p.read_bytes())
    return h.hexdigest()


@pytest.mark.slow
def test_same_seed_same_capture(tmp_path):
    spec = RigSpec().scaled(0.25)
    a = simulate_capture(tmp_path / "a", ["plane"], spec, seed=5)
    b = simulate_capture(tmp_path / "b", ["plane"], spec, seed=5)
    c = simulate_capture(tmp_path / "c", ["plane"], spec, seed=6)
    assert _digest(a) == _digest(b) != _digest(c)


def test_refuses_non_empty_folder_and_unknown_scene(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(MultislitError, match="not empty"):
        simulate_capture(tmp_path / "x", ["plane"], RigSpec().scaled(0.25))
    with pytest.raises(MultislitError, match="unknown scene 'moon'"):
        simulate_capture(tmp_path / "y", ["moon"], RigSpec().scaled(0.25))
