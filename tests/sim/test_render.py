"""The renderer checked against geometry it must obey (not against itself)."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from multislit.sim.render import render
from multislit.sim.rig import SimulatedRig
from multislit.sim.scene import large_plane, reference_board, standard_object, steps


def _no_dots(spec):
    return replace(spec, dots=replace(spec.dots, power=0.0))


def true_stripe_u(rig, plane, k):
    """Rows v and the u where slit k's true plane meets ``plane``, projected with distortion."""
    P = rig.projector.planes()[k]
    d = np.cross(P[:3], plane[:3])
    d /= np.linalg.norm(d)
    p0 = np.linalg.solve(np.stack([P[:3], plane[:3], d]), -np.array([P[3], plane[3], 0.0]))
    X = p0 + np.linspace(-1500, 1500, 30001)[:, None] * d
    uv = rig.camera.project(X)
    w, h = rig.camera.image_size
    ok = (
        np.isfinite(uv).all(1)
        & (uv[:, 0] > 6)
        & (uv[:, 0] < w - 6)
        & (uv[:, 1] > 6)
        & (uv[:, 1] < h - 6)
    )
    uv = uv[ok][np.argsort(uv[ok, 1])]
    rows = np.arange(int(uv[0, 1]) + 1, int(uv[-1, 1]))
    return rows, np.interp(rows, uv[:, 1], uv[:, 0])


def peak_centre(img, v, u0):
    """3-point Gaussian (log-parabola) peak position near u0 in row v."""
    i = int(round(u0))
    row = img[v, i - 3 : i + 4].astype(float)
    j = int(np.argmax(row))
    if j in (0, 6):
        return np.nan
    lo, c, hi = np.log(row[j - 1 : j + 2] + 1e-12)
    return i - 3 + j + 0.5 * (lo - hi) / (lo - 2 * c + hi)


@pytest.mark.parametrize("make", [lambda: reference_board(900), lambda: large_plane(tilt_deg=25)])
def test_stripe_centre_lies_on_true_slit_plane(clean_spec, make):
    rig = SimulatedRig.build(_no_dots(clean_spec))
    scene = make()
    r = render(rig, scene, np.random.default_rng(0))
    plane = np.array(scene.info["plane"])
    errs = []
    for k in range(rig.projector.num_slits):
        rows, ut = true_stripe_u(rig, plane, k)
        errs += [peak_centre(r.radiance, v, u) - u for v, u in zip(rows, ut, strict=True)]
    errs = np.array(errs)
    errs = errs[np.isfinite(errs)]
    assert len(errs) > 5000
    assert np.sqrt(np.mean(errs**2)) <= 0.05
    assert np.abs(errs).max() <= 0.1


def test_shadowed_pixels_get_no_laser_light(clean_spec):
    spec = _no_dots(replace(clean_spec, sensor=replace(clean_spec.sensor, ambient=0.0)))
    rig = SimulatedRig.build(spec)
    scene = steps()
    r = render(rig, scene, np.random.default_rng(0), ambient=True)
    xyz = r.xyz.reshape(-1, 3).astype(float)
    hit = np.isfinite(xyz).all(1)
    # independent occlusion test: is the segment point -> projector blocked?
    p = rig.projector
    to = p.origin - xyz[hit]
    dist = np.linalg.norm(to, axis=1)
    t, _ = scene.first_hit_t(xyz[hit] + 1e-3 * to / dist[:, None], to / dist[:, None])
    blocked = np.zeros(len(xyz), bool)
    blocked[np.flatnonzero(hit)[t < dist - 1.0]] = True
    phi, psi, _ = p.local(np.where(hit[:, None], xyz, 0.0))
    in_sheet = (
        hit
        & (np.abs(phi[:, None] - p.angles[None]).min(1) < p.sigma)
        & (np.abs(psi) < p.fan_half - 0.05)
    )
    h, w = r.slit.shape
    blocked2 = blocked.reshape(h, w)
    core = cv2.erode(blocked2.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool).ravel()
    shadow_sheet = in_sheet & core
    lit_sheet = (
        in_sheet
        & ~blocked
        & ~cv2.dilate(blocked2.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool).ravel()
    )
    assert shadow_sheet.sum() > 100, "the steps scene must have slits falling into shadows"
    rad = r.radiance.ravel()
    assert rad[shadow_sheet].max() < 1e-4
    assert np.median(rad[lit_sheet]) > 0.1
    assert not r.lit.ravel()[shadow_sheet].any()
    assert (r.slit.ravel()[shadow_sheet] == -1).all()


@pytest.mark.slow
def test_marker_corners_appear_at_projected_xyz(clean_spec):
    spec = replace(clean_spec, sensor=replace(clean_spec.sensor, blur_sigma_px=1.5, supersample=6))
    rig = SimulatedRig.build(spec)
    scene, markers, _ = standard_object()
    r = render(rig, scene, np.random.default_rng(0), lasers=False)
    uv = rig.camera.project(np.array([m["xyz"] for m in markers]))
    img = (r.radiance / r.radiance.max()).astype(np.float32)
    found = cv2.cornerSubPix(
        img,
        uv.astype(np.float32).reshape(-1, 1, 2).copy(),
        (5, 5),
        (-1, -1),
        (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4),
    ).reshape(-1, 2)
    err = np.linalg.norm(found - uv, axis=1)
    # cornerSubPix's own error on a blurred step corner is ~0.05 px: a half-pixel slip would fail
    assert err.max() < 0.15 and np.sqrt(np.mean(err**2)) < 0.08
    # and the pattern around each corner is a checker: diagonal quadrants alike, neighbours differ
    rad = r.radiance
    for u, v in uv:
        q = [rad[int(v + dv), int(u + du)] for du, dv in ((4, 4), (-4, -4), (4, -4), (-4, 4))]
        assert abs(q[0] - q[1]) < 0.2 * max(q) and abs(q[2] - q[3]) < 0.2 * max(q)
        assert abs(q[0] - q[2]) > 0.5 * max(q)


def test_marker_edges_are_integrated_over_the_pixel(small_spec):
    """Pixels on a marker's edges are supersampled on an n-rooks lattice: the found corners lie
    where the markers project, well below the detector's own scatter. Measured (half size,
    default noise): 0.025 px RMS per coordinate; a square 3 x 3 grid of samples gave 0.065 px
    (its coverage steps by thirds along an edge near a pixel axis)."""
    from multislit.calibrate.markers import find_marker_corners

    rig = SimulatedRig.build(small_spec)
    scene, markers, _ = standard_object()
    r = render(rig, scene, np.random.default_rng(1), lasers=False)
    uv = rig.camera.project(np.array([m["xyz"] for m in markers]))
    det = find_marker_corners(r.image, uv + 1.0, [m["id"] for m in markers])
    assert det.found.all()
    err = det.uv - uv
    assert np.sqrt(np.mean(err**2)) < 0.035 and np.abs(err).max() < 0.1


def test_same_seed_same_image_other_seed_other_noise(small_rig):
    scene = reference_board(900)
    a = render(small_rig, scene, np.random.default_rng(7)).image
    b = render(small_rig, scene, np.random.default_rng(7)).image
    c = render(small_rig, scene, np.random.default_rng(8)).image
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    # the scene and the dots are the same, only the noise differs
    assert np.median(np.abs(a.astype(int) - c.astype(int))) <= 2
    assert np.corrcoef(a.ravel(), c.ravel())[0, 1] > 0.95


def test_slits_numbered_left_to_right(small_rig):
    r = render(small_rig, reference_board(900), np.random.default_rng(0))
    for v in range(50, 500, 50):
        ks = r.slit[v][r.slit[v] >= 0]
        runs = ks[np.r_[True, np.diff(ks) != 0]]
        assert np.all(np.diff(runs) > 0)
        assert runs[0] == 0 and runs[-1] == small_rig.projector.num_slits - 1


def test_dots_stay_in_their_slit_bands(small_rig):
    """With the dot projector on the grating axis, each dot keeps its place beside its slit."""
    p = small_rig.projector
    spacing = np.median(np.diff(p.angles))
    band = small_rig.spec.dots.band_halfwidth * spacing
    for dist in (780.0, 1020.0):
        scene = reference_board(dist)
        o = np.broadcast_to(small_rig.dots.origin, small_rig.dots.directions.shape).copy()
        hit = scene.cast(o, small_rig.dots.directions)
        phi, _, _ = p.local(hit.point[np.isfinite(hit.t)])
        assert np.abs(phi[:, None] - p.angles[None]).min(1).max() <= band + 1e-9


def test_sensor_saturates_and_quantises(small_rig):
    spec = replace(small_rig.spec, slits=replace(small_rig.spec.slits, power=5.0))
    img = render(SimulatedRig.build(spec), reference_board(780), np.random.default_rng(0)).image
    assert img.dtype == np.uint8 and img.max() == 255 and (img == 255).sum() > 1000


@pytest.mark.parametrize(
    "name", sorted(__import__("multislit.sim.scene", fromlist=["SCENES"]).SCENES)
)
def test_every_scene_renders_with_slits(name):
    from multislit.sim.rig import RigSpec
    from multislit.sim.scene import make_scene

    rig = SimulatedRig.build(RigSpec().scaled(0.25))
    r = render(rig, make_scene(name), np.random.default_rng(0))
    assert r.image.shape == (256, 320)
    assert (r.slit >= 0).sum() > 500, "slits must fall on every scene"
    assert len(np.unique(r.slit[r.slit >= 0])) >= 15


def test_stripe_snr_is_the_slits_step_over_the_pixels_noise(small_spec):
    """The truth's ``stripe_snr``: its step is what the slits add to the noise-free image (to
    the rounding), its noise what two noisy renderings of the scene differ by."""
    spec = replace(_no_dots(small_spec), sensor=replace(small_spec.sensor, speckle_contrast=0.0))
    quiet = replace(spec, sensor=replace(spec.sensor, noise=False))
    dark = replace(quiet, slits=replace(quiet.slits, power=0.0))
    scene = reference_board(900)
    rng = np.random.default_rng
    clean = render(SimulatedRig.build(quiet), scene, rng(0))
    step = clean.image.astype(float) - render(SimulatedRig.build(dark), scene, rng(0)).image
    on = clean.stripe_snr > 0
    assert on.mean() > 0.05 and np.all(clean.stripe_snr[clean.slit >= 0] > 0)
    # without noise the pixel's noise is the rounding alone
    assert np.abs(step[on] - clean.stripe_snr[on] * np.sqrt(1 / 12)).max() <= 1.0
    rig = SimulatedRig.build(spec)
    a, b = (render(rig, scene, rng(s)) for s in (1, 2))
    assert np.array_equal(a.stripe_snr, b.stripe_snr)  # noise-free, as the truth is
    strong = on & (step >= 20)
    sigma = step[strong] / a.stripe_snr[strong]
    z = (a.image[strong].astype(float) - b.image[strong]) / (np.sqrt(2) * sigma)
    assert 0.9 < z.std() < 1.1, z.std()
