"""Simulator speed: time to render one image of each scene at full size (1280x1024).

Run: .venv/bin/python benchmarks/bench_sim.py  (prints a table; median of 3 renders per scene)
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from multislit.sim import (
    SCENES,
    SimulatedRig,
    make_scene,
    reference_board,
    render,
    standard_object,
)
from multislit.sim.render import camera_rays


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    rig = SimulatedRig.build()
    camera_rays(rig)  # the per-camera ray table is built once per rig, not per image
    rng = np.random.default_rng(0)
    scenes = [
        ("reference board", reference_board(900), True),
        ("target (markers)", standard_object()[0], False),
    ]
    scenes += [(name, make_scene(name), True) for name in SCENES]
    w, h = rig.camera.image_size
    print(f"render time per {w}x{h} image, median of 3 (2-core machine), seconds")
    for name, scene, lasers in scenes:
        ts = []
        for _ in range(3):
            t = time.perf_counter()
            render(rig, scene, rng, lasers=lasers)
            ts.append(time.perf_counter() - t)
        print(f"  {name:<18s} {statistics.median(ts):6.2f}")


if __name__ == "__main__":
    main()
