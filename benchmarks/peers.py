"""Peer methods on the same simulated scenes: Gray-code structured light and dot block matching.

Run:  .venv/bin/python benchmarks/peers.py            (half-size rig, 640x512, ~1 min)
      .venv/bin/python benchmarks/peers.py --full     (full-size rig, 1280x1024, slower)

Prints markdown tables (for benchmarks/RESULTS.md): per method and scene the images one
measurement needs, whether the object must stay still over them, the points one measurement
gives (and per captured image), the accuracy against the renderer's ground truth, the
processing time, and VDI/VDE 2634-2 sphere and flatness figures.

Accuracy is measured per pixel against the true surface point seen by that pixel's centre.
Pixels at depth edges (the true depth changes by more than ``EDGE_MM`` within 3x3 pixels or
the neighbourhood sees nothing) are left out for every method: there a pixel mixes two surfaces
and the centre's truth is not the only right answer. Points more than ``OUTLIER_MM`` off are
counted as outliers and left out of the RMS; the table gives both.

Our method (``ours``): the full rig, calibrated from the hand readings with one reference set,
``multislit.scan.scan_image`` on one image per scene.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace

import numpy as np
from dot_blocks import match_dots
from patterns import (
    PatternProjector,
    decode_gray_code,
    gray_code_patterns,
    prepare_patterns,
    render_patterns,
    triangulate_columns,
)

from multislit.errors import MultislitError
from multislit.measure import (
    flatness_error,
    markdown_table,
    probing_error_form,
    probing_error_size,
)
from multislit.sim import RigSpec, Scene, SimulatedRig, render
from multislit.sim.scene import large_plane, reference_board, spheres, steps

EDGE_MM = 5.0
OUTLIER_MM = 5.0
FPS = 60.0  # camera frame rate assumed for the capture time
REF_DISTANCE = 900.0  # mm, the dot matcher's reference board


@dataclass
class PeerResult:
    """One method on one scene: points (H, W, 3) and the truth they are compared with."""

    method: str
    scene: str
    images: int
    still: bool
    xyz: np.ndarray  # (H, W, 3) mm, NaN where no point
    truth: np.ndarray  # (H, W, 3) mm
    seconds: float  # processing time of one measurement (decode + triangulate)
    camera_centre: np.ndarray


def edge_mask(truth: np.ndarray, centre: np.ndarray, edge_mm: float = EDGE_MM) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood of true points spans more than ``edge_mm`` in range."""
    r = np.linalg.norm(truth - centre, axis=-1)
    r = np.where(np.isfinite(r), r, np.inf)
    h, w = r.shape
    p = np.pad(r, 1, mode="edge")
    lo = np.full((h, w), np.inf)
    hi = np.full((h, w), -np.inf)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            nb = p[dy : dy + h, dx : dx + w]
            lo = np.minimum(lo, nb)
            hi = np.maximum(hi, nb)
    return ~np.isfinite(hi) | (hi - lo > edge_mm)


def stats(res: PeerResult) -> dict[str, float]:
    """Points, RMS of inliers, outlier fraction (off depth edges)."""
    valid = np.isfinite(res.xyz).all(axis=-1)
    keep = valid & ~edge_mask(res.truth, res.camera_centre)
    e = np.linalg.norm(res.xyz[keep] - res.truth[keep], axis=-1)
    inl = e <= OUTLIER_MM
    return {
        "points": int(valid.sum()),
        "rms": float(np.sqrt(np.mean(e[inl] ** 2))) if inl.any() else float("nan"),
        "median": float(np.median(e)) if e.size else float("nan"),
        "outliers": float(np.mean(~inl)) if e.size else float("nan"),
    }


# --------------------------------------------------------------------------- peers
def gray_code(
    rig: SimulatedRig,
    scene: Scene,
    rng: np.random.Generator,
    size: tuple[int, int] = (1024, 768),
) -> PeerResult:
    """Peer 1: column Gray codes from a projector at the slit projector's place."""
    proj = PatternProjector.from_rig(rig, size=size)
    geom = prepare_patterns(rig, scene, proj, supersample=2)
    pats = gray_code_patterns(*proj.size)
    images = render_patterns(geom, pats, rng)
    t = time.perf_counter()
    dec = decode_gray_code(images, proj.size[0])
    xyz = triangulate_columns(rig.camera, proj, dec.columns)
    dt = time.perf_counter() - t
    return PeerResult(
        f"Gray code ({size[0]}x{size[1]} projector)",
        scene.name,
        len(pats),
        True,
        xyz,
        geom.xyz.astype(float),
        dt,
        rig.camera.centre,
    )


def dot_matching(
    rig: SimulatedRig, scene: Scene, rng: np.random.Generator, reference: np.ndarray
) -> PeerResult:
    """Peer 2: the rig's dots alone, block matching against a board at REF_DISTANCE."""
    img = render(rig, scene, rng).image
    t = time.perf_counter()
    dd = match_dots(
        rig, img, reference, reference_board(REF_DISTANCE).info["plane"], window=21, min_score=0.8
    )
    dt = time.perf_counter() - t
    w, h = dd.camera.image_size
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    o, d = dd.camera.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
    truth = scene.cast(o, d).point.reshape(h, w, 3)
    return PeerResult(
        "dot block matching (21 px NCC)", scene.name, 1, False, dd.xyz, truth, dt, dd.camera.centre
    )


_OURS_RIGS: dict[RigSpec, tuple] = {}  # spec -> (calibration, reference), prepared once


def _ours_rig(spec: RigSpec, seed: int = 0) -> tuple:
    """Calibrate (the paper's hand readings) and prepare the reference once per rig."""
    if spec not in _OURS_RIGS:
        import tempfile
        from pathlib import Path

        from multislit.calibrate import calibrate_capture
        from multislit.identify import capture_reference
        from multislit.io import Capture
        from multislit.sim.simulate import simulate_capture

        with tempfile.TemporaryDirectory() as tmp:
            cap = Capture.open(simulate_capture(Path(tmp) / "cap", [], spec, seed=seed))
            cal = calibrate_capture(cap, source="hand").calibration
            _OURS_RIGS[spec] = (cal, capture_reference(cap))
    return _OURS_RIGS[spec]


def ours(spec: RigSpec, scene: Scene, rng: np.random.Generator) -> PeerResult | None:
    """OUR METHOD (multiple slits identified by random dots): one image.

    The full rig (slits and dots) renders one image of ``scene``; the rig is calibrated from
    the hand readings and the reference set prepared once per rig (not timed); ``scan_image``
    identifies and triangulates. Each point is put at its nearest pixel; its truth is the
    scene's first hit along the camera ray through the point's sub-pixel (u, v) (elsewhere the
    truth at pixel centres, used for the depth-edge mask).
    """
    from multislit.reconstruct import scan_image

    cal, ref = _ours_rig(spec)
    rig = SimulatedRig.build(spec)
    rend = render(rig, scene, rng)
    res = scan_image(rend.image, ref, cal, name=scene.name)
    w, h = spec.camera.image_size
    truth = rend.xyz.astype(float).reshape(h, w, 3).copy()
    xyz = np.full((h, w, 3), np.nan)
    if res.num_points:
        uv = np.c_[res.u, res.v]
        hit = scene.cast(*rig.camera.rays(uv))
        iu = np.clip(np.round(res.u).astype(int), 0, w - 1)
        iv = np.clip(np.round(res.v).astype(int), 0, h - 1)
        xyz[iv, iu] = res.points
        truth[iv, iu] = hit.point
    return PeerResult(
        f"ours ({spec.slits.num_slits} slits + dots, hand calibration)",
        scene.name,
        1,
        False,
        xyz,
        truth,
        res.seconds,
        rig.camera.centre,
    )


# --------------------------------------------------------------------------- acceptance
def sphere_figures(res: PeerResult, scene: Scene) -> list[list[object]]:
    """PS and PF (VDI/VDE 2634-2) per sphere of the scene, from the points on each sphere."""
    rows: list[list[object]] = []
    valid = np.isfinite(res.xyz).all(axis=-1) & ~edge_mask(res.truth, res.camera_centre)
    for k, s in enumerate(scene.info.get("spheres", [])):
        c, r = np.asarray(s["centre"]), float(s["radius"])
        on = valid & (np.abs(np.linalg.norm(res.truth - c, axis=-1) - r) < 0.01)
        pts = res.xyz[on]
        good = np.linalg.norm(pts - res.truth[on], axis=-1) <= OUTLIER_MM
        row: list[object] = [res.method, f"sphere {k} (d={2 * r:.0f})", len(pts)]
        for p in (pts, pts[good]):
            try:
                row += [
                    probing_error_size(p, 2 * r),
                    probing_error_form(p),
                    probing_error_form(p, exclude=0.003),
                ]
            except MultislitError:
                row += [float("nan")] * 3
        rows.append(row)
    return rows


def flatness_figure(res: PeerResult) -> list[object]:
    valid = np.isfinite(res.xyz).all(axis=-1) & ~edge_mask(res.truth, res.camera_centre)
    pts = res.xyz[valid]
    try:
        return [res.method, len(pts), flatness_error(pts), flatness_error(pts, exclude=0.003)]
    except MultislitError:
        return [res.method, len(pts), float("nan"), float("nan")]


# --------------------------------------------------------------------------- main
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 1024x768, got {text!r}") from None
    return w, h


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="full-size rig (1280x1024)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--projector",
        type=_size,
        nargs="+",
        default=[(1024, 768)],
        help="Gray-code projector resolution(s) WxH (default 1024x768)",
    )
    args = ap.parse_args(argv)
    spec = RigSpec() if args.full else RigSpec().scaled(0.5)
    rng = np.random.default_rng(args.seed)
    rig = SimulatedRig.build(spec)
    dot_rig = SimulatedRig.build(replace(spec, slits=replace(spec.slits, power=0.0)))
    reference = render(dot_rig, reference_board(REF_DISTANCE), rng).image
    scenes = [large_plane(), spheres(), steps()]

    w, h = spec.camera.image_size
    rows: list[list[object]] = []
    sphere_rows: list[list[object]] = []
    flat_rows: list[list[object]] = []
    for scene in scenes:
        results = [gray_code(rig, scene, rng, size) for size in args.projector]
        results.append(dot_matching(dot_rig, scene, rng, reference))
        mine = ours(spec, scene, rng)
        for res in results + ([mine] if mine is not None else []):
            s = stats(res)
            rows.append(
                [
                    res.method,
                    scene.name,
                    res.images,
                    "yes" if res.still else "no",
                    s["points"],
                    round(s["points"] / res.images),
                    s["rms"],
                    s["median"],
                    100 * s["outliers"],
                    1000 * res.images / FPS,
                    res.seconds,
                ]
            )
            if scene.name == "spheres":
                sphere_rows += sphere_figures(res, scene)
            if scene.name == "plane":
                flat_rows.append(flatness_figure(res))
        if mine is None:
            rows.append(["ours (slits + dots)", scene.name, 1, "no"] + ["pending"] * 7)

    print(f"Peers on simulated scenes, camera {w}x{h}, seed {args.seed}\n")
    print(
        markdown_table(
            [
                "method",
                "scene",
                "images needed",
                "stillness required",
                "points / measurement",
                "points / image",
                f"RMS error (mm, |e|<={OUTLIER_MM:.0f})",
                "median |e| (mm)",
                f"outliers >{OUTLIER_MM:.0f} mm (%)",
                f"capture at {FPS:.0f} fps (ms)",
                "processing (s)",
            ],
            rows,
            digits=3,
        )
    )
    print(
        "Spheres, VDI/VDE 2634-2 (mm): PS = fitted - true diameter, PF = range of residuals;"
        f" all points off depth edges, then only those within {OUTLIER_MM:.0f} mm of the truth"
        " (a diagnostic the guideline does not allow)\n"
    )
    print(
        markdown_table(
            [
                "method",
                "sphere",
                "points",
                "PS",
                "PF",
                "PF (0.3 % left out)",
                f"PS (|e|<={OUTLIER_MM:.0f})",
                f"PF (|e|<={OUTLIER_MM:.0f})",
                f"PF (|e|<={OUTLIER_MM:.0f}, 0.3 % left out)",
            ],
            sphere_rows,
        )
    )
    print("Plane, flatness error F (mm): range of distances to the LSQ plane\n")
    print(markdown_table(["method", "points", "F", "F (0.3 % left out)"], flat_rows))


if __name__ == "__main__":
    main()
