"""Slit identification accuracy on simulated scenes against ground truth, by both methods.

For each rig (25 slits; 49 slits with a grating of twice the pitch) the scenes are simulated,
the capture is calibrated (:func:`multislit.calibrate.calibrate_capture`: the camera, the slit
planes and the dot projector, which the identification by the dots' geometry needs) and every
scene is identified by each method (``--method``: ``geometry``, the dots' geometry, the
default; ``template``, the paper's template matching) on the same image with the same
reference. Per rig, scene and method: the share of output points with the correct slit, the
share wrong with confidence >= 0.5, the coverage of lit stripe-centre pixels, and the time of
the identification per frame.

Run:  .venv/bin/python benchmarks/bench_identify.py [--scale 1.0] [--seed 11] [--losses]
      [--method geometry template] [--write]

The bars (>= 99.5 % correct, <= 0.1 % wrong with confidence >= 0.5, >= 90 % coverage) are for
the rig's own resolution (scale 1). At ``--scale 0.5`` the stripes keep
their pixel width but lie half as far apart: the 49-slit rig there is as dense as 98 slits at
full size (the tests use half size for 25 slits and full size for 49).

``--losses`` adds, per scene and method, where the coverage is lost
(``sim.evaluate.coverage_losses``). ``--write`` records the tables in benchmarks/RESULTS.md (a
section per camera scale).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from results import command_line, write_section

from multislit.calibrate import calibrate_capture
from multislit.errors import MultislitError
from multislit.identify import METHODS, IdentifyOptions, identify, prepare_reference
from multislit.io import Capture
from multislit.reconstruct import rig_of
from multislit.sim.evaluate import LOSSES, coverage_losses, identification_metrics
from multislit.sim.rig import RigSpec, dense_rig
from multislit.sim.simulate import simulate_capture

SCENES = ["holes", "spheres", "steps", "freeform", "textured"]


def rigs(scale: float) -> dict[str, RigSpec]:
    out = {"25 slits": RigSpec(), "49 slits": dense_rig()}
    return {k: (v.scaled(scale) if scale != 1.0 else v) for k, v in out.items()}


def calibrated(cap: Capture):
    """The capture's reference and calibrated rig (None and why, if it cannot be had)."""
    try:
        res = calibrate_capture(cap)
    except MultislitError as exc:  # report it, go on with the template method
        print(f"calibration failed: {type(exc).__name__}: {exc}")
        ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
        return ref, None
    ref = res.reference
    if ref is None:
        ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
    if res.calibration.dot_projector is None:
        print("the calibration has no dot projector: the geometry method is not run")
        return ref, None
    return ref, rig_of(res.calibration)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="camera scale (1 = 1280x1024)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument(
        "--method", nargs="+", choices=METHODS, default=list(METHODS), help="methods to run"
    )
    ap.add_argument(
        "--losses", action="store_true", help="also print where the coverage is lost, per scene"
    )
    ap.add_argument(
        "--write", action="store_true", help="record the tables in benchmarks/RESULTS.md"
    )
    args = ap.parse_args()
    if not args.scale > 0:  # also NaN
        ap.error(
            f"--scale must be a positive number (1: 1280x1024, 0.5: half size), got {args.scale}"
        )
    print(
        f"identification vs truth, camera scale {args.scale}, seed {args.seed}, "
        f"methods {', '.join(args.method)}"
    )
    rows, losses = [], []
    with tempfile.TemporaryDirectory() as d:
        for name, spec in rigs(args.scale).items():
            cap = Capture.open(
                simulate_capture(Path(d) / name.replace(" ", ""), SCENES, spec, seed=args.seed)
            )
            ref, rig = calibrated(cap)
            for p in cap.scans:
                img = cap.image(p)
                truth = np.load(cap.root / "truth" / f"{p.stem}.npz")["slit"]
                for method in args.method:
                    cells = f"| {name} | {p.stem} | {method} |"
                    if method == "geometry" and rig is None:
                        rows.append(cells + " not run (no calibrated dot projector) | | | | |")
                        print(rows[-1], flush=True)
                        continue
                    t = time.perf_counter()
                    ident = identify(img, ref, rig, options=IdentifyOptions(method=method))
                    dt = time.perf_counter() - t
                    m = identification_metrics(ident, truth)
                    if args.losses:
                        losses.append((name, p.stem, method, coverage_losses(ident, truth)))
                    rows.append(
                        cells + f" {m['points']} | {100 * m['correct']:.2f} % | "
                        f"{100 * m['wrong_confident']:.2f} % | {100 * m['coverage']:.1f} % | "
                        f"{1e3 * dt:.0f} |"
                    )
                    print(rows[-1], flush=True)

    out = [
        "| rig | scene | method | points | correct | wrong, conf >= 0.5 | coverage | ms/frame |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    if losses:
        out += [
            "",
            "Where the coverage is lost: shares of the lit stripe-centre pixels (%).",
            "",
            "| rig | scene | method | " + " | ".join(LOSSES) + " |",
            "|---|---|---|" + "---|" * len(LOSSES),
        ]
        for name, scene, method, loss in losses:
            cells = " | ".join(f"{100 * loss[k]:.1f}" for k in LOSSES)
            out.append(f"| {name} | {scene} | {method} | {cells} |")
    print("\n" + "\n".join(out))
    if args.write:
        text = (
            f"Camera scale {args.scale} (1: 1280x1024), render seed {args.seed}. Bars: >= 99.5 % "
            "of the identified points correct, <= 0.1 % wrong with confidence >= 0.5, >= 90 % of "
            "the lit stripe-centre pixels covered. The ms/frame column is the identification "
            "alone.\n\n" + "\n".join(out)
        )
        write_section(
            f"bench_identify_{args.scale:g}",
            f"Identification vs truth (camera scale {args.scale:g})",
            text,
            command_line("bench_identify.py"),
        )
        print("written to benchmarks/RESULTS.md")


if __name__ == "__main__":
    main()
