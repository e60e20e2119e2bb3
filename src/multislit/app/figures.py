"""Figures like the paper's (matplotlib, Agg; imported lazily so the core does not need it).

* :func:`slit_addresses_figure` -- the captured image with each identified stripe point drawn
  in its slit's colour and numbered (paper Fig. 23; Fig. 28a).
* :func:`point_cloud_figure` -- the measured points in the target frame, coloured by depth
  (paper Fig. 24 and 28b).
* :func:`hole_edges_figure` -- the hole-edge points in the plate's plane with the fitted
  circles and their diameters (paper Fig. 28c).

Each writes a PNG and returns its path. Install the ``figures`` extra for matplotlib.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from multislit.errors import MultislitError

__all__ = ["slit_addresses_figure", "point_cloud_figure", "hole_edges_figure"]


def _figure(width: float, height: float) -> Any:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - depends on the environment
        raise MultislitError(
            "figures need matplotlib: pip install 'multislit[figures]' (or matplotlib)"
        ) from None
    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | Path) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=fig.dpi, facecolor=fig.get_facecolor())
    return p


def _slit_colours(n: int) -> np.ndarray:
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    # neighbouring slits get clearly different colours (tab10 without its grey, which would
    # look like the white of unidentified points); the 9 colours repeat every 9 slits
    idx = [0, 1, 2, 3, 4, 5, 6, 8, 9]
    return np.array([cmap(idx[k % 9]) for k in range(max(n, 1))])


def slit_addresses_figure(
    image: ArrayLike,
    u: ArrayLike,
    v: ArrayLike,
    slit: ArrayLike,
    path: str | Path,
    title: str = "Slit addresses",
    num_slits: int | None = None,
    unidentified_uv: ArrayLike | None = None,
) -> Path:
    """The image with identified stripe points in their slit's colour (paper Fig. 23).

    Parameters
    ----------
    image : (H, W) uint8/uint16, the scan
    u, v : (K,) px, stripe points; slit : (K,) int slit number (-1: not identified)
    path : PNG to write
    num_slits : number of slits (colours); default from ``slit``
    unidentified_uv : (M, 2) px, points that were found but not identified (drawn white)
    """
    img = np.asarray(image, dtype=float)
    h, w = img.shape
    u = np.asarray(u, float)
    v = np.asarray(v, float)
    s = np.asarray(slit).astype(int)
    n = int(num_slits or (s.max() + 1 if s.size else 1))
    fig = _figure(10.0, 10.0 * h / w + 0.6)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0 - 0.6 / (10.0 * h / w + 0.6)))
    hi = np.percentile(img, 99.8) or 1.0
    fig.set_facecolor("black")
    ax.imshow(img, cmap="gray", vmin=0, vmax=hi * 2.5, interpolation="nearest")
    if unidentified_uv is not None:
        q = np.asarray(unidentified_uv, float).reshape(-1, 2)
        ax.scatter(q[:, 0], q[:, 1], s=1.5, c="white", marker="s", linewidths=0)
    m = s >= 0
    col = _slit_colours(n)
    ax.scatter(u[m], v[m], s=2.0 * 1000.0 / w, c=col[s[m]], marker="s", linewidths=0)
    # the slit number once per slit, at the middle of its longest run of points
    for k in np.unique(s[m]):
        sel = s == k
        # staggered along the slit (30 / 50 / 70 % of its points) so that labels do not overlap
        j = np.argsort(v[sel])[int(sel.sum() * (0.3, 0.5, 0.7)[k % 3])]
        ax.text(
            u[sel][j] + 3,
            v[sel][j],
            str(k),
            color=col[k],
            fontsize=8,
            fontweight="bold",
            bbox={"facecolor": "black", "alpha": 0.6, "pad": 1, "linewidth": 0},
        )
    ax.set_xlim(0, w - 1)
    ax.set_ylim(h - 1, 0)
    ax.set_axis_off()
    fig.suptitle(title, fontsize=11, color="white")
    return _save(fig, path)


def point_cloud_figure(
    points: ArrayLike,
    path: str | Path,
    title: str = "Measured points",
    max_points: int = 30000,
    elev: float = 25.0,
    azim: float = -60.0,
) -> Path:
    """The measured points: a 3-D view and a front view (x-y), coloured by depth z.

    Parameters
    ----------
    points : (N, 3) mm, target frame
    path : PNG to write
    max_points : at most this many points are drawn (evenly subsampled)
    """
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) > max_points:
        p = p[:: int(np.ceil(len(p) / max_points))]
    fig = _figure(13.0, 6.0)
    if len(p) == 0:
        ax = fig.add_subplot(1, 1, 1)
        ax.text(0.5, 0.5, "no points", ha="center", va="center")
        ax.set_axis_off()
        fig.suptitle(title)
        return _save(fig, path)
    lo, hi = np.percentile(p[:, 2], [1, 99])
    if hi <= lo:
        lo, hi = lo - 1, hi + 1
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    sc = ax.scatter(
        p[:, 0], p[:, 2], p[:, 1], c=p[:, 2], cmap="viridis", vmin=lo, vmax=hi, s=0.5,
        linewidths=0,
    )  # fmt: skip
    ax.set_xlabel("X [mm]")
    ax.set_ylabel("Z [mm]")
    ax.set_zlabel("Y [mm]")
    ax.view_init(elev=elev, azim=azim)
    # robust limits: a few far points (e.g. a wall seen through a hole) must not shrink the view
    plo, phi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
    rng = max(float((phi - plo).max()) / 2 * 1.1, 1.0)
    mid = (plo + phi) / 2
    ax.set_xlim(mid[0] - rng, mid[0] + rng)
    ax.set_ylim(mid[2] - rng, mid[2] + rng)
    ax.set_zlim(mid[1] - rng, mid[1] + rng)
    ax.set_title("3-D view")
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.scatter(p[:, 0], p[:, 1], c=p[:, 2], cmap="viridis", vmin=lo, vmax=hi, s=0.5,
                linewidths=0)  # fmt: skip
    ax2.set_xlim(mid[0] - rng, mid[0] + rng)
    ax2.set_ylim(mid[1] - rng, mid[1] + rng)
    ax2.set_aspect("equal")
    ax2.set_xlabel("X [mm]")
    ax2.set_ylabel("Y [mm]")
    ax2.set_title("front view (colour: depth Z)")
    cb = fig.colorbar(sc, ax=[ax, ax2], shrink=0.8, pad=0.02)
    cb.set_label("Z [mm]")
    fig.suptitle(f"{title} ({len(points)} points)", fontsize=11)
    return _save(fig, path)


def hole_edges_figure(
    measurement: Any,
    path: str | Path,
    points: ArrayLike | None = None,
    title: str = "Hole edges and fitted circles",
    truth: list[dict] | None = None,
) -> Path:
    """Hole-edge points in the plate's plane with the fitted circles (paper Fig. 28c).

    Parameters
    ----------
    measurement : a :class:`~multislit.measure.HoleMeasurement`
    path : PNG to write
    points : (N, 3) mm, the scan's points, drawn faintly (plate points only)
    truth : optional list of {"centre": xyz, "diameter": mm}: the true holes (dashed)
    """
    from multislit.geometry import project_to_plane

    pl = np.asarray(measurement.plane, float)
    fig = _figure(10.0, 7.0)
    ax = fig.add_subplot(1, 1, 1)
    if points is not None:
        p = np.asarray(points, float).reshape(-1, 3)
        on = np.abs(p @ pl[:3] + pl[3]) < 2.0
        q = project_to_plane(p[on], pl)
        ax.scatter(q[:, 0], q[:, 1], s=0.2, c="0.75", linewidths=0, label="plate points")
    e = measurement.edges
    if len(e):
        qe = project_to_plane(e.points, pl)
        ax.scatter(qe[:, 0], qe[:, 1], s=14, c="tab:red", marker="x", label="edge points")
    t = np.linspace(0, 2 * np.pi, 361)
    if truth:
        for k, tr in enumerate(truth):
            c = project_to_plane(np.asarray(tr["centre"], float)[None], pl)[0]
            r = tr["diameter"] / 2
            ax.plot(c[0] + r * np.cos(t), c[1] + r * np.sin(t), "--", color="0.4", lw=0.8,
                    label="true holes" if k == 0 else None)  # fmt: skip
    first = True
    for h in measurement.holes:
        c = project_to_plane(np.asarray(h.centre, float)[None], pl)[0]
        if h.measurable:
            r = h.diameter / 2
            ax.plot(c[0] + r * np.cos(t), c[1] + r * np.sin(t), color="tab:blue", lw=1.2,
                    label="fitted circles" if first else None)  # fmt: skip
            first = False
            ax.annotate(
                f"D = {h.diameter:.2f} mm\n{h.n_inliers} edges, {h.n_slits} slits",
                (c[0], c[1] + r),
                xytext=(0, 6),
                textcoords="offset points",
                ha="center",
                fontsize=8,
                color="tab:blue",
            )
        else:
            ax.annotate(
                "not measurable", (c[0], c[1]), fontsize=7, color="0.3", ha="center",
                xytext=(0, -10), textcoords="offset points",
            )  # fmt: skip
    if len(e):
        lo = qe.min(axis=0) - 30
        hi = qe.max(axis=0) + 30
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("in-plane e1 [mm]")
    ax.set_ylabel("in-plane e2 [mm]")
    ax.legend(loc="lower right", fontsize=8, markerscale=1.5)
    fig.suptitle(f"{title} ({measurement.method} edges)", fontsize=11)
    return _save(fig, path)
