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
  1 MP;
- the **dot projector** (:func:`dot_projector_errors`): the true dots and the calibrated rays
  landed on the middle reference board's plane (the true rays from the true source, imaged by
  the true camera; the calibrated ones from the calibrated source, imaged by the calibrated
  camera): the share of the true dots in the image with a ray within 0.5 px (and 1 px), the
  share of the rays with no true dot within 1 px (spurious), the RMS px of the rays that have
  one from it on the three boards' planes, the rays' brightness against the true relative
  brightness (the simulator's dot brightness over the power of the slit whose band the dot
  lies in: Spearman's rank correlation, and the robust spread of their log ratio), and the
  dot projector's time. Goals: 90 % within 0.5 px, at most 3 % spurious.

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

import multislit.calibrate.pipeline as pipeline
from multislit.calibrate import calibrate_capture, format_report
from multislit.calibrate.camera import rms
from multislit.geometry import camera_from_dict
from multislit.io import Capture
from multislit.reconstruct import triangulate

#: Goals of the dot projector: the true dots in the image with a ray within 0.5 px, the rays
#: with no true dot within 1 px.
DOT_RECALL_GOAL = 0.9
DOT_SPURIOUS_GOAL = 0.03
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


def dot_projector_errors(capture: Path, cal) -> dict[str, Any] | None:
    """The calibrated dot projector against the simulator's truth (module docstring); None
    without one."""
    from scipy.spatial import cKDTree
    from scipy.stats import spearmanr

    from multislit.sim import RigSpec, SimulatedRig

    proj = cal.dot_projector
    if proj is None:
        return None
    rig = SimulatedRig.build(
        RigSpec.from_dict(json.loads((capture / "rig.json").read_text())["simulator"]["rig"])
    )
    z_rig = float(rig.spec.camera.position[2])
    w, h = rig.camera.image_size

    def land(origin, dirs, dist):
        t = (z_rig - dist - origin[2]) / dirs[:, 2]
        return origin + t[:, None] * dirs

    dists = sorted(rig.spec.reference_distances)
    true_uv = [rig.camera.project(land(rig.dots.origin, rig.dots.directions, d)) for d in dists]
    ours_uv = [cal.camera.project(land(proj.source, proj.directions, d)) for d in dists]
    mid = len(dists) // 2
    t_mid, o_mid = true_uv[mid], ours_uv[mid]
    inside = (t_mid[:, 0] >= 0) & (t_mid[:, 0] <= w - 1) & (t_mid[:, 1] >= 0)
    inside &= t_mid[:, 1] <= h - 1
    covered, _ = cKDTree(o_mid).query(t_mid[inside])
    d, i = cKDTree(t_mid).query(o_mid)
    match = d <= 1.0
    err = np.concatenate(
        [
            np.linalg.norm(o[match] - t[i[match]], axis=1)
            for t, o in zip(true_uv, ours_uv, strict=True)
        ]
    )
    out = {
        "in_image": int(inside.sum()),
        "rays": int(proj.num_dots),
        "recall_05": float(np.mean(covered < 0.5)),
        "recall_1": float(np.mean(covered < 1.0)),
        "spurious": float(np.mean(~match)),
        "rms_px": rms(err),
        "source_mm": float(np.linalg.norm(proj.source - rig.dots.origin)),
        "beta_known": float(np.mean(np.isfinite(proj.brightness))),
        "beta_rho": float("nan"),
        "beta_spread": float("nan"),
    }
    beta = proj.brightness
    ok = match & np.isfinite(beta) & (beta > 0)
    if ok.sum() > 10:
        p = rig.projector
        phi, _, _ = p.local(rig.dots.origin + rig.dots.directions[i[ok]])
        k = np.argmin(np.abs(phi[:, None] - p.angles[None, :]), axis=1)
        true_beta = rig.dots.brightness[i[ok]] / p.powers[k]
        lr = np.log(beta[ok] / true_beta)
        out["beta_rho"] = float(spearmanr(beta[ok], true_beta).statistic)
        out["beta_spread"] = float(1.4826 * np.median(np.abs(lr - np.median(lr))))
    return out


def measure(capture: Path, source: str = "auto", report: bool = False) -> dict[str, Any]:
    """Calibrate ``capture`` and compare with its truth (see the module docstring)."""
    cap = Capture.open(capture)
    scan = sorted((capture / "scans").glob("*.png"))[0].stem
    dot_secs: list[float] = []
    real = pipeline.capture_dot_projector

    def timed(*args, **kwargs):
        t = time.perf_counter()
        try:
            return real(*args, **kwargs)
        finally:
            dot_secs.append(time.perf_counter() - t)

    pipeline.capture_dot_projector = timed
    try:
        t0 = time.perf_counter()
        r = calibrate_capture(cap, source=source)
        secs = time.perf_counter() - t0
    finally:
        pipeline.capture_dot_projector = real
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
        "dots": dot_projector_errors(capture, cal),
        "dot_seconds": sum(dot_secs) if dot_secs else float("nan"),
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


def _dot_row(m: dict[str, Any]) -> str:
    d = m["dots"]
    if d is None:
        return f"| {m['capture']} | {m['image']} | no dot projector | | | | | | |"
    ok = d["recall_05"] >= DOT_RECALL_GOAL and d["spurious"] <= DOT_SPURIOUS_GOAL
    return (
        f"| {m['capture']} | {m['image']} | {d['rays']} for {d['in_image']} | "
        f"{100 * d['recall_05']:.1f} / {100 * d['recall_1']:.1f} | {100 * d['spurious']:.1f} | "
        f"{d['rms_px']:.3f} | {d['source_mm']:.2f} | {d['beta_rho']:.2f} / "
        f"{d['beta_spread']:.2f} | {'met' if ok else 'missed'} | {m['dot_seconds']:.2f} |"
    )


DOT_HEADER = (
    "| capture | image | rays for in-image dots | dots with a ray within 0.5 / 1 px % | "
    "spurious rays % | ray RMS px | source error mm | brightness: Spearman / log spread | "
    "goal 90 % / 3 % | dot projector s |\n|---|---|---|---|---|---|---|---|---|---|"
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
    rows, dot_rows = [], []
    if args.zoo:
        from multislit.sim.zoo import simulate_zoo_capture

        size = tuple(int(x) for x in args.size.lower().split("x"))
        if args.default:
            row, dot_row = _default(args.out / "default", False, source)
            rows.append(row)
            dot_rows.append(dot_row)
        for seed in args.zoo:
            cap_dir = args.out / f"zoo_{seed}_{size[0]}x{size[1]}"
            if not (cap_dir / "rig.json").is_file():
                simulate_zoo_capture(cap_dir, seed, scenes=1, max_size=size, overwrite=True)
            m = measure(cap_dir, source)
            rows.append(_row(m))
            dot_rows.append(_dot_row(m))
            print(rows[-1], flush=True)
            print(dot_rows[-1], flush=True)
    else:
        row, dot_row = _default(args.out, args.half, source, report=True)
        rows.append(row)
        dot_rows.append(dot_row)
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
        if not args.no_folds:
            dot_text = (
                "The calibrated dot projector against the simulator's truth: the true dots and "
                "the calibrated rays landed on the middle reference board's plane (the true rays "
                "imaged by the true camera, the calibrated ones by the calibrated camera). Dots "
                "with a ray: the share of the true dots in the image with a ray within 0.5 (1) px; "
                "spurious: the share of the rays with no true dot within 1 px; ray RMS: the rays "
                "that have one, from it on the three boards' planes; brightness: the rays' "
                "brightness against the simulator's dot brightness over the power of the slit "
                "whose band the dot lies in (Spearman's rank correlation, and the robust spread "
                "of the log of their ratio about its median). Zoo seeds 1000 and up are held out."
                "\n\n" + DOT_HEADER + "\n" + "\n".join(dot_rows) + "\n"
            )
            write_section(
                "bench_calibration_dots",
                "Dot projector against the truth",
                dot_text,
                command_line("bench_calibration.py"),
            )


def _default(out: Path, half: bool, source: str, report: bool = False) -> tuple[str, str]:
    """Simulate (unless present) and measure the default rig's capture; print its rows."""
    if not (out / "rig.json").is_file():
        from multislit.sim.rig import RigSpec
        from multislit.sim.simulate import simulate_capture

        if half:
            simulate_capture(out, ["holes", "steps"], RigSpec().scaled(0.5), seed=3)
        else:
            simulate_capture(out, ["plane"], RigSpec(), seed=0)
    m = measure(out, source, report=report)
    row = _row(m, default_rig=not half)
    dot_row = _dot_row(m)
    print(HEADER)
    print(row, flush=True)
    print(DOT_HEADER)
    print(dot_row, flush=True)
    return row, dot_row


if __name__ == "__main__":
    main()
