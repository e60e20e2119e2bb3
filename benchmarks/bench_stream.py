"""Frames per second of ``multislit stream`` (1 and 2 worker processes) and ``multislit batch``
(a local Dask cluster of 2 worker processes) on simulated frames.

A capture of the default rig (25 slits) is simulated and calibrated (hand readings); its scans
(holes plate, steps, spheres, free-form body) are repeated to make a folder of frames. Each
run writes the PLY files and ``frames.jsonl`` of an OUT folder, as the commands do. "frames per
second" counts from the first frame read to the last frame written (worker start-up included);
"after the first frame" from the first frame written to the last (start-up left out); "wall" is
the whole call, with the reference preparation (once per run) and the cluster's start. The
package's kernels are compiled before the runs (``multislit.compile_kernels``), so that Numba's
cache holds them for every process; each worker loads them as it starts.

Run:  .venv/bin/python benchmarks/bench_stream.py [--scale 0.5] [--frames 24] [--no-write]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from results import command_line, write_section  # noqa: E402

from multislit import compile_kernels  # noqa: E402
from multislit.app.batch import batch  # noqa: E402
from multislit.app.stream import stream  # noqa: E402
from multislit.calibrate import calibrate_capture, write_calibration  # noqa: E402
from multislit.sim import RigSpec, simulate_capture  # noqa: E402

SCENES = ["holes", "steps", "spheres", "freeform"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.5, help="camera resolution factor")
    ap.add_argument("--frames", type=int, default=24, help="frames per run")
    ap.add_argument("--no-write", action="store_true", help="do not update RESULTS.md")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        spec = RigSpec().scaled(args.scale) if args.scale != 1.0 else RigSpec()
        print("simulating and calibrating ...", flush=True)
        cap = simulate_capture(work / "cap", SCENES, spec, seed=5)
        write_calibration(calibrate_capture(cap, source="hand"), cap / "calibration.json")
        frames = work / "frames"
        frames.mkdir()
        for i in range(args.frames):
            name = SCENES[i % len(SCENES)]
            shutil.copy(cap / "scans" / f"{name}.png", frames / f"f{i:04d}_{name}.png")
        # compiled code in Numba's cache first, for the workers too (each loads it as it starts)
        compile_kernels()
        rows = []
        stamps: list[float] = []

        def progress(summary, final=False):
            if not final:
                stamps.append(time.perf_counter())

        load = os.getloadavg()[0]
        runs = [
            ("stream, 1 worker", lambda out: stream(cap, frames, out, progress=progress)),
            (
                "stream, 2 worker processes",
                lambda out: stream(cap, frames, out, workers=2, progress=progress),
            ),
            (
                "batch, Dask local cluster, 2 worker processes",
                lambda out: batch(cap, frames, out, progress=progress),
            ),
        ]
        for i, (label, run) in enumerate(runs):
            stamps.clear()
            t0 = time.perf_counter()
            s = run(work / f"out{i}")
            wall = time.perf_counter() - t0
            steady = (len(stamps) - 1) / (stamps[-1] - stamps[0])
            rows.append((label, s.frames, s.fps, steady, wall))
            print(
                f"{label}: {s.frames} frames, {s.fps:.2f} fps, after the first frame "
                f"{steady:.2f} fps, wall {wall:.1f} s",
                flush=True,
            )
    w, h = spec.camera.image_size
    lines = [
        f"{args.frames} simulated frames of {w}x{h} px, {spec.slits.num_slits} slits "
        f"({', '.join(SCENES)} in turn), PLY and index written; 2-core machine (one worker: "
        "OpenCV's and Numba's threads on both cores; worker processes: one thread each); load "
        f"average {load:.1f} before the runs (other work on the machine slows every figure).",
        "",
        "| run | frames | frames per second | after the first frame | wall, s |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {lab} | {n} | {fps:.2f} | {steady:.2f} | {wall:.1f} |"
        for lab, n, fps, steady, wall in rows
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        write_section(
            "stream",
            "Frames per second: stream and batch",
            text,
            command_line("bench_stream.py"),
        )


if __name__ == "__main__":
    main()
