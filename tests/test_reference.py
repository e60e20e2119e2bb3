import json

import numpy as np
import pytest

from multislit.capture import Capture
from multislit.errors import ReferenceImageError
from multislit.geometry import PinholeCamera
from multislit.reference import ReferenceSet, curve_u, prepare_reference


def test_reference_curves_follow_the_true_slits(scenes_capture, scenes_reference):
    ref = scenes_reference
    assert ref.curves.shape[:2] == (3, 25)
    for r, name in enumerate(ref.names):
        truth = np.load(scenes_capture / "truth" / f"{name}.npz")["slit"]
        for v in range(40, 480, 40):
            row = truth[v]
            for k in range(25):
                cols = np.flatnonzero(row == k)
                assert abs(curve_u(ref.curves[r, k], float(v)) - cols.mean()) < 0.6


def test_epipole_is_the_dot_projectors_image(scenes_capture, scenes_reference):
    models = json.loads((scenes_capture / "truth" / "models.json").read_text())
    cam = PinholeCamera.from_dict(models["camera"])
    pinhole = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.rvec, cam.tvec)
    true_e = pinhole.project(np.array(models["dot_projector"]["origin"]))[0]
    e = scenes_reference.epipole
    est = e[:2] / e[2]
    # the epipole lies far outside the image: compare directions seen from the image centre
    c = np.array([320.0, 256.0])
    ang = np.degrees(
        np.arccos(
            np.dot(est - c, true_e - c) / np.linalg.norm(est - c) / np.linalg.norm(true_e - c)
        )
    )
    assert ang < 0.5
    assert scenes_reference.epipole_residual_px < 0.5


def test_save_and_load(scenes_reference, tmp_path):
    p = tmp_path / "ref.npz"
    scenes_reference.save(p)
    back = ReferenceSet.load(p)
    assert np.allclose(back.curves, scenes_reference.curves) and back.num_slits == 25
    with pytest.raises(ReferenceImageError, match="not found"):
        ReferenceSet.load(tmp_path / "none.npz")


def test_reference_with_a_missing_slit_is_an_error(scenes_capture):
    cap = Capture.open(scenes_capture)
    imgs = [cap.image(p).copy() for p in cap.references]
    # black out the rightmost slit in the second image
    truth = np.load(scenes_capture / "truth" / f"{cap.references[1].stem}.npz")["slit"]
    imgs[1][truth == 24] = 0
    imgs[1][:, :] = np.where(
        np.roll(truth == 24, 2, axis=1) | np.roll(truth == 24, -2, axis=1), 0, imgs[1]
    )
    with pytest.raises(
        ReferenceImageError, match=r"ref_0900: found 24 slits in most rows, expected 25"
    ):
        prepare_reference(imgs, 25, [p.stem for p in cap.references])


def test_too_few_reference_images(scenes_capture):
    cap = Capture.open(scenes_capture)
    with pytest.raises(ReferenceImageError, match=">= 2 reference images"):
        prepare_reference([cap.image(cap.references[0])], 25)


def test_wrong_number_of_slits_is_an_error(scenes_capture):
    cap = Capture.open(scenes_capture)
    with pytest.raises(ReferenceImageError, match="expected 26"):
        prepare_reference([cap.image(p) for p in cap.references], 26)
