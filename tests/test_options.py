"""The scan's options: one validated value per stage, from the command line and an options
file to the library, written into the output."""

from __future__ import annotations

import json

import numpy as np
import pytest

import multislit as ms
from multislit.app.cli import main
from multislit.errors import MultislitError
from multislit.identify import IdentifyOptions
from multislit.reconstruct import RefineOptions, ScanOptions
from multislit.stripes import ExtractionOptions


def test_options_round_trip_and_defaults(tmp_path):
    o = ScanOptions()
    assert o.extraction == ExtractionOptions() and o.extraction.channel is None
    assert o.identification.method == "geometry" and o.identification.min_confidence is None
    assert o.identification.confidence == 0.98 and o.refinement.min_angle_deg == 2.0
    custom = ScanOptions(
        ExtractionOptions(
            channel="auto", reject_texture=True, method="steger", k_sigma=6, leaning=False
        ),
        IdentifyOptions(method="template", min_confidence=0.5, depth_range=(500, 1500)),
        RefineOptions(refine_centres=False, min_angle_deg=5),
    )
    assert ScanOptions.from_dict(json.loads(json.dumps(custom.to_dict()))) == custom
    path = tmp_path / "o.json"
    path.write_text(json.dumps({"extraction": {"reject_texture": True}}))
    loaded = ScanOptions.load(path)
    assert loaded.extraction.reject_texture and loaded.refinement == RefineOptions()
    assert loaded.with_extraction(channel="green").extraction.channel == "green"
    with pytest.raises(AttributeError):
        loaded.extraction.channel = "red"  # frozen


@pytest.mark.parametrize(
    "d, match",
    [
        ({"extraction": {"chanel": "red"}}, "unknown option\\(s\\) 'chanel'; the options are"),
        ({"extraction": {"channel": "uv"}}, "extraction.channel must be one of"),
        ({"extraction": {"reject_texture": "yes"}}, "reject_texture must be true or false"),
        ({"extraction": {"k_sigma": -1}}, "k_sigma must be a positive number"),
        ({"extraction": {"min_length": 2.5}}, "min_length must be an integer"),
        ({"extraction": {"method": "mean"}}, "method must be one of"),
        ({"extraction": {"leaning": "no"}}, "leaning must be true or false"),
        ({"identification": {"min_confidence": 2}}, "min_confidence must be a number in"),
        ({"refinement": {"min_angle_deg": "2"}}, "min_angle_deg must be a number of degrees"),
        ({"refinement": {"refine_centres": 1}}, "refine_centres must be true or false"),
        ({"scan": {}}, "unknown option\\(s\\) 'scan'"),
        ([1, 2], "must be a JSON object"),
    ],
)
def test_bad_options_are_one_line(tmp_path, capsys, d, match):
    with pytest.raises(MultislitError, match=match) as exc:
        ScanOptions.from_dict(d)
    assert "\n" not in str(exc.value)
    path = tmp_path / "o.json"
    path.write_text(json.dumps(d))
    assert main(["scan", str(tmp_path), "--options", str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    with pytest.raises(MultislitError, match="options must be a ScanOptions"):
        ms.scan_image(np.zeros((8, 8), np.uint8), None, None, {"extraction": {}})


def test_scan_takes_the_photo_mode_and_the_channel_from_the_data(calibrated, tmp_path, capsys):
    """``multislit scan CAPTURE --reject-texture --channel auto``: the options reach the
    extraction (the photo mode's results differ from the default's) and are written into
    each PLY's header; an options file gives the same."""
    out = tmp_path / "pts"
    argv = ["scan", str(calibrated), "--image", str(calibrated / "scans" / "holes.png")]
    assert main([*argv, "-o", str(out), "--reject-texture", "--channel", "auto"]) == 0
    head = (out / "holes.ply").read_bytes().split(b"end_header")[0].decode()
    line = next(x for x in head.splitlines() if x.startswith("comment options "))
    used = ScanOptions.from_dict(json.loads(line[len("comment options ") :]))
    assert used.extraction.reject_texture and used.extraction.channel == "auto"
    photo = ms.read_ply(out / "holes.ply")
    assert main([*argv, "-o", str(tmp_path / "plain")]) == 0
    plain = ms.read_ply(tmp_path / "plain" / "holes.ply")
    assert len(photo["x"]) > 1000 and len(photo["x"]) != len(plain["x"])
    opts = tmp_path / "photo.json"
    opts.write_text(json.dumps(used.to_dict()))
    assert main([*argv, "-o", str(tmp_path / "file"), "--options", str(opts)]) == 0
    again = ms.read_ply(tmp_path / "file" / "holes.ply")
    assert all(np.array_equal(photo[k], again[k]) for k in photo)
    capsys.readouterr()


def test_the_library_takes_the_same_options(calibrated):
    cap = ms.Capture.open(calibrated)
    cal = ms.Calibration.load(calibrated / "calibration.json")
    ref = ms.capture_reference(cap)
    img = cap.image(calibrated / "scans" / "holes.png")
    photo = ScanOptions().with_extraction(reject_texture=True)
    res = ms.scan_image(img, ref, cal, photo)
    assert res.options == photo and res.to_dict()["options"]["extraction"]["reject_texture"]
    by_capture = ms.scan_capture(cap, cal, ref, images=[calibrated / "scans" / "holes.png"],
                                 options=photo)["holes"]  # fmt: skip
    assert np.array_equal(by_capture.points, res.points)
    strict = ms.scan_image(
        img, ref, cal, ScanOptions(identification=IdentifyOptions(min_confidence=0.999999))
    )
    default = ms.scan_image(img, ref, cal)
    assert 0 < strict.num_points < default.num_points
    holes = ms.measure_holes(img, ref, cal, photo)
    assert holes.scan.options == photo and holes.measurable
