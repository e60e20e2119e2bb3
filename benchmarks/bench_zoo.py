"""Identification on zoo rigs and scenes (drawn at random), scored on the objects apart from the wall.

For each seed: :func:`multislit.sim.simulate_zoo_capture` draws a rig and the scenes and writes
the capture (or reuses it from ``--keep``); the capture is calibrated
(:func:`multislit.calibrate.calibrate_capture`: the camera, the slit planes and the dot
projector); every scan is identified by each method (``--method``: the dots' geometry, the
paper's template matching, or both). Per scene and method it prints the object coverage (true
stripe-centre pixels on the objects with a point of the right slit) of the resolvable centres
(where the stripe stands at least ``RESOLVABLE_SNR`` noise sigmas out of the pixel's noise, by
the truth's ``stripe_snr``) and of all, the share of points on the objects with a wrong slit
(all, and at confidence >= 0.5), the share of the objects' centres too faint to resolve and
where the resolvable ones are lost, the backdrop's resolvable coverage and wrong share, and the
time; then, per method, how many scenes meet the goals (resolvable object coverage >= 90 %,
wrong <= 0.2 %, <= 0.1 % at confidence >= 0.5; backdrop >= 95 % and <= 0.1 % wrong) and,
per kind of object (spheres, rods, boxes, ...), where its resolvable centres go.

``--confidence C [C ...]`` identifies every scene at each of these required confidences
(``IdentifyOptions.min_confidence``) instead of the method's default: the same tables and goals
per confidence, how much of the objects each confidence covers against how many of their points
it labels wrong. ``--write`` records them in a section of their own.

Seeds: 0-99 are tuning seeds (look at them while developing); 1000 and above are held out
(report on them, never tune on them). ``--held-out N`` runs seeds 1000, 1001, ...; seeds of
``--seeds`` all 1000 or above are reported as held out too.

Run:  .venv/bin/python benchmarks/bench_zoo.py [--seeds 0 1 2] [--held-out N] [--size 640 512]
      [--scenes 2] [--method geometry template] [--confidence 0.9 0.98 0.995] [--keep DIR]
      [--write]
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from results import command_line, write_section

from multislit.calibrate import calibrate_capture
from multislit.errors import MultislitError
from multislit.identify import METHODS, IdentifyOptions, identify, prepare_reference
from multislit.io import Capture
from multislit.reconstruct import rig_of
from multislit.sim import RESOLVABLE_SNR, coverage_losses, object_metrics, simulate_zoo_capture

TUNING_SEEDS = (0, 1, 2)
HELD_OUT_START = 1000


def _calibrate(cap: Capture):
    """The calibration result, or None and why it failed."""
    try:
        return calibrate_capture(cap), ""
    except MultislitError as exc:  # report every failure, go on with what can run
        return None, f"failed: {type(exc).__name__}: {str(exc)[:160]}"


def _calibration_summary(res) -> str:
    sp = res.calibration.slit_planes
    missing = np.flatnonzero(~sp.valid).tolist()
    dots = res.dots
    return f"ok ({res.source}), slits without a plane: {missing or 'none'} of {sp.num_slits}, " + (
        f"dot projector {dots.tracked} rays ({dots.rms_px:.2f} px RMS)"
        if dots is not None
        else "no dot projector"
    )


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


def _capture(folder: Path, seed: int, size: tuple[int, int], scenes: int) -> Capture:
    """The zoo capture of ``seed``: reused when ``folder`` holds it, else simulated there."""
    if (folder / "rig.json").is_file():
        try:
            cap = Capture.open(folder)
        except MultislitError as exc:
            raise SystemExit(f"{exc}; remove {folder} to simulate it again") from None
        if len(cap.scans) == scenes:
            return cap
        raise SystemExit(f"{folder} holds another capture ({len(cap.scans)} scenes); remove it")
    return Capture.open(simulate_zoo_capture(folder, seed, scenes=scenes, max_size=size))


def _goals(rows: list[tuple[str, dict, dict]]) -> list[str]:
    """Per method, the scenes that meet each goal, from (method, object, backdrop) scores."""
    out = []
    for method in dict.fromkeys(m for m, _, _ in rows):
        got = [(o, b) for m, o, b in rows if m == method]
        cov = np.array([100 * o["coverage_resolvable"] for o, _ in got])
        wrong = np.array([100 * o["wrong"] for o, _ in got])
        sure = np.array([100 * o["wrong_confident"] for o, _ in got])
        bcov = np.array([100 * b["coverage_resolvable"] for _, b in got])
        bwrong = np.array([100 * b["wrong"] for _, b in got])
        n = len(got)
        out.append(
            f"- {method}, {n} scenes: resolvable object coverage {cov.min():.1f}-{cov.max():.1f} "
            f"% (mean {cov.mean():.1f} %), >= 90 % on {(cov >= 90).sum()}; object wrong "
            f"{wrong.min():.2f}-{wrong.max():.2f} % (mean {wrong.mean():.2f} %), <= 0.2 % on "
            f"{(wrong <= 0.2).sum()}, <= 0.1 % at confidence >= 0.5 on {(sure <= 0.1).sum()}; "
            f"backdrop >= 95 % on {(bcov >= 95).sum()}, <= 0.1 % wrong on "
            f"{(bwrong <= 0.1).sum()}; every goal on "
            f"{((cov >= 90) & (wrong <= 0.2) & (sure <= 0.1) & (bcov >= 95) & (bwrong <= 0.1)).sum()}"
        )
    return out


def _kinds(truth, seen: np.ndarray) -> dict[str, np.ndarray]:
    """The objects' resolvable pixels ``seen`` (H, W) split by kind of object: the primitives'
    names without their numbers (``sphere``, ``ballbar_rod``, ``stairs_step``, ...)."""
    kinds: dict[str, list[int]] = {}
    for i, name in enumerate(truth["names"]):
        kinds.setdefault(re.sub(r"\d+", "", str(name)), []).append(i)
    out = {k: seen & np.isin(truth["obj"], ids) for k, ids in kinds.items()}
    return {k: m for k, m in out.items() if m.any()}


def _by_kind(tally: dict[str, dict[str, Counter]]) -> list[str]:
    """Per method, a table of where each kind of object's resolvable centres go."""
    out = []
    for method, kinds in tally.items():
        out += [
            f"Where the resolvable centres go by kind of object ({method}; shares of the kind's "
            "centres over all scenes):",
            "",
            "| kind | centres | covered | no centre | unlinked | unidentified | left out | wrong |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for kind, c in sorted(kinds.items(), key=lambda kv: -kv[1]["n"]):
            n = max(c["n"], 1)
            out.append(
                f"| {kind} | {c['n']:.0f} | {100 * c['covered'] / n:.1f} % | "
                f"{100 * c['no_centre'] / n:.1f} % | {100 * c['unlinked'] / n:.1f} % | "
                f"{100 * c['segment_unidentified'] / n:.1f} % | "
                f"{100 * c['point_left_out'] / n:.1f} % | {100 * c['wrong'] / n:.1f} % |"
            )
        out.append("")
    return out


def _runs(methods: list[str], confidences: list[float] | None) -> list[tuple[str, IdentifyOptions]]:
    """(label, options) per identification of a scene: each method at its default confidence,
    or at each of ``confidences`` (the label then names it)."""
    if not confidences:
        return [(m, IdentifyOptions(method=m)) for m in methods]
    return [
        (f"{m} at {c:g}", IdentifyOptions(method=m, min_confidence=c))
        for m in methods
        for c in confidences
    ]


def run_seed(
    seed: int,
    folder: Path,
    size: tuple[int, int],
    scenes: int,
    runs: list[tuple[str, IdentifyOptions]],
    rows: list,
    tally: dict[str, dict[str, Counter]],
) -> list[str]:
    """Simulate (or reuse), calibrate and identify one zoo seed; print its lines, return them;
    each scene's (label, object scores, backdrop scores) appended to ``rows`` per run of
    ``runs`` ((label, options), :func:`_runs`), its losses by kind of object added to
    ``tally`` (label -> kind -> counts)."""
    cap = _capture(folder, seed, size, scenes)
    res, why = _calibrate(cap)
    summary = _calibration_summary(res) if res is not None else why
    lines = [f"Seed {seed}: {_rig_summary(cap)}; calibration {summary}.", ""]
    print(lines[0], flush=True)
    ref = res.reference if res is not None and res.reference is not None else None
    if ref is None:
        ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
    rig = None
    if res is not None and res.calibration.dot_projector is not None:
        rig = rig_of(res.calibration)
    lines += [
        "| seed | scene | method | object coverage, resolvable / all | object wrong | "
        "object wrong, conf >= 0.5 | objects' centres faint | resolvable lost: no centre / "
        "unidentified / left out | backdrop coverage, resolvable | backdrop wrong | ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in cap.scans:
        img = cap.image(p)
        truth = np.load(cap.root / "truth" / f"{p.stem}.npz")
        if "stripe_snr" not in truth:
            raise SystemExit(
                f"{folder}: its truth has no stripe_snr (simulated by an older version); "
                "remove the folder to simulate it again"
            )
        snr = truth["stripe_snr"]
        for label, options in runs:
            cells = f"| {seed} | {p.stem} | {label} |"
            try:
                t = time.perf_counter()
                ident = identify(img, ref, rig, options=options)
                dt = time.perf_counter() - t
            except MultislitError as exc:
                lines.append(cells + f" not run: {str(exc)[:100]} | | | | | | | |")
                print(lines[-1], flush=True)
                continue
            m = object_metrics(ident, truth["slit"], truth["object"], snr)
            o, b = m["object"], m["backdrop"]
            rows.append((label, o, b))
            seen = truth["object"] & (snr >= RESOLVABLE_SNR)
            lost: Counter = Counter()  # the scene's, summed over the kinds of object
            for kind, mask in _kinds(truth, seen).items():
                c = tally.setdefault(label, {}).setdefault(kind, Counter())
                got = coverage_losses(ident, truth["slit"], mask=mask, counts=True)
                c.update(got)
                c["n"] += sum(got.values())
                lost.update(got)
            n_seen = max(sum(lost.values()), 1)
            faint = 100 * (1 - o["centres_resolvable"] / max(1, o["centres"]))
            lines.append(
                cells + f" {100 * o['coverage_resolvable']:.1f} / {100 * o['coverage']:.1f} % | "
                f"{100 * o['wrong']:.2f} % | {100 * o['wrong_confident']:.2f} % | {faint:.1f} % | "
                f"{100 * lost['no_centre'] / n_seen:.1f} / "
                f"{100 * lost['segment_unidentified'] / n_seen:.1f} / "
                f"{100 * lost['point_left_out'] / n_seen:.1f} % | {100 * b['coverage_resolvable']:.1f} % | "
                f"{100 * b['wrong']:.2f} % | {1e3 * dt:.0f} |"
            )
            print(lines[-1], flush=True)
    return lines + [""]


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
    ap.add_argument(
        "--method", nargs="+", choices=METHODS, default=list(METHODS), help="methods to run"
    )
    ap.add_argument(
        "--confidence",
        type=float,
        nargs="+",
        default=None,
        metavar="C",
        help="identify at each of these required confidences (0..1) instead of the method's "
        "default, to see what each covers against what it labels wrong",
    )
    ap.add_argument(
        "--keep", type=Path, default=None, help="keep the captures here (and reuse them)"
    )
    ap.add_argument(
        "--write", action="store_true", help="record the tables in benchmarks/RESULTS.md"
    )
    args = ap.parse_args()
    seeds = (
        list(range(HELD_OUT_START, HELD_OUT_START + args.held_out)) if args.held_out else args.seeds
    )
    if args.keep is not None and args.keep.exists() and not args.keep.is_dir():
        ap.error(f"--keep: {args.keep} is not a folder")
    try:
        runs = _runs(args.method, args.confidence)
    except ValueError as exc:
        ap.error(f"--confidence: {exc}")
    held_out = min(seeds) >= HELD_OUT_START
    if not held_out and max(seeds) >= HELD_OUT_START:
        ap.error(f"mix no tuning seeds (< {HELD_OUT_START}) with held-out ones")
    print(
        f"zoo identification, seeds {seeds}, images at most {args.size[0]}x{args.size[1]} px, "
        f"runs {', '.join(label for label, _ in runs)}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        lines = [
            f"Images at most {args.size[0]}x{args.size[1]} px, {args.scenes} scenes per seed; "
            f"{'held-out' if held_out else 'tuning'} seeds {seeds}. Coverage: true "
            "stripe-centre pixels with a point of the right slit (resolvable: the stripe stands "
            f"at least {RESOLVABLE_SNR:g} noise sigmas out of the pixel's noise; faint: the "
            "others); wrong: shares of the points.",
            "",
        ]
        rows: list = []
        tally: dict[str, dict[str, Counter]] = {}
        for seed in seeds:
            folder = root / f"zoo_{seed}_{args.size[0]}x{args.size[1]}_{args.scenes}"
            lines += run_seed(seed, folder, tuple(args.size), args.scenes, runs, rows, tally)
        goals = _goals(rows)
        kinds = _by_kind(tally)
        print("\n".join(goals + [""] + kinds))
        lines += ["Goals, per method:", "", *goals, "", *kinds]
    if args.write:
        kind = "held_out" if held_out else "tuning"
        by = " by the required confidence" if args.confidence else ""
        write_section(
            f"bench_zoo_{kind}" + ("_confidence" if args.confidence else ""),
            f"Objects apart from the backdrop{by}: zoo rigs and scenes "
            f"({kind.replace('_', '-')} seeds)",
            "\n".join(lines).rstrip(),
            command_line("bench_zoo.py"),
        )
        print("written to benchmarks/RESULTS.md")


if __name__ == "__main__":
    main()
