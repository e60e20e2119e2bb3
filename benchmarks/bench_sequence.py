"""Identification of a sequence of frames with and without the previous frame's prior.

The prior is the template method's (:func:`multislit.identify.identify_template`, ``method=
"template"``); the identification by the dots' geometry scores every slit of every frame.

The simulator renders a sphere and a box moving 4 mm per frame across the default rig's
field (1280x1024 px, 25 slits) in front of a wall (:func:`multislit.sim.simulate_sequence`,
30 frames, seed 0). The reference is prepared once. Every frame is extracted once; its
identification is timed twice, ``identify_template(image, reference, extraction=...)`` (the
full search) and ``identify_template(..., previous=...)`` with the identification the prior
made of the frame before (the chain a camera stream runs; the first frame has no previous and
is searched in full both ways). One ``cv2.medianBlur`` (5x5) pass over the same frame is timed
next to each: the ratio identification / medianBlur holds better than ms on a busy machine.

Reported: ms per frame of identification (median and range over the frames after the first,
each frame's time the median of ``--repeat`` runs, the two ways taking turns) both ways and in medianBlur passes; the
agreement (share of all points with the same slit either way, and the points labelled both
ways with different slits); against the truth, both ways, the objects' and the wall's
points: share correct, share wrong (on another slit's stripe) and coverage (share of the true
stripe-centre pixels with a point of their slit), pooled over the frames
(:func:`multislit.sim.object_metrics`).

Run:  .venv/bin/python benchmarks/bench_sequence.py [--frames 30] [--repeat 5] [--write]
(OpenCV, BLAS and Numba on one thread: the script re-executes itself with
OPENBLAS/OMP/MKL/NUMBA_NUM_THREADS=1 as bench_speed.py. ``--write`` replaces the sequence
section of benchmarks/RESULTS.md.)
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_speed import median_blur_s, on_threads  # noqa: E402
from results import command_line, write_section  # noqa: E402

from multislit import compile_kernels  # noqa: E402
from multislit.identify import identify_template, prepare_reference  # noqa: E402
from multislit.sim import RigSpec, object_metrics, simulate_sequence  # noqa: E402
from multislit.stripes import extract_slits  # noqa: E402

WAYS = ("full", "prior")


def timed_pair(fa, fb, repeat: int):
    """(result of ``fa``, of ``fb``, median seconds of each): ``repeat`` runs of each, taking
    turns, so that both see the same load of a shared machine."""
    ta, tb, ra, rb = [], [], None, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        ra = fa()
        t1 = time.perf_counter()
        rb = fb()
        t2 = time.perf_counter()
        ta.append(t1 - t0)
        tb.append(t2 - t1)
    return ra, rb, statistics.median(ta), statistics.median(tb)


def pooled(metrics: list[dict], region: str) -> dict:
    """Shares pooled over the frames: correct and wrong over points, coverage over centres."""
    pts = sum(m[region]["points"] for m in metrics)
    cen = sum(m[region]["centres"] for m in metrics)
    return {
        "points": pts,
        "correct": sum(m[region]["correct"] * m[region]["points"] for m in metrics) / max(pts, 1),
        "wrong": sum(m[region]["wrong"] * m[region]["points"] for m in metrics) / max(pts, 1),
        "coverage": sum(m[region]["coverage"] * m[region]["centres"] for m in metrics)
        / max(cen, 1),
    }


def run(frames: int, repeat: int) -> dict:
    compile_kernels()  # untimed: the reference's preparation below is timed without compiling
    t0 = time.perf_counter()
    seq = simulate_sequence(RigSpec(), frames=frames, seed=0)
    sim_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref = prepare_reference(seq.references, seq.spec.slits.num_slits, seq.reference_names)
    prep_s = time.perf_counter() - t0
    # warm-up, untimed: caches built on the reference, compiled kernels loaded
    ex0 = extract_slits(
        seq.images[0], stripe_width_px=ref.stripe_width_px, dot_size_px=ref.dot_size_px
    )
    first = identify_template(seq.images[0], ref, extraction=ex0)
    identify_template(seq.images[0], ref, extraction=ex0, previous=first)
    rows, idents = [], {w: [] for w in WAYS}
    prev = None
    for f, img in enumerate(seq.images):
        blur = median_blur_s(img)
        t0 = time.perf_counter()
        ex = extract_slits(img, stripe_width_px=ref.stripe_width_px, dot_size_px=ref.dot_size_px)
        t_ex = time.perf_counter() - t0
        full, pri, t_full, t_pri = timed_pair(
            lambda img=img, ex=ex: identify_template(img, ref, extraction=ex),
            lambda img=img, ex=ex, prev=prev: identify_template(
                img, ref, extraction=ex, previous=prev
            ),
            repeat,
        )
        prev = pri
        idents["full"].append(full)
        idents["prior"].append(pri)
        rows.append({"frame": f, "blur": blur, "extract": t_ex, "full": t_full, "prior": t_pri})
    same = np.concatenate([a.slit == b.slit for a, b in zip(*idents.values(), strict=True)])
    differ = np.concatenate(
        [
            (a.slit >= 0) & (b.slit >= 0) & (a.slit != b.slit)
            for a, b in zip(*idents.values(), strict=True)
        ]
    )
    only = {
        w: int(
            sum(
                np.sum((x.slit >= 0) & (y.slit < 0))
                for x, y in zip(idents[w], idents[WAYS[1 - i]], strict=True)
            )
        )
        for i, w in enumerate(WAYS)
    }
    truth = {
        w: [
            object_metrics(d, t, o)
            for d, t, o in zip(idents[w], seq.truth_slit, seq.truth_object, strict=True)
        ]
        for w in WAYS
    }
    return {
        "frames": frames,
        "repeat": repeat,
        "size": seq.spec.camera.image_size,
        "slits": seq.spec.slits.num_slits,
        "step_mm": float(seq.offsets[1, 0] - seq.offsets[0, 0]) if frames > 1 else 0.0,
        "simulate_s": sim_s,
        "prepare_s": prep_s,
        "rows": rows,
        "points": int(same.size),
        "same": float(same.mean()) if same.size else 1.0,
        "differ": int(differ.sum()),
        "only": only,
        "metrics": {w: {r: pooled(truth[w], r) for r in ("object", "backdrop")} for w in WAYS},
    }


def report(r: dict) -> str:
    later = r["rows"][1:] or r["rows"]
    w, h = r["size"]
    lines = [
        f"{r['frames']} frames, {w}x{h} px, {r['slits']} slits, the objects moving "
        f"{r['step_mm']:.0f} mm per frame; identification only (the extraction, the same both "
        f"ways, is timed apart); medians over the frames after the first, each frame's time the "
        f"median of {r['repeat']} runs, the two ways taking turns.",
        "",
        "| identification | ms per frame, median (range) | x medianBlur, median (range) |",
        "|---|---|---|",
    ]
    for way, label in (("full", "full search"), ("prior", "with the previous frame's prior")):
        ms = [1e3 * x[way] for x in later]
        ratio = [x[way] / x["blur"] for x in later]
        lines.append(
            f"| {label} | {statistics.median(ms):.0f} ({min(ms):.0f}-{max(ms):.0f}) "
            f"| {statistics.median(ratio):.0f} ({min(ratio):.0f}-{max(ratio):.0f}) |"
        )
    ex = [1e3 * x["extract"] for x in later]
    blur = [1e3 * x["blur"] for x in later]
    speed = [x["full"] / x["prior"] for x in later]
    lines += [
        "",
        f"Extraction {statistics.median(ex):.0f} ms a frame, one medianBlur pass "
        f"{statistics.median(blur):.2f} ms (medians). Full search / prior per frame: median "
        f"{statistics.median(speed):.2f}x ({min(speed):.2f}-{max(speed):.2f}).",
        "",
        f"Agreement over all {r['points']} points of the {r['frames']} frames: "
        f"{100 * r['same']:.2f} % carry the same slit (or none) either way; {r['differ']} are "
        f"labelled both ways with different slits; {r['only']['full']} are labelled by the full "
        f"search only, {r['only']['prior']} with the prior only.",
        "",
        "| identification | region | points | correct % | wrong % | coverage % |",
        "|---|---|---|---|---|---|",
    ]
    for way in WAYS:
        for region in ("object", "backdrop"):
            m = r["metrics"][way][region]
            lines.append(
                f"| {way} | {region} | {m['points']} | {100 * m['correct']:.2f} "
                f"| {100 * m['wrong']:.2f} | {100 * m['coverage']:.1f} |"
            )
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines += [
        "",
        f"Rendering the sequence took {r['simulate_s']:.0f} s, preparing the reference "
        f"{r['prepare_s']:.1f} s. Load average at the end (1, 5, 15 min): {load} on "
        f"{os.cpu_count()} cores.",
    ]
    return "\n".join(lines)


def main() -> None:
    on_threads(1)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30, help="frames (default 30)")
    ap.add_argument(
        "--repeat", type=int, default=5, help="timed runs per frame and way (default 5)"
    )
    ap.add_argument(
        "--write", action="store_true", help="replace the sequence section of benchmarks/RESULTS.md"
    )
    args = ap.parse_args()
    if args.frames < 2:
        ap.error("--frames must be >= 2")
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    cv2.setNumThreads(1)
    text = report(run(args.frames, args.repeat))
    print(text)
    if args.write:
        write_section(
            "bench_sequence",
            "A sequence of frames: identification with the previous frame's prior (one core)",
            text,
            command_line("bench_sequence.py"),
        )


if __name__ == "__main__":
    main()
