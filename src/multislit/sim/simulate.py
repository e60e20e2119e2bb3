"""Write a complete simulated capture folder (format ``multislit-capture/1``) plus ground truth.

Layout written (see ``docs/capture-format.md``)::

    rig.json, target.json, calibration/{markers,slits}.png, reference/ref_DDDD.png,
    scans/<scene>.png, truth/models.json, truth/<image>.npz

Each ``truth/<image>.npz`` holds per pixel ``xyz`` (float32, mm, world; NaN: nothing seen),
``slit`` (int16, the slit lighting the point, -1: none), ``lit`` (bool, in the slit projector's
view), ``obj`` (int16, index of the primitive seen, -1: nothing), ``object`` (bool, the surface
is an object, not the backdrop), ``names`` (the scene's primitive names, by index) and, in the
images with the lasers on, ``stripe_snr`` (float32, the slits' light at the pixel in noise
sigmas of the pixel, :func:`multislit.sim.render.stripe_snr`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from multislit.errors import MultislitError
from multislit.io import Target, write_image, write_rig_json
from multislit.sim.primitives import Scene
from multislit.sim.render import Rendered, render
from multislit.sim.rig import RigSpec, SimulatedRig
from multislit.sim.scene import TargetDesign, make_scene, reference_board, standard_object

Progress = Callable[[int, int, str], None]


def _hand_readings(
    rig: SimulatedRig,
    rendered: Rendered,
    faces: list[dict],
    rng: np.random.Generator,
    per_slit: int = 2,
) -> list[dict]:
    """Hand readings as in the paper: points on the slits on the target faces, read off its scales.

    Each reading is exactly on the slit plane and the face plane (the scale is read to ~0.2 mm
    along the slit line); ``uv`` is its true projection.
    """
    planes = rig.projector.planes()
    out = []
    slit = rendered.slit
    xyz = rendered.xyz.astype(float)
    for k in range(len(planes)):
        vv, uu = np.nonzero(slit == k)
        if vv.size == 0:
            continue
        pts = xyz[vv, uu]
        for f in faces:
            fp = np.asarray(f["plane"])
            on = np.abs(pts @ fp[:3] + fp[3]) < 0.5
            if on.sum() < 10:
                continue
            # the line slit-plane x face-plane; points along it at random places seen in the image
            cand = pts[on]
            d = np.cross(planes[k, :3], fp[:3])
            d /= np.linalg.norm(d)
            for p in cand[rng.choice(len(cand), size=min(per_slit, len(cand)), replace=False)]:
                # project p onto the line (closest point satisfying both planes)
                A = np.stack([planes[k, :3], fp[:3], d])
                b = -np.array([planes[k, 3], fp[3], -d @ p])
                q = np.linalg.solve(A, b) + d * rng.normal(0, 0.2)
                uv = rig.camera.project(q)[0]
                out.append({"slit": int(k), "xyz": q.round(3).tolist(), "uv": uv.round(3).tolist()})
    return out


def _jobs(
    spec: RigSpec, scene_objs: list[Scene], target_scene: Scene
) -> tuple[list[tuple[str, Scene, bool]], dict]:
    """The images to render (name, scene, lasers on) and the reference boards' true planes."""
    jobs: list[tuple[str, Scene, bool]] = [
        ("calibration/markers", target_scene, False),
        ("calibration/slits", target_scene, True),
    ]
    ref_planes = {}
    for dist in spec.reference_distances:
        sc = reference_board(dist)
        ref_planes[f"ref_{dist:04.0f}"] = sc.info["plane"]
        jobs.append((f"reference/ref_{dist:04.0f}", sc, True))
    for sc in scene_objs:
        jobs.append((f"scans/{sc.name}", sc, True))
    return jobs, ref_planes


def _check_reference(rig: SimulatedRig, r: Rendered, name: str) -> None:
    """Raise if a reference image does not show every slit."""
    seen = np.unique(r.slit[r.slit >= 0])
    missing = sorted(set(range(rig.projector.num_slits)) - set(seen.tolist()))
    if missing:
        raise MultislitError(
            f"rig design: slit(s) {missing} do not reach the camera's view on the "
            f"reference board {name}; every reference image must show all slits: "
            f"narrow the fan (larger slits.pitch_um), aim camera and projector closer, "
            f"or change reference_distances"
        )


def _save_truth(path: Path, r: Rendered, scene: Scene) -> None:
    """One image's per-pixel truth (see the module's docstring)."""
    extra = {} if r.stripe_snr is None else {"stripe_snr": r.stripe_snr}
    np.savez_compressed(
        path,
        xyz=r.xyz,
        slit=r.slit,
        lit=r.lit,
        obj=r.obj,
        object=scene.is_object(r.obj),
        names=np.array(scene.names, dtype=str),
        **extra,
    )


def simulate_capture(
    outdir: str | Path,
    scenes: Sequence[str | Scene] = ("holes",),
    spec: RigSpec | None = None,
    seed: int = 0,
    hand_readings: bool = True,
    progress: Progress | None = None,
    overwrite: bool = False,
    target: TargetDesign | None = None,
) -> Path:
    """Simulate a rig and write a complete capture folder with ground truth.

    Parameters
    ----------
    outdir : folder to create (must be empty or absent unless ``overwrite``)
    scenes : named scenes (``multislit.sim.SCENES``) or Scene objects, one scan each
    spec : the rig (default: the paper's rig)
    seed : seeds every image's noise; the same seed gives the same images
    hand_readings : add the paper's ``slit_points`` hand readings to target.json
    progress : called as ``progress(i, n, name)`` before each image
    overwrite : allow writing into a folder that is not empty
    target : the calibration target's design (default: ``TargetDesign()``)

    Returns
    -------
    The capture folder's path.
    """
    out = Path(outdir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise MultislitError(
            f"output folder {out} is not empty; choose a new folder or allow overwriting (--overwrite)"
        )
    spec = spec or RigSpec()
    rig = SimulatedRig.build(spec)
    scene_objs = [make_scene(s) if isinstance(s, str) else s for s in scenes]
    names = [s.name for s in scene_objs]
    if len(set(names)) != len(names):
        raise MultislitError(f"scene names must be unique, got {names}")
    target_scene, markers, faces = standard_object(target or TargetDesign())
    jobs, ref_planes = _jobs(spec, scene_objs, target_scene)

    seeds = np.random.SeedSequence(seed).spawn(len(jobs) + 1)
    truth_dir = out / "truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    rendered_slits = None
    for i, (name, sc, lasers) in enumerate(jobs):
        if progress:
            progress(i, len(jobs), name)
        r = render(rig, sc, np.random.default_rng(seeds[i]), lasers=lasers)
        write_image(out / f"{name}.png", r.image)
        if lasers:
            _save_truth(truth_dir / f"{Path(name).name}.npz", r, sc)
        if name == "calibration/slits":
            rendered_slits = r
        if name.startswith("reference/"):
            _check_reference(rig, r, name)
    if progress:
        progress(len(jobs), len(jobs), "done")

    rng = np.random.default_rng(seeds[-1])
    uv = rig.camera.project(np.array([m["xyz"] for m in markers]))
    w, h = spec.camera.image_size
    for m, p in zip(markers, uv, strict=True):
        # a person's click: within a few px of the corner
        m["uv_hint"] = (p + rng.uniform(-4, 4, 2)).clip([0, 0], [w - 1, h - 1]).round(1).tolist()
    tdict: dict = {"markers": markers, "faces": faces}
    if hand_readings and rendered_slits is not None:
        tdict["slit_points"] = _hand_readings(rig, rendered_slits, faces, rng)
    Target.from_dict(tdict, num_slits=spec.slits.num_slits)  # validate what we write
    (out / "target.json").write_text(json.dumps(tdict, indent=1))
    write_rig_json(
        out,
        spec.camera.image_size,
        spec.slits.num_slits,
        source="multislit simulator",
        simulator={"rig": spec.to_dict(), "seed": seed, "scenes": names},
    )
    models = {
        "camera": rig.camera.to_dict(),
        "projector": rig.projector.to_dict(),
        "dot_projector": rig.dots.to_dict(),
        "reference_planes": ref_planes,
        "scenes": {sc.name: sc.info for sc in scene_objs},
        "markers_true_uv": {m["id"]: p.tolist() for m, p in zip(markers, uv, strict=True)},
    }
    (truth_dir / "models.json").write_text(json.dumps(models, indent=1))
    return out
