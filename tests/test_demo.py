"""The demo at half size: completes, writes its figures and JSON with the expected keys."""

from __future__ import annotations

import json

import pytest

from multislit.app.cli import main


@pytest.mark.slow
def test_demo_half_size(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--scale", "0.5", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert {"table1", "calibration", "scans", "time_per_frame_s", "figures", "report"} <= set(d)
    assert {"dlt_rms_px", "camera_rms_px", "slit_plane_rms_median_mm"} <= set(d["calibration"])
    assert set(d["scans"]) == {"holes", "holes_tilt20"}
    for s in d["scans"].values():
        assert s["correct_share"] > 0.98
    rows = {(r["scene"], r["hole"]): r for r in d["table1"]}
    assert len(rows) == 6
    for r in rows.values():
        assert {"actual", "estimated", "error", "paper_estimated", "paper_error"} <= set(r)
    d1 = rows[("holes", "D1")]
    assert d1["estimated"] is not None and abs(d1["error"]) < 1.0
    assert rows[("holes", "D2")]["paper_estimated"] == 49.5
    for f in d["figures"].values():
        assert (out / f.split("/")[-1]).is_file()
    assert {"slit_addresses", "point_cloud", "hole_edges_holes"} <= set(d["figures"])
    assert json.loads((out / "demo.json").read_text())["table1"] == d["table1"]
