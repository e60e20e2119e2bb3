"""Command-line interface: a thin layer over the library. All printing happens here."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from multislit import __version__
from multislit.errors import MultislitError


def _progress(prefix: str):
    """A one-line progress indicator on stderr (only on a terminal)."""
    tty = sys.stderr.isatty()
    t0 = time.perf_counter()

    def cb(i: int, n: int, name: str) -> None:
        el = time.perf_counter() - t0
        msg = f"\r{prefix} [{i}/{n}] {name:<28s} {el:6.1f} s"
        if tty:
            sys.stderr.write(msg)
            if i >= n:
                sys.stderr.write("\n")
            sys.stderr.flush()
        elif i >= n:
            sys.stderr.write(msg.lstrip("\r") + "\n")

    return cb


def cmd_simulate(args: argparse.Namespace) -> int:
    from multislit.sim import SCENES, RigSpec, simulate_capture

    spec = RigSpec.load(args.rig) if args.rig else RigSpec()
    if args.slits:
        from dataclasses import replace

        spec = replace(spec, slits=replace(spec.slits, num_slits=args.slits))
    if args.scale != 1.0:
        spec = spec.scaled(args.scale)
    scenes = list(SCENES) if args.scene == ["all"] else (args.scene or ["holes"])
    out = simulate_capture(
        args.outdir,
        scenes,
        spec,
        seed=args.seed,
        progress=_progress("simulate"),
        overwrite=args.overwrite,
    )
    w, h = spec.camera.image_size
    print(
        f"wrote capture {out} ({w}x{h} px, {spec.slits.num_slits} slits, scans: {', '.join(scenes)})"
    )
    return 0


def cmd_rig(args: argparse.Namespace) -> int:
    from multislit.sim import RigSpec

    print(RigSpec().to_json())
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from multislit.app.demo import run_demo

    result = run_demo(Path(args.out), seed=args.seed, scale=args.scale, progress=_progress("demo"))
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for line in result["report"]:
            print(line)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from multislit.calibrate import calibrate_capture, format_report, write_calibration

    capture = Path(args.capture)
    result = calibrate_capture(capture, source=args.source)
    out = Path(args.output) if args.output else capture / "calibration.json"
    write_calibration(result, out)
    for line in format_report(result):
        print(line)
    print(f"wrote {out}")
    return 0


def cmd_scan(args: argparse.Namespace) -> int:
    from multislit.errors import MeasurementError
    from multislit.io import Capture
    from multislit.reconstruct import scan_capture

    cap = Capture.open(args.capture, require_target=False)
    images = [Path(args.image)] if args.image else None
    if images is None and not cap.scans:
        raise MeasurementError(
            f"no scans in {cap.root / 'scans'} (no *.png images); add scans or use --image FILE"
        )
    n = len(images) if images else len(cap.scans)
    outdir = Path(args.output) if args.output else cap.root / "points"
    results = scan_capture(
        cap,
        calibration=args.calibration,
        images=images,
        progress=_progress("scan") if n > 3 else None,
    )
    outdir.mkdir(parents=True, exist_ok=True)
    for name, res in results.items():
        path = res.write_ply(outdir / f"{name}.ply", comment=f"multislit scan {name}")
        print(f"{res.summary()} -> {path}")
    return 0


def cmd_holes(args: argparse.Namespace) -> int:
    from multislit.errors import MeasurementError
    from multislit.measure import measure_holes, measure_holes_from_points
    from multislit.reconstruct import ScanResult

    src = Path(args.source)
    measurements = {}
    if src.is_dir():
        from multislit.identify import capture_reference
        from multislit.io import Capture
        from multislit.reconstruct import load_capture_calibration

        cap = Capture.open(src, require_target=False)
        cal = load_capture_calibration(cap, args.calibration)
        paths = [Path(args.image)] if args.image else list(cap.scans)
        if not paths:
            raise MeasurementError(
                f"no scans to measure: {cap.root / 'scans'} has no *.png images (or give one image)"
            )
        ref = capture_reference(cap)
        for path in paths:
            measurements[path.stem] = measure_holes(
                cap.image(path), ref, cal, min_slits=args.min_slits, name=path.stem
            )
    elif src.is_file():
        res = ScanResult.from_ply(src)
        measurements[src.stem] = measure_holes_from_points(res, min_slits=args.min_slits)
    else:
        raise MeasurementError(f"not a PLY file or capture folder: {src}")
    if args.json:
        print(json.dumps({k: m.to_dict() for k, m in measurements.items()}, indent=1))
        return 0
    for name, m in measurements.items():
        print(
            f"{name}: plate plane RMS {m.plane_rms:.3f} mm, {len(m.edges)} edge points "
            f"({m.method}), {len(m.measurable)} measurable hole(s)"
        )
        for i, h in enumerate(m.holes, 1):
            c = ", ".join(f"{x:.2f}" for x in h.centre)
            if h.measurable:
                print(
                    f"  hole {i}: centre ({c}) mm, diameter {h.diameter:.2f} mm, "
                    f"{h.n_inliers}/{h.n_points} edge points, {h.n_slits} slits, "
                    f"fit RMS {h.rms:.3f} mm"
                )
            else:
                print(f"  hole {i}: near ({c}) mm, not measurable: {h.reason}")
        if m.method == "geometric":
            print(
                "  (edges from the points only: the rows left unidentified at each stripe end "
                "make holes come out too large, by millimetres; give the capture folder for "
                "sub-pixel edges)"
            )
    return 0


def build_parser() -> argparse.ArgumentParser:
    from multislit.sim import SCENES

    p = argparse.ArgumentParser(
        prog="multislit",
        description="Single-shot 3D measurement with multiple laser slits and random dots.",
    )
    p.add_argument("--version", action="version", version=f"multislit {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser(
        "simulate", help="simulate a rig and write a capture folder with ground truth"
    )
    s.add_argument("outdir", help="capture folder to create")
    s.add_argument(
        "--scene",
        action="append",
        choices=[*SCENES, "all"],
        help="scan scene (repeatable; default holes; 'all' for every scene)",
    )
    s.add_argument("--seed", type=int, default=0, help="noise seed (same seed, same images)")
    s.add_argument("--rig", help="rig description JSON (see 'multislit rig')")
    s.add_argument("--slits", type=int, help="override the number of slits")
    s.add_argument(
        "--scale", type=float, default=1.0, help="camera resolution factor (0.5: 640x512)"
    )
    s.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("rig", help="print the default rig description (JSON) to edit for --rig")
    r.set_defaults(func=cmd_rig)

    c = sub.add_parser("calibrate", help="calibrate camera and projector from a capture folder")
    c.add_argument("capture", help="capture folder (rig.json, target.json, calibration/*.png)")
    c.add_argument(
        "-o", "--output", help="calibration file to write (default CAPTURE/calibration.json)"
    )
    c.add_argument(
        "--source",
        choices=["auto", "hand"],
        default="auto",
        help="points on the slits: auto (from calibration/slits.png, identified slits; falls "
        "back to the hand readings if identification is unavailable) or hand (target.json "
        "slit_points, the paper's way); default auto",
    )
    c.set_defaults(func=cmd_calibrate)

    sc = sub.add_parser("scan", help="measure the scans of a capture: 3D points as PLY files")
    sc.add_argument("capture", help="capture folder (rig.json, reference/, scans/)")
    sc.add_argument("-o", "--output", help="folder for the PLY files (default CAPTURE/points)")
    sc.add_argument("--image", help="scan only this image (default: every scans/*.png)")
    sc.add_argument("--calibration", help="calibration file (default CAPTURE/calibration.json)")
    sc.set_defaults(func=cmd_scan)

    ho = sub.add_parser("holes", help="measure holes in a flat plate (paper Table 1)")
    ho.add_argument(
        "source",
        help="a PLY from 'multislit scan' (edges from the points) or a capture folder "
        "(sub-pixel edges from the images)",
    )
    ho.add_argument("--image", help="with a capture: only this scan image")
    ho.add_argument("--calibration", help="with a capture: calibration file")
    ho.add_argument(
        "--min-slits", type=int, default=3, help="fewest slits crossing a measurable hole"
    )
    ho.add_argument("--json", action="store_true", help="print the results as JSON")
    ho.set_defaults(func=cmd_holes)

    d = sub.add_parser("demo", help="the paper's experiment end to end on the simulated rig")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    d.add_argument("--scale", type=float, default=1.0, help="camera resolution factor")
    d.add_argument("--json", action="store_true", help="print the figures as JSON")
    d.set_defaults(func=cmd_demo)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except MultislitError as exc:
        print(f"multislit {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
