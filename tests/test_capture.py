import json
import shutil

import cv2
import numpy as np
import pytest

from multislit.errors import CaptureError
from multislit.io import Capture, read_image


def _copy(src, tmp_path):
    dst = tmp_path / "cap"
    shutil.copytree(src, dst)
    return dst


def test_simulated_capture_is_valid(small_capture):
    cap = Capture.open(small_capture)
    assert cap.image_size == (640, 512) and cap.num_slits == 25
    assert len(cap.references) == 3 and [p.stem for p in cap.scans] == ["holes", "steps"]
    assert len(cap.target.markers) >= 10 and len(cap.target.faces) >= 3
    # markers on >= 3 non-coplanar faces: the marker points span 3D
    xyz = cap.target.marker_xyz
    s = np.linalg.svd(xyz - xyz.mean(0), compute_uv=False)
    assert s[2] > 0.1 * s[0]
    for p in [cap.markers_image, cap.slits_image, *cap.references, *cap.scans]:
        assert cap.image(p).shape == (512, 640)


def test_missing_rig_json(small_capture, tmp_path):
    d = _copy(small_capture, tmp_path)
    (d / "rig.json").unlink()
    with pytest.raises(CaptureError, match="missing file: .*rig.json"):
        Capture.open(d)


def test_not_a_folder(tmp_path):
    with pytest.raises(CaptureError, match="capture folder not found"):
        Capture.open(tmp_path / "nope")


@pytest.mark.parametrize(
    "patch, message",
    [
        ({"format": "multislit-capture/9"}, "this reader understands"),
        ({"image_size": [640]}, "image_size"),
        ({"num_slits": 0}, "num_slits"),
    ],
)
def test_malformed_rig_json(small_capture, tmp_path, patch, message):
    d = _copy(small_capture, tmp_path)
    rig = json.loads((d / "rig.json").read_text())
    rig.update(patch)
    (d / "rig.json").write_text(json.dumps(rig))
    with pytest.raises(CaptureError, match=message):
        Capture.open(d)


def test_invalid_json(small_capture, tmp_path):
    d = _copy(small_capture, tmp_path)
    (d / "target.json").write_text("{not json")
    with pytest.raises(CaptureError, match="not valid JSON"):
        Capture.open(d)


def test_too_few_references(small_capture, tmp_path):
    d = _copy(small_capture, tmp_path)
    for p in sorted((d / "reference").glob("*.png"))[1:]:
        p.unlink()
    with pytest.raises(CaptureError, match="found 1 reference image"):
        Capture.open(d)


def test_wrong_image_size(small_capture, tmp_path):
    d = _copy(small_capture, tmp_path)
    cv2.imwrite(str(d / "scans" / "holes.png"), np.zeros((100, 120), np.uint8))
    cap = Capture.open(d)
    with pytest.raises(CaptureError, match="is 120x100 px but rig.json says image_size 640x512"):
        cap.image(cap.scans[0])


def test_bad_image_file(tmp_path):
    p = tmp_path / "x.png"
    p.write_bytes(b"not a png")
    with pytest.raises(CaptureError, match="not a valid PNG"):
        read_image(p)
    with pytest.raises(CaptureError, match="image not found"):
        read_image(tmp_path / "missing.png")


def test_sixteen_bit_images_are_read(tmp_path):
    img = (np.arange(64 * 32).reshape(32, 64) * 30).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    back = read_image(tmp_path / "a.png", (64, 32))
    assert back.dtype == np.uint16 and np.array_equal(back, img)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda t: t.pop("markers"), "missing 'markers'"),
        (lambda t: t["markers"][0].pop("uv_hint"), r"markers\[0\] needs"),
        (lambda t: t["markers"][1].update(xyz=[1, 2]), r"markers\[1\]\.xyz must be a list of 3"),
        (lambda t: t["markers"][1].update(id=t["markers"][0]["id"]), "duplicate marker id"),
        (lambda t: t["faces"][0].update(plane=[0, 0, 0, 1]), "zero normal"),
        (
            lambda t: t["slit_points"][0].update(slit=99),
            r"slit is 99, but the rig has slits 0\.\.24",
        ),
    ],
)
def test_malformed_target(small_capture, tmp_path, mutate, message):
    d = _copy(small_capture, tmp_path)
    t = json.loads((d / "target.json").read_text())
    mutate(t)
    (d / "target.json").write_text(json.dumps(t))
    with pytest.raises(CaptureError, match=message):
        Capture.open(d)


def test_unknown_keys_are_ignored(small_capture, tmp_path):
    d = _copy(small_capture, tmp_path)
    rig = json.loads((d / "rig.json").read_text())
    rig["vendor_notes"] = {"anything": 1}
    (d / "rig.json").write_text(json.dumps(rig))
    (d / "notes.txt").write_text("hello")
    assert Capture.open(d).num_slits == 25
