"""Command-line interface: a thin layer over the library. All printing happens here."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from . import __version__
from .errors import MultislitError


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
    from .sim.rig import RigSpec
    from .sim.scene import SCENES
    from .sim.simulate import simulate_capture

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
    from .sim.rig import RigSpec

    print(RigSpec().to_json())
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    result = run_demo(Path(args.out), seed=args.seed, scale=args.scale, progress=_progress("demo"))
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for line in result["report"]:
            print(line)
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .sim.scene import SCENES

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

    d = sub.add_parser("demo", help="the paper's experiment end to end on the simulated rig")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--seed", type=int, default=0)
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
