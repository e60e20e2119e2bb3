"""Slit identification accuracy on simulated scenes against ground truth.

For each rig (25 slits; 49 slits with a grating of twice the pitch) and each scene: the share of
output points with the correct slit, the share wrong with confidence >= 0.5, the coverage of
lit stripe-centre pixels, and the time per frame.

Run:  .venv/bin/python benchmarks/bench_identify.py [--scale 1.0] [--seed 11] [--losses]

The bars (>= 99.5 % correct, <= 0.1 % wrong with confidence >= 0.5, >= 90 % coverage) are for
the rig's own resolution (scale 1). At ``--scale 0.5`` the stripes keep
their pixel width but lie half as far apart: the 49-slit rig there is as dense as 98 slits at
full size (the tests use half size for 25 slits and full size for 49).

``--losses`` adds, per scene, where the coverage is lost (``sim.evaluate.coverage_losses``).
``--follow-stripe off`` and ``--depth-margin`` run the identification in internal modes the
library does not offer (upright templates; a limited measuring volume), for comparison.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from multislit.identify import prepare_reference
from multislit.identify.labelling import _identify
from multislit.identify.matching import _Options
from multislit.io import Capture
from multislit.sim.evaluate import LOSSES, coverage_losses, identification_metrics
from multislit.sim.rig import RigSpec, dense_rig
from multislit.sim.simulate import simulate_capture

SCENES = ["holes", "spheres", "steps", "freeform", "textured"]


def rigs(scale: float) -> dict[str, RigSpec]:
    out = {"25 slits": RigSpec(), "49 slits": dense_rig()}
    return {k: (v.scaled(scale) if scale != 1.0 else v) for k, v in out.items()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0, help="camera scale (1 = 1280x1024)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument(
        "--follow-stripe",
        choices=("line", "off"),
        default=_Options().follow_stripe,
        help="how the scan template follows its stripe (line: the library's)",
    )
    ap.add_argument(
        "--depth-margin",
        type=float,
        default=_Options().depth_margin,
        help="the measuring volume's margin (inf: no limit, the library's)",
    )
    ap.add_argument(
        "--losses", action="store_true", help="also print where the coverage is lost, per scene"
    )
    args = ap.parse_args()
    if not args.scale > 0:  # also NaN
        ap.error(
            f"--scale must be a positive number (1: 1280x1024, 0.5: half size), got {args.scale}"
        )
    options = _Options(follow_stripe=args.follow_stripe, depth_margin=args.depth_margin)
    print(
        f"identification vs truth, camera scale {args.scale}, seed {args.seed}, "
        f"follow_stripe={args.follow_stripe}, depth_margin={args.depth_margin}"
    )
    print("| rig | scene | points | correct | wrong, conf >= 0.5 | coverage | ms/frame |")
    print("|---|---|---|---|---|---|---|")
    losses = []
    with tempfile.TemporaryDirectory() as d:
        for name, spec in rigs(args.scale).items():
            cap = Capture.open(
                simulate_capture(Path(d) / name.replace(" ", ""), SCENES, spec, seed=args.seed)
            )
            ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
            for p in cap.scans:
                img = cap.image(p)
                t = time.perf_counter()
                ident = _identify(img, ref, None, options)
                dt = time.perf_counter() - t
                truth = np.load(cap.root / "truth" / f"{p.stem}.npz")["slit"]
                m = identification_metrics(ident, truth)
                if args.losses:
                    losses.append((name, p.stem, coverage_losses(ident, truth)))
                print(
                    f"| {name} | {p.stem} | {m['points']} | {100 * m['correct']:.2f} % | "
                    f"{100 * m['wrong_confident']:.2f} % | {100 * m['coverage']:.1f} % | {1e3 * dt:.0f} |"
                )

    if losses:
        print("\nshare of the lit stripe-centre pixels (%)")
        print("| rig | scene | " + " | ".join(LOSSES) + " |")
        print("|---|---|" + "---|" * len(LOSSES))
        for name, scene, loss in losses:
            cells = " | ".join(f"{100 * loss[k]:.1f}" for k in LOSSES)
            print(f"| {name} | {scene} | {cells} |")


if __name__ == "__main__":
    main()
