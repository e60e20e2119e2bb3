"""Peer methods in the simulator: pattern projector, Gray codes, dot block matching."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from multislit.errors import MeasurementError, MultislitError
from multislit.sim import RigSpec, SimulatedRig, render
from multislit.sim.scene import large_plane, reference_board, spheres

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from dot_blocks import match_dots, rectified_camera  # noqa: E402
from patterns import (  # noqa: E402  (the peer methods live with the benchmarks)
    PatternProjector,
    decode_gray_code,
    gray_code_patterns,
    n_gray_bits,
    prepare_patterns,
    render_pattern,
    render_patterns,
    triangulate_columns,
)


@pytest.fixture(scope="module")
def quarter_rig():
    return SimulatedRig.build(RigSpec().scaled(0.25))


def test_gray_code_sequence_matches_opencv_order():
    p = gray_code_patterns(16, 4)
    assert p.shape == (2 + 2 * 4, 4, 16) and p.dtype == np.uint8
    assert np.all(p[0] == 255) and np.all(p[1] == 0)
    # OpenCV's GrayCodePattern(16, 4) column images (MSB first, each followed by its inverse)
    msb = [0] * 8 + [255] * 8
    lsb = [0, 255, 255, 0] * 4
    assert p[2, 0].tolist() == msb and p[3, 0].tolist() == [255 - x for x in msb]
    assert p[8, 0].tolist() == lsb
    # adjacent columns differ in exactly one bit
    bits = p[2::2, 0, :] > 0
    assert np.all(np.sum(bits[:, 1:] != bits[:, :-1], axis=0) == 1)
    assert n_gray_bits(1024) == 10 and n_gray_bits(1025) == 11


def test_decode_ideal_images_roundtrip():
    width = 300
    pats = gray_code_patterns(width, 2).astype(np.float32)
    imgs = (20 + 0.8 * pats).astype(np.uint8)  # offset and gain: only the pairs' order counts
    dec = decode_gray_code(imgs, width)
    assert np.array_equal(dec.columns[0], np.arange(width))
    with pytest.raises(MeasurementError, match="images must be"):
        decode_gray_code(imgs[:-1], width)


def test_projector_covers_the_slit_fan_and_planes_hold_its_pixels(quarter_rig):
    proj = PatternProjector.from_rig(quarter_rig)
    assert proj.size == (1024, 768)
    np.testing.assert_allclose(proj.origin, quarter_rig.projector.origin)
    # the slits' directions land inside the projector image
    ang = quarter_rig.projector.angles
    d = np.stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)], axis=1) @ proj.R
    uv = proj.project(proj.origin + 900 * d)
    assert np.all((uv[:, 0] > 0) & (uv[:, 0] < 1023))
    # a column plane holds the points that project onto that column
    rng = np.random.default_rng(0)
    x = np.array([0, 0, 100.0]) + rng.uniform(-200, 200, (50, 3))
    uv = proj.project(x)
    pl = proj.column_planes(uv[:, 0])
    np.testing.assert_allclose(np.einsum("ij,ij->i", pl[:, :3], x) + pl[:, 3], 0, atol=1e-9)
    with pytest.raises(MultislitError):
        PatternProjector(proj.origin, proj.R, -1.0)


def test_render_pattern_light_and_shadow(quarter_rig, rng):
    scene = spheres()
    proj = PatternProjector.from_rig(quarter_rig)
    geom = prepare_patterns(quarter_rig, scene, proj, supersample=1)
    h, w = geom.shape
    assert geom.xyz.shape == (h, w, 3) and geom.gain.shape == (h * w,)
    white = np.full((proj.size[1], proj.size[0]), 255, np.uint8)
    imgs = render_patterns(geom, np.stack([white, 0 * white]), rng)
    assert imgs.shape == (2, h, w)
    assert imgs[0].mean() > imgs[1].mean() + 30
    # some wall pixels lie in the spheres' shadow from the projector: no projector light there
    assert np.count_nonzero(geom.gain == 0) > 0.01 * geom.gain.size
    with pytest.raises(MultislitError, match="pattern must be"):
        render_pattern(geom, white[:10], rng)


def test_gray_code_decode_and_triangulate_plane(quarter_rig):
    """Quarter size: a camera pixel spans ~2 projector columns (2.2 mm of depth each)."""
    scene = large_plane()
    proj = PatternProjector.from_rig(quarter_rig)
    geom = prepare_patterns(quarter_rig, scene, proj, supersample=2)
    imgs = render_patterns(geom, gray_code_patterns(*proj.size), np.random.default_rng(1))
    dec = decode_gray_code(imgs, proj.size[0])
    assert dec.valid.mean() > 0.99
    true_cols = proj.project(geom.xyz.reshape(-1, 3))[:, 0].reshape(geom.shape)
    dc = (dec.columns - true_cols)[dec.valid]
    assert abs(np.mean(dc)) < 0.05  # unbiased
    assert np.mean(np.abs(dc) <= 2.5) > 0.99  # within the blurred pixel footprint (~2 columns)
    # triangulation itself is exact with the true columns
    exact = triangulate_columns(quarter_rig.camera, proj, true_cols)
    assert np.nanmax(np.linalg.norm(exact - geom.xyz, axis=-1)) < 1e-3
    xyz = triangulate_columns(quarter_rig.camera, proj, dec.columns)
    err = np.linalg.norm(xyz - geom.xyz, axis=-1)[dec.valid]
    assert np.sqrt(np.mean(err**2)) < 2.0  # quantisation: ~0.8 column x 2.2 mm


def test_gray_code_coarse_projector_decodes_nearest_column(quarter_rig):
    """Projector columns wider than camera pixels: the decoded column is the true one."""
    proj = PatternProjector.from_rig(quarter_rig, size=(128, 96))
    geom = prepare_patterns(quarter_rig, large_plane(), proj, supersample=2)
    imgs = render_patterns(geom, gray_code_patterns(*proj.size), np.random.default_rng(2))
    dec = decode_gray_code(imgs, proj.size[0])
    true_cols = proj.project(geom.xyz.reshape(-1, 3))[:, 0].reshape(geom.shape)
    ok = dec.valid & np.isfinite(true_cols)
    assert np.mean(dec.columns[ok] == np.round(true_cols[ok])) > 0.9


def test_rectified_camera_rows_are_epipolar_lines(quarter_rig):
    rect, b = rectified_camera(quarter_rig)
    assert b == pytest.approx(np.linalg.norm(quarter_rig.dots.origin - quarter_rig.camera.centre))
    # a dot ray's points at different depths project onto one row
    o = quarter_rig.dots.origin
    d = quarter_rig.dots.directions[:20]
    for t in (700.0, 1100.0):
        uv_t = rect.project(o + t * d)
        if t == 700.0:
            v0 = uv_t[:, 1]
        else:
            np.testing.assert_allclose(uv_t[:, 1], v0, atol=1e-6)


def test_dot_matching_on_a_board(quarter_rig):
    spec = replace(quarter_rig.spec, slits=replace(quarter_rig.spec.slits, power=0.0))
    rig = SimulatedRig.build(spec)
    rng = np.random.default_rng(3)
    ref_scene = reference_board(900)
    ref = render(rig, ref_scene, rng).image
    scene = reference_board(820)
    img = render(rig, scene, rng).image
    dd = match_dots(rig, img, ref, ref_scene.info["plane"], window=21, min_score=0.8)
    assert dd.valid.mean() > 0.3
    plane = np.array(scene.info["plane"])
    dist = np.abs(dd.xyz[dd.valid] @ plane[:3] + plane[3])
    assert np.median(dist) < 0.5
    with pytest.raises(MeasurementError, match="window"):
        match_dots(rig, img, ref, ref_scene.info["plane"], window=4)
