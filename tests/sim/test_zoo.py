"""The zoo of random rigs and scenes, the object/backdrop truth, and the object metrics."""

from types import SimpleNamespace

import numpy as np
import pytest

from multislit.errors import MultislitError
from multislit.sim import (
    RigSpec,
    SimulatedRig,
    object_metrics,
    random_rig,
    random_scene,
    render,
)
from multislit.sim.render import camera_rays
from multislit.sim.scene import spheres
from multislit.sim.zoo import NEAR_FRACTION, RIG_Z, zoo_target


@pytest.mark.parametrize("seed", range(12))
def test_zoo_rig_is_reproducible_and_in_range(seed):
    spec = random_rig(np.random.default_rng(seed))
    assert spec == random_rig(np.random.default_rng(seed))
    cam, slits, dots = spec.camera, spec.slits, spec.dots
    w, h = cam.image_size
    assert 0.28e6 <= w * h <= 5.2e6
    assert abs(cam.dist[0]) <= 0.15
    baseline = slits.position[0] - cam.position[0]
    assert 200 <= baseline <= 500
    standoff = cam.position[2] - cam.look_at[2]
    assert 500 <= standoff <= 1500
    assert 15 <= slits.num_slits <= 61
    assert dots.pattern in ("bands", "uniform")
    assert abs(dots.offset[0]) <= 10 and 20 <= abs(dots.offset[1]) <= 80
    assert min(spec.reference_distances) < standoff < max(spec.reference_distances)
    spec.validate()
    assert RigSpec.from_json(spec.to_json()) == spec
    t = zoo_target(spec)
    assert t.corner_z < RIG_Z - standoff < t.corner_z + t.depth


def test_zoo_rigs_differ_between_seeds():
    specs = [random_rig(np.random.default_rng(s)) for s in range(6)]
    assert len({s.camera.image_size for s in specs}) > 3
    assert {s.dots.pattern for s in specs} == {"bands", "uniform"}


@pytest.mark.parametrize("seed", [0, 3, 7])
def test_zoo_scene_is_reproducible_in_view_and_volume(seed):
    spec = random_rig(np.random.default_rng(seed))
    a = random_scene(np.random.default_rng(100 + seed), spec, objects=5)
    b = random_scene(np.random.default_rng(100 + seed), spec, objects=5)
    assert a.names == b.names and a.info == b.info
    assert a.backdrop == ("wall",) and a.names[-1] == "wall"
    small = spec.scaled(160 / spec.camera.image_size[0])
    rig = SimulatedRig.build(small)
    o, d = camera_rays(rig)
    hit = a.cast(o, d)
    obj = a.is_object(hit.obj)
    assert obj.mean() > 0.02  # objects are in view
    standoff = spec.camera.position[2] - spec.camera.look_at[2]
    dist = RIG_Z - hit.point[obj, 2]
    assert dist.min() >= NEAR_FRACTION * standoff - 1.0
    wall_dist = RIG_Z - hit.point[hit.obj == len(a.primitives) - 1, 2]
    assert dist.max() <= wall_dist.max() + 1e-6


def test_object_mask_on_a_simple_scene():
    rig = SimulatedRig.build(RigSpec().scaled(0.25))
    scene = spheres()
    r = render(rig, scene, np.random.default_rng(0))
    mask = scene.is_object(r.obj)
    names = scene.names
    assert names[-1] == "wall" and scene.backdrop == ("wall",)
    assert np.array_equal(mask, (r.obj >= 0) & (r.obj < len(names) - 1))
    c = rig.camera.project(np.array([s["centre"] for s in scene.info["spheres"]]))
    for u, v in np.round(c).astype(int):
        assert mask[v, u]
    assert not mask[0, 0] and r.obj[0, 0] == names.index("wall")
    assert 0.02 < mask.mean() < 0.5


def test_truth_files_carry_the_object_mask(small_capture):
    t = np.load(small_capture / "truth" / "holes.npz")
    assert t["names"].tolist() == ["plate", "wall"]
    assert np.array_equal(t["object"], t["obj"] == 0)
    assert t["object"].any() and (t["obj"] == 1).any()


def _ident(points):
    """A hand-made identification from (u, v, slit, confidence) rows."""
    p = np.array(points, float).reshape(-1, 4)
    slit = p[:, 2].astype(int)
    return SimpleNamespace(
        u=p[:, 0],
        v=p[:, 1],
        slit=slit,
        confidence=p[:, 3],
        identified=slit >= 0,
        segment=np.zeros(len(p), int),
    )


def test_object_metrics_on_a_hand_made_identification():
    truth = np.full((4, 20), -1, np.int16)
    truth[:, 2:4] = 0  # slit 0 on the backdrop: centre at u = 2.5
    truth[:, 10:12] = 1  # slit 1 on the object: centre at u = 10.5
    obj = np.zeros((4, 20), bool)
    obj[:, 8:14] = True
    ident = _ident(
        [
            (10.5, 0, 1, 0.9),  # object, right
            (10.5, 1, 1, 0.9),  # object, right
            (10.5, 2, 0, 0.9),  # object, wrong, confident
            (10.5, 3, 0, 0.2),  # object, wrong, unsure
            (2.5, 0, 0, 0.9),  # backdrop, right
            (2.5, 1, -1, 0.0),  # not identified
        ]
    )
    m = object_metrics(ident, truth, obj)
    o, b = m["object"], m["backdrop"]
    assert o["points"] == 4 and o["centres"] == 4
    assert o["coverage"] == 0.5 and o["correct"] == 0.5
    assert o["wrong"] == 0.5 and o["wrong_confident"] == 0.25
    assert b["points"] == 1 and b["centres"] == 4
    assert b["coverage"] == 0.25 and b["correct"] == 1.0 and b["wrong"] == 0.0
    with pytest.raises(MultislitError, match="truth_object"):
        object_metrics(ident, truth, obj[:2])
