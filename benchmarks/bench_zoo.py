"""Identification on zoo rigs and scenes (drawn at random), scored on the objects apart from the wall.

For each seed: :func:`multislit.sim.simulate_zoo_capture` draws a rig and two scenes and writes
the capture; the capture is calibrated (:func:`multislit.calibrate.calibrate_capture`; a failure is reported, the
identification does not need it); the reference is prepared and every scan identified. Per
scene it prints the object coverage (true stripe-centre pixels on the objects with a point of
the right slit), the share of points on the objects with a wrong slit (all, and at confidence
>= 0.5), and the same coverage and wrong share on the backdrop.

Seeds: 0-99 are tuning seeds (look at them while developing); 1000 and above are held out
(report on them, never tune on them). ``--held-out`` runs seeds 1000, 1001, ...

Run:  .venv/bin/python benchmarks/bench_zoo.py [--seeds 0 1 2] [--held-out] [--size 640 512]
      [--option NAME=VALUE ...]  (an identification mode to compare, not written)
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from results import command_line, write_section

from multislit.calibrate import calibrate_capture
from multislit.identify import prepare_reference
from multislit.identify.labelling import _identify
from multislit.identify.matching import _Options
from multislit.io import Capture
from multislit.sim import coverage_losses, object_metrics, simulate_zoo_capture

TUNING_SEEDS = (0, 1, 2)
HELD_OUT_START = 1000


def _calibrate(cap: Capture) -> str:
    """Calibrate; a short report: slits without a plane, or why it failed."""
    try:
        res = calibrate_capture(cap)
    except Exception as exc:  # report every failure, go on with identification
        return f"failed: {type(exc).__name__}: {str(exc)[:160]}"
    sp = res.calibration.slit_planes
    if sp is None:
        return f"ok ({res.source}), no slit planes"
    missing = np.flatnonzero(~sp.valid).tolist()
    return f"ok ({res.source}), slits without a plane: {missing or 'none'} of {sp.num_slits}"


def _rig_summary(cap: Capture) -> str:
    spec = cap.rig.get("simulator", {}).get("rig", {}) if isinstance(cap.rig, dict) else {}
    cam, slits, dots = spec.get("camera", {}), spec.get("slits", {}), spec.get("dots", {})
    w, h = cam.get("image_size", cap.image_size)
    standoff = cam.get("position", [0, 0, 0])[2] - cam.get("look_at", [0, 0, 0])[2]
    base = abs(slits.get("position", [0])[0] - cam.get("position", [0])[0])
    return (
        f"{w}x{h} px, k1 {cam.get('dist', [0])[0]:+.3f}, {slits.get('num_slits')} slits, "
        f"dots {dots.get('pattern')}, standoff {standoff:.0f} mm, baseline {base:.0f} mm"
    )


def run_seed(
    seed: int, folder: Path, size: tuple[int, int], scenes: int, options: _Options
) -> list[str]:
    """Simulate, calibrate and identify one zoo seed; print its lines and return them."""
    cap = Capture.open(simulate_zoo_capture(folder, seed, scenes=scenes, max_size=size))
    lines = [f"Seed {seed}: {_rig_summary(cap)}; calibration {_calibrate(cap)}.", ""]
    print(lines[0])
    ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
    lines += [
        "| seed | scene | object coverage | object wrong | object wrong, conf >= 0.5 | "
        "objects lost: no centre / unidentified / left out | backdrop coverage | "
        "backdrop wrong | ms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p in cap.scans:
        img = cap.image(p)
        t = time.perf_counter()
        ident = _identify(img, ref, None, options)
        dt = time.perf_counter() - t
        truth = np.load(cap.root / "truth" / f"{p.stem}.npz")
        m = object_metrics(ident, truth["slit"], truth["object"])
        o, b = m["object"], m["backdrop"]
        lost = coverage_losses(ident, truth["slit"], mask=truth["object"])
        share = {k: 100 * n / max(1, sum(lost.values())) for k, n in lost.items()}
        lines.append(
            f"| {seed} | {p.stem} | {100 * o['coverage']:.1f} % | {100 * o['wrong']:.2f} % | "
            f"{100 * o['wrong_confident']:.2f} % | {share['no_centre']:.1f} / "
            f"{share['segment_unidentified']:.1f} / {share['point_left_out']:.1f} % | "
            f"{100 * b['coverage']:.1f} % | "
            f"{100 * b['wrong']:.2f} % | {1e3 * dt:.0f} |"
        )
        print(lines[-1])
    return lines + [""]


def _parse_options(ap: argparse.ArgumentParser, pairs: list[str]) -> _Options:
    """``_Options`` with the ``NAME=VALUE`` pairs set (values of the field's type)."""
    fields = _Options.__dataclass_fields__
    kw = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or name not in fields:
            ap.error(f"--option must be NAME=VALUE with NAME one of {sorted(fields)}, got {pair!r}")
        kind = type(getattr(_Options(), name))
        try:
            kw[name] = (
                value if kind is str else (value.lower() == "true" if kind is bool else kind(value))
            )
        except ValueError:
            ap.error(f"--option {name} needs a {kind.__name__}, got {value!r}")
    return _Options(**kw)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog=(
            f"Tuning seeds: 0-99 (default {' '.join(map(str, TUNING_SEEDS))}). Held-out seeds: "
            f"{HELD_OUT_START} and above, for reporting only (--held-out)."
        ),
    )
    ap.add_argument("--seeds", type=int, nargs="+", default=list(TUNING_SEEDS))
    ap.add_argument(
        "--held-out",
        type=int,
        default=0,
        metavar="N",
        help=f"run the first N held-out seeds ({HELD_OUT_START}, ...) instead of --seeds",
    )
    ap.add_argument(
        "--size",
        type=int,
        nargs=2,
        default=(640, 512),
        metavar=("W", "H"),
        help="largest camera image, px (the rig is scaled down to fit; 1920 1080: full HD)",
    )
    ap.add_argument("--scenes", type=int, default=2, help="scenes per seed")
    ap.add_argument("--keep", type=Path, default=None, help="write the captures here")
    ap.add_argument(
        "--option",
        action="append",
        metavar="NAME=VALUE",
        help="an identification mode to compare (repeatable), a field of "
        "multislit.identify.matching._Options, e.g. template_half_width=1.0, search_px=2, "
        "references=all, depth_margin=0.25",
    )
    ap.add_argument(
        "--write", action="store_true", help="record the tables in benchmarks/RESULTS.md"
    )
    args = ap.parse_args()
    options = _parse_options(ap, args.option or [])
    if args.option and args.write:
        ap.error("--write records the library's own identification: leave out --option")
    seeds = (
        list(range(HELD_OUT_START, HELD_OUT_START + args.held_out)) if args.held_out else args.seeds
    )
    print(
        f"zoo identification, seeds {seeds}, images at most {args.size[0]}x{args.size[1]} px"
        + (f", options {', '.join(args.option)}" if args.option else "")
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        lines = [
            f"Images at most {args.size[0]}x{args.size[1]} px, {args.scenes} scenes per seed; "
            f"{'held-out' if args.held_out else 'tuning'} seeds {seeds}. Coverage: true "
            "stripe-centre pixels with a point of the right slit; wrong: shares of the points.",
            "",
        ]
        for seed in seeds:
            lines += run_seed(seed, root / f"zoo_{seed}", tuple(args.size), args.scenes, options)
    if args.write:
        kind = "held_out" if args.held_out else "tuning"
        write_section(
            f"bench_zoo_{kind}",
            f"Objects apart from the backdrop: zoo rigs and scenes ({kind.replace('_', '-')} seeds)",
            "\n".join(lines).rstrip(),
            command_line("bench_zoo.py"),
        )
        print("written to benchmarks/RESULTS.md")


if __name__ == "__main__":
    main()
