"""Calibration against the truth of simulated captures: the camera and the triangulation.

Per capture, ``calibrate_capture`` (automatic points on the slits and the reference boards, the
default; ``--hand`` for the paper's hand readings) is compared with the simulator's truth:

- **camera**: true 3D points of the three reference boards (every 8th pixel of each board's
  truth, the whole image at the near, middle and far end of the measuring volume) projected by
  the calibrated camera, against their true pixels: RMS over all, in the image's four corner
  cells of a 3 x 3 grid, in the centre cell, the largest, and per board;
- **triangulation**: true stripe pixels of the scan (true pixels of points on the true slit
  planes) triangulated with the calibration against their true 3D points (RMS, mm; the worst
  slit's; and with the calibrated camera and the true planes, the camera's share);
- the **depth of 0.03 px**: the RMS 3D error that a 0.03 px shift across the stripe makes on
  the same true points (true camera and planes), the triangulation tolerance of a rig below
  1 MP.

Captures: ``OUT`` itself (simulated unless present: ``simulate_capture(OUT, ["plane"],
RigSpec(), seed=0)``, the default rig at full size; ``--half``: the tests' half-size capture
``["holes", "steps"]``, ``RigSpec().scaled(0.5)``, seed 3), or with ``--zoo SEED ...`` the zoo
rigs ``OUT/zoo_SEED_WxH`` (``simulate_zoo_capture(..., SEED, scenes=1, max_size=--size)``,
simulated unless present). The goals: camera within 0.03 px RMS over the whole image; true
stripe pixels within 0.05 mm RMS on rigs of 1 MP or more (within the depth of 0.03 px below),
0.02 mm on the default rig.

Usage::

    .venv/bin/python benchmarks/bench_calibration.py /tmp/calib/default
    .venv/bin/python benchmarks/bench_calibration.py /tmp/calib --zoo 1000 1001 1002 1003 1004 1005
    .venv/bin/python benchmarks/bench_calibration.py /tmp/calib --zoo 1000 ... --default --write

``--write`` records the table of the rigs measured (``--default`` adds the default rig) in
benchmarks/RESULTS.md; ``--no-folds`` leaves the target's folds out of the adjustment (its own
section).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from results import command_line, write_section

from multislit.calibrate import calibrate_capture, format_report
from multislit.calibrate.camera import rms
from multislit.geometry import camera_from_dict
from multislit.io import Capture
from multislit.reconstruct import triangulate

#: Goals: camera RMS over the whole image (px); true stripe pixels (mm) on rigs of >= 1 MP and
#: on the default rig; the image error whose depth is the tolerance below 1 MP (px).
CAMERA_GOAL_PX = 0.03
TRIANGULATION_GOAL_MM = 0.05
DEFAULT_GOAL_MM = 0.02
SMALL_RIG_PX = 0.03


def _truth(capture: Path) -> tuple[Any, np.ndarray]:
    m = json.loads((capture / "truth" / "models.json").read_text())
    return camera_from_dict(m["camera"]), np.array(m["projector"]["planes"])


def _true_stripe_points(capture: Path, scan: str) -> tuple[np.ndarray, np.ndarray]:
    """True 3D points (N, 3) mm on the true slit planes, every 7th stripe pixel of ``scan``'s
    truth, and their slits (N,)."""
    _, planes = _truth(capture)
    tr = np.load(capture / "truth" / f"{scan}.npz")
    vv, uu = np.nonzero(tr["slit"] >= 0)
    X = tr["xyz"][vv, uu].astype(float)
    k = tr["slit"][vv, uu].astype(np.intp)
    X = X - (np.einsum("ij,ij->i", X, planes[k, :3]) + planes[k, 3])[:, None] * planes[k, :3]
    sel = np.arange(0, len(X), 7)
    return X[sel], k[sel]


def truth_errors(
    capture: Path, cal, scan: str = "plane", per_slit: bool = False, true_planes: bool = False
) -> tuple[float, np.ndarray] | tuple[float, np.ndarray, np.ndarray]:
    """Share of valid triangulations and errors (mm) of true points of ``scan``'s truth.

    With ``per_slit``, also each error's slit number; with ``true_planes``, triangulated with
    the calibration's camera and the true slit planes (the camera's share of the error).
    """
    cam, planes = _truth(capture)
    X, k = _true_stripe_points(capture, scan)
    use = planes if true_planes else cal.slit_planes.planes
    Y, ok = triangulate(cal.camera, use, cam.project(X), k)
    cal_ok = cal.slit_planes.valid[k]
    share = float(ok[cal_ok].mean())
    ok &= cal_ok
    err = np.linalg.norm(Y[ok] - X[ok], axis=1)
    return (share, err, k[ok]) if per_slit else (share, err)


def depth_of_pixels(capture: Path, scan: str, px: float = SMALL_RIG_PX) -> float:
    """RMS 3D error (mm) that shifting the true stripe pixels by ``px`` across the stripe (along
    the image row, both ways) makes when triangulated with the true camera and planes."""
    cam, planes = _truth(capture)
    X, k = _true_stripe_points(capture, scan)
    uv = cam.project(X)
    errs = []
    for s in (-px, px):
        Y, ok = triangulate(cam, planes, uv + [s, 0.0], k)
        errs.append(np.linalg.norm(Y[ok] - X[ok], axis=1))
    return rms(np.concatenate(errs))


def camera_errors(capture: Path, camera) -> dict[str, float]:
    """Reprojection errors (px) of true 3D points of the reference boards by ``camera``."""
    true_cam, _ = _truth(capture)
    errs, uvs, boards = [], [], {}
    for f in sorted((capture / "truth").glob("ref_*.npz")):
        xyz = np.load(f)["xyz"][::8, ::8].reshape(-1, 3).astype(float)
        xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
        uv = true_cam.project(xyz)
        e = np.linalg.norm(camera.project(xyz) - uv, axis=1)
        errs.append(e)
        uvs.append(uv)
        boards[f.stem] = rms(e)
    e, uv = np.concatenate(errs), np.concatenate(uvs)
    w, h = true_cam.image_size
    cu = np.clip((uv[:, 0] / w * 3).astype(int), 0, 2)
    cv = np.clip((uv[:, 1] / h * 3).astype(int), 0, 2)
    return {
        "rms": rms(e),
        "corners": rms(e[(cu != 1) & (cv != 1)]),
        "centre": rms(e[(cu == 1) & (cv == 1)]),
        "max": float(e.max()),
        "boards": boards,
    }


def measure(capture: Path, source: str = "auto", report: bool = False) -> dict[str, Any]:
    """Calibrate ``capture`` and compare with its truth (see the module docstring)."""
    cap = Capture.open(capture)
    scan = sorted((capture / "scans").glob("*.png"))[0].stem
    t0 = time.perf_counter()
    r = calibrate_capture(cap, source=source)
    secs = time.perf_counter() - t0
    if report:
        print("\n".join(format_report(r)))
    cal = r.calibration
    valid = cal.slit_planes.valid
    _, err, k = truth_errors(capture, cal, scan, per_slit=True)
    per = np.array([rms(err[k == j]) if np.any(k == j) else np.nan for j in range(len(valid))])
    worst = int(np.nanargmax(per))
    _, cam_err = truth_errors(capture, cal, scan, true_planes=True)
    w, h = cap.image_size
    return {
        "capture": capture.name,
        "image": f"{w}x{h}",
        "mp": w * h / 1e6,
        "slits": len(valid),
        "planed": int(valid.sum()),
        "camera": camera_errors(capture, cal.camera),
        "triangulation_mm": rms(err),
        "worst_slit": (worst, float(per[worst])),
        "camera_alone_mm": rms(cam_err),
        "depth_of_003_px_mm": depth_of_pixels(capture, scan),
        "slit_model": getattr(getattr(r, "bundle", None), "kind", "(sequential)"),
        "seconds": secs,
    }


def _tolerance(m: dict[str, Any], default_rig: bool) -> tuple[float, str]:
    if default_rig:
        return DEFAULT_GOAL_MM, f"{DEFAULT_GOAL_MM} mm (default rig)"
    if m["mp"] >= 1.0:
        return TRIANGULATION_GOAL_MM, f"{TRIANGULATION_GOAL_MM} mm"
    d = m["depth_of_003_px_mm"]
    return d, f"{d:.4f} mm (depth of {SMALL_RIG_PX} px; < 1 MP)"


def _row(m: dict[str, Any], default_rig: bool = False) -> str:
    c = m["camera"]
    tol, tol_text = _tolerance(m, default_rig)
    cam_ok = c["rms"] <= CAMERA_GOAL_PX
    tri_ok = m["triangulation_mm"] <= tol
    boards = " / ".join(f"{v:.4f}" for v in c["boards"].values())
    return (
        f"| {m['capture']} | {m['image']} ({m['mp']:.2f} MP) | {m['slits']} "
        f"({m['planed']} planed) | {c['rms']:.4f} / {c['corners']:.4f} / {c['centre']:.4f} "
        f"({boards}) | {'met' if cam_ok else 'missed'} | {m['triangulation_mm']:.4f} (slit "
        f"{m['worst_slit'][0]}: {m['worst_slit'][1]:.4f}; camera alone {m['camera_alone_mm']:.4f}) "
        f"| {tol_text} | {'met' if tri_ok else 'missed'} | {m['slit_model']} | "
        f"{m['seconds']:.1f} |"
    )


HEADER = (
    "| capture | image | slits | camera RMS px: all / corners / centre (near / middle / far "
    "board) | camera goal 0.03 px | true stripe pixels RMS mm | tolerance | triangulation "
    "goal | slit planes | calibration s |\n|---|---|---|---|---|---|---|---|---|---|"
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="capture folder, or the zoo captures' folder")
    ap.add_argument("--half", action="store_true", help="half-size rig (as the tests)")
    ap.add_argument("--hand", action="store_true", help="the hand readings (source='hand')")
    ap.add_argument("--zoo", type=int, nargs="+", help="zoo seeds: rigs under OUT")
    ap.add_argument(
        "--size", default="1280x1024", help="zoo: largest image WxH (default 1280x1024)"
    )
    ap.add_argument(
        "--default", action="store_true", help="with --zoo: also the default rig (OUT/default)"
    )
    ap.add_argument("--write", action="store_true", help="record the table in RESULTS.md")
    ap.add_argument(
        "--no-folds", action="store_true", help="leave the target's folds out of the adjustment"
    )
    args = ap.parse_args()
    if args.no_folds:  # benchmark-only switch: the adjustment without the folds' observations
        import multislit.calibrate.pipeline as pipeline

        real = pipeline.fold_points
        pipeline.fold_points = lambda image, camera, faces: real(image, camera, ())
    source = "hand" if args.hand else "auto"
    rows = []
    if args.zoo:
        from multislit.sim.zoo import simulate_zoo_capture

        size = tuple(int(x) for x in args.size.lower().split("x"))
        if args.default:
            rows.append(_default(args.out / "default", False, source))
        for seed in args.zoo:
            cap_dir = args.out / f"zoo_{seed}_{size[0]}x{size[1]}"
            if not (cap_dir / "rig.json").is_file():
                simulate_zoo_capture(cap_dir, seed, scenes=1, max_size=size, overwrite=True)
            m = measure(cap_dir, source)
            rows.append(_row(m))
            print(rows[-1], flush=True)
    else:
        rows.append(_default(args.out, args.half, source, report=True))
    if args.write:
        text = (
            "Truth of simulated captures against `calibrate_capture` (automatic points on the "
            "slits and the reference boards, one bundle adjustment). Camera: true 3D points of "
            "the three reference boards (every 8th pixel: the whole image at the near, middle "
            "and far end of the measuring volume) projected by the calibrated camera, against "
            "their true pixels; corners = the four corner cells of a 3 x 3 grid. True stripe "
            "pixels: every 7th true stripe pixel of the scan, triangulated with the calibration; "
            "'camera alone' with the calibrated camera and the true planes. Tolerance: 0.05 mm "
            "on rigs of 1 MP or more, 0.02 mm on the default rig, below 1 MP the RMS 3D error "
            "that 0.03 px across the stripe makes on the same points. Zoo seeds 1000 and up are "
            "held out.\n\n" + HEADER + "\n" + "\n".join(rows) + "\n"
        )
        name, title = "bench_calibration", "Calibration against the truth (bundle adjustment)"
        if args.no_folds:
            name += "_no_folds"
            title += ", without the target's folds"
        write_section(name, title, text, command_line("bench_calibration.py"))


def _default(out: Path, half: bool, source: str, report: bool = False) -> str:
    """Simulate (unless present) and measure the default rig's capture; print its row."""
    if not (out / "rig.json").is_file():
        from multislit.sim.rig import RigSpec
        from multislit.sim.simulate import simulate_capture

        if half:
            simulate_capture(out, ["holes", "steps"], RigSpec().scaled(0.5), seed=3)
        else:
            simulate_capture(out, ["plane"], RigSpec(), seed=0)
    m = measure(out, source, report=report)
    row = _row(m, default_rig=not half)
    print(HEADER)
    print(row, flush=True)
    return row


if __name__ == "__main__":
    main()
