"""The demo: the paper's experiment (section 6.2, Table 1) end to end on the simulated rig.

1. Simulate the rig: the standard object (markers image, slits image), the reference boards,
   and the holes plate (holes of 100, 50 and 30 mm) at about 0.9 m, flat and tilted 20 deg.
2. Calibrate camera and projector (:mod:`multislit.calibrate`, the paper's hand readings of
   points on the slits, section 6.2.2).
3. Prepare the reference set once, scan both plates, measure the holes with sub-pixel edges.
4. Print Table 1 (actual, estimated, error) next to the paper's figures, the calibration RMS
   values, the share of correctly identified points (against the simulator's truth), the
   time per frame, and write the figures (paper Fig. 23, 24/28b, 28c).

The paper projected the slits across each hole. With the default rig (25 slits about 18 mm
apart on the plate) the 30 mm hole is crossed by at most two slits, too few for a circle; the
demo rig therefore has a grating of twice the pitch and twice the slits (49 slits about 9 mm
apart at full size over the same field, so every hole is crossed by >= 3 slits); the plate
is the simulator's ``holes`` plate unchanged. At reduced ``scale`` the pitch (and the number
of slits) is reduced so that the stripes stay far enough apart in the image.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from multislit.calibrate import calibrate_capture, write_calibration
from multislit.errors import MultislitError
from multislit.identify import capture_reference
from multislit.io import Capture, json_safe, write_json
from multislit.measure import measure_holes
from multislit.sim import Progress, RigSpec, simulate_capture

#: The paper's Table 1: (name, actual, estimated, error), mm.
PAPER_TABLE1 = (("D1", 100.0, 99.7, -0.3), ("D2", 50.0, 49.5, -0.5), ("D3", 30.0, 29.9, -0.1))
DEMO_PITCH_UM = 68.0  # twice the default grating pitch: slits half as far apart
DEMO_NUM_DOTS = 24000  # twice the default: the same dots per (smaller) template
MIN_STRIPE_SPACING_SCALE = 90.0  # pitch_um <= this x scale keeps >= ~13 px between stripes
DEMO_SCENES = ("holes", "holes_tilted")  # the simulator's Table 1 plate, flat and tilted 20 deg


def demo_rig(scale: float = 1.0) -> RigSpec:
    """The demo's rig: the default rig with a denser grating over the same field of slits.

    Full size: pitch 68 um, 49 slits (default 34 um, 25 slits); at ``scale`` < 0.75 the pitch
    is ``90 x scale`` um so that the stripes stay >= ~13 px apart in the image.
    """
    if not (0.2 <= scale <= 2.0):
        raise MultislitError(f"scale must be in [0.2, 2], got {scale}")
    base = RigSpec()
    pitch = min(DEMO_PITCH_UM, MIN_STRIPE_SPACING_SCALE * scale)
    half = round((base.slits.num_slits - 1) / 2 * pitch / base.slits.pitch_um)
    spec = replace(
        base,
        slits=replace(base.slits, pitch_um=pitch, num_slits=2 * half + 1),
        dots=replace(base.dots, num_dots=DEMO_NUM_DOTS),
    )
    return spec if scale == 1.0 else spec.scaled(scale)


def identification_truth(capture_dir: Path, name: str, result: Any) -> dict[str, float]:
    """Shares of correctly identified points against the simulator's truth image.

    correct : identified points whose slit number is the true one (truth: the slit lighting
        the point's nearest pixel)
    identified : identified points / stripe points found on a true slit
    """
    tz = np.load(capture_dir / "truth" / f"{name}.npz")
    tslit = tz["slit"]
    h, w = tslit.shape
    ident = result.identification
    u = np.clip(np.round(ident.u).astype(int), 0, w - 1)
    v = np.clip(np.round(ident.v).astype(int), 0, h - 1)
    true_all = tslit[v, u]
    on_slit = true_all >= 0
    idm = ident.slit >= 0
    correct = float(np.mean(true_all[idm] == ident.slit[idm])) if idm.any() else float("nan")
    share = float(np.count_nonzero(idm & on_slit) / max(1, np.count_nonzero(on_slit)))
    return {"correct": correct, "identified": share, "points": int(idm.sum())}


def _match_holes(measured: list, truth: list[dict]) -> list[Any]:
    """For each true hole the measured hole nearest its centre (within its radius), or None."""
    out = []
    for tr in truth:
        c = np.asarray(tr["centre"], float)
        best = None
        for h in measured:
            d = float(np.linalg.norm(np.asarray(h.centre) - c))
            if d < tr["diameter"] / 2 and (best is None or d < best[0]):
                best = (d, h)
        out.append(None if best is None else best[1])
    return out


def run_demo(
    out: Path,
    seed: int = 0,
    scale: float = 1.0,
    progress: Progress | None = None,
    figures: bool = True,
) -> dict[str, Any]:
    """Run the demo, writing everything into ``out``; return its figures and report lines.

    Parameters
    ----------
    out : folder for the capture, the PLY files, the figures and ``demo.json`` (created)
    seed : noise seed of the simulation. Default 0.
    scale : camera resolution factor, in [0.2, 2] (0.5: 640x512); see :func:`demo_rig`.
        Default 1.
    progress : called as ``progress(i, n, name)`` while the capture is simulated. Default None.
    figures : write the PNG figures (needs matplotlib). Default True.

    Returns
    -------
    The contents of ``demo.json``: ``table1`` (one row per hole and scene), ``calibration``,
    ``scans``, ``time_per_frame_s``, ``timing_s``, ``figures`` and ``report`` (the lines the
    command line prints). NaN values are None.
    """
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = demo_rig(scale)
    t0 = time.perf_counter()
    cap_dir = simulate_capture(
        out / "capture", list(DEMO_SCENES), spec, seed=seed, progress=progress, overwrite=True
    )
    t_sim = time.perf_counter() - t0
    cap = Capture.open(cap_dir)
    truth = json.loads((cap_dir / "truth" / "models.json").read_text())

    t0 = time.perf_counter()
    calres = calibrate_capture(cap, source="hand")
    cal = calres.calibration
    write_calibration(calres, cap_dir / "calibration.json")
    t_cal = time.perf_counter() - t0

    t0 = time.perf_counter()
    ref = calres.reference if calres.reference is not None else capture_reference(cap)
    t_ref = time.perf_counter() - t0  # ~0 when the calibration prepared it (its time counts there)

    rows: list[dict[str, Any]] = []
    scans: dict[str, Any] = {}
    figs: dict[str, str] = {}
    for path in cap.scans:
        name = path.stem
        img = cap.image(path)
        res, hm = _scan_and_measure(img, ref, cal, name, out)
        tr_scene = truth["scenes"][name]
        idt = identification_truth(cap_dir, name, res)
        scans[name] = _scan_summary(res, hm, tr_scene["plane"], idt)
        rows.extend(_table1_rows(name, hm, tr_scene["holes"]))
        if figures:
            figs.update(_scan_figures(out, name, img, res, hm, tr_scene["holes"], cap.num_slits))

    w, h = cap.image_size
    wall = time.perf_counter() - t_start
    spacing = _slit_spacing_on_plate(cal, truth["scenes"]["holes"]["plane"])
    result: dict[str, Any] = {
        "capture": str(cap_dir),
        "image_size": [w, h],
        "num_slits": cap.num_slits,
        "rig_note": _rig_note(spec, cap.num_slits, spacing),
        "calibration": _calibration_summary(calres),
        "scans": scans,
        "table1": rows,
        "time_per_frame_s": float(np.mean([s["seconds"] for s in scans.values()])),
        "timing_s": {
            "simulation": round(t_sim, 2),
            "calibration": round(t_cal, 2),
            "reference": round(t_ref, 2),
            "total": round(wall, 2),
        },
        "figures": figs,
    }
    result["report"] = _report_lines(result)
    write_json(out / "demo.json", result)
    return json_safe(result)


def _scan_and_measure(img: np.ndarray, ref: Any, cal: Any, name: str, out: Path) -> tuple[Any, Any]:
    """Measure the plate's holes in one image; write the scan they used as ``out/<name>.ply``."""
    hm = measure_holes(img, ref, cal, name=name)
    res = hm.scan
    res.write_ply(out / f"{name}.ply", comment=f"multislit demo scan {name}")
    return res, hm


def _scan_summary(res: Any, hm: Any, plane: list[float], idt: dict[str, float]) -> dict[str, Any]:
    """One scan's entry in ``demo.json``: the scan, its plate points against the true plane
    (points within 5 mm of it), its identification against the truth and its holes."""
    pl = np.asarray(plane, float)
    d = res.points @ pl[:3] + pl[3]
    on = np.abs(d) < 5.0
    return {
        **res.to_dict(),
        "plate_rms_mm": float(np.sqrt(np.mean(d[on] ** 2))) if on.any() else None,
        "plate_mean_mm": float(np.mean(d[on])) if on.any() else None,
        "correct_share": idt["correct"],
        "identified_share": idt["identified"],
        "holes": hm.to_dict(),
    }


def _table1_rows(name: str, hm: Any, true_holes: list[dict]) -> list[dict[str, Any]]:
    """Table 1 rows of one scan: each true hole with its measurement and the paper's figures."""
    matched = _match_holes(hm.measurable, true_holes)
    unmeasured = _match_holes([x for x in hm.holes if not x.measurable], true_holes)
    rows = []
    for (label, _actual, p_est, p_err), tr, h, hu in zip(
        PAPER_TABLE1, true_holes, matched, unmeasured, strict=True
    ):
        est = None if h is None else float(h.diameter)
        rows.append(
            {
                "scene": name,
                "hole": label,
                "actual": float(tr["diameter"]),
                "estimated": est,
                "error": None if est is None else est - float(tr["diameter"]),
                "paper_estimated": p_est,
                "paper_error": p_err,
                "edge_points": None if h is None else int(h.n_inliers),
                "slits": None if h is None else h.n_slits,
                "fit_rms_mm": None if h is None else float(h.rms),
                "note": ""
                if h is not None
                else ("not measurable: " + hu.reason if hu is not None else "not found"),
            }
        )
    return rows


def _scan_figures(
    out: Path,
    name: str,
    img: np.ndarray,
    res: Any,
    hm: Any,
    true_holes: list[dict],
    num_slits: int,
) -> dict[str, str]:
    """Write one scan's figures (slit addresses and points for the flat plate; hole edges for
    every scan); return their paths by name."""
    from multislit.app.figures import hole_edges_figure, point_cloud_figure, slit_addresses_figure

    figs: dict[str, str] = {}
    ident = res.identification
    un = ident.slit < 0
    if name == "holes":
        figs["slit_addresses"] = str(
            slit_addresses_figure(
                img,
                ident.u,
                ident.v,
                ident.slit,
                out / "fig23_slit_addresses.png",
                title=f"Slit addresses of scan '{name}' (cf. paper Fig. 23); white: not identified",
                num_slits=num_slits,
                unidentified_uv=np.c_[ident.u[un], ident.v[un]],
            )
        )
        figs["point_cloud"] = str(
            point_cloud_figure(
                res.points,
                out / "fig28b_point_cloud.png",
                title=f"Points of scan '{name}' in the target frame (cf. Fig. 24/28b)",
            )
        )
    figs[f"hole_edges_{name}"] = str(
        hole_edges_figure(
            hm,
            out / f"fig28c_hole_edges_{name}.png",
            points=res.points,
            title=f"Hole edges of '{name}' and fitted circles (cf. Fig. 28c)",
            truth=true_holes,
        )
    )
    return figs


def _calibration_summary(calres: Any) -> dict[str, Any]:
    """The calibration's figures in ``demo.json``: source, camera RMS (px), slit planes (mm)."""
    cal = calres.calibration
    rep = calres.report()
    return {
        "source": calres.source,
        "dlt_rms_px": float(cal.dlt_rms_px),
        "camera_rms_px": float(cal.camera_rms_px),
        "slit_plane_rms_median_mm": rep["slit_planes"]["median_rms_mm"],
        "projector_matrix_rms_median_mm": rep["projector_matrix"]["median_rms_mm"],
        "markers_used": len(rep["markers"]["used"]),
    }


def _rig_note(spec: RigSpec, num_slits: int, spacing: float) -> str:
    """One line on why the demo's grating differs from the default rig's."""
    return (
        f"grating pitch {spec.slits.pitch_um:g} um, {num_slits} slits (default "
        f"{RigSpec().slits.pitch_um:g} um, {RigSpec().slits.num_slits} slits): slits "
        f"~{spacing:.1f} mm apart on the plate at 0.9 m, so that each hole is crossed by "
        ">= 3 slits (30 mm hole: at full size); the simulator's holes plate unchanged"
    )


def _slit_spacing_on_plate(cal: Any, plane: list[float]) -> float:
    """Median distance (mm) between neighbouring slit lines on the plate along its x axis."""
    sp = cal.slit_planes.planes
    pl = np.asarray(plane, float)
    # the slits cross the plate's horizontal line through y = 0: solve both planes and y = 0
    xs = []
    for p in sp:
        if not np.all(np.isfinite(p)):
            continue
        A = np.stack([p[:3], pl[:3], [0.0, 1.0, 0.0]])
        xs.append(np.linalg.solve(A, -np.array([p[3], pl[3], 0.0])))
    xs = np.array(xs)
    if len(xs) < 2:
        return float("nan")
    return float(np.median(np.linalg.norm(np.diff(xs, axis=0), axis=1)))


def _fmt(x: float | None, spec: str = "6.2f") -> str:
    return " " * (len(format(0.0, spec)) - 3) + "n/a" if x is None else format(x, spec)


def _report_lines(r: dict[str, Any]) -> list[str]:
    w, h = r["image_size"]
    c = r["calibration"]
    lines = [
        f"simulated capture: {r['capture']} ({w}x{h} px, {r['num_slits']} slits)",
        f"  rig: {r['rig_note']}",
        f"calibration ({c['source']} readings of points on the slits, paper 6.2.2): "
        f"camera DLT RMS {c['dlt_rms_px']:.3f} px, refined {c['camera_rms_px']:.3f} px "
        f"({c['markers_used']} markers); slit planes RMS median "
        f"{_fmt(c['slit_plane_rms_median_mm'], '.4f')} mm; paper's 2x4 projector matrix "
        f"{_fmt(c['projector_matrix_rms_median_mm'], '.4f')} mm",
    ]
    for name, s in r["scans"].items():
        lines.append(
            f"scan {name}: {s['points']} points, {s['slits_found']} slits, "
            f"{100 * s['correct_share']:.2f} % of the identified points correctly identified, "
            f"{100 * s['identified_share']:.1f} % of the stripe points identified; "
            f"points on the plate {_fmt(s['plate_rms_mm'], '.3f')} mm RMS from the true plane; "
            f"{s['seconds']:.2f} s"
        )
    lines.append("")
    lines.append("Table 1: hole diameters [mm] (sub-pixel edges, circle fit)")
    lines.append(
        f"  {'scene':<13s} {'hole':<4s} {'actual':>7s} {'estimated':>9s} {'error':>7s}"
        f" {'edges':>5s} {'slits':>5s}   | paper: {'estimated':>9s} {'error':>6s}"
    )
    for row in r["table1"]:
        lines.append(
            f"  {row['scene']:<13s} {row['hole']:<4s} {row['actual']:7.1f} "
            f"{_fmt(row['estimated'], '9.2f')} {_fmt(row['error'], '+7.2f')} "
            f"{row['edge_points'] if row['edge_points'] is not None else '-':>5} "
            f"{row['slits'] if row['slits'] is not None else '-':>5}   |        "
            f"{row['paper_estimated']:9.1f} {row['paper_error']:+6.1f}"
            + (f"   ({row['note']})" if row["note"] else "")
        )
    t = r["timing_s"]
    lines.append("")
    lines.append(
        f"time per frame (identify + triangulate): {r['time_per_frame_s']:.2f} s; "
        f"simulation {t['simulation']:.1f} s, calibration {t['calibration']:.1f} s, "
        f"reference {t['reference']:.1f} s, total {t['total']:.1f} s"
    )
    for k, v in r["figures"].items():
        lines.append(f"figure {k}: {v}")
    return lines
