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


# --------------------------------------------------------------------------- viewpoint, pictures
def _seen_cloud(cal, n=3000, seed=0):
    """Points on two surfaces in front of the calibration's camera, with the image position
    each is seen at: (N, 3) mm and (N, 2) px."""
    rng = np.random.default_rng(seed)
    w, h = cal.image_size
    uv = np.stack([rng.uniform(0, w, n), rng.uniform(0, h, n)], axis=1)
    origin, ray = cal.camera.rays(uv)
    depth = np.where(uv[:, 0] < w / 2, 800.0, 950.0) + 40 * np.sin(uv[:, 1] / 60)
    centre = np.asarray(cal.camera.centre)
    t = (depth - 0.0) / np.linalg.norm(ray, axis=1)
    xyz = centre + ray * t[:, None]
    return xyz, cal.camera.project(xyz)


def _scene_camera(page: str) -> dict:
    m = re.search(r'"camera":(\{"eye":\{[^}]*\},"up":\{[^}]*\},"center":\{[^}]*\}\})', page)
    assert m, "the page has no camera viewpoint"
    return json.loads(m.group(1))


def test_page_opens_from_the_cameras_viewpoint(tmp_path: Path):
    from tests.test_calibration import _calibration

    cal = _calibration()
    xyz, uv = _seen_cloud(cal)
    ply = tmp_path / "scan.ply"
    write_ply(ply, xyz, u=uv[:, 0], v=uv[:, 1], slit=np.zeros(len(xyz), np.int64))
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    want = (np.asarray(cal.camera.centre) - 0.5 * (lo + hi)) / np.max(hi - lo)
    w, h = cal.image_size
    _, rays = cal.camera.rays(np.array([[w / 2, 0.0], [w / 2, h]]))
    up = (rays[0] - rays[1]) / np.linalg.norm(rays[0] - rays[1])
    # the calibration, or a camera matrix fitted to u v and x y z (no lens distortion in it:
    # close, not exact)
    for calibration, tol_deg, tol in ((cal, 0.1, 0.001), (None, 3.0, 0.1)):
        page = write_view(ply, tmp_path / "v.html", calibration=calibration).read_text()
        cam = _scene_camera(page)
        eye = np.array([cam["eye"][k] for k in "xyz"])
        got_up = np.array([cam["up"][k] for k in "xyz"])
        cos = eye @ want / np.linalg.norm(eye) / np.linalg.norm(want)
        assert np.degrees(np.arccos(min(cos, 1.0))) < tol_deg, (eye, want)
        assert abs(np.linalg.norm(eye) / np.linalg.norm(want) - 1) < tol
        assert np.degrees(np.arccos(min(got_up @ up, 1.0))) < tol_deg
        assert "seen from the camera" in page
    cal.save(tmp_path / "cal.json")  # by file, on the command line
    argv = ["view", str(ply), "-o", str(tmp_path / "c.html"), "--calibration"]
    assert main([*argv, str(tmp_path / "cal.json")]) == 0
    assert "seen from the camera: cal.json" in (tmp_path / "c.html").read_text()
    flat = tmp_path / "flat.ply"  # one plane and no calibration: Plotly's own view
    write_ply(flat, xyz * [1, 1, 0], u=uv[:, 0], v=uv[:, 1])
    assert '"camera":{"eye"' not in write_view(flat, tmp_path / "f.html").read_text()


def test_pictures_shown_beside_the_plot(tmp_path: Path):
    out = _out_folder(tmp_path, frames=3, n=500)
    for i in (0, 2):
        img = np.full((60, 80, 3), 40 * (i + 1), np.uint8)
        cv2.imwrite(str(out / f"frame_{i:06d}.png"), img)
    page = write_view(out, tmp_path / "v.html").read_text()
    assert 'id="picture"' in page and "plotly_sliderchange" in page
    pictures = json.loads(re.search(r"const pictures = (\[.*?\]);", page).group(1))
    assert [p.startswith("data:image/jpeg;base64,") for p in pictures] == [True, False, True]
    assert len(set(pictures)) == 3  # each frame its own
    (tmp_path / "bare").mkdir()
    bare = _out_folder(tmp_path / "bare", frames=1, n=50)
    assert 'id="picture"' not in write_view(bare, tmp_path / "b.html").read_text()


def test_scan_picture_marks_points_by_slit_and_those_left_out(tmp_path: Path):
    from multislit.app.pictures import LEFT_OUT_BGR, scan_picture
    from multislit.reconstruct import ScanResult

    h, w = 120, 160
    rng = np.random.default_rng(1)
    u = rng.uniform(5, w - 5, 400)
    v = rng.uniform(5, h - 5, 400)
    slit = np.where(np.arange(400) < 300, (u // 20).astype(np.int64), -1)  # 100 left out
    ply = tmp_path / "s.ply"
    write_ply(ply, np.c_[u, v, u * 0], u=u, v=v, slit=slit)
    res = ScanResult.from_ply(ply)
    pic = scan_picture(np.full((h, w), 100, np.uint8), res, num_slits=8)
    assert pic.shape == (h, w, 3) and pic.dtype == np.uint8
    magenta = np.all(pic == LEFT_OUT_BGR, axis=2)
    assert magenta[np.rint(v[300:]).astype(int), np.rint(u[300:]).astype(int)].mean() > 0.8
    kept = pic[np.rint(v[:300]).astype(int), np.rint(u[:300]).astype(int)]
    assert len({tuple(c) for c in kept}) >= 6  # the slits in their own colours
    assert not np.all(kept == LEFT_OUT_BGR, axis=1).any()
    with pytest.raises(MeasurementError, match="ScanResult"):
        scan_picture(np.zeros((h, w), np.uint8), "not a result")
