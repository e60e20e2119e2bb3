"""Single-shot pipeline speed per frame at full size (1280x1024), one core.

Stages timed per frame: slit/dot extraction, identification, centre refinement (what
``scan_image`` does by default), triangulation; the reference is prepared beforehand (once per
rig). The slit planes and camera for triangulation are the
simulator's true models (the timing does not depend on their values). The floor a frame cannot
beat is one cv2.medianBlur pass over the same frame.

Run:  .venv/bin/python benchmarks/bench_speed.py [--slits 25 49] [--repeat 7]
(OpenCV is pinned to one thread and the BLAS behind NumPy's matrix products too -- the script
re-executes itself with OPENBLAS/OMP/MKL_NUM_THREADS=1: "one core".)

Identification uses data derived from the reference alone (window sums of the dot images, a
transposed copy), built on first use and kept with the reference: once per rig. It is timed
separately ("reference precompute") and not part of the per-frame times.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from multislit.geometry import PinholeCamera
from multislit.identify import identify, prepare_reference, template_size
from multislit.io import Capture
from multislit.reconstruct import triangulate
from multislit.sim import RigSpec, simulate_capture
from multislit.stripes import extract_slits, refine_centres


def run(num_slits: int, repeat: int, workdir: Path) -> dict:
    spec = RigSpec()
    if num_slits != 25:
        spec = replace(
            spec, slits=replace(spec.slits, num_slits=num_slits, pitch_um=34.0 * num_slits / 25)
        )
    cap_dir = simulate_capture(workdir / f"cap{num_slits}", ["holes", "steps"], spec, seed=1)
    cap = Capture.open(cap_dir)
    ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
    models = json.loads((cap_dir / "truth" / "models.json").read_text())
    cam = PinholeCamera.from_dict(models["camera"])
    planes = np.array(models["projector"]["planes"])
    t0 = time.perf_counter()
    ref.window_sums(*template_size(ref))
    ref.dots_transposed()
    precompute_ms = 1e3 * (time.perf_counter() - t0)
    rows = []
    for p in cap.scans:
        img = cap.image(p)
        t_med, t_ex, t_id, t_ref, t_tri, npts = [], [], [], [], [], 0
        for _ in range(repeat):
            t0 = time.perf_counter()
            cv2.medianBlur(img, 5)
            t1 = time.perf_counter()
            ex = extract_slits(
                img, stripe_width_px=ref.stripe_width_px, dot_size_px=ref.dot_size_px
            )
            t2 = time.perf_counter()
            ident = identify(img, ref, extraction=ex)
            t3 = time.perf_counter()
            u, _ = refine_centres(
                img, ident.u, ident.v, ident.segment, ex.stripe_width_px, ex.dot_size_px
            )
            t4 = time.perf_counter()
            ok = ident.identified
            pts, valid = triangulate(cam, planes, np.c_[u[ok], ident.v[ok]], ident.slit[ok])
            t5 = time.perf_counter()
            t_med.append(t1 - t0)
            t_ex.append(t2 - t1)
            t_id.append(t3 - t2)
            t_ref.append(t4 - t3)
            t_tri.append(t5 - t4)
            npts = int(valid.sum())
        total = statistics.median(np.add(np.add(np.add(t_ex, t_id), t_ref), t_tri))
        rows.append(
            {
                "slits": num_slits,
                "scene": p.stem,
                "points": npts,
                "median_blur_ms": 1e3 * statistics.median(t_med),
                "extract_ms": 1e3 * statistics.median(t_ex),
                "identify_ms": 1e3 * statistics.median(t_id),
                "refine_ms": 1e3 * statistics.median(t_ref),
                "triangulate_ms": 1e3 * statistics.median(t_tri),
                "total_ms": 1e3 * total,
                "points_per_s": npts / total,
                "precompute_ms": precompute_ms,
            }
        )
    return rows


_ONE_THREAD = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main() -> None:
    if any(os.environ.get(k) != "1" for k in _ONE_THREAD):
        # the BLAS reads its thread count when NumPy is loaded: start again with one thread
        os.environ.update(dict.fromkeys(_ONE_THREAD, "1"))
        os.execv(sys.executable, [sys.executable, *sys.argv])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--slits", type=int, nargs="+", default=[25, 49], help="rigs to time (default 25 49)"
    )
    ap.add_argument(
        "--repeat", type=int, default=5, help="runs per frame; the median is kept (default 5)"
    )
    args = ap.parse_args()
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as d:
        rows = [r for n in args.slits for r in run(n, args.repeat, Path(d))]
    print(
        "| slits | scene | points | medianBlur ms | extract ms | identify ms | refine ms | triangulate ms | total ms | x medianBlur | points/s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['slits']} | {r['scene']} | {r['points']} | {r['median_blur_ms']:.1f} | {r['extract_ms']:.1f} | "
            f"{r['identify_ms']:.1f} | {r['refine_ms']:.1f} | {r['triangulate_ms']:.1f} | {r['total_ms']:.1f} | "
            f"{r['total_ms'] / r['median_blur_ms']:.0f} | {r['points_per_s']:.0f} |"
        )
    for n in args.slits:
        ms = next(r["precompute_ms"] for r in rows if r["slits"] == n)
        print(f"\nreference precompute (once per rig), {n} slits: {ms:.0f} ms")


if __name__ == "__main__":
    main()
