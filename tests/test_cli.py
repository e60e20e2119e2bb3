import json

import pytest

from multislit.app.cli import main


@pytest.mark.slow
def test_simulate_writes_a_capture(tmp_path, capsys):
    rc = main(
        ["simulate", str(tmp_path / "c"), "--scene", "spheres", "--scale", "0.25", "--seed", "2"]
    )
    assert rc == 0
    assert "wrote capture" in capsys.readouterr().out
    assert (tmp_path / "c" / "scans" / "spheres.png").is_file()


def test_errors_are_messages_not_tracebacks(tmp_path, capsys):
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({"slits": {"colour": "red"}}))
    rc = main(["simulate", str(tmp_path / "c"), "--rig", str(rig)])
    err = capsys.readouterr().err
    assert rc == 2 and "error: rig description [slits]: unknown key(s) ['colour']" in err
    assert "Traceback" not in err


def test_rig_prints_editable_json(capsys):
    assert main(["rig"]) == 0
    assert json.loads(capsys.readouterr().out)["slits"]["num_slits"] == 25
