"""Automatic calibration on a simulated capture: slit-plane residuals and triangulation error.

Simulates ``simulate_capture(out, ["plane"], RigSpec(), seed=0)`` (full size, 1280x1024;
``--half``: the tests' half-size capture, ``["holes", "steps"]``, ``RigSpec().scaled(0.5)``,
seed 3) unless ``out`` already holds a capture, runs
``calibrate_capture(out)`` (automatic projector calibration, the default) and prints:

- the per-slit residual of the automatic points to their planes (median and max, mm), the
  number of slits with a plane, and the RMS over all their points;
- the RMS error (mm) of true stripe points (true pixels on the true planes, from the scan's
  truth) triangulated with the calibration, as ``tests/test_calibrate.py::truth_triangulation``.

``--zoo SEED ...``: zoo rigs instead (``simulate_zoo_capture(out/zoo_SEED_WxH, SEED,
scenes=1, max_size=--size)``, simulated unless present); per rig, calibrated from the target
alone (``references=False``) and with the reference boards (the default): slits planed, the
RMS error of true stripe points of the scan against the truth, the worst slit's, and whether
every slit seen on the reference boards has a plane.

Usage::

    .venv/bin/python benchmarks/bench_calibration.py /tmp/calib_full/cap
    .venv/bin/python benchmarks/bench_calibration.py /tmp/calib_full/cap --no-refine
    .venv/bin/python benchmarks/bench_calibration.py /tmp/calib_full/cap --no-references
    .venv/bin/python benchmarks/bench_calibration.py /tmp/zoo --zoo 0 1 2 1000 1001 1002
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
from multislit.calibrate import calibrate_capture, format_report
from multislit.calibrate.camera import rms
from multislit.geometry import camera_from_dict
from multislit.reconstruct import triangulate


def truth_errors(
    capture: Path, cal, scan: str = "plane", per_slit: bool = False, true_planes: bool = False
) -> tuple[float, np.ndarray] | tuple[float, np.ndarray, np.ndarray]:
    """Share of valid triangulations and errors (mm) of true points of ``scan``'s truth.

    With ``per_slit``, also each error's slit number; with ``true_planes``, triangulated with
    the calibration's camera and the true slit planes (the camera's share of the error).
    """
    m = json.loads((capture / "truth" / "models.json").read_text())
    cam, planes = camera_from_dict(m["camera"]), np.array(m["projector"]["planes"])
    tr = np.load(capture / "truth" / f"{scan}.npz")
    vv, uu = np.nonzero(tr["slit"] >= 0)
    X = tr["xyz"][vv, uu].astype(float)
    k = tr["slit"][vv, uu].astype(np.intp)
    X = X - (np.einsum("ij,ij->i", X, planes[k, :3]) + planes[k, 3])[:, None] * planes[k, :3]
    sel = np.arange(0, len(X), 7)
    X, k = X[sel], k[sel]
    use = planes if true_planes else cal.slit_planes.planes
    Y, ok = triangulate(cal.camera, use, cam.project(X), k)
    cal_ok = cal.slit_planes.valid[k]
    share = float(ok[cal_ok].mean())
    ok &= cal_ok
    err = np.linalg.norm(Y[ok] - X[ok], axis=1)
    return (share, err, k[ok]) if per_slit else (share, err)


def zoo_rig(out: Path, seed: int, size: tuple[int, int]) -> None:
    """Print the figures of one zoo rig, calibrated without and with the reference boards."""
    from multislit.calibrate.boards import reference_stripes
    from multislit.io import Capture
    from multislit.sim.zoo import simulate_zoo_capture

    cap_dir = out / f"zoo_{seed}_{size[0]}x{size[1]}"
    if not (cap_dir / "rig.json").is_file():
        simulate_zoo_capture(cap_dir, seed, scenes=1, max_size=size, overwrite=True)
    cap = Capture.open(cap_dir)
    shown = reference_stripes(cap).shown()
    scan = sorted((cap_dir / "scans").glob("*.png"))[0].stem
    for refs in (False, True):
        t0 = time.perf_counter()
        try:
            r = calibrate_capture(cap, references=refs)
        except ValueError as exc:
            print(f"seed {seed} {'boards' if refs else 'target'}: error {exc}")
            continue
        secs = time.perf_counter() - t0
        valid = r.calibration.slit_planes.valid
        _, err, k = truth_errors(cap_dir, r.calibration, scan, per_slit=True)
        per = np.array([rms(err[k == j]) if np.any(k == j) else np.nan for j in range(len(valid))])
        worst = int(np.nanargmax(per))
        _, cam_err = truth_errors(cap_dir, r.calibration, scan, true_planes=True)
        print(
            f"seed {seed} ({cap.image_size[0]}x{cap.image_size[1]}, {len(valid)} slits) "
            f"{'target+boards' if refs else 'target only  '}: planed {int(valid.sum())}/"
            f"{len(valid)} (missing {np.flatnonzero(~valid).tolist()}), seen on boards and "
            f"unplaned {np.flatnonzero(shown & ~valid).tolist()}; true pixels RMS "
            f"{rms(err):.4f} mm, worst slit {worst} {per[worst]:.4f} mm (the camera alone, "
            f"true planes: {rms(cam_err):.4f} mm); {secs:.1f} s"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="capture folder (simulated here if missing)")
    ap.add_argument("--half", action="store_true", help="half-size rig (as the tests)")
    ap.add_argument("--no-refine", action="store_true", help="extraction's centres only")
    ap.add_argument(
        "--refine", type=json.loads, default=None, help="refine_centres keyword arguments (JSON)"
    )
    ap.add_argument(
        "--no-references", action="store_true", help="the target alone (no reference boards)"
    )
    ap.add_argument("--zoo", type=int, nargs="+", help="zoo seeds: rigs under OUT")
    ap.add_argument(
        "--size", default="1280x1024", help="zoo: largest image WxH (default 1280x1024)"
    )
    args = ap.parse_args()
    if args.zoo:
        size = tuple(int(x) for x in args.size.lower().split("x"))
        for seed in args.zoo:
            zoo_rig(args.out, seed, size)
        return
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
    r = calibrate_capture(args.out, references=not args.no_references)
    secs = time.perf_counter() - t0
    sp = r.calibration.slit_planes
    scan = "holes" if (args.out / "truth" / "holes.npz").is_file() else "plane"
    share, err, k = truth_errors(args.out, r.calibration, scan, per_slit=True)
    per = np.array([rms(err[k == j]) if np.any(k == j) else np.nan for j in range(len(sp.valid))])
    print("\n".join(format_report(r)))
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
    worst = int(np.nanargmax(per))
    print(f"true points per slit: worst slit {worst} {per[worst]:.4f} mm")
    print(f"calibration {secs:.1f} s")


if __name__ == "__main__":
    main()
