import json

import numpy as np
import pytest

from multislit.errors import MultislitError
from multislit.sim.rig import RigSpec, SimulatedRig


def test_defaults_follow_the_paper():
    rig = SimulatedRig.build()
    assert rig.camera.image_size == (1280, 1024) and rig.projector.num_slits == 25
    base = np.linalg.norm(rig.camera.centre - rig.projector.origin)
    assert base == pytest.approx(450.0)
    # dot projector displaced along the slits (the sheets' common axis), tens of mm
    off = rig.dots.origin - rig.projector.origin
    axis = rig.projector.axis[1]
    assert 10 < np.linalg.norm(off) < 100 and abs(abs(off @ axis) - np.linalg.norm(off)) < 1e-9


def test_grating_planes_share_an_axis_and_are_not_equally_spaced():
    rig = SimulatedRig.build()
    planes = rig.projector.planes()
    o, a = rig.projector.axis
    for q in (o, o + 300 * a):
        assert np.abs(planes[:, :3] @ q + planes[:, 3]).max() < 1e-9
    s = np.sin(rig.projector.angles)
    assert np.allclose(np.diff(s), np.diff(s)[0])  # sin(theta_m) = m lambda / pitch
    assert np.ptp(np.diff(np.tan(rig.projector.angles))) > 1e-4  # so tan is not equally spaced


def test_rig_json_round_trip(tmp_path):
    spec = RigSpec().scaled(0.5)
    p = tmp_path / "rig.json"
    p.write_text(spec.to_json())
    assert RigSpec.load(p) == spec


@pytest.mark.parametrize(
    "d, message",
    [
        ({"camera": {"focal": 10}}, "unknown key"),
        ({"lens": {}}, "unknown section"),
        ({"dots": {"pattern": "grid"}}, "bands' or 'uniform"),
        ({"slits": {"num_slits": 49, "pitch_um": 5.0}}, "increase pitch_um"),
        ({"reference_distances": [900]}, ">= 2 board distances"),
    ],
)
def test_bad_rig_descriptions(d, message):
    with pytest.raises(MultislitError, match=message):
        RigSpec.from_dict(json.loads(json.dumps(d)))


def test_missing_rig_file(tmp_path):
    with pytest.raises(MultislitError, match="rig file not found"):
        RigSpec.load(tmp_path / "nope.json")


@pytest.mark.parametrize("factor", [0, -1.0])
def test_bad_scale_factor(factor):
    with pytest.raises(MultislitError, match="scale factor must be a positive number"):
        RigSpec().scaled(factor)
