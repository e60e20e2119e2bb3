"""The demo: the paper's experiment on the simulated rig.

Stages available so far: simulate the rig (standard object, reference boards, the holes plate and
a scene with steps) and write a contact sheet of the captured images to look at.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .capture import Capture
from .sim.rig import RigSpec
from .sim.simulate import Progress, simulate_capture


def contact_sheet(paths: list[Path], labels: list[str], tile_width: int = 640) -> np.ndarray:
    """Tile images (3 per row) scaled to ``tile_width`` with a label on each; (H, W) uint8."""
    tiles = []
    for p, label in zip(paths, labels, strict=True):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img.dtype != np.uint8:
            img = (img / 257).astype(np.uint8)
        h, w = img.shape
        t = cv2.resize(img, (tile_width, round(h * tile_width / w)), interpolation=cv2.INTER_AREA)
        cv2.putText(t, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, 255, 2, cv2.LINE_AA)
        tiles.append(t)
    while len(tiles) % 3:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i : i + 3]) for i in range(0, len(tiles), 3)]
    return np.vstack(rows)


def run_demo(
    out: Path, seed: int = 0, scale: float = 1.0, progress: Progress | None = None
) -> dict[str, Any]:
    """Run the demo, writing everything into ``out``; returns the figures and report lines."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = RigSpec() if scale == 1.0 else RigSpec().scaled(scale)
    t0 = time.perf_counter()
    cap_dir = simulate_capture(
        out / "capture", ["holes", "steps"], spec, seed=seed, progress=progress, overwrite=True
    )
    t_sim = time.perf_counter() - t0
    cap = Capture.open(cap_dir)
    paths = [cap.markers_image, cap.slits_image, *cap.references[:1], *cap.scans]
    labels = ["calibration/markers", "calibration/slits", f"reference/{cap.references[0].name}"]
    labels += [f"scans/{p.name}" for p in cap.scans]
    sheet = contact_sheet(paths, labels)
    sheet_path = out / "capture_overview.png"
    cv2.imwrite(str(sheet_path), sheet)
    n_images = 2 + len(cap.references) + len(cap.scans)
    w, h = cap.image_size
    report = [
        f"simulated capture: {cap_dir} ({n_images} images, {w}x{h} px, {cap.num_slits} slits)",
        f"  markers on the standard object: {len(cap.target.markers)}; faces: {len(cap.target.faces)}",
        f"  reference boards: {', '.join(p.stem for p in cap.references)}",
        f"  scans: {', '.join(p.stem for p in cap.scans)}",
        f"  simulation time: {t_sim:.1f} s ({t_sim / n_images:.2f} s per image)",
        f"overview of the captured images: {sheet_path}",
    ]
    return {
        "capture": str(cap_dir),
        "image_size": [w, h],
        "num_slits": cap.num_slits,
        "images": n_images,
        "simulation_seconds": round(t_sim, 2),
        "overview": str(sheet_path),
        "report": report,
    }
