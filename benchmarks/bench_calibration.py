"""Automatic calibration on a simulated capture: slit-plane residuals and triangulation error.

Simulates ``simulate_capture(out, ["plane"], RigSpec(), seed=0)`` (full size, 1280x1024;
``--half``: the tests' half-size capture, ``["holes", "steps"]``, ``RigSpec().scaled(0.5)``,
seed 3) unless ``out`` already holds a capture, runs
``calibrate_capture(out)`` (automatic projector calibration, the default) and prints:

- the per-slit residual of the automatic points to their planes (median and max, mm), the
  number of slits with a plane, and the RMS over all their points;
- the RMS error (mm) of true stripe points (true pixels on the true planes, from the scan's
  truth) triangulated with the calibration, as ``tests/test_calibrate.py::truth_triangulation``.

Usage::

    PYTHONPATH=src python benchmarks/bench_calibration.py /tmp/calib_full/cap
    PYTHONPATH=src python benchmarks/bench_calibration.py /tmp/calib_full/cap --no-refine
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import numpy as np

import multislit.calibrate.pipeline as pipeline
import multislit.calibrate.slit_points as slit_points
from multislit.calibrate import calibrate_capture
from multislit.calibrate.camera import rms
from multislit.geometry import camera_from_dict
from multislit.reconstruct import triangulate


def truth_errors(capture: Path, cal, scan: str = "plane") -> tuple[float, np.ndarray]:
    """Share of valid triangulations and errors (mm) of true points of ``scan``'s truth."""
    m = json.loads((capture / "truth" / "models.json").read_text())
    cam, planes = camera_from_dict(m["camera"]), np.array(m["projector"]["planes"])
    tr = np.load(capture / "truth" / f"{scan}.npz")
    vv, uu = np.nonzero(tr["slit"] >= 0)
    X = tr["xyz"][vv, uu].astype(float)
    k = tr["slit"][vv, uu].astype(np.intp)
    X = X - (np.einsum("ij,ij->i", X, planes[k, :3]) + planes[k, 3])[:, None] * planes[k, :3]
    sel = np.arange(0, len(X), 7)
    X, k = X[sel], k[sel]
    Y, ok = triangulate(cal.camera, cal.slit_planes.planes, cam.project(X), k)
    cal_ok = cal.slit_planes.valid[k]
    share = float(ok[cal_ok].mean())
    ok &= cal_ok
    return share, np.linalg.norm(Y[ok] - X[ok], axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="capture folder (simulated here if missing)")
    ap.add_argument("--half", action="store_true", help="half-size rig (as the tests)")
    ap.add_argument("--no-refine", action="store_true", help="extraction's centres only")
    ap.add_argument(
        "--refine", type=json.loads, default=None, help="refine_centres keyword arguments (JSON)"
    )
    args = ap.parse_args()
    if not (args.out / "rig.json").is_file():
        from multislit.sim.rig import RigSpec
        from multislit.sim.simulate import simulate_capture

        if args.half:
            simulate_capture(args.out, ["holes", "steps"], RigSpec().scaled(0.5), seed=3)
        else:
            simulate_capture(args.out, ["plane"], RigSpec(), seed=0)
    # benchmark-only switches: the extraction's centres, or other refine_centres settings
    if args.no_refine:
        pipeline.auto_slit_points = functools.partial(slit_points.auto_slit_points, refine=False)
    elif args.refine is not None:
        slit_points._REFINE = args.refine
    t0 = time.perf_counter()
    r = calibrate_capture(args.out)
    secs = time.perf_counter() - t0
    sp = r.calibration.slit_planes
    scan = "holes" if (args.out / "truth" / "holes.npz").is_file() else "plane"
    share, err = truth_errors(args.out, r.calibration, scan)
    print(f"source {r.source}, {len(r.points)} points, steps {dict(r.points.steps)}")
    print(
        f"slit planes: {int(sp.valid.sum())} of {len(sp.valid)} slits, residual median "
        f"{np.nanmedian(sp.rms_mm):.4f} mm, max {np.nanmax(sp.rms_mm):.4f} mm "
        f"(from axis: {list(sp.from_axis)})"
    )
    fit = np.isfinite(sp.rms_mm) & (sp.counts > 0)
    pooled = np.sqrt(np.sum(sp.counts[fit] * sp.rms_mm[fit] ** 2) / np.sum(sp.counts[fit]))
    print(f"slit-plane RMS over all {int(sp.counts[fit].sum())} points: {pooled:.4f} mm")
    print(f"true points: {share:.4f} valid, RMS {rms(err):.4f} mm vs truth ({len(err)} points)")
    print(f"calibration {secs:.1f} s")


if __name__ == "__main__":
    main()
