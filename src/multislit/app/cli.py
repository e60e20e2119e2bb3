"""Command-line interface: a thin layer over the library. All printing happens here."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from multislit import __version__
from multislit.errors import MultislitError
from multislit.io.paths import as_path, check_output_dir


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


#: The largest camera the simulator is asked for, in pixels (W x H). Its peak memory grows by
#: about 0.35 GB per Mpx (0.64 GB at 1280x1024, 2.0 GB at 2560x2048: ``/usr/bin/time -v
#: multislit simulate OUT --scene plane --scale 2``), so this is about 6 GB.
_MAX_SIM_PIXELS = 16_000_000

#: Simulator memory per camera pixel, bytes (see :data:`_MAX_SIM_PIXELS`).
_SIM_BYTES_PER_PIXEL = 354


def _check_seed(seed: int) -> None:
    if seed < 0:
        raise MultislitError(f"--seed must be a non-negative integer, got {seed}")


def _check_sim_size(spec, option: str) -> None:
    """Refuse a simulated camera too large for memory (``option`` names what set its size)."""
    w, h = spec.camera.image_size
    if w * h > _MAX_SIM_PIXELS:
        gb = w * h * _SIM_BYTES_PER_PIXEL / 1e9
        raise MultislitError(
            f"{option} gives a {w}x{h} px camera ({w * h / 1e6:.1f} Mpx, about {gb:.0f} GB of "
            f"memory to simulate); the limit is {_MAX_SIM_PIXELS / 1e6:.0f} Mpx (about "
            f"{_MAX_SIM_PIXELS * _SIM_BYTES_PER_PIXEL / 1e9:.0f} GB): use a smaller one"
        )


def _refuse_inputs(outputs: Sequence[Path], inputs: Sequence[Path], option: str) -> None:
    """Refuse to write an output over one of the command's input files."""
    seen = {}
    for q in inputs:
        if q.is_file():
            seen[q.resolve()] = q
    for out in outputs:
        r = Path(out).resolve()
        hit = seen.get(r)
        if hit is None and r.exists():
            hit = next((q for q in seen.values() if os.path.samefile(q, r)), None)
        if hit is not None:
            raise MultislitError(
                f"the output {out} would overwrite an input of the command ({hit}); "
                f"choose another {option}"
            )


def _capture_files(cap) -> list[Path]:
    """The files of a capture folder that the commands read (never written over)."""
    return [
        cap.root / "rig.json",
        cap.root / "target.json",
        cap.markers_image,
        cap.slits_image,
        *cap.references,
        *cap.scans,
    ]


def cmd_simulate(args: argparse.Namespace) -> int:
    from multislit.io import read_json
    from multislit.sim import SCENES, RigSpec, simulate_capture

    _check_seed(args.seed)
    check_output_dir(args.outdir, "OUTDIR")
    if args.slits is not None and args.slits < 1:
        raise MultislitError(f"--slits must be a positive number of slits, got {args.slits}")
    if not math.isfinite(args.scale):
        raise MultislitError(f"--scale must be a finite positive number, got {args.scale}")
    try:
        spec = RigSpec.from_dict(read_json(args.rig, what="rig file")) if args.rig else RigSpec()
        if args.slits is not None:
            from dataclasses import replace

            spec = replace(spec, slits=replace(spec.slits, num_slits=args.slits))
        if args.scale != 1.0:
            spec = spec.scaled(args.scale)
        spec.validate()
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        if isinstance(exc, MultislitError):
            raise
        raise MultislitError(
            f"rig file {args.rig}: a value has the wrong type ({exc}); compare with 'multislit rig'"
        ) from None
    _check_sim_size(spec, f"--scale {args.scale:g}" if args.scale != 1.0 else "the rig file")
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

    _check_seed(args.seed)
    check_output_dir(args.out, "--out")
    result = run_demo(Path(args.out), seed=args.seed, scale=args.scale, progress=_progress("demo"))
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for line in result["report"]:
            print(line)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from multislit.calibrate import calibrate_capture, format_report, write_calibration
    from multislit.io import Capture

    capture = as_path(args.capture, "CAPTURE")
    out = as_path(args.output, "-o") if args.output is not None else capture / "calibration.json"
    if out.is_dir():
        raise MultislitError(f"-o {out} is a folder; give the calibration file's name")
    check_output_dir(out.parent, "-o")
    _refuse_inputs([out], _capture_files(Capture.open(capture)), "-o")
    result = calibrate_capture(capture, source=args.source)
    write_calibration(result, out)
    for line in format_report(result):
        print(line)
    print(f"wrote {out}")
    return 0


def cmd_scan(args: argparse.Namespace) -> int:
    from multislit.app.pictures import encode_png, scan_picture
    from multislit.errors import MeasurementError
    from multislit.io import Capture, write_bytes_atomic
    from multislit.reconstruct import scan_capture

    outdir = check_output_dir(args.output, "-o") if args.output is not None else None
    cap = Capture.open(args.capture, require_target=False)
    images = [as_path(args.image, "--image")] if args.image is not None else None
    if images is None and not cap.scans:
        raise MeasurementError(
            f"no scans in {cap.root / 'scans'} (no *.png images); add scans or use --image FILE"
        )
    n = len(images) if images else len(cap.scans)
    outdir = outdir if outdir is not None else check_output_dir(cap.root / "points", "-o")
    cal_file = (
        as_path(args.calibration, "--calibration")
        if args.calibration is not None
        else cap.root / "calibration.json"
    )
    outputs = [outdir / f"{p.stem}{ext}" for p in (images or cap.scans) for ext in (".ply", ".png")]
    _refuse_inputs(outputs, [*_capture_files(cap), *(images or []), cal_file], "-o")
    results = scan_capture(
        cap,
        calibration=args.calibration,
        images=images,
        progress=_progress("scan") if n > 3 else None,
        options=_scan_options(args),
    )
    outdir.mkdir(parents=True, exist_ok=True)
    failed = []
    paths = {p.stem: p for p in (images or cap.scans)}
    for name, res in results.items():
        if res.num_points == 0:
            failed.append(f"{name}: {res.message or 'no points'}")
            continue
        path = res.write_ply(outdir / f"{name}.ply", comment=f"multislit scan {name}")
        if args.pictures:
            plane = cap.image(paths[name], channel=res.options.extraction.channel)
            picture = scan_picture(plane, res, num_slits=cap.num_slits)
            write_bytes_atomic(outdir / f"{name}.png", encode_png(picture))
        print(f"{res.summary()} -> {path}")
    if failed:
        raise MeasurementError(
            f"{len(failed)} of {len(results)} scan(s) gave no points (no PLY written): "
            + "; ".join(failed)
        )
    return 0


def cmd_holes(args: argparse.Namespace) -> int:
    from multislit.errors import MeasurementError
    from multislit.measure import measure_holes

    src = as_path(args.source, "SOURCE")
    measurements = {}
    if src.is_dir():
        from multislit.identify import capture_reference
        from multislit.io import Capture
        from multislit.reconstruct import load_capture_calibration

        cap = Capture.open(src, require_target=False)
        cal = load_capture_calibration(cap, args.calibration)
        paths = [as_path(args.image, "--image")] if args.image is not None else list(cap.scans)
        if not paths:
            raise MeasurementError(
                f"no scans to measure: {cap.root / 'scans'} has no *.png images (or give one image)"
            )
        ref = capture_reference(cap)
        options = _scan_options(args)
        for path in paths:
            measurements[path.stem] = measure_holes(
                cap.image(path, channel=options.extraction.channel),
                ref,
                cal,
                options,
                min_slits=args.min_slits,
                name=path.stem,
            )
    elif src.is_file():
        raise MeasurementError(_holes_from_ply_refused(src))
    else:
        raise MeasurementError(f"not a PLY file or capture folder: {src}")
    if args.json:
        d = {k: {**m.to_dict(), "options": options.to_dict()} for k, m in measurements.items()}
        print(json.dumps(d, indent=1))
        return 0
    for m in measurements.values():
        print(m.summary())
    return 0


def _camera_features(items: Sequence[str] | None) -> list[tuple[str, str]]:
    from multislit.errors import MultislitError

    out = []
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise MultislitError(f"--pylon {item!r}: give NAME=VALUE, e.g. ExposureTime=2000")
        out.append((key, value))
    return out


def cmd_stream(args: argparse.Namespace) -> int:
    from multislit.app.stream import ProgressLine, stream

    s = stream(
        args.capture,
        args.source,
        args.output,
        workers=args.workers,
        camera_features=_camera_features(args.pylon),
        prior=args.prior,
        pictures=args.pictures,
        progress=ProgressLine("stream: "),
        **_frame_settings(args),
    )
    print(f"wrote {s.frames} frame(s) to {s.out} ({s.skipped} skipped, {s.dropped} dropped)")
    return 0


def cmd_batch(args: argparse.Namespace) -> int:
    from multislit.app.batch import batch
    from multislit.app.stream import ProgressLine

    s = batch(
        args.capture,
        args.source,
        args.output,
        address=args.dask,
        workers=args.workers,
        pictures=args.pictures,
        progress=ProgressLine("batch: "),
        **_frame_settings(args),
    )
    print(f"wrote {s.frames} frame(s) to {s.out} ({s.skipped} skipped)")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from multislit.app.view import write_view

    path = write_view(
        args.source,
        args.output,
        color=args.color,
        max_points=args.max_points,
        calibration=args.calibration,
    )
    print(f"wrote {path}")
    return 0


_PICTURES_HELP = (
    "write beside each PLY a picture (NAME.png): the frame with the stripe points coloured by "
    "slit and the stripe centres left out in magenta"
)


def _scan_option_flags(p: argparse.ArgumentParser, dot_points: bool = True) -> None:
    """The flags of the scan's options (:class:`~multislit.reconstruct.ScanOptions`);
    ``--dot-points`` where the command writes points."""
    from multislit.identify import METHODS
    from multislit.stripes import CHANNEL_CHOICES

    p.add_argument(
        "--channel",
        choices=CHANNEL_CHOICES,
        help="colour images: the laser's channel; auto: in each image the plane in which the "
        "stripes stand out most, clipped planes avoided (default: --options, else rig.json "
        "laser_channel, else auto)",
    )
    p.add_argument(
        "--reject-texture",
        action="store_true",
        default=None,
        help="the photo mode: keep only centres that look like a laser line (photos of a "
        "line on a checkerboard, a turntable, a textured object)",
    )
    p.add_argument(
        "--method",
        choices=METHODS,
        help="how slits are identified: geometry (default: where the calibrated dot "
        "projector's rays put the dots beside each piece of stripe, and its neighbours) or "
        "template (the paper's template matching with the reference images)",
    )
    if dot_points:
        p.add_argument(
            "--dot-points",
            action="store_true",
            default=None,
            help="also measure the dots the identification by the dots' geometry identified (each "
            "where its line of sight crosses its dot's ray): points between the slits, written "
            "to the PLY with the property dot = 1",
        )
    p.add_argument(
        "--options",
        metavar="FILE.json",
        help='the scan\'s options, stage by stage: {"extraction": {...}, '
        '"identification": {...}, "refinement": {...}}; --channel, --reject-texture, '
        "--method and --dot-points override it",
    )


def _scan_options(args: argparse.Namespace):
    """The ScanOptions of the command line: the options file, then the flags."""
    from multislit.reconstruct import ScanOptions

    options = ScanOptions.load(args.options) if args.options is not None else ScanOptions()
    changes = {}
    if args.channel is not None:
        changes["channel"] = args.channel
    if args.reject_texture is not None:
        changes["reject_texture"] = args.reject_texture
    if changes:
        options = options.with_extraction(**changes)
    if args.method is not None:
        options = replace(
            options, identification=replace(options.identification, method=args.method)
        )
    if getattr(args, "dot_points", None):
        options = replace(options, refinement=replace(options.refinement, dot_points=True))
    return options


def _frame_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", help="capture folder (rig.json, reference/, calibration.json)")
    p.add_argument(
        "source",
        help="frames: an image folder or glob (PNG/TIFF/JPEG, 8/16 bit), a video file, "
        "camera:N (OpenCV) or basler:[SERIAL] (pypylon)",
    )
    p.add_argument("-o", "--output", required=True, help="OUT folder for frame_*.ply, frames.jsonl")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--every", type=int, default=1, help="scan every K-th frame (default 1)")
    p.add_argument(
        "--on-bad-frame",
        choices=["skip", "stop"],
        default="skip",
        help="a frame of the wrong size or unreadable: skip and count it (default) or stop",
    )
    _scan_option_flags(p)
    p.add_argument("--calibration", help="calibration file (default CAPTURE/calibration.json)")
    p.add_argument("--overwrite", action="store_true", help="replace frames already in OUT")
    p.add_argument("--pictures", action="store_true", help=_PICTURES_HELP)


def _frame_settings(args: argparse.Namespace) -> dict:
    """The keyword arguments of ``stream`` and ``batch`` that :func:`_frame_options` reads."""
    return {
        "max_frames": args.max_frames,
        "every": args.every,
        "on_bad_frame": args.on_bad_frame,
        "options": _scan_options(args),
        "calibration": args.calibration,
        "overwrite": args.overwrite,
    }


def _holes_from_ply_refused(ply: Path) -> str:
    """Why ``holes PLY`` is refused, with the command that measures the holes properly."""
    cap, image = "CAPTURE", "CAPTURE/scans/NAME.png"
    guess = ply.parent.parent  # 'multislit scan' writes CAPTURE/points/NAME.ply
    if (guess / "rig.json").is_file() and (guess / "scans" / f"{ply.stem}.png").is_file():
        cap, image = str(guess), str(guess / "scans" / f"{ply.stem}.png")
    return (
        f"{ply}: holes are not measured from a PLY: its points alone put the hole edges "
        "millimetres outside the rims (the rows left unidentified at each stripe end); measure "
        f"from the capture, whose images give sub-pixel edges: multislit holes {cap} --image {image}"
    )


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
    sc.add_argument("--pictures", action="store_true", help=_PICTURES_HELP)
    _scan_option_flags(sc)
    sc.set_defaults(func=cmd_scan)

    ho = sub.add_parser("holes", help="measure holes in a flat plate (paper Table 1)")
    ho.add_argument(
        "source",
        help="a capture folder (sub-pixel edges from its scan images); a PLY is refused, with "
        "the command for its capture",
    )
    ho.add_argument("--image", help="with a capture: only this scan image")
    ho.add_argument("--calibration", help="with a capture: calibration file")
    ho.add_argument(
        "--min-slits", type=int, default=3, help="fewest slits crossing a measurable hole"
    )
    ho.add_argument("--json", action="store_true", help="print the results as JSON")
    _scan_option_flags(ho, dot_points=False)
    ho.set_defaults(func=cmd_holes)

    st = sub.add_parser("stream", help="scan a stream of frames: camera, video or images")
    _frame_options(st)
    st.add_argument("--workers", type=int, default=1, help="processes scanning frames (default 1)")
    st.add_argument(
        "--prior",
        action="store_true",
        help="with --method template: check each frame's stripes against the previous "
        "frame's slits first (faster on a moving scene; frames in order, --workers 1)",
    )
    st.add_argument(
        "--pylon",
        action="append",
        metavar="NAME=VALUE",
        help="set a Basler camera feature (repeatable), e.g. ExposureTime=2000",
    )
    st.set_defaults(func=cmd_stream)

    ba = sub.add_parser("batch", help="scan an archive of frames on a Dask cluster")
    _frame_options(ba)
    ba.add_argument("--dask", metavar="ADDRESS", help="Dask scheduler (default: a local cluster)")
    ba.add_argument(
        "--workers", type=int, default=2, help="local cluster workers (default 2; not with --dask)"
    )
    ba.set_defaults(func=cmd_batch)

    vw = sub.add_parser("view", help="an interactive 3D view (HTML) of a PLY or an OUT folder")
    vw.add_argument("source", help="a PLY file or an OUT folder of 'multislit stream'")
    vw.add_argument("-o", "--output", required=True, help="HTML file to write")
    vw.add_argument("--color", choices=["depth", "slit"], default="depth", help="initial colouring")
    vw.add_argument(
        "--max-points", type=int, default=50000, help="points drawn per frame (default 50000)"
    )
    vw.add_argument(
        "--calibration",
        help="the rig's calibration: the page opens from its camera's viewpoint (default: the "
        "capture's beside a scan's PLY, or the one OUT/run.json names)",
    )
    vw.set_defaults(func=cmd_view)

    d = sub.add_parser("demo", help="the paper's experiment end to end on the simulated rig")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    d.add_argument("--scale", type=float, default=1.0, help="camera resolution factor")
    d.add_argument("--json", action="store_true", help="print the figures as JSON")
    d.set_defaults(func=cmd_demo)
    return p


class _Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``): the command ends like on Ctrl-C, its worker processes and cluster
    closed and its files left whole."""


def _terminated(signum: int, frame: object) -> None:
    raise _Terminated


def _text_streams() -> None:
    """stdout and stderr write any file name: characters the terminal's encoding lacks (or
    bytes of a name that is not UTF-8) as backslash escapes instead of an exception."""
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _text_streams()
    main_thread = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, _terminated) if main_thread else None
    try:
        return _run(args)
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def _run(args: argparse.Namespace) -> int:
    try:
        return int(args.func(args) or 0)
    except MultislitError as exc:
        print(f"multislit {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file system failure the command did not foresee
        where = f": {exc.filename}" if exc.filename else ""
        print(f"multislit {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2
    except _Terminated:
        print("terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
