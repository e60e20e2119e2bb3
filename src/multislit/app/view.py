"""An interactive 3D view of point clouds as one self-contained HTML page (``multislit view``).

The page is drawn with Plotly, whose JavaScript is written into the page, so it opens without a
network. Drag to rotate, scroll to zoom; buttons colour the points by depth (z in the target
frame, mm) or by slit number; for an OUT folder of ``multislit stream`` a slider steps through
the frames.

Needs Plotly (the optional extra ``pip install 'multislit[view]'``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from multislit.app.index import INDEX_FILE, frame_file, read_index
from multislit.errors import MeasurementError
from multislit.io import read_ply, write_text_atomic
from multislit.io.paths import as_path

__all__ = ["load_frames", "write_view"]


_MARKER_PX = 2
_DEPTH_SCALE = "Viridis"
_SLIT_SCALE = "Turbo"
_BACKGROUND = "white"
_MAX_TOTAL_POINTS = 2_000_000  # over all frames: keeps a long sequence's page openable


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
    p = as_path(source, "source", error=MeasurementError)
    if p.is_dir():
        index = p / INDEX_FILE
        if index.is_file():
            entries = [(frame_file(d["frame"]), d["source"]) for d in read_index(index)]
        else:
            entries = [(q.name, "") for q in sorted(p.glob("frame_*.ply"))]
        if not entries:
            raise MeasurementError(f"{p}: no frames (frame_*.ply) in the folder")
        files = [(p / name, f"{Path(name).stem} {src}".strip()) for name, src in entries]
    elif p.is_file():
        files = [(p, p.name)]
    else:
        raise MeasurementError(f"{p}: no such PLY file or folder")
    out = []
    for path, label in files:
        d = read_ply(path)
        if not {"x", "y", "z"} <= set(d):
            raise MeasurementError(f"{path}: the PLY has no x y z properties")
        out.append((label, d))
    return out


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

    loaded = load_frames(source)
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
        "scene": {
            "aspectmode": "data",
            "xaxis": {"title": {"text": "x (mm)"}},
            "yaxis": {"title": {"text": "y (mm)"}},
            "zaxis": {"title": {"text": "z (mm)"}},
        },
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
    fig.update_layout(**layout)
    html = fig.to_html(
        include_plotlyjs=True,
        full_html=True,
        auto_play=False,
        default_height="95vh",
        config={"displaylogo": False},
    )
    try:
        write_text_atomic(out, html)
    except OSError as exc:
        raise MeasurementError(f"-o {out}: cannot write the page ({exc})") from None
    return out
