"""An interactive 3D view of point clouds as one self-contained HTML page (``multislit view``).

The page is drawn with Plotly, whose JavaScript is written into the page, so it opens without a
network. It opens looking from the camera (the rig's calibration: given, beside the capture of
a scan's PLY, or named by an OUT folder's ``run.json``; else a camera matrix fitted to the
points' image positions), as the frame was seen. Drag to rotate, scroll to zoom; buttons colour
the points by depth (z in the target frame, mm) or by slit number; for an OUT folder of
``multislit stream`` a slider steps through the frames. Where a PLY has its picture beside it
(``--pictures``: the frame with the stripe points coloured by slit and those left out in
magenta), the picture is shown next to the 3D plot, following the slider.

Needs Plotly (the optional extra ``pip install 'multislit[view]'``).
"""

from __future__ import annotations

import base64
import html
import json
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from multislit.app.index import INDEX_FILE, RUN_FILE, frame_file, read_index
from multislit.calibrate import Calibration
from multislit.calibrate.camera import calibrate_dlt
from multislit.errors import MeasurementError, MultislitError
from multislit.io import parse_json, read_ply, write_text_atomic
from multislit.io.capture import decode_image_file
from multislit.io.paths import as_path
from multislit.reconstruct import CALIBRATION_FILE

__all__ = ["load_frames", "write_view", "find_calibration", "camera_view"]


_MARKER_PX = 2
_DEPTH_SCALE = "Viridis"
_SLIT_SCALE = "Turbo"
_BACKGROUND = "white"
_MAX_TOTAL_POINTS = 2_000_000  # over all frames: keeps a long sequence's page openable
_DLT_POINTS = 2000  # points fitted for a viewpoint from a PLY alone
_DLT_MAX_PX = 2.0  # median residual of that fit, px, for it to count as a camera
_PICTURE_WIDTH = 960  # px: pictures shown beside the plot are scaled down to this
_PICTURE_QUALITY = 85  # JPEG quality of those
_MAX_PICTURES = 300  # a longer sequence shows the pictures of evenly spaced frames only


def load_frames(source: str | os.PathLike[str]) -> list[tuple[str, dict[str, NDArray]]]:
    """The point clouds of a PLY file or of an OUT folder, in frame order.

    Parameters
    ----------
    source : a PLY file, or a folder with ``frames.jsonl`` and ``frame_*.ply`` (without the
        index, its ``frame_*.ply`` files in name order)

    Returns
    -------
    list of (label, vertex properties) with ``x y z`` (mm) and, if the file has them, ``slit``

    Raises
    ------
    MeasurementError
        A missing source, a folder without frames, a PLY without ``x y z``.
    """
    out = []
    for path, label in _frame_paths(source):
        d = read_ply(path)
        if not {"x", "y", "z"} <= set(d):
            raise MeasurementError(f"{path}: the PLY has no x y z properties")
        out.append((label, d))
    return out


def _frame_paths(source: str | os.PathLike[str]) -> list[tuple[Path, str]]:
    """The PLY files of a PLY or OUT folder source and their labels, in frame order."""
    p = as_path(source, "source", error=MeasurementError)
    if p.is_dir():
        index = p / INDEX_FILE
        if index.is_file():
            entries = [(frame_file(d["frame"]), d["source"]) for d in read_index(index)]
        else:
            entries = [(q.name, "") for q in sorted(p.glob("frame_*.ply"))]
        if not entries:
            raise MeasurementError(f"{p}: no frames (frame_*.ply) in the folder")
        return [(p / name, f"{Path(name).stem} {src}".strip()) for name, src in entries]
    if p.is_file():
        return [(p, p.name)]
    raise MeasurementError(f"{p}: no such PLY file or folder")


# --------------------------------------------------------------------------- viewpoint
def find_calibration(source: str | os.PathLike[str]) -> Path | None:
    """The calibration of the rig that made ``source``, if it can be found: for a PLY of
    ``multislit scan`` in ``CAPTURE/points``, ``CAPTURE/calibration.json``; for an OUT folder,
    the calibration its ``run.json`` names."""
    p = as_path(source, "source", error=MeasurementError)
    if p.is_dir():
        run = p / RUN_FILE
        if run.is_file():
            try:
                cal = parse_json(run.read_bytes(), where=str(run)).get("calibration")
            except (MultislitError, OSError, AttributeError):
                return None
            if isinstance(cal, str) and Path(cal).is_file():
                return Path(cal)
        return None
    capture = p.resolve().parent.parent
    cal = capture / CALIBRATION_FILE
    return cal if (capture / "rig.json").is_file() and cal.is_file() else None


def _camera_of(
    calibration: Calibration | str | os.PathLike[str] | None, source: str | os.PathLike[str]
) -> tuple[Any, tuple[int, int], str]:
    """(camera, image size, where it came from) of the viewpoint, or (None, (0, 0), '')."""
    if isinstance(calibration, Calibration):
        return calibration.camera, calibration.image_size, "the calibration"
    path = calibration if calibration is not None else find_calibration(source)
    if path is None:
        return None, (0, 0), ""
    cal = Calibration.load(path)
    return cal.camera, cal.image_size, Path(path).name


def _camera_from_points(d: dict[str, NDArray]) -> tuple[Any, tuple[int, int]]:
    """A camera matrix fitted to a PLY's points and their image positions (x y z, u v), or
    None where they do not determine one (no u v, too few, all on one plane)."""
    if not {"u", "v"} <= set(d):
        return None, (0, 0)
    xyz = np.stack([d["x"], d["y"], d["z"]], axis=1).astype(np.float64)
    uv = np.stack([d["u"], d["v"]], axis=1).astype(np.float64)
    ok = np.isfinite(xyz).all(axis=1) & np.isfinite(uv).all(axis=1)
    xyz, uv = xyz[ok], uv[ok]
    if len(xyz) > _DLT_POINTS:
        keep = np.linspace(0, len(xyz) - 1, _DLT_POINTS).round().astype(np.int64)
        xyz, uv = xyz[keep], uv[keep]
    if len(xyz) < 6:
        return None, (0, 0)
    size = (int(np.ceil(uv[:, 0].max())) + 1, int(np.ceil(uv[:, 1].max())) + 1)
    try:
        camera, residuals = calibrate_dlt(xyz, uv, image_size=size)
    except MultislitError:
        return None, (0, 0)
    if not np.median(residuals) < _DLT_MAX_PX:  # not one camera's points (or NaN)
        return None, (0, 0)
    return camera, size


def camera_view(camera: Any, image_size: tuple[int, int], lo: NDArray, hi: NDArray) -> dict:
    """Plotly's ``scene.camera`` that looks from ``camera``'s centre at the middle of the box
    ``lo`` .. ``hi`` (mm) with the image's top up, for a scene whose axes span that box with
    ``aspectmode="manual"`` and aspect ratios proportional to the box's sides (the scene's
    unit is the box's longest side)."""
    w, h = image_size
    mid = 0.5 * (lo + hi)
    unit = float(np.max(hi - lo)) or 1.0
    _, rays = camera.rays(np.array([[0.5 * w, 0.0], [0.5 * w, float(h)]]))
    up = rays[0] - rays[1]  # from the image's bottom to its top
    eye = (np.asarray(camera.centre, np.float64) - mid) / unit
    norm = float(np.linalg.norm(up))
    up = up / norm if norm > 0 else np.array([0.0, 0.0, 1.0])
    return {
        "eye": dict(zip("xyz", (float(x) for x in eye), strict=True)),
        "up": dict(zip("xyz", (float(x) for x in up), strict=True)),
        "center": {"x": 0.0, "y": 0.0, "z": 0.0},
    }


# --------------------------------------------------------------------------- pictures
def _picture_of(ply: Path) -> str:
    """The picture beside a PLY (``NAME.png``) as a data URL of a JPEG at most
    ``_PICTURE_WIDTH`` px wide, or '' when there is none or it is unreadable."""
    png = ply.with_suffix(".png")
    if not png.is_file():
        return ""
    try:
        img = decode_image_file(png)
    except MultislitError:
        return ""
    if img.shape[1] > _PICTURE_WIDTH:
        scale = _PICTURE_WIDTH / img.shape[1]
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, _PICTURE_QUALITY])
    return "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _take(d: dict[str, NDArray], max_points: int) -> tuple[NDArray, NDArray]:
    """(K, 3) float64 points and (K,) slit numbers (-1 if unknown), at most ``max_points``;
    points with a NaN or infinite coordinate are left out (they cannot be drawn)."""
    xyz = np.stack([d["x"], d["y"], d["z"]], axis=1).astype(np.float64)
    slit = d["slit"].astype(np.int64) if "slit" in d else np.full(len(xyz), -1, np.int64)
    finite = np.isfinite(xyz).all(axis=1)
    xyz, slit = xyz[finite], slit[finite]
    if len(xyz) > max_points:
        keep = np.linspace(0, len(xyz) - 1, max_points).round().astype(np.int64)
        xyz, slit = xyz[keep], slit[keep]
    return xyz, slit


def write_view(
    source: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    color: str = "depth",
    max_points: int = 50000,
    calibration: Calibration | str | os.PathLike[str] | None = None,
) -> Path:
    """Write the interactive page of a PLY file or an OUT folder.

    Parameters
    ----------
    source : a PLY file or an OUT folder (see :func:`load_frames`)
    output : the HTML file to write (whole or not at all); must not be ``source``
    color : {'depth', 'slit'}
        The colouring shown first (the page has buttons for both). Default depth.
    max_points : int
        Points drawn per frame, evenly taken from the file's order; a sequence draws at most
        2,000,000 points in all (fewer per frame when it is long). Default 50000.
    calibration : Calibration or its file, optional
        The rig whose camera the page looks from. Default: :func:`find_calibration`, else a
        camera matrix fitted to the first frame's points and image positions, else Plotly's
        default view.

    Returns
    -------
    Path of the page.

    Raises
    ------
    MeasurementError
        Bad source or options, no Plotly, or the page cannot be written.
    """
    if color not in ("depth", "slit"):
        raise MeasurementError(f"color must be 'depth' or 'slit', got {color!r}")
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < 1:
        raise MeasurementError(f"max_points must be an integer >= 1, got {max_points!r}")
    out = Path(output)
    if out.exists() and (out.is_dir() or out.resolve() == Path(source).resolve()):
        raise MeasurementError(f"-o {out}: give a new HTML file name (it is an input or folder)")
    if out.suffix.lower() not in (".html", ".htm"):
        raise MeasurementError(f"-o {out}: the page's name must end in .html")
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise MeasurementError(
            "multislit view needs Plotly: pip install 'multislit[view]'"
        ) from None

    paths = _frame_paths(source)
    loaded = load_frames(source)
    camera, size, seen_by = _camera_of(calibration, source)
    if camera is None:
        camera, size = _camera_from_points(loaded[0][1])
        seen_by = "a camera fitted to the points" if camera is not None else ""
    per_frame = max(1, min(max_points, _MAX_TOTAL_POINTS // len(loaded)))
    frames = [(label, *_take(d, per_frame)) for label, d in loaded]
    all_z = np.concatenate([f[1][:, 2] for f in frames])
    all_s = np.concatenate([f[2] for f in frames])
    zlim = (float(all_z.min()), float(all_z.max())) if all_z.size else (0.0, 1.0)
    slim = (0, int(max(all_s.max(), 0))) if all_s.size else (0, 1)

    def traces(xyz: NDArray, slit: NDArray, first: bool = False) -> list:
        # a frame's traces leave "visible" alone: the colour buttons own it
        common = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "mode": "markers"}
        shown = ({"visible": color == "depth"}, {"visible": color == "slit"}) if first else ({}, {})
        depth = go.Scatter3d(
            **common,
            name="depth",
            **shown[0],
            marker={
                "size": _MARKER_PX,
                "color": xyz[:, 2],
                "colorscale": _DEPTH_SCALE,
                "cmin": zlim[0],
                "cmax": zlim[1],
                "colorbar": {"title": {"text": "z (mm)"}},
            },
            hovertemplate="x %{x:.2f}<br>y %{y:.2f}<br>z %{z:.2f} mm<extra></extra>",
        )
        by_slit = go.Scatter3d(
            **common,
            name="slit",
            **shown[1],
            customdata=slit,
            marker={
                "size": _MARKER_PX,
                "color": slit,
                "colorscale": _SLIT_SCALE,
                "cmin": slim[0],
                "cmax": slim[1],
                "colorbar": {"title": {"text": "slit"}},
            },
            hovertemplate="slit %{customdata}<br>x %{x:.2f}<br>y %{y:.2f}<br>z %{z:.2f} mm"
            "<extra></extra>",
        )
        return [depth, by_slit]

    _, xyz0, slit0 = frames[0]
    fig = go.Figure(data=traces(xyz0, slit0, first=True))
    menus = [
        {
            "type": "buttons",
            "direction": "right",
            "x": 0.0,
            "y": 1.0,
            "xanchor": "left",
            "yanchor": "bottom",
            "buttons": [
                {"label": "colour by depth", "method": "restyle", "args": ["visible", [1, 0]]},
                {"label": "colour by slit", "method": "restyle", "args": ["visible", [0, 1]]},
            ],
        }
    ]
    layout: dict = {
        "title": {
            "text": Path(source).name + (f": {len(frames)} frames" if len(frames) > 1 else ""),
            "x": 0.5,
        },
        "scene": _scene(frames, camera, size),
        "paper_bgcolor": _BACKGROUND,
        "showlegend": False,
        "margin": {"l": 0, "r": 0, "t": 60, "b": 0},
        "updatemenus": menus,
        "uirevision": "keep",
    }
    if len(frames) > 1:
        fig.frames = [
            go.Frame(name=str(i), data=traces(xyz, slit), traces=[0, 1])
            for i, (_, xyz, slit) in enumerate(frames)
        ]
        layout["sliders"] = [
            {
                "active": 0,
                "currentvalue": {"prefix": ""},
                "pad": {"t": 10},
                "steps": [
                    {
                        "label": label,
                        "method": "animate",
                        "args": [
                            [str(i)],
                            {"mode": "immediate", "frame": {"duration": 0, "redraw": True}},
                        ],
                    }
                    for i, (label, _, _) in enumerate(frames)
                ],
            }
        ]
    if seen_by:
        layout["title"]["text"] += f" (seen from the camera: {seen_by})"
    fig.update_layout(**layout)
    pictures = [_picture_of(path) for path, _ in paths[:_MAX_PICTURES]]
    page = _page(fig, pictures, Path(source).name, more=len(paths) > _MAX_PICTURES)
    try:
        write_text_atomic(out, page)
    except OSError as exc:
        raise MeasurementError(f"-o {out}: cannot write the page ({exc})") from None
    return out


def _scene(frames: list, camera: Any, size: tuple[int, int]) -> dict:
    """The scene's layout: axes in mm and, with a camera, its viewpoint (axes spanning the
    points' box, aspect ratios in proportion)."""
    scene: dict = {
        "aspectmode": "data",
        "xaxis": {"title": {"text": "x (mm)"}},
        "yaxis": {"title": {"text": "y (mm)"}},
        "zaxis": {"title": {"text": "z (mm)"}},
    }
    xyz = np.concatenate([f[1] for f in frames]) if frames else np.zeros((0, 3))
    if camera is None or not len(xyz):
        return scene
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    hi = np.maximum(hi, lo + 1e-3)  # a flat cloud keeps a positive side
    unit = float(np.max(hi - lo))
    scene["aspectmode"] = "manual"
    scene["aspectratio"] = dict(zip("xyz", (float(x) for x in (hi - lo) / unit), strict=True))
    for k, a, b in zip("xyz", lo, hi, strict=True):
        scene[f"{k}axis"]["range"] = [float(a), float(b)]
    scene["camera"] = camera_view(camera, size, lo, hi)
    return scene


def _page(fig: Any, pictures: list[str], title: str, *, more: bool) -> str:
    """The whole page: the plot, and beside it the frames' pictures (following the slider)
    where there are any."""
    plot = fig.to_html(
        include_plotlyjs=True,
        full_html=False,
        auto_play=False,
        default_height="95vh",
        config={"displaylogo": False},
        div_id="view",
    )
    if not any(pictures):
        body = plot
    else:
        note = f"<p>pictures of the first {len(pictures)} frames only</p>" if more else ""
        body = (
            '<div style="display:flex;align-items:flex-start">'
            f'<div style="flex:0 0 60%;max-width:60%">{plot}</div>'
            '<div style="flex:0 0 40%;max-width:40%;box-sizing:border-box;padding:8px">'
            f'<img id="picture" alt="the frame and its points" style="width:100%" '
            f'src="{pictures[0]}"><p id="caption">points coloured by slit; magenta: stripe '
            f"centres left out</p>{note}</div></div>"
            "<script>"
            f"const pictures = {json.dumps(pictures)};"
            "const view = document.getElementById('view');"
            "function follow() {"
            "if (!view.on) { setTimeout(follow, 50); return; }"
            "view.on('plotly_sliderchange', e => {"
            "const p = pictures[e.step._index] || '';"
            "const img = document.getElementById('picture');"
            "img.src = p; img.style.visibility = p ? 'visible' : 'hidden';});}"
            "follow();"
            "</script>"
        )
    return (
        '<!DOCTYPE html><html><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title></head>"
        f'<body style="margin:0;background:{_BACKGROUND}">{body}</body></html>'
    )
