"""Single-shot pipeline speed per frame at full size (1280x1024), on one core or ``--threads N``.

The default pipeline (``scan_image`` with the default options) timed per frame, stage by stage
as it runs them, from the image array to 3D points: slit/dot extraction, identification by the
dots' geometry, centre refinement, triangulation. Each simulated capture is calibrated first
(``calibrate_capture``: the camera, the slit planes and the dot projector the geometry needs;
not timed), and the staged frame is checked to give the points ``scan_image`` gives. Beside
it, not in the total, the paper's template identification (``method="template"``) of the same
frame from the same extraction, and the frame's dots (``frame_dots``: the dots' list and
response the identification by the dots' geometry makes first) timed apart: the dots' share of
the identification. The floor a frame cannot beat is one ``cv2.medianBlur`` (5x5) pass over the
same frame, timed in the same run next to each frame, always on one thread: the ratio total /
medianBlur is the figure that holds on a busy machine, where absolute times are not, and with
``--threads N`` it shows what N threads gain against the same yardstick.

Reported per rig (25 and 49 slits): the median over ``--repeat`` runs of each scan (scenes
``holes``, ``spheres`` and ``steps``) of the ms per stage, the total, the dots' share, the
template identification, the medianBlur ms, the ratio, points per second, and the peak memory
of one frame; the time to prepare the reference (``prepare_reference`` on the capture's
reference images, once per rig).

Memory: "peak MB" is tracemalloc's peak of the Python and NumPy allocations during one frame
of the pipeline (arrays made by OpenCV's Python bindings and the compiled kernels' work arrays included,
OpenCV's internal buffers not), measured in a separate, untimed run; "max RSS" is the
process's resident-set high-water mark at the end (``resource.getrusage``: interpreter,
libraries, the simulated captures and the reference included).

Where the time goes: the functions that take the most time of their own (cProfile's
tottime, ms per frame; a compiled kernel counts as one function, OpenCV calls by name) over one
more run of the pipeline on every scan, profiled apart from the timed runs.

Compiled kernels (Numba) are loaded or compiled before timing (``multislit.compile_kernels``),
and every frame runs once, untimed, first.

Run:  .venv/bin/python benchmarks/bench_speed.py [--slits 25 49] [--repeat 5] [--threads N]
                                                 [--write]
(OpenCV, the BLAS behind NumPy and Numba run on ``--threads`` threads, 1 by default: "one
core". The BLAS and Numba read their thread count as they load, so the script re-executes
itself with OPENBLAS/OMP/MKL/NUMBA_NUM_THREADS=N; OpenCV's is set with ``cv2.setNumThreads``.
``--write`` replaces the speed section of benchmarks/RESULTS.md, that of N threads for N > 1.)
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import resource
import statistics
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import NoReturn

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from results import command_line, write_section  # noqa: E402

from multislit import compile_kernels, set_threads  # noqa: E402
from multislit.calibrate import calibrate_capture  # noqa: E402
from multislit.identify import IdentifyOptions, identify, prepare_reference  # noqa: E402
from multislit.identify.evidence import frame_dots  # noqa: E402
from multislit.io import Capture  # noqa: E402
from multislit.reconstruct import faded_ends, rig_of, scan_image, triangulate  # noqa: E402
from multislit.sim import RigSpec, simulate_capture  # noqa: E402
from multislit.stripes import extract_slits, refine_centres  # noqa: E402

STAGES = ("extract", "identify", "refine", "triangulate")
#: Timed beside the pipeline, not in its total: the template identification of the same frame.
TEMPLATE = "template_identify"
#: ... and the frame's dots, the identification's first step, timed apart: its share of it.
DOTS = "dots"
BESIDE = (DOTS, TEMPLATE)
SCENES = ("holes", "spheres", "steps")
GOALS_MS = {25: 16.0, 49: 33.0}  # the camera-rate goals per frame, one core
GOAL_PASSES = 8  # the goal in medianBlur passes at 25 slits
TOP = 10  # functions listed in the profile


def frame(img, ref, cal, rig, template: bool = True) -> tuple[list[float], int]:
    """One frame through the default pipeline, stage by stage as ``scan_image`` runs them (the
    default options): the seconds of each stage, then of the frame's dots and of the template
    identification of the same extraction (not stages; 0 without ``template``), and the valid
    3D points."""
    t0 = time.perf_counter()
    ex = extract_slits(img, stripe_width_px=ref.stripe_width_px, dot_size_px=ref.dot_size_px)
    t1 = time.perf_counter()
    ident = identify(img, ref, rig, extraction=ex, match_dots=False)
    t2 = time.perf_counter()
    sw, ds = ex.stripe_width_px, ex.dot_size_px
    u, _ = refine_centres(img, ident.u, ident.v, ident.segment, sw, ds, noise_sigma=ex.noise_sigma)
    t3 = time.perf_counter()
    ok = ident.identified & ~faded_ends(ident)
    planes = cal.slit_planes.planes
    _, valid = triangulate(cal.camera, planes, np.c_[u[ok], ident.v[ok]], ident.slit[ok])
    t4 = time.perf_counter()
    if template:
        frame_dots(ex, ref.spacing_px)
    t5 = time.perf_counter()
    if template:
        identify(img, ref, options=IdentifyOptions(method="template"), extraction=ex)
    t6 = time.perf_counter()
    return [t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5], int(valid.sum())


def median_blur_s(img: np.ndarray, passes: int = 3) -> float:
    """Seconds of one cv2.medianBlur 5x5 pass on one thread (the yardstick whatever the
    pipeline's threads): the mean of ``passes`` passes in a row."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        t0 = time.perf_counter()
        for _ in range(passes):
            cv2.medianBlur(img, 5)
        return (time.perf_counter() - t0) / passes
    finally:
        cv2.setNumThreads(threads)


def run(num_slits: int, repeat: int, workdir: Path) -> tuple[list[dict], dict]:
    spec = RigSpec()
    if num_slits != 25:
        spec = replace(
            spec, slits=replace(spec.slits, num_slits=num_slits, pitch_um=34.0 * num_slits / 25)
        )
    cap_dir = simulate_capture(workdir / f"cap{num_slits}", list(SCENES), spec, seed=1)
    cap = Capture.open(cap_dir)
    refs = [cap.image(p) for p in cap.references]
    prep = []
    for _ in range(3):
        t0 = time.perf_counter()
        ref = prepare_reference(refs, cap.num_slits)
        prep.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    cal = calibrate_capture(cap).calibration
    calibrate_s = time.perf_counter() - t0
    rig = rig_of(cal)
    images = {p.stem: cap.image(p) for p in cap.scans}
    # warm-up, untimed in the table: caches built on the reference, compiled kernels loaded
    first = None
    for name, img in images.items():
        s, npts = frame(img, ref, cal, rig)
        first = sum(s[: len(STAGES)]) if first is None else first
        want = len(scan_image(img, ref, cal).points)
        if npts != want:
            raise SystemExit(
                f"{num_slits} slits, {name}: the staged frame gives {npts} points but "
                f"scan_image {want}: the stages timed here are not scan_image's"
            )
    rows = []
    for name, img in images.items():
        stage, blur, npts = [], [], 0
        for _ in range(repeat):
            blur.append(median_blur_s(img))
            s, npts = frame(img, ref, cal, rig)
            stage.append(s)
        tracemalloc.start()
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        frame(img, ref, cal, rig, template=False)
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
        st = np.array(stage)
        total = float(np.median(st[:, : len(STAGES)].sum(axis=1)))
        mb = statistics.median(blur)
        row = {"slits": num_slits, "scene": name, "points": npts, "median_blur_ms": 1e3 * mb}
        row.update(
            {f"{k}_ms": 1e3 * float(np.median(st[:, i])) for i, k in enumerate((*STAGES, *BESIDE))}
        )
        row.update(
            total_ms=1e3 * total,
            ratio=total / mb,
            points_per_s=npts / total,
            peak_mb=peak / 2**20,
        )
        rows.append(row)
    prof = cProfile.Profile()
    prof.enable()
    for img in images.values():
        frame(img, ref, cal, rig, template=False)
    prof.disable()
    top = hot_spots(pstats.Stats(prof), len(images))
    return rows, {
        "slits": num_slits,
        "prepare_s": prep,
        "calibrate_s": calibrate_s,
        "first_s": first,
        "top": top,
    }


def hot_spots(stats: pstats.Stats, frames: int) -> list[tuple[str, float]]:
    """The ``TOP`` functions by time of their own: (``module:function`` or the built-in's
    name, ms per frame)."""
    own = []
    for (path, _, func), (_, _, tottime, _, _) in stats.stats.items():
        if path == "~":  # a built-in: "<built-in method cv2.morphologyEx>" and the like
            name = func.strip("<>{}").replace("built-in method ", "")
        else:
            name = f"{Path(path).stem}:{func}"
        own.append((name, 1e3 * tottime / frames))
    merged: dict[str, float] = {}
    for name, ms in own:
        merged[name] = merged.get(name, 0.0) + ms
    return sorted(merged.items(), key=lambda kv: -kv[1])[:TOP]


#: The variables the BLAS behind NumPy (OpenBLAS, MKL, OpenMP) and Numba read their thread
#: counts from as they load.
_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def threads_named(threads: int) -> str:
    """ "one thread" or "N threads"."""
    return "one thread" if threads == 1 else f"{threads} threads"


def table(rows: list[dict], preps: list[dict], threads: int = 1) -> str:
    on = threads_named(threads)
    lines = [
        f"OpenCV, BLAS and Numba on {on} (the medianBlur pass on one thread).",
        "",
        "| slits | scene | points | medianBlur ms | extract ms | identify ms | refine ms "
        "| triangulate ms | total ms | x medianBlur | points/s | peak MB "
        "| dots ms (in identify) | template identify ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['slits']} | {r['scene']} | {r['points']} | {r['median_blur_ms']:.2f} "
            f"| {r['extract_ms']:.1f} | {r['identify_ms']:.1f} | {r['refine_ms']:.1f} "
            f"| {r['triangulate_ms']:.1f} | {r['total_ms']:.1f} | {r['ratio']:.0f} "
            f"| {r['points_per_s']:.0f} | {r['peak_mb']:.0f} | {r[f'{DOTS}_ms']:.1f} "
            f"| {r[f'{TEMPLATE}_ms']:.1f} |"
        )
    lines.append("")
    lines.append(
        "Per stage, in medianBlur passes of the same frame (median over the scans; the dots, "
        "timed apart, are the identification's first step, counted in it; the template "
        "identification beside the pipeline, not in it):"
    )
    lines.append("")
    for n in sorted({r["slits"] for r in rows}):
        rs = [r for r in rows if r["slits"] == n]
        parts = ", ".join(
            f"{k.replace('_', ' ')} "
            f"{statistics.median(r[f'{k}_ms'] / r['median_blur_ms'] for r in rs):.1f}"
            for k in (*STAGES, *BESIDE)
        )
        lines.append(f"- {n} slits: {parts}")
    lines.append("")
    for n in sorted({r["slits"] for r in rows}):
        rs = [r for r in rows if r["slits"] == n]
        total = statistics.median(r["total_ms"] for r in rs)
        goal = GOALS_MS.get(n)
        if goal is not None:
            passes = statistics.median(r["ratio"] for r in rs)
            extra = f"; {passes:.0f} passes against {GOAL_PASSES}" if n == 25 else ""
            lines.append(
                f"- {n} slits against the goal (one core): {total:.0f} ms on {on} against "
                f"{goal:.0f} ms ({total / goal:.1f}x){extra}"
            )
    lines.append("")
    for p in preps:
        spots = ", ".join(f"{name} {ms:.1f}" for name, ms in p["top"])
        lines.append(f"Where the time goes, {p['slits']} slits (ms per frame, own time): {spots}.")
        lines.append("")
    for p in preps:
        s = p["prepare_s"]
        lines.append(
            f"Reference preparation (`prepare_reference`, {p['slits']} slits): "
            f"{min(s):.2f}-{max(s):.2f} s over {len(s)} runs; the first frame after it "
            f"(caches built on the reference, compiled kernels loaded) {1e3 * p['first_s']:.0f} ms; "
            f"calibration (`calibrate_capture`, not timed in the frames) {p['calibrate_s']:.0f} s."
        )
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    lines.append(f"\nProcess max RSS at the end: {rss:.0f} MB.")
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines.append(f"Load average at the end (1, 5, 15 min): {load} on {os.cpu_count()} cores.")
    return "\n".join(lines)


def on_threads(threads: int) -> None:
    """Run this benchmark with OpenCV, the BLAS and Numba on ``threads`` threads. The BLAS and
    Numba read their thread count as they load, so the process starts again with the
    variables set (once); OpenCV's and Numba's are then set in the process."""
    if any(os.environ.get(k) != str(threads) for k in _THREAD_VARS):
        os.environ.update(dict.fromkeys(_THREAD_VARS, str(threads)))
        os.execv(sys.executable, [sys.executable, *sys.argv])
    set_threads(threads)


class _Parser(argparse.ArgumentParser):
    """Bad arguments get one line and exit status 2 (no usage block)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message}\n")


def _at_least(least: int) -> Callable[[str], int]:
    """An argparse type: a whole number of at least ``least`` (argparse names the option)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"a whole number is needed, got {text!r}") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"at least {least} is needed, got {value}")
        return value

    return parse


def main() -> None:
    ap = _Parser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--slits",
        type=_at_least(2),
        nargs="+",
        default=[25, 49],
        help="rigs to time (default 25 49)",
    )
    ap.add_argument(
        "--repeat",
        type=_at_least(1),
        default=5,
        help="runs per frame; the median is kept (default 5)",
    )
    ap.add_argument(
        "--threads",
        type=_at_least(1),
        default=1,
        help="threads of OpenCV, the BLAS and Numba (default 1: one core)",
    )
    ap.add_argument(
        "--write",
        action="store_true",
        help="replace the speed section of benchmarks/RESULTS.md (N threads: a section of its own)",
    )
    args = ap.parse_args()
    on_threads(args.threads)
    compile_kernels()
    rows, preps = [], []
    with tempfile.TemporaryDirectory() as d:
        for n in args.slits:
            r, p = run(n, args.repeat, Path(d))
            rows += r
            preps.append(p)
    text = table(rows, preps, args.threads)
    print(text)
    if args.write:
        note = (
            f"OpenCV, BLAS and Numba on {threads_named(args.threads)}; medians over the runs "
            "of each frame; the pipeline is `scan_image`'s with the default options "
            '(identification by the dots\' geometry); "refine" is its centre refinement; '
            "\"dots\" is the frame's dots (`frame_dots`), the identification's first step, timed "
            'apart; "template identify" is the paper\'s template identification of the same '
            'frame, beside the pipeline, not in its total; "peak MB" is tracemalloc\'s peak of '
            "the Python/NumPy allocations in one frame of the pipeline.\n\n"
        )
        one = args.threads == 1
        write_section(
            "bench_speed" if one else f"bench_speed_threads{args.threads}",
            "Speed (one core, full size 1280x1024)"
            if one
            else f"Speed ({args.threads} threads, full size 1280x1024)",
            note + text,
            command_line("bench_speed.py"),
        )


if __name__ == "__main__":
    main()
