import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from multislit.errors import ReferenceImageError
from multislit.geometry import PinholeCamera
from multislit.identify import (
    WINDOW_SUMS,
    ReferenceSet,
    bilinear_patch_moments,
    curve_u,
    intersect_line_curves,
    prepare_reference,
    sample_patches,
    sample_sheared_patches,
    window_sums,
)
from multislit.identify.patches import _remap_patches
from multislit.identify.reference import _fit_curves
from multislit.io import Capture


def test_reference_curves_follow_the_true_slits(scenes_capture, scenes_reference):
    ref = scenes_reference
    assert ref.curves.shape[:2] == (3, 25)
    for r, name in enumerate(ref.names):
        truth = np.load(scenes_capture / "truth" / f"{name}.npz")["slit"]
        for v in range(40, 480, 40):
            row = truth[v]
            for k in range(25):
                cols = np.flatnonzero(row == k)
                assert abs(curve_u(ref.curves[r, k], float(v)) - cols.mean()) < 0.6


def test_epipole_is_the_dot_projectors_image(scenes_capture, scenes_reference):
    models = json.loads((scenes_capture / "truth" / "models.json").read_text())
    cam = PinholeCamera.from_dict(models["camera"])
    pinhole = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.rvec, cam.tvec)
    true_e = pinhole.project(np.array(models["dot_projector"]["origin"]))[0]
    e = scenes_reference.epipole
    est = e[:2] / e[2]
    # the epipole lies far outside the image: compare directions seen from the image centre
    c = np.array([320.0, 256.0])
    ang = np.degrees(
        np.arccos(
            np.dot(est - c, true_e - c) / np.linalg.norm(est - c) / np.linalg.norm(true_e - c)
        )
    )
    assert ang < 0.5
    assert scenes_reference.epipole_residual_px < 0.5


def _epipole_error_deg(capture, ref) -> float:
    """Angle (deg) between the estimated and the true epipole, seen from the image centre."""
    models = json.loads((capture / "truth" / "models.json").read_text())
    cam = PinholeCamera.from_dict(models["camera"])
    pinhole = PinholeCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.rvec, cam.tvec)
    true_e = pinhole.project(np.array(models["dot_projector"]["origin"]))[0]
    est = ref.epipole[:2] / ref.epipole[2]
    c = np.array(ref.image_size, float) / 2
    a, b = est - c, true_e - c
    return float(np.degrees(np.arccos(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b))))


@pytest.mark.slow
def test_epipole_on_a_rig_with_many_slits_and_few_dots(tmp_path):
    """Zoo seed 2 (a tuning seed): 41 slits 10.7 px apart, 0.017 dots per px^2. A template
    0.6 slit spacings tall holds about two dots and matches by chance; one sized from the dot
    density finds the epipole (templates 0.6 spacings tall put it 5.5 deg off, residual 14 px)."""
    from multislit.sim import simulate_zoo_capture

    cap_dir = simulate_zoo_capture(tmp_path / "cap", 2, scenes=1)
    cap = Capture.open(cap_dir)
    ref = prepare_reference([cap.image(p) for p in cap.references], cap.num_slits)
    assert ref.num_slits == 41 and ref.spacing_px < 12
    assert _epipole_error_deg(cap_dir, ref) < 0.5
    assert ref.epipole_residual_px < 0.5


def test_save_and_load(scenes_reference, tmp_path):
    p = tmp_path / "ref.npz"
    scenes_reference.save(p)
    back = ReferenceSet.load(p)
    assert np.allclose(back.curves, scenes_reference.curves) and back.num_slits == 25
    with pytest.raises(ReferenceImageError, match="not found"):
        ReferenceSet.load(tmp_path / "none.npz")


def test_reference_with_a_missing_slit_is_an_error(scenes_capture):
    cap = Capture.open(scenes_capture)
    imgs = [cap.image(p).copy() for p in cap.references]
    # black out the rightmost slit in the second image
    truth = np.load(scenes_capture / "truth" / f"{cap.references[1].stem}.npz")["slit"]
    imgs[1][truth == 24] = 0
    imgs[1][:, :] = np.where(
        np.roll(truth == 24, 2, axis=1) | np.roll(truth == 24, -2, axis=1), 0, imgs[1]
    )
    with pytest.raises(
        ReferenceImageError, match=r"ref_0900: found 24 slits in most rows, expected 25"
    ):
        prepare_reference(imgs, 25, [p.stem for p in cap.references])


def test_reference_curves_from_slits_broken_into_short_pieces():
    """A board whose slits the linking breaks into pieces shorter than the image's twentieth
    (dense slits, dots on them), plus a residue of dots lined up along the rows: every slit is
    numbered from the rows that show all of them, and its curve is the true one."""
    h, n = 400, 6
    rows = np.arange(h, dtype=np.float64)
    true_u = [40.0 + 30.0 * k + 0.02 * rows + 1e-5 * (rows - 200) ** 2 for k in range(n)]
    u, v, seg = [], [], []
    s = 0
    for k in range(n):
        # pieces of 12 rows, each slit's breaks at other rows than its neighbours'
        for start in range(-(3 * k % 12), h, 12):
            r = rows[max(start, 0) : start + 12]
            u.append(true_u[k][r.astype(int)])
            v.append(r)
            seg.append(np.full(r.size, s))
            s += 1
    # a residue of dots lined up along v between slits 2 and 3, over rows 100-107
    u.append(np.full(8, 0.5 * (true_u[2][100] + true_u[3][100])))
    v.append(np.arange(100.0, 108.0))
    seg.append(np.full(8, s))
    ex = SimpleNamespace(u=np.concatenate(u), v=np.concatenate(v), segment=np.concatenate(seg))
    coeffs, vrange = _fit_curves(ex, n, "broken", h)
    for k in range(n):
        assert np.max(np.abs(curve_u(coeffs[k], rows) - true_u[k])) < 1e-6
        assert vrange[k, 0] == 0 and vrange[k, 1] == h - 1


def test_too_few_reference_images(scenes_capture):
    cap = Capture.open(scenes_capture)
    with pytest.raises(ReferenceImageError, match=">= 2 reference images"):
        prepare_reference([cap.image(cap.references[0])], 25)


def test_wrong_number_of_slits_is_an_error(scenes_capture):
    cap = Capture.open(scenes_capture)
    with pytest.raises(ReferenceImageError, match="expected 26"):
        prepare_reference([cap.image(p) for p in cap.references], 26)


# --------------------------------------------------------------------------- window sums
def _sparse_dots(rng, shape):
    """A dot-like image: mostly zeros, a few bright blobs (like the separated dot images)."""
    img = np.where(rng.random(shape) < 0.05, rng.uniform(20, 230, shape), 0.0)
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)


def _window_sums_by_integrals(image, half_w, half_h):
    """window_sums from cv2.integral images of the float64 products, one per sum."""
    im = np.asarray(image, np.float64)
    ph, pw = 2 * half_h + 1, 2 * half_w + 1
    prods = [
        im,
        im * im,
        im[:, :-1] * im[:, 1:],
        im[:-1, :] * im[1:, :],
        im[:-1, :-1] * im[1:, 1:],
        im[:-1, 1:] * im[1:, :-1],
    ]
    out = np.zeros((im.shape[0] - ph + 1, im.shape[1] - pw + 1, 6), np.float32)
    for c, q in enumerate(prods):
        ii = cv2.integral(q, sdepth=cv2.CV_64F)
        box = ii[ph:, pw:] - ii[:-ph, pw:] - ii[ph:, :-pw] + ii[:-ph, :-pw]
        out[: box.shape[0], : box.shape[1], c] = box
    return out


@pytest.mark.parametrize(("shape", "half_w", "half_h"), [((70, 90), 4, 9), ((41, 23), 7, 3)])
def test_window_sums_equal_integral_images(rng, shape, half_w, half_h):
    img = _sparse_dots(rng, shape) + rng.uniform(0, 1, shape).astype(np.float32)
    want = _window_sums_by_integrals(img, half_w, half_h)
    assert np.array_equal(window_sums(img, half_w, half_h), want)
    assert np.array_equal(window_sums(img, half_w, half_h, x_major=True), want.transpose(1, 0, 2))
    out = np.full(want.transpose(1, 0, 2).shape, np.nan, np.float32)  # every element written
    window_sums(img, half_w, half_h, x_major=True, out=out)
    assert np.array_equal(out, want.transpose(1, 0, 2))
    with pytest.raises(ValueError, match="out must be"):
        window_sums(img, half_w, half_h, out=out)


@pytest.mark.parametrize(("half_w", "half_h"), [(4, 9), (7, 3)])
def test_bilinear_patch_moments_match_sampled_patches(rng, half_w, half_h):
    img = _sparse_dots(rng, (70, 90))
    sums = window_sums(img, half_w, half_h)
    assert sums.shape == (70 - 2 * half_h, 90 - 2 * half_w, len(WINDOW_SUMS))
    c = np.c_[rng.uniform(half_w, 89 - half_w, 400), rng.uniform(half_h, 69 - half_h, 400)]
    c[:4] = [[half_w, half_h], [89 - half_w, 69 - half_h], [half_w, 30.0], [40.5, 69 - half_h]]
    c[4:40, 1] = np.round(c[4:40, 1])  # whole rows, as the stripe centres are
    patches = sample_patches(img, c, half_w, half_h).reshape(len(c), -1).astype(np.float64)
    s1, s2 = bilinear_patch_moments(sums, c[:, 0] - half_w, c[:, 1] - half_h)
    assert np.allclose(s1, patches.sum(axis=1), rtol=1e-5, atol=1e-3)
    assert np.allclose(s2, (patches**2).sum(axis=1), rtol=1e-5, atol=1e-3)
    # several images, x-major layout: the same numbers
    stack = np.stack([np.zeros_like(sums), sums]).transpose(0, 2, 1, 3).copy()
    t1, t2 = bilinear_patch_moments(
        stack, c[:, 0] - half_w, c[:, 1] - half_h, np.ones(len(c), np.intp), x_major=True
    )
    assert np.allclose(t1, s1) and np.allclose(t2, s2)


def test_reference_keeps_derived_arrays(scenes_reference, tmp_path):
    ref = scenes_reference
    w, h = ref.image_size
    sums = ref.window_sums(5, 8)
    assert sums.shape == (ref.dots.shape[0], w - 10, h - 16, len(WINDOW_SUMS))  # x-major
    assert ref.window_sums(5, 8) is sums and not sums.flags.writeable
    assert np.array_equal(sums[1].transpose(1, 0, 2), window_sums(ref.dots[1], 5, 8))
    dt = ref.padded_dots(transposed=True)
    assert ref.padded_dots(transposed=True) is dt and not dt.flags.writeable
    assert dt.flags.c_contiguous and np.array_equal(dt[2, :, :h], ref.dots[2].T)
    assert not dt[:, :, h:].any()  # the padding after each row is zeros
    d = ref.padded_dots()
    assert np.array_equal(d[:, :, :w], ref.dots) and not d[:, :, w:].any()
    # the cache is not part of the saved file; a loaded set builds its own
    p = tmp_path / "ref.npz"
    ref.save(p)
    back = ReferenceSet.load(p)
    assert np.allclose(back.window_sums(5, 8), sums, rtol=1e-2, atol=1.0)  # float16 dots


def test_intersections_stop_when_converged(scenes_reference):
    ref = scenes_reference
    rng = np.random.default_rng(5)
    uv = np.c_[rng.uniform(0, 640, 50), rng.uniform(0, 512, 50)]
    lines = ref.epipolar_lines(uv)[:, None, :]
    coeffs = ref.curves[0][None, :, :]
    v0 = np.broadcast_to(uv[:, 1:2], (50, ref.num_slits))
    v = intersect_line_curves(lines, coeffs, v0)
    full = intersect_line_curves(lines, coeffs, v0, iterations=20, tol=0.0)
    assert np.allclose(v, full, atol=1e-6)
    # on the curve and on the line
    u = curve_u(coeffs, v)
    assert np.abs(lines[..., 0] * u + lines[..., 1] * v + lines[..., 2]).max() < 1e-6


@pytest.mark.parametrize(("half_w", "half_h"), [(3, 8), (6, 2)])
def test_sample_patches_blend_like_remap(rng, half_w, half_h):
    img = _sparse_dots(rng, (60, 80))
    c = np.c_[rng.uniform(-4, 84, 300), rng.uniform(-4, 64, 300)]  # some leave the image
    for centres in (c, np.c_[c[:, 0], np.round(c[:, 1])]):  # sub-pixel and whole rows
        got = sample_patches(img, centres, half_w, half_h)
        want = _remap_patches(img, centres, half_w, half_h)
        assert got.shape == (300, 2 * half_h + 1, 2 * half_w + 1)
        assert np.allclose(got, want, atol=1e-3)
    assert not np.any(sample_patches(img, np.array([[-50.0, -50.0]]), half_w, half_h))


def test_sheared_patches_shift_each_row(rng):
    img = _sparse_dots(rng, (60, 80))
    centres = np.c_[rng.uniform(10, 70, 50), np.round(rng.uniform(12, 48, 50))]
    half_w, half_h = 4, 6
    ph = 2 * half_h + 1
    # no shift: the upright patch
    flat = sample_sheared_patches(img, centres, half_w, half_h, np.zeros((50, ph)))
    assert np.allclose(flat, sample_patches(img, centres, half_w, half_h), atol=1e-3)
    # row j shifted by s_j: that row of the upright patch centred s_j further right
    shift = rng.uniform(-3, 3, (50, ph))
    got = sample_sheared_patches(img, centres, half_w, half_h, shift)
    for j in (0, half_h, ph - 1):
        moved = sample_patches(img, centres + np.c_[shift[:, j], np.zeros(50)], half_w, half_h)
        assert np.allclose(got[:, j], moved[:, j], atol=1e-3)
    with pytest.raises(ValueError, match="row_shift must have shape"):
        sample_sheared_patches(img, centres, half_w, half_h, np.zeros((50, ph - 1)))
    # ... and moved down by r_j as well: that row of the patch centred (s_j, r_j) away
    rise = rng.uniform(-2, 2, (50, ph))
    got = sample_sheared_patches(img, centres, half_w, half_h, shift, row_rise=rise)
    for j in (0, half_h, ph - 1):
        moved = sample_patches(img, centres + np.c_[shift[:, j], rise[:, j]], half_w, half_h)
        assert np.allclose(got[:, j], moved[:, j], atol=1e-3)
    assert not np.allclose(got, sample_sheared_patches(img, centres, half_w, half_h, shift))
    with pytest.raises(ValueError, match="row_rise must have shape"):
        sample_sheared_patches(img, centres, half_w, half_h, shift, row_rise=rise[:, 1:])


def test_sheared_patches_space_their_columns(rng):
    img = _sparse_dots(rng, (60, 80))
    centres = np.c_[rng.uniform(20, 60, 30), np.round(rng.uniform(12, 48, 30))]
    half_w, half_h = 4, 6
    ph = 2 * half_h + 1
    shift = rng.uniform(-2, 2, (30, ph))
    scale = rng.uniform(0.5, 1.5, 30)
    got = sample_sheared_patches(img, centres, half_w, half_h, shift, col_scale=scale)
    # column i of row j: the image at (u + s_j + c i, v + j - half_h)
    for j in (0, half_h, ph - 1):
        for i in (-half_w, 0, half_w):
            at = centres + np.c_[shift[:, j] + scale * i, np.full(30, j - half_h)]
            want = sample_patches(img, at, 0, 0)[:, 0, 0]
            assert np.allclose(got[:, j, i + half_w], want, atol=1e-3)
    ones = sample_sheared_patches(img, centres, half_w, half_h, shift, col_scale=np.ones(30))
    assert np.array_equal(ones, sample_sheared_patches(img, centres, half_w, half_h, shift))
    with pytest.raises(ValueError, match="col_scale must be > 0"):
        sample_sheared_patches(img, centres, half_w, half_h, shift, col_scale=-scale)
    with pytest.raises(ValueError, match=r"col_scale must have shape \(30,\)"):
        sample_sheared_patches(img, centres, half_w, half_h, shift, col_scale=scale[1:])
