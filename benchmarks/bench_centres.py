"""Stripe-centre precision as 3D error: each sub-pixel centre method against the truth.

For each scene, the image is rendered with the simulator's default noise (shot and read noise,
laser speckle, dots along the slits), the slits are extracted with each centre method, every
centre is given its true slit (the truth image at its pixel) and triangulated with the true
camera and slit planes; the error of a point is its distance to where its camera ray truly meets
the scene. So the figures are the stripe centres' own contribution to the 3D error, free of
calibration and identification.

The last column, ``refined``, is the Gaussian extraction's points re-centred by
:func:`multislit.stripes.refine_centres` (what ``scan_image`` triangulates by default); its
``ok`` figure is the share of points actually re-centred (the others keep their Gaussian
centre).

Reported per method: RMS (mm) of the points within 1 mm of the truth, the median (mm), and the
share (%) of points more than 1 mm off (centres on the wrong surface at occlusions and edges).

Run:  .venv/bin/python benchmarks/bench_centres.py [--scale 1.0] [--slits 25] [--seed 0]
      [--degree auto]
"""

from __future__ import annotations

import argparse

import numpy as np

from multislit.reconstruct import triangulate
from multislit.sim.render import render
from multislit.sim.rig import RigSpec, SimulatedRig, dense_rig
from multislit.sim.scene import large_plane, spheres, steps, textured
from multislit.stripes import CENTRE_METHODS, extract_slits, refine_centres


def point_errors(rig: SimulatedRig, rendered, scene, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(M,) mm: distance of each triangulated centre (true slit, true models) to the truth."""
    h, w = rendered.slit.shape
    iu = np.clip(np.round(u).astype(int), 0, w - 1)
    iv = np.clip(np.round(v).astype(int), 0, h - 1)
    k = rendered.slit[iv, iu].astype(int)
    on = k >= 0
    uv = np.c_[u, v][on]
    X, ok = triangulate(rig.camera, rig.projector.planes(), uv, k[on])
    o, d = rig.camera.rays(uv)
    t, _ = scene.first_hit_t(o, d)
    ok &= np.isfinite(t)
    return np.linalg.norm(X - (o + t[:, None] * d), axis=1)[ok]


def summary(e: np.ndarray) -> dict[str, float]:
    inl = e < 1.0
    return {
        "rms_mm": float(np.sqrt(np.mean(e[inl] ** 2))),
        "median_mm": float(np.median(e)),
        "over_1mm_pct": float(100 * (~inl).mean()),
        "points": int(e.size),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="image scale (1 = 1280x1024)")
    ap.add_argument("--slits", type=int, default=25, choices=(25, 49))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--degree",
        default="auto",
        choices=("auto", "0", "1", "2"),
        help="degree of refine_centres' along-stripe fit (default auto)",
    )
    a = ap.parse_args()
    spec = dense_rig() if a.slits == 49 else RigSpec()
    if a.scale != 1.0:
        spec = spec.scaled(a.scale)
    rig = SimulatedRig.build(spec)
    w, h = spec.camera.image_size
    print(f"# stripe-centre error in 3D, {a.slits} slits, {w}x{h}, seed {a.seed}")
    print("# RMS of points within 1 mm / median (mm) / points more than 1 mm off (%)")
    print(f"{'scene':10s}" + "".join(f"{m:>26s}" for m in CENTRE_METHODS) + f"{'refined':>36s}")
    for scene in (large_plane(15), steps(), spheres(), textured()):
        r = render(rig, scene, np.random.default_rng(a.seed))
        cells = []
        for method in CENTRE_METHODS:
            ex = extract_slits(r.image, method=method)
            m = ex.segment >= 0
            s = summary(point_errors(rig, r, scene, ex.u[m], ex.v[m]))
            cells.append(f"{s['rms_mm']:.3f} / {s['median_mm']:.3f} / {s['over_1mm_pct']:4.2f}%")
            if method == "gaussian":
                gauss = ex
        m = gauss.segment >= 0
        u, ok = refine_centres(
            r.image,
            gauss.u,
            gauss.v,
            gauss.segment,
            gauss.stripe_width_px,
            gauss.dot_size_px,
            degree=a.degree if a.degree == "auto" else int(a.degree),
        )
        s = summary(point_errors(rig, r, scene, u[m], gauss.v[m]))
        cells.append(
            f"{s['rms_mm']:.3f} / {s['median_mm']:.3f} / {s['over_1mm_pct']:4.2f}%"
            f" (ok {100 * ok[m].mean():4.1f}%)"
        )
        print(
            f"{scene.name:10s}" + "".join(f"{c:>26s}" for c in cells[:-1]) + f"{cells[-1]:>36s}",
            flush=True,
        )


if __name__ == "__main__":
    main()
