"""The dot projector calibrated from the reference boards, against the simulator's truth."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from multislit.calibrate import Calibration
from multislit.errors import CalibrationError
from multislit.geometry.dots import DotProjector, dot_frame
from multislit.io import Capture
from multislit.sim import RigSpec, SimulatedRig
from multislit.stripes import SlitExtractionError
from multislit.stripes.dots import DotCentres, dots_off_stripes, find_dots, near_stripes


@pytest.fixture(scope="module")
def calibrated(small_calibrated):
    return small_calibrated


def _true_rig(capture) -> SimulatedRig:
    cap = Capture.open(capture)
    return SimulatedRig.build(RigSpec.from_dict(cap.rig["simulator"]["rig"]))


def test_source_found_within_a_few_mm(calibrated, small_capture):
    rig = _true_rig(small_capture)
    fit = calibrated.dots
    assert fit is not None, calibrated.notes
    err = np.linalg.norm(fit.projector.source - rig.dots.origin)
    assert err < 5.0, err  # mm; 40 mm from the slit projector along the slits
    # each board's own centres of the rays' dots (blends and speckle included): 0.31 px
    assert fit.rms_px < 0.4, fit.report()


def _landing(rig, calibrated, depth):
    """The true dots' and the calibrated rays' images on a plane facing the rig at ``depth``
    mm (the true dots: those in the image, 5 px clear of its sides)."""
    proj = calibrated.dots.projector
    z = 1000.0 - depth  # the rig looks along -Z from Z = 1000 mm

    def land(origin, directions):
        t = (z - origin[2]) / directions[:, 2]
        return origin + t[:, None] * directions

    truth = rig.camera.project(land(rig.dots.origin, rig.dots.directions))
    w, h = rig.camera.image_size
    inside = (truth[:, 0] > 5) & (truth[:, 0] < w - 6) & (truth[:, 1] > 5) & (truth[:, 1] < h - 6)
    ours = calibrated.calibration.camera.project(land(proj.source, proj.directions))
    return truth, inside, ours


@pytest.mark.parametrize("depth", [750.0, 900.0, 1050.0])
def test_rays_put_dots_where_the_true_dots_land(calibrated, small_capture, depth):
    """On a plane facing the rig at three depths (the middle one between the boards, the
    others at and beyond the outer ones), each calibrated ray lands within a pixel of a true
    dot, and most true dots in the image have a ray."""
    rig = _true_rig(small_capture)
    truth, inside, ours = _landing(rig, calibrated, depth)
    d, _ = cKDTree(truth).query(ours)
    assert np.median(d) < 0.5, np.median(d)
    assert np.mean(d < 1.0) > 0.9, np.mean(d < 1.0)
    covered, _ = cKDTree(ours).query(truth[inside])
    assert np.mean(covered < 1.0) > 0.7, np.mean(covered < 1.0)


def test_recall_and_accuracy_against_the_truth(calibrated, small_capture):
    """On the middle board's plane (900 mm; measured: 68 % of the true dots in the image have
    a ray within 0.5 px and 80 % within 1 px, 3.7 % of the rays have no true dot within 1 px)."""
    rig = _true_rig(small_capture)
    truth, inside, ours = _landing(rig, calibrated, 900.0)
    covered, _ = cKDTree(ours).query(truth[inside])
    assert np.mean(covered < 0.5) > 0.6, np.mean(covered < 0.5)
    assert np.mean(covered < 1.0) > 0.75, np.mean(covered < 1.0)
    d, _ = cKDTree(truth).query(ours)
    assert np.mean(d > 1.0) < 0.06, np.mean(d > 1.0)
    assert np.median(d[d <= 1.0]) < 0.25, np.median(d[d <= 1.0])


def test_brightness_follows_the_true_dots(calibrated, small_capture):
    """Each ray's brightness (its dot's response over the nearest stripe's peak) ranks the
    dots as the simulator's brightness over the slit's power does (Spearman 0.61 measured)."""
    from scipy.stats import spearmanr

    rig = _true_rig(small_capture)
    proj = calibrated.dots.projector
    beta = proj.brightness
    assert beta.shape == (proj.num_dots,)
    assert np.mean(np.isfinite(beta)) > 0.95
    assert np.all(beta[np.isfinite(beta)] > 0)
    # the true ray nearest each calibrated one, and the slit whose band it lies in
    truth, _, ours = _landing(rig, calibrated, 900.0)
    d, i = cKDTree(truth).query(ours)
    ok = (d < 0.5) & np.isfinite(beta)
    phi, _, _ = rig.projector.local(rig.dots.origin + rig.dots.directions[i[ok]])
    k = np.argmin(np.abs(phi[:, None] - rig.projector.angles[None, :]), axis=1)
    relative = rig.dots.brightness[i[ok]] / rig.projector.powers[k]
    rho = spearmanr(beta[ok], relative).statistic
    assert rho > 0.5, rho


def test_reference_depths_are_the_boards(calibrated, small_capture):
    cap = Capture.open(small_capture)
    boards = cap.rig["simulator"]["rig"]["reference_distances"]
    got = calibrated.dots.projector.reference_depths
    assert got.shape == (len(boards),)
    # the boards stand at these distances from the rig along -Z; the camera looks slightly
    # sideways, so its axis meets them a little farther
    assert np.all(np.abs(np.sort(got) - np.sort(boards)) < 0.05 * np.array(boards))


def test_the_calibration_file_keeps_the_dot_projector(calibrated, tmp_path):
    cal = calibrated.calibration
    back = Calibration.load(cal.save(tmp_path / "cal.json"))
    a, b = cal.dot_projector, back.dot_projector
    assert b is not None and b.num_dots == a.num_dots
    np.testing.assert_allclose(b.source, a.source)
    np.testing.assert_allclose(b.directions, a.directions, atol=1e-8)
    np.testing.assert_allclose(b.reference_depths, a.reference_depths)
    np.testing.assert_allclose(b.brightness, a.brightness, atol=1e-5, equal_nan=True)
    np.testing.assert_array_equal(np.isnan(b.brightness), np.isnan(a.brightness))
    assert b.spot_sigma_px == pytest.approx(a.spot_sigma_px, abs=1e-6)


def test_the_spots_sigma_is_the_boards(calibrated):
    """The sigma of the boards' spots on their sharp response (the median over the boards,
    1.25 px measured; the references' dot FWHM is 1.79 px, a Gaussian's sigma of 0.76 px: the
    dots' tails reach farther), kept for the scans; unknown in a file without it."""
    proj = calibrated.calibration.dot_projector
    assert 1.0 < proj.spot_sigma_px < 1.5, proj.spot_sigma_px
    d = proj.to_dict()
    del d["spot_sigma_px"]
    assert math.isnan(DotProjector.from_dict(d).spot_sigma_px)
    assert replace(proj, spot_sigma_px=math.nan).to_dict()["spot_sigma_px"] == -1.0
    with pytest.raises(CalibrationError, match="spot_sigma_px"):
        replace(proj, spot_sigma_px=0.0)


def test_a_calibration_file_without_brightness_loads(calibrated):
    """calibration.json written before the rays had a brightness: every ray's is unknown."""
    d = json.loads(calibrated.calibration.to_json())
    del d["dot_projector"]["brightness"]
    back = Calibration.from_dict(d).dot_projector
    assert back.num_dots == calibrated.calibration.dot_projector.num_dots
    assert back.brightness.shape == (back.num_dots,) and np.all(np.isnan(back.brightness))


def test_unknown_brightness_is_written_as_minus_one(calibrated):
    proj = calibrated.calibration.dot_projector
    beta = proj.brightness.copy()
    beta[:3] = np.nan
    d = replace(proj, brightness=beta).to_dict()
    assert d["brightness"][:3] == [-1.0, -1.0, -1.0]
    back = DotProjector.from_dict(d)
    assert np.all(np.isnan(back.brightness[:3]))
    np.testing.assert_allclose(back.brightness[3:], beta[3:], atol=1e-5)


def test_the_report_states_the_dot_projector(calibrated):
    from multislit.calibrate import format_report

    lines = [x for x in format_report(calibrated) if x.startswith("dot projector:")]
    assert len(lines) == 1 and "px RMS" in lines[0], lines


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.pop("psi"), "dot_projector has no psi"),
        (lambda d: d.__setitem__("source", [0.0, "x", 1.0]), "dot_projector is malformed"),
        (lambda d: d.__setitem__("frame", np.eye(3).tolist()[:2]), "frame must be a 3x3"),
        (lambda d: d.__setitem__("phi", d["phi"][:-1]), "phi and psi"),
        (lambda d: d.__setitem__("reference_depths", [-5.0]), "reference_depths"),
        (lambda d: d.__setitem__("brightness", d["brightness"][:-1]), "brightness"),
    ],
)
def test_a_malformed_dot_projector_is_named(calibrated, change, message):
    d = json.loads(calibrated.calibration.to_json())
    change(d["dot_projector"])
    with pytest.raises(CalibrationError, match=message):
        Calibration.from_dict(d)


def test_dot_frame_is_a_rotation_with_y_along_the_slits():
    rng = np.random.default_rng(0)
    dirs = rng.normal([0, 0, 1], 0.1, (50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    f = dot_frame(dirs, [0.1, 1.0, 0.0])
    np.testing.assert_allclose(f @ f.T, np.eye(3), atol=1e-12)
    assert f[1] @ np.array([0.1, 1.0, 0.0]) > 0.99
    proj = DotProjector(np.zeros(3), f, *_angles(dirs, f))
    np.testing.assert_allclose(proj.directions, dirs, atol=1e-12)


def _angles(dirs, f):
    p = dirs @ f.T
    return np.arctan2(p[:, 0], p[:, 2]), np.arcsin(p[:, 1])


def _spots(shape, uv, sigma, amp):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    img = np.zeros(shape, np.float32)
    for (u, v), a in zip(uv, amp, strict=True):
        img += a * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    return img


def test_find_dots_centres_gaussian_spots_to_a_tenth_of_a_pixel():
    rng = np.random.default_rng(3)
    uv = np.stack([rng.uniform(5, 95, 30), rng.uniform(5, 75, 30)], 1)
    keep = cKDTree(uv).query(uv, k=2)[0][:, 1] > 6  # separate spots
    uv = uv[keep]
    img = _spots((80, 100), uv, 1.0, np.full(len(uv), 50.0))
    img += rng.normal(0, 1.0, img.shape).astype(np.float32)
    dots = find_dots(img, 1.0, 1.0 * 2.3548)
    d, i = cKDTree(dots.uv).query(uv)
    assert np.all(d < 0.1), d.max()
    assert len(dots) == len(uv)  # no dot from the noise


def test_find_dots_rejects_bad_arguments():
    with pytest.raises(SlitExtractionError, match="dot_image"):
        find_dots(np.zeros(5), 1.0, 2.0)
    with pytest.raises(SlitExtractionError, match="noise_sigma"):
        find_dots(np.zeros((5, 5)), -1.0, 2.0)
    with pytest.raises(SlitExtractionError, match="dot_size_px"):
        find_dots(np.zeros((5, 5)), 1.0, math.nan)


def test_speckle_on_a_stripe_is_not_a_dot():
    """Beside a stripe, a peak a fifth of the stripe's height or more is a dot; weaker is
    speckle on the stripe."""
    shape = (40, 60)
    u = np.full(40, 20.0)
    v = np.arange(40.0)
    zone = near_stripes(u, v, shape, 3.0)
    dots = DotCentres(
        np.array([21.0, 22.0, 40.0]), np.array([10.0, 25.0, 10.0]), np.array([20.0, 60.0, 20.0])
    )
    kept, near = dots_off_stripes(dots, zone, u, v, np.full(40, 200.0), 3.0, 0.2)
    np.testing.assert_array_equal(kept.u, [22.0, 40.0])
    np.testing.assert_array_equal(near, [True, False])


@pytest.mark.parametrize("radius", [0.5, 3.0, 4.7])
def test_near_stripes_is_the_distance_transform_below_the_radius(radius):
    """The places near a stripe are those OpenCV's distance transform puts within the radius,
    at the image's edges too."""
    rng = np.random.default_rng(2)
    shape = (50, 70)
    u = np.r_[rng.uniform(-2, 72, 60), 0.0, 69.0]
    v = np.r_[rng.uniform(-2, 52, 60), 0.0, 49.0]
    marks = np.full(shape, 255, np.uint8)
    marks[np.clip(np.rint(v).astype(int), 0, 49), np.clip(np.rint(u).astype(int), 0, 69)] = 0
    want = cv2.distanceTransform(marks, cv2.DIST_L2, 3) < radius
    np.testing.assert_array_equal(near_stripes(u, v, shape, radius), want)


def _board_image(rng, dots_uv, amp, shape=(160, 200), spacing=20.0):
    """A synthetic reference image: vertical stripes (sigma 1.2 px) every ``spacing`` px on a
    flat background, Gaussian dots (sigma 1.0 px) at ``dots_uv``, noise (sigma 1.5)."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w].astype(float)
    img = np.full(shape, 20.0)
    for c in np.arange(10.0, w - 5, spacing):
        img += 120.0 * np.exp(-0.5 * ((xx - c) / 1.2) ** 2)
    img += _spots(shape, dots_uv, 1.0, amp)
    img += rng.normal(0.0, 1.5, shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _singles_and_pairs(rng):
    """40 dots clear of one another and 12 pairs 2.2-2.8 px apart (one peak in a dot-sized
    smoothing) in a 200 x 160 image: (M, 2) px, and which are of a pair (M,) bool."""
    single = np.stack([rng.uniform(8, 192, 40), rng.uniform(8, 152, 40)], axis=1)
    single = single[cKDTree(single).query(single, k=2)[0][:, 1] > 9]
    ang = rng.uniform(0, np.pi, 12)
    sep = rng.uniform(2.2, 2.8, 12)
    first = np.stack([rng.uniform(12, 188, 12), rng.uniform(12, 148, 12)], axis=1)
    second = first + sep[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    uv = np.concatenate([single, first, second])
    keep = np.ones(len(uv), bool)
    d, j = cKDTree(uv).query(uv, k=2)
    pair = np.r_[np.zeros(len(single), bool), np.ones(24, bool)]
    keep &= pair | (d[:, 1] > 9)  # single dots clear of every other one
    return uv[keep], pair[keep]


def test_board_dots_are_centred_beside_their_neighbours():
    """Dots clear of the stripes and on them are fitted within 0.2 px; of pairs 2.2-2.8 px
    apart (one peak in a dot-sized smoothing) most are, every one within 0.5 px (measured: 79 %
    within 0.2 px, the worst 0.37 px)."""
    from multislit.calibrate.board_dots import read_board

    rng = np.random.default_rng(5)
    uv, pair = _singles_and_pairs(rng)
    amp = rng.uniform(60.0, 100.0, len(uv))
    img = _board_image(rng, uv, amp)
    board = read_board(img, stripe_width_px=2.83, dot_size_px=2.35)
    got = board.dots.uv
    dist, _ = cKDTree(got).query(uv)
    assert np.mean(dist[~pair] < 0.2) > 0.9, np.sort(dist[~pair])[-5:]
    assert np.mean(dist[pair] < 0.2) > 0.7, np.sort(dist[pair])[-8:]
    assert np.all(dist[pair] < 0.5), np.sort(dist[pair])[-8:]
    # and no dot where there is none: the fitted dots of 8 standard errors are true ones (the
    # fit's errors leave out how the noise is correlated between pixels: noise reaches 6)
    strong = board.dots.z >= 8.0
    d_back, _ = cKDTree(uv).query(got[strong])
    assert np.mean(d_back < 0.5) > 0.95, np.mean(d_back < 0.5)


def test_a_frames_dots_are_centred_as_the_boards_dots():
    """A scan's identified dots (:func:`centre_dots`, given where they were found) are fitted
    as a board's dots are (:func:`read_board`): one spot model on one sharp response, so the
    dots clear of others get the board's centres (measured: within 0.008 px but one, 0.14 px);
    the blended pairs are split as on a board, up to where the frame's noise, measured beside
    its stripes, tips a second spot in or out (measured: 17 of 24 within 0.2 px of the truth,
    the board 18); a dot given where no spot is keeps its centre."""
    from multislit.calibrate.board_dots import read_board
    from multislit.stripes.dots import centre_dots

    rng = np.random.default_rng(5)
    uv, pair = _singles_and_pairs(rng)
    img = _board_image(rng, uv, rng.uniform(60.0, 100.0, len(uv)))
    board = read_board(img, stripe_width_px=2.83, dot_size_px=2.35)
    view = board.view
    found = uv + rng.uniform(-0.4, 0.4, uv.shape)
    found = np.concatenate([found, [[100.0, 3.5]]])  # no dot there
    angle, _ = view.lookup(found[:, 0], found[:, 1])
    sg = board.sharp.profile_sigma
    u, v, fitted = centre_dots(view.extraction, found[:, 0], found[:, 1], angle, sg)
    assert not fitted[-1] and (u[-1], v[-1]) == (100.0, 3.5)
    assert fitted[:-1].all()
    got = np.stack([u, v], axis=1)[:-1]
    _, i = cKDTree(board.dots.uv).query(uv)
    diff = np.linalg.norm(got - board.dots.uv[i], axis=1)
    assert np.mean(diff[~pair] < 0.01) > 0.9, np.sort(diff[~pair])[-5:]
    err = np.linalg.norm(got - uv, axis=1)
    assert np.mean(err[pair] < 0.2) > 0.7, np.sort(err[pair])[-8:]
