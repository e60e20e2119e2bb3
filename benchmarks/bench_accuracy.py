"""VDI/VDE 2634-2-style acceptance of the single-shot scanner on simulated scans.

One simulated rig (the default: 25 slits identified by random dots), calibrated once from the
paper's hand readings (``calibrate_capture(capture, source="hand")``) with one reference set, scans:

* spheres (radius 60 mm, ~0.14 of the measuring volume's diagonal) at three positions and
  depths (800, 900, 1000 mm): probing error size PS and form PF from the points within
  r + 5 mm of the true centre;
* a ball bar (two spheres r = 40 mm, 300 mm apart) at 0, 45 and 90 deg in the image plane and
  tilted 30 deg in depth: sphere-spacing error SD;
* a flat plate of 360 x 260 mm (~half the diagonal) fronto-parallel and tilted 25 deg about the
  vertical and about the horizontal axis: flatness error F from the points within 5 mm of the
  true plane;

and the demo's hole table (:func:`multislit.app.demo.run_demo`, its own rig with 49 slits).
Ranges are given with all points and with the 0.3 % largest residuals left out (the guideline
allows that). No MPE is specified for this rig, so no pass/fail.

Run:  .venv/bin/python benchmarks/bench_accuracy.py [--scale S] [--seed N] [--no-write]
(default full size, 1280x1024; writes the tables into benchmarks/RESULTS.md), or with
``--seeds N N ...`` the run-to-run spread: the suite without the holes once per seed, each a
repeat of the whole experiment (a section of its own in RESULTS.md)
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from results import RESULTS, command_line, write_section

from multislit.calibrate import Calibration, calibrate_capture
from multislit.errors import MultislitError
from multislit.geometry import fit_sphere
from multislit.identify import ReferenceSet, capture_reference
from multislit.io import Capture
from multislit.measure import (
    flatness_error,
    markdown_table,
    probing_error_form,
    probing_error_size,
    sphere_spacing_error,
)
from multislit.reconstruct import ScanResult, scan_image
from multislit.sim import Polygon, Primitive, Scene, Sphere, constant
from multislit.sim.rig import RigSpec
from multislit.sim.simulate import simulate_capture

RIG_Z = 1000.0  # the rig's z in the world (scene.py convention)
WALL_Z = RIG_Z - 1150.0  # a far wall behind every artefact
SELECT_MM = 5.0  # points within r + 5 mm of a true sphere centre, 5 mm of a true plane
EXCLUDE = 0.003  # the guideline's 0.3 %


# --------------------------------------------------------------------------- artefacts
def _wall() -> Polygon:
    return Polygon((0, 0, WALL_Z), (0, 0, 1), texture=constant(0.55), name="wall")


def sphere_scene(name: str, centre: tuple[float, float, float], radius: float) -> Scene:
    """One sphere before the far wall; truth ``info["spheres"]``."""
    prims: list[Primitive] = [Sphere(centre, radius, name="sphere"), _wall()]
    return Scene(name, prims, {"spheres": [{"centre": list(centre), "radius": radius}]})


def bar_scene(
    name: str,
    direction: tuple[float, float, float],
    length: float = 300.0,
    radius: float = 40.0,
    mid: tuple[float, float, float] = (0.0, 0.0, RIG_Z - 900.0),
) -> Scene:
    """A ball bar: two spheres ``length`` apart along ``direction`` about ``mid``."""
    e = np.asarray(direction, float)
    e /= np.linalg.norm(e)
    c1 = np.asarray(mid, float) - 0.5 * length * e
    c2 = np.asarray(mid, float) + 0.5 * length * e
    prims: list[Primitive] = [Sphere(c1, radius, name="ball1"), Sphere(c2, radius, name="ball2")]
    prims.append(_wall())
    info = {
        "spheres": [
            {"centre": c1.tolist(), "radius": radius},
            {"centre": c2.tolist(), "radius": radius},
        ],
        "length": length,
    }
    return Scene(name, prims, info)


def plate_scene(
    name: str,
    normal: tuple[float, float, float],
    size: tuple[float, float] = (360.0, 260.0),
    centre: tuple[float, float, float] = (0.0, 0.0, RIG_Z - 900.0),
) -> Scene:
    """A flat rectangular plate (``size`` mm) before the far wall; truth ``info["plane"]``."""
    a, b = size[0] / 2, size[1] / 2
    plate = Polygon(
        centre,
        normal,
        outline=np.array([[-a, -b], [a, -b], [a, b], [-a, b]], float),
        texture=constant(0.75),
        name="plate",
    )
    return Scene(name, [plate, _wall()], {"plane": plate.plane.tolist(), "size": list(size)})


def _tilt(axis: str, deg: float) -> tuple[float, float, float]:
    t = np.radians(deg)
    return (np.sin(t), 0.0, np.cos(t)) if axis == "y" else (0.0, np.sin(t), np.cos(t))


def default_artefacts(full: bool = True) -> list[Scene]:
    """The suite's scenes: 3 spheres of 120 mm, 3 of 40 mm, 4 ball bars, 3 plates (``full``);
    else 1 sphere, 1 bar, 1 plate."""
    z = RIG_Z
    spheres = [
        sphere_scene("sphere_800", (-100.0, 80.0, z - 800.0), 60.0),
        sphere_scene("sphere_900", (0.0, 0.0, z - 900.0), 60.0),
        sphere_scene("sphere_1000", (110.0, -80.0, z - 1000.0), 60.0),
    ]
    # small spheres (d = 40 mm) at 0.9 m, in three places: crossed by two or three slits
    small = [
        sphere_scene(f"sphere40_{i}", (x, y, z - 900.0), 20.0)
        for i, (x, y) in enumerate(((-120.0, 60.0), (5.0, -10.0), (130.0, -70.0)))
    ]
    c30, s30 = np.cos(np.radians(30)), np.sin(np.radians(30))
    bars = [
        bar_scene("bar_0deg", (1.0, 0.0, 0.0)),
        bar_scene("bar_45deg", (1.0, 1.0, 0.0)),
        bar_scene("bar_90deg", (0.0, 1.0, 0.0)),
        bar_scene("bar_depth30", (c30, 0.0, s30)),
    ]
    plates = [
        plate_scene("plate_0deg", (0.0, 0.0, 1.0)),
        plate_scene("plate_y25deg", _tilt("y", 25.0)),
        plate_scene("plate_x25deg", _tilt("x", 25.0)),
    ]
    if full:
        return spheres + small + bars + plates
    return [spheres[1], bars[0], plates[1]]


# --------------------------------------------------------------------------- rig
@dataclass
class PreparedRig:
    """A simulated capture calibrated once (hand readings) with its reference set."""

    capture: Capture
    calibration: Calibration
    reference: ReferenceSet
    scenes: dict[str, dict[str, Any]]  # truth models.json "scenes"
    seconds: dict[str, float]


def prepare_rig(spec: RigSpec, scenes: list[Scene], out: Path, seed: int) -> PreparedRig:
    """Simulate the capture (calibration, reference and the scans), calibrate, prepare."""
    t0 = time.perf_counter()
    cap_dir = simulate_capture(out, scenes, spec, seed=seed, overwrite=True)
    t1 = time.perf_counter()
    cap = Capture.open(cap_dir)
    cal = calibrate_capture(cap, source="hand").calibration
    t2 = time.perf_counter()
    ref = capture_reference(cap)
    t3 = time.perf_counter()
    truth = json.loads((cap_dir / "truth" / "models.json").read_text())["scenes"]
    secs = {"simulation": t1 - t0, "calibration": t2 - t1, "reference": t3 - t2}
    return PreparedRig(cap, cal, ref, truth, secs)


def scan(rig: PreparedRig, name: str) -> ScanResult:
    path = rig.capture.root / "scans" / f"{name}.png"
    return scan_image(rig.capture.image(path), rig.reference, rig.calibration, name=name)


# --------------------------------------------------------------------------- metrics
def _safe(f, *a, **k) -> float:
    try:
        return float(f(*a, **k))
    except MultislitError:
        return float("nan")


def _near_sphere(points: np.ndarray, sphere: dict) -> np.ndarray:
    """(N,) bool: the points within r + SELECT_MM of the true centre."""
    c = np.asarray(sphere["centre"], float)
    return np.linalg.norm(points - c, axis=1) < float(sphere["radius"]) + SELECT_MM


def on_sphere(points: np.ndarray, sphere: dict) -> np.ndarray:
    """The points within r + SELECT_MM of the true centre."""
    return points[_near_sphere(points, sphere)]


def diameter_se(points: np.ndarray) -> float:
    """Standard error (mm) of the fitted diameter of ``points`` (N, 3) mm: ``2 sqrt(C[r, r])``
    with ``C = s^2 (J^T J)^-1`` at the least-squares sphere (J: the residuals' Jacobian in
    centre and radius, s^2: residual sum of squares / (N - 4)). It takes the residuals as
    independent, so it is a lower bound where they are correlated along the stripes; it shows
    how well the points' coverage of the sphere determines the size (two short nearly parallel
    arcs determine it poorly)."""
    f = fit_sphere(points)
    d = points - f.centre
    rho = np.linalg.norm(d, axis=1)
    J = np.column_stack([-d / rho[:, None], -np.ones(len(points))])
    s2 = float(np.sum(f.residuals**2)) / max(len(points) - 4, 1)
    try:
        return float(2.0 * np.sqrt(s2 * np.linalg.inv(J.T @ J)[3, 3]))
    except np.linalg.LinAlgError:  # the points do not determine the sphere
        return float("inf")


def arc_coverage(res: ScanResult, pixels: dict, name: str) -> list[tuple[int, int, int]]:
    """Per slit crossing primitive ``name``: (slit, its true stripe-centre pixels there with a
    point of that slit, its true stripe-centre pixels there) (``pixels``: the image's truth npz
    arrays)."""
    from multislit.sim.evaluate import object_metrics

    region = pixels["obj"] == list(pixels["names"]).index(name)
    tslit = pixels["slit"]
    out = []
    for k in np.unique(tslit[region & (tslit >= 0)]):
        m = object_metrics(res.identification, tslit, region & (tslit == k))["object"]
        if m["centres"]:
            out.append((int(k), round(m["coverage"] * m["centres"]), int(m["centres"])))
    return out


def evaluate(res: ScanResult, truth: dict, pixels: dict | None = None) -> list[dict[str, Any]]:
    """Acceptance rows of one scan: PS/PF for a lone sphere, SD for a bar, F for a plate.

    ``pixels`` (optional): the image's per-pixel truth (``truth/<name>.npz``); with it a lone
    sphere's note gives each slit arc's found/true stripe-centre rows."""
    rows: list[dict[str, Any]] = []
    name = res.name
    pts = res.points
    if "plane" in truth:
        pl = np.asarray(truth["plane"], float)
        p = pts[np.abs(pts @ pl[:3] + pl[3]) < SELECT_MM]
        rms = float(np.sqrt(np.mean((p @ pl[:3] + pl[3]) ** 2))) if len(p) else float("nan")
        rows.append(
            {
                "artefact": name,
                "quantity": "F",
                "value": _safe(flatness_error, p),
                "value_excl": _safe(flatness_error, p, exclude=EXCLUDE),
                "points": len(p),
                "note": f"{truth['size'][0]:.0f}x{truth['size'][1]:.0f} mm plate; "
                f"RMS to true plane {rms:.3f} mm",
            }
        )
    elif "length" in truth:
        s1, s2 = truth["spheres"]
        pa, pb = on_sphere(pts, s1), on_sphere(pts, s2)
        sd = _safe(sphere_spacing_error, pa, pb, float(truth["length"]))
        rows.append(
            {
                "artefact": name,
                "quantity": "SD",
                "value": sd,
                "value_excl": None,
                "points": len(pa) + len(pb),
                "note": f"L = {truth['length']:.0f} mm, balls r = {s1['radius']:.0f} mm; "
                f"{len(pa)} + {len(pb)} points",
            }
        )
    else:
        for s in truth["spheres"]:
            near = _near_sphere(pts, s)
            p = pts[near]
            d = 2.0 * float(s["radius"])
            c = np.asarray(s["centre"], float)
            dist = float(np.linalg.norm(c - np.array([-225.0, 0.0, RIG_Z])))
            arcs = len(
                np.unique(res.slit[np.linalg.norm(pts - c, axis=1) < s["radius"] + SELECT_MM])
            )
            cover, arc_rows = "", []
            if pixels is not None:
                arc_rows = arc_coverage(res, pixels, "sphere")
                cover = "; rows found/true " + ", ".join(f"{k}: {a}/{b}" for k, a, b in arc_rows)
            try:
                off = float(np.linalg.norm(fit_sphere(p).centre - c))
                note = (
                    f"d = {d:.0f} mm at {dist:.0f} mm from the camera; centre off {off:.3f} mm; "
                    f"SE(d) {diameter_se(p):.3f} mm; {arcs} slit arcs{cover}"
                )
            except MultislitError as exc:
                note = f"no fit ({arcs} slit arcs{cover}): {exc}"
            rows.append(
                {
                    "artefact": name,
                    "quantity": "PS",
                    "value": _safe(probing_error_size, p, d),
                    "value_excl": None,
                    "points": len(p),
                    "note": note,
                    "arcs": arc_rows,
                }
            )
            rows.append(
                {
                    "artefact": name,
                    "quantity": "PF",
                    "value": _safe(probing_error_form, p),
                    "value_excl": _safe(probing_error_form, p, exclude=EXCLUDE),
                    "points": len(p),
                    "note": "",
                }
            )
    return rows


def volume_diagonal(spec: RigSpec) -> float:
    """Diagonal (mm) of the measuring volume: the image's field at the middle reference
    distance times the span of the reference distances."""
    w, h = spec.camera.image_size
    f = spec.camera.focal_px
    dmid = float(np.median(spec.reference_distances))
    depth = max(spec.reference_distances) - min(spec.reference_distances)
    return float(np.sqrt((w * dmid / f) ** 2 + (h * dmid / f) ** 2 + depth**2))


# --------------------------------------------------------------------------- suite
def run_suite(
    scale: float = 1.0, seed: int = 0, full: bool = True, holes: bool = True
) -> dict[str, Any]:
    """Run the acceptance suite; returns rows, hole rows, timings and the markdown text."""
    spec = RigSpec() if scale == 1.0 else RigSpec().scaled(scale)
    scenes = default_artefacts(full)
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rig = prepare_rig(spec, scenes, Path(tmp) / "capture", seed)
        rows: list[dict[str, Any]] = []
        scan_s: list[float] = []
        for sc in scenes:
            res = scan(rig, sc.name)
            scan_s.append(res.seconds)
            with np.load(rig.capture.root / "truth" / f"{sc.name}.npz") as z:
                pixels = {k: z[k] for k in ("obj", "names", "slit")}
            rows += evaluate(res, rig.scenes[sc.name], pixels)
        hole_rows: list[dict[str, Any]] = []
        if holes:
            from multislit.app.demo import run_demo

            demo = run_demo(Path(tmp) / "demo", seed=seed, scale=scale, figures=False)
            hole_rows = demo["table1"]
    wall = time.perf_counter() - t_start
    out = {
        "image_size": spec.camera.image_size,
        "num_slits": spec.slits.num_slits,
        "diagonal_mm": volume_diagonal(spec),
        "rows": rows,
        "holes": hole_rows,
        "seconds": {**{k: round(v, 1) for k, v in rig.seconds.items()}, "total": round(wall, 1)},
        "scan_seconds_mean": float(np.mean(scan_s)),
    }
    out["markdown"] = to_markdown(out)
    return out


def to_markdown(r: dict[str, Any]) -> str:
    w, h = r["image_size"]
    lines = [
        f"Rig: simulated default rig, {w}x{h} px, {r['num_slits']} slits, default noise; "
        f"measuring volume diagonal ~{r['diagonal_mm']:.0f} mm (field at 900 mm x reference "
        "depth span 780-1020 mm). One hand-reading calibration and one reference set for all "
        "scans. Points selected by distance to the true artefact (spheres r + 5 mm, plates "
        "5 mm). No MPE is specified, so no pass/fail. Sphere notes: SE(d) is the fitted "
        "diameter's standard error from the fit's covariance (residuals taken as independent); "
        "rows found/true, per slit arc, counts the sphere's true stripe-centre rows that have a "
        "point of that slit.\n",
        markdown_table(
            ["artefact", "quantity", "value (mm)", "0.3 % left out (mm)", "points", "note"],
            [
                [x["artefact"], x["quantity"], x["value"], x["value_excl"], x["points"], x["note"]]
                for x in r["rows"]
            ],
        ),
    ]
    if r["holes"]:
        lines.append(
            "Holes plate (the demo, `multislit.app.demo.run_demo`: its own rig, 49 slits, "
            "calibrated and referenced once), diameters in mm:\n"
        )
        lines.append(
            markdown_table(
                [
                    "scene",
                    "hole",
                    "actual",
                    "estimated",
                    "error",
                    "edge points",
                    "slits",
                    "paper error",
                    "note",
                ],
                [
                    [
                        x["scene"],
                        x["hole"],
                        x["actual"],
                        x["estimated"],
                        x["error"],
                        x["edge_points"],
                        x["slits"],
                        x["paper_error"],
                        x["note"],
                    ]
                    for x in r["holes"]
                ],
                digits=2,
            )
        )
    s = r["seconds"]
    lines.append(
        f"Timing: simulation {s['simulation']} s, calibration {s['calibration']} s, reference "
        f"{s['reference']} s, mean scan (identify + triangulate) {r['scan_seconds_mean']:.2f} s, "
        f"whole run {s['total']} s.\n"
    )
    return "\n".join(lines)


def spread(seeds: list[int], scale: float = 1.0) -> dict[str, Any]:
    """The suite (without the holes) once per seed, each a repeat of the whole experiment
    (the calibration's and the scans' images drawn anew, the hand readings too); per artefact
    and quantity the median, least and largest absolute value over the seeds, and the small
    spheres' slit arcs that get no point."""
    runs = []
    t0 = time.perf_counter()
    for i, seed in enumerate(seeds):
        runs.append(run_suite(scale, seed, full=True, holes=False))
        print(f"seed {seed} done ({i + 1}/{len(seeds)}, {time.perf_counter() - t0:.0f} s)")
    keys = [(x["artefact"], x["quantity"]) for x in runs[0]["rows"]]
    table = []
    for art, q in keys:
        v = np.array(
            [
                abs(x["value"])
                for r in runs
                for x in r["rows"]
                if (x["artefact"], x["quantity"]) == (art, q)
            ]
        )
        ok = v[np.isfinite(v)]
        over = f"{np.count_nonzero(ok > 0.2)}" if q in ("SD", "PS") else "-"
        table.append(
            [
                art,
                q,
                float(np.median(ok)) if ok.size else float("nan"),
                float(ok.min()) if ok.size else float("nan"),
                float(ok.max()) if ok.size else float("nan"),
                over,
                int(np.count_nonzero(~np.isfinite(v))),
            ]
        )
    lost, arcs, seeds_lost = 0, 0, set()
    for seed, r in zip(seeds, runs, strict=True):
        for x in r["rows"]:
            if x["artefact"].startswith("sphere40") and x["quantity"] == "PS":
                for _, found, _ in x.get("arcs", []):
                    arcs += 1
                    if found == 0:
                        lost += 1
                        seeds_lost.add(seed)
    w, h = runs[0]["image_size"]
    text = "\n".join(
        [
            f"The suite above (without the holes) on {len(seeds)} noise seeds "
            f"({seeds[0]}-{seeds[-1]}): each seed repeats the whole experiment, the same artefacts "
            "at the same places, every image (calibration, reference, scans) and the hand "
            f"readings drawn anew; {w}x{h} px, {runs[0]['num_slits']} slits. Absolute values "
            '(mm); "> 0.2": the seeds whose PS or SD is above 0.2 mm; "no fit": the seeds '
            "whose points do not determine the value.\n",
            markdown_table(
                ["artefact", "quantity", "median", "least", "largest", "> 0.2", "no fit"],
                table,
            ),
            f"The 40 mm spheres' slit arcs with no point of their slit: {lost} of {arcs}, on "
            f"{len(seeds_lost)} of {len(seeds)} seeds"
            + (f" ({', '.join(str(s) for s in sorted(seeds_lost))})" if seeds_lost else "")
            + f". Whole run {time.perf_counter() - t0:.0f} s.\n",
        ]
    )
    return {"runs": runs, "markdown": text}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="rig resolution factor (1: full)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        metavar="N",
        help="the spread over these noise seeds instead (the suite without the holes on each)",
    )
    ap.add_argument("--no-holes", action="store_true", help="skip the demo's hole table")
    ap.add_argument("--no-write", action="store_true", help="do not update RESULTS.md")
    args = ap.parse_args(argv)
    if args.seeds:
        r = spread(args.seeds, args.scale)
        print(r["markdown"])
        if not args.no_write:
            cmd = command_line("bench_accuracy.py", argv)
            write_section(
                "bench_accuracy_spread",
                "Accuracy over noise seeds (run-to-run spread)",
                r["markdown"],
                cmd,
            )
            print(f"written to {RESULTS}")
        return
    r = run_suite(args.scale, args.seed, full=True, holes=not args.no_holes)
    print(r["markdown"])
    if not args.no_write:
        cmd = command_line("bench_accuracy.py", argv)
        write_section("bench_accuracy", "Accuracy (VDI/VDE 2634-2 style)", r["markdown"], cmd)
        print(f"written to {RESULTS}")


if __name__ == "__main__":
    main()
