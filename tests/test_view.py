"""`multislit view`: one self-contained HTML page, checked in headless Chromium."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from multislit.app.cli import main
from multislit.app.view import load_frames, write_view
from multislit.errors import MeasurementError
from multislit.io import write_ply

pytest.importorskip("plotly", reason="plotly (multislit[view]) not installed")

_CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=800,600",
]


def _cloud(n: int, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A wavy sheet of n points (mm) over 20 slits."""
    rng = np.random.default_rng(int(shift))
    x = rng.uniform(-200, 200, n)
    y = rng.uniform(-150, 150, n)
    z = 40 * np.sin(x / 60.0 + shift) * np.cos(y / 80.0)
    slit = np.clip(((x + 200) / 20).astype(np.int64), 0, 19)
    return np.stack([x, y, z], 1), slit


def _out_folder(root: Path, frames: int = 3, n: int = 3000) -> Path:
    out = root / "out"
    out.mkdir()
    lines = []
    for i in range(frames):
        pts, slit = _cloud(n, shift=float(i))
        write_ply(out / f"frame_{i:06d}.ply", pts, u=pts[:, 0], v=pts[:, 1], slit=slit)
        lines.append(json.dumps({"frame": i, "source": f"img{i}.png", "points": n, "slits": 20}))
    (out / "frames.jsonl").write_text("\n".join(lines) + "\n")
    return out


def test_page_is_self_contained_with_a_frame_slider(tmp_path: Path):
    out = _out_folder(tmp_path)
    page = write_view(out, tmp_path / "view.html", max_points=1000)
    html = page.read_text()
    assert not re.search(r"<script[^>]+src=", html)  # plotly.js is inside the page
    assert not re.search(r"<link[^>]+href=", html)  # no style sheet to fetch
    assert "Plotly.newPlot" in html or "Plotly.react" in html
    for i in range(3):
        assert f"frame_{i:06d} img{i}.png" in html  # a slider step per frame
    assert "colour by slit" in html and "colour by depth" in html
    frames = load_frames(out)
    assert [label for label, _ in frames] == [f"frame_{i:06d} img{i}.png" for i in range(3)]


def test_single_ply_and_bad_input(tmp_path: Path, capsys):
    pts, slit = _cloud(500)
    ply = tmp_path / "a.ply"
    write_ply(ply, pts, slit=slit)
    assert main(["view", str(ply), "-o", str(tmp_path / "a.html"), "--color", "slit"]) == 0
    assert (tmp_path / "a.html").stat().st_size > 1_000_000  # the library is inlined
    with pytest.raises(MeasurementError, match="no such PLY file or folder"):
        write_view(tmp_path / "missing.ply", tmp_path / "b.html")
    with pytest.raises(MeasurementError, match="no frames"):
        (tmp_path / "empty").mkdir()
        write_view(tmp_path / "empty", tmp_path / "b.html")
    with pytest.raises(MeasurementError, match="end in .html"):
        write_view(ply, tmp_path / "b.png")
    code = main(["view", str(ply), "-o", str(ply)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert ply.read_bytes().startswith(b"ply\n")  # the input is untouched


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _coloured_pixels(png: Path) -> int:
    """Strongly coloured pixels left of the colour bar, below the buttons and above the slider."""
    img = cv2.imread(str(png))
    h, w = img.shape[:2]
    hsv = cv2.cvtColor(img[int(0.15 * h) : int(0.6 * h), : int(0.8 * w)], cv2.COLOR_BGR2HSV)
    return int(np.count_nonzero((hsv[:, :, 1] > 90) & (hsv[:, :, 2] > 40)))


@pytest.mark.slow
def test_headless_chromium_draws_the_cloud(tmp_path: Path):
    exe = _chromium()
    if exe is None:
        pytest.skip("Chromium not installed (make test installs Debian's chromium)")
    out = _out_folder(tmp_path)
    shots = {}
    for name, source in (("cloud", out), ("empty", None)):
        if source is None:  # the same page without points: the check must see the difference
            source = tmp_path / "none.ply"
            write_ply(source, np.zeros((0, 3)), slit=np.zeros(0, np.int64))
        page = write_view(source, tmp_path / f"{name}.html")
        shot = tmp_path / f"{name}.png"
        subprocess.run(
            [
                exe,
                *_CHROMIUM_FLAGS,
                f"--user-data-dir={tmp_path / 'profile'}",
                f"--screenshot={shot}",
                page.resolve().as_uri(),
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )
        shots[name] = _coloured_pixels(shot)
    assert shots["cloud"] > 2000, shots
    assert shots["empty"] < 50, shots


def test_index_that_is_not_utf8_is_one_line(tmp_path: Path, capsys):
    out = _out_folder(tmp_path, frames=1, n=50)
    (out / "frames.jsonl").write_bytes(b'{"frame": 0, "source": "caf\xe9.png"}\n')
    code = main(["view", str(out), "-o", str(tmp_path / "v.html")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "frames.jsonl line 1 is not UTF-8 text" in err


def test_points_with_nan_are_left_out_of_the_colour_range(tmp_path: Path):
    ply = tmp_path / "nan.ply"
    rows = ["1 2 3 0", "4 5 -6 1", "nan 1 2 1", "1 2 nan 2", "1 inf 1 2", "7 8 9 2"]
    head = "ply\nformat ascii 1.0\nelement vertex 6\n"
    head += "".join(f"property float {k}\n" for k in "xyz") + "property int slit\nend_header\n"
    ply.write_text(head + "\n".join(rows) + "\n")
    html = write_view(ply, tmp_path / "nan.html").read_text()
    cmin = re.findall(r'"cmin":([^,}]+)', html)
    cmax = re.findall(r'"cmax":([^,}]+)', html)
    assert cmin and cmax and "null" not in cmin + cmax, (cmin, cmax)
    assert "-6.0" in cmin and "9.0" in cmax  # the finite points' depth range
