"""Stripes at any angle: the column pass, the merge of the two passes, the box tops."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.special import erf

from multislit.sim import RigSpec, SimulatedRig, render
from multislit.sim.evaluate import _centres_in, _near_centres
from multislit.sim.scene import make_scene
from multislit.stripes import (
    ExtractionOptions,
    SlitExtractionError,
    StripeCentres,
    extract_slits,
)
from multislit.stripes.ridges import chain_angles, join_collinear, leaning_regions, merge_passes


def _add_dot(img, x, y, peak, sigma=0.8):
    """Add a Gaussian dot of ``peak`` at (``x``, ``y``) to ``img`` (in place), within 4 px."""
    h, w = img.shape
    r0, r1 = max(0, int(y) - 4), min(h, int(y) + 6)
    c0, c1 = max(0, int(x) - 4), min(w, int(x) + 6)
    v, u = np.mgrid[r0:r1, c0:c1]
    img[r0:r1, c0:c1] += peak * np.exp(-0.5 * ((u - x) ** 2 + (v - y) ** 2) / sigma**2)


def _leaning(angle_deg, *, spacing=20.0, sigma=1.3, amp=120.0, dots=400, seed=0, shape=(240, 320)):
    """An 8-bit image of parallel Gaussian stripes leaning ``angle_deg`` from the vertical
    (positive: right going down), ``spacing`` px apart across, with random dots, ambient light,
    read and shot noise; the truth: the signed distance across the stripes from each pixel
    to the nearest centre line (px) and each pixel's stripe (-1: farther than 1 px)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    a = np.radians(angle_deg)
    v, u = np.mgrid[0:h, 0:w].astype(float)
    ph = ((u - w / 2) * np.cos(a) - (v - h / 2) * np.sin(a) - rng.uniform(0, spacing)) / spacing
    k = np.rint(ph)
    d = (ph - k) * spacing
    s = sigma * np.sqrt(2)
    img = amp * 0.5 * (erf((d + 0.5) / s) - erf((d - 0.5) / s)) * sigma * np.sqrt(2 * np.pi)
    for x, y, peak in zip(
        rng.uniform(0, w, dots), rng.uniform(0, h, dots), rng.uniform(40, 90, dots), strict=True
    ):
        _add_dot(img, x, y, peak)
    img += 30.0
    img += rng.normal(0, 1, img.shape) * np.sqrt(4.0 + 0.05 * img)
    truth = np.where(np.abs(d) <= 1.0, (k - k.min()).astype(np.int16), -1).astype(np.int16)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), truth, (a, spacing, ph)


@pytest.mark.parametrize("angle", [0.0, 30.0, 50.0, 60.0, 75.0, 85.0, 90.0, -60.0, -88.0])
def test_stripes_at_any_angle_are_found_and_centred(angle):
    img, truth, (a, spacing, ph) = _leaning(angle)
    ex = extract_slits(img)
    h, w = img.shape
    inner = np.zeros((h, w), bool)
    inner[12:-12, 12:-12] = True
    # every true centre of the inner image has a linked point within 1.5 px across
    linked = ex.segment >= 0
    lu, lv = ex.u[linked], ex.v[linked]
    near = _near_centres(lu, lv, _centres_in(truth, inner), h, w)
    assert np.mean([len(i) > 0 for i in near]) >= 0.98
    # each linked point lies on a stripe: its distance across to the nearest centre line
    # (phase interpolated at the point) is small, and unbiased
    r = np.clip(np.rint(lv).astype(int), 0, h - 1)
    c = np.clip(np.rint(lu).astype(int), 0, w - 1)
    # the phase is linear in (u, v): its value at the point from the pixel's and the gradient
    p = ph[r, c] + ((lu - c) * np.cos(a) - (lv - r) * np.sin(a)) / spacing
    err = (p - np.rint(p)) * spacing
    inside = inner[r, c]
    assert np.mean(np.abs(err[inside]) <= 1.5) >= 0.995
    good = inside & (np.abs(err) <= 1.5)
    assert np.sqrt(np.mean(err[good] ** 2)) <= 0.08
    assert abs(np.mean(err[good])) <= 0.02
    # the direction of each point, and which pass found it
    d = np.degrees(ex.angle[linked][good])
    off = (d - angle + 90.0) % 180.0 - 90.0  # the direction is a line: modulo 180 degrees
    assert np.percentile(np.abs(off), 95) <= 3.0
    col = ex.by_column[linked][good]
    if abs(angle) < 40:
        assert not col.any()
    if abs(angle) > 50:
        assert col.mean() >= 0.99
        # whole columns, sub-pixel rows
        assert np.all(ex.u[ex.by_column] == np.rint(ex.u[ex.by_column]))


@pytest.mark.parametrize("angle", [0.0, 10.0, 25.0, -35.0])
def test_near_vertical_stripes_leave_the_row_pass_alone(angle):
    img, _, _ = _leaning(angle, dots=800, seed=3)
    ex = extract_slits(img)
    assert not ex.by_column.any()
    # the row pass's points, as they were: whole rows
    assert np.all(ex.v == np.rint(ex.v))


@pytest.mark.parametrize("angle", [44.0, 46.0])
def test_a_stripe_found_by_both_passes_is_kept_once(angle):
    img, _, (a, spacing, ph) = _leaning(angle, seed=5)
    ex = extract_slits(img)
    lk = ex.segment >= 0
    u, v, seg = ex.u[lk], ex.v[lk], ex.segment[lk]
    # no two points of different segments within 0.75 px of each other: no stripe twice
    pts = np.stack([u, v], axis=1)
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    other = seg[:, None] != seg[None, :]
    assert not (other & (d < 0.75)).any()
    # each stripe one segment from one pass (the pieces cut at the image's border aside)
    h, w = img.shape
    r, c = np.clip(np.rint(v).astype(int), 0, h - 1), np.clip(np.rint(u).astype(int), 0, w - 1)
    stripe = np.rint(ph[r, c])
    for s in np.unique(seg):
        m = seg == s
        assert len(np.unique(stripe[m])) == 1
        assert len(np.unique(ex.by_column[lk][m])) == 1
    per_stripe = [len(np.unique(seg[stripe == k])) for k in np.unique(stripe)]
    assert np.mean(np.array(per_stripe) == 1) >= 0.8, per_stripe


def test_dots_in_a_row_make_no_leaning_stripe():
    # upright stripes, and dots lined up along rows in strings of four, 3 px apart
    img, _, _ = _leaning(0.0, dots=0, seed=7)
    img = img.astype(float)
    rng = np.random.default_rng(1)
    h, w = img.shape
    for _ in range(40):
        x0, y0 = rng.uniform(20, w - 40), rng.uniform(20, h - 20)
        for j in range(4):
            _add_dot(img, x0 + 3.0 * j, y0, 70.0)
    ex = extract_slits(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    assert not ex.by_column.any()


def test_chain_angles_follow_each_segment():
    v = np.arange(20.0)
    u_row = 5.0 + 0.5 * v  # a segment along the rows, leaning atan(0.5)
    uc = np.arange(30.0)
    v_col = 40.0 - 0.2 * uc  # along the columns: up to the right, leaning -atan(1 / 0.2)
    u = np.r_[u_row, uc]
    vv = np.r_[v, v_col]
    seg = np.r_[np.zeros(20, np.int64), np.ones(30, np.int64)]
    by_col = np.r_[np.zeros(20, bool), np.ones(30, bool)]
    ang = chain_angles(u, vv, seg, by_col)
    np.testing.assert_allclose(ang[:20], np.arctan(0.5), atol=1e-9)
    np.testing.assert_allclose(ang[20:], -np.arctan(5.0), atol=1e-9)
    # unlinked points have none
    assert np.isnan(chain_angles(u, vv, np.where(seg == 0, -1, seg), by_col)[:20]).all()


def test_join_collinear_bridges_a_gap_along_the_stripe_only():
    b = np.arange(60.0)
    a = 10.0 + 0.3 * b
    seg = np.where(b < 25, 0, 1).astype(np.int64)
    keep = (b < 22) | (b >= 25)  # three columns missing
    a, b, seg = a[keep], b[keep], seg[keep]
    got = join_collinear(a, b, seg, 6, 1.0)
    assert len(np.unique(got)) == 1
    # the same pieces 2 px apart across: not one stripe
    off = np.where(seg == 1, a + 2.0, a)
    assert len(np.unique(join_collinear(off, b, seg, 6, 1.0))) == 2
    # a gap too wide: not joined
    far = np.where(seg == 1, b + 10.0, b)
    assert len(np.unique(join_collinear(10.0 + 0.3 * far, far, seg, 6, 1.0))) == 2
    # two candidates for one end: neither joined
    a3 = np.r_[a, 10.0 + 0.3 * b[seg == 1] + 0.5]
    b3 = np.r_[b, b[seg == 1]]
    s3 = np.r_[seg, np.full(int((seg == 1).sum()), 2)]
    got3 = join_collinear(a3, b3, s3, 6, 1.0)
    assert len(np.unique(got3)) == 3


def _centres(u, v):
    u = np.asarray(u, float)
    return StripeCentres(u, np.asarray(v, float), np.full(u.size, 50.0), np.full(u.size, 3.0))


def test_merge_gives_a_stripe_found_twice_to_the_pass_it_leans_less_from():
    # one stripe leaning 50 degrees, found by the row pass (whole rows) and the column pass
    # (whole columns); another, leaning 10 degrees, by the row pass only
    t = np.tan(np.radians(50.0))
    rv = np.arange(40.0)
    ru = 100.0 + t * rv
    cu = np.arange(100.0, 100.0 + t * 39)
    cv = (cu - 100.0) / t
    rv2 = np.arange(40.0)
    ru2 = 20.0 + 0.18 * rv2
    rows = _centres(np.r_[ru, ru2], np.r_[rv, rv2])
    row_seg = np.r_[np.zeros(40, np.int64), np.ones(40, np.int64)]
    cols = _centres(cu, cv)
    col_seg = np.zeros(cu.size, np.int64)

    link = {"max_du": 1.5, "max_gap": 2, "min_length": 10}
    m = merge_passes(rows, row_seg, cols, col_seg, link, 10.0, (np.zeros(0), np.zeros(0)))
    # the leaning stripe from the column pass alone; the upright one from the row pass
    lean = m.centres.u > 60.0
    assert m.by_column[lean].all() and not m.by_column[~lean].any()
    assert lean.sum() == cu.size
    assert len(np.unique(m.segment)) == 2
    # ordered by (row, u), numbered by mean u
    key = np.rint(m.centres.v) * 1e4 + m.centres.u
    assert np.all(np.diff(key) >= 0)
    assert (m.segment[~lean] == 0).all() and (m.segment[lean] == 1).all()
    np.testing.assert_allclose(m.angle[lean], np.radians(50.0), atol=0.02)
    np.testing.assert_allclose(m.angle[~lean], np.arctan(0.18), atol=1e-6)


def _box_tops(seed):
    rig = SimulatedRig.build(RigSpec().scaled(0.5))
    scene = make_scene("box_tops")
    r = render(rig, scene, np.random.default_rng(seed))
    xyz = r.xyz.reshape(-1, 3)
    names = [p.name for p in scene.primitives]
    top = np.zeros(r.slit.shape, bool)
    for t in scene.info["tops"]:
        i = names.index(t["name"])
        on = np.isfinite(xyz[:, 0]) & (r.obj.reshape(-1) == i)
        n = np.zeros_like(xyz)
        n[on] = scene.primitives[i].normal(xyz[on].astype(float))
        top |= ((n @ np.asarray(t["normal"])) > 0.9).reshape(top.shape)
    return r, top


def test_the_stripes_on_box_tops_are_found():
    r, top = _box_tops(seed=1)
    h, w = top.shape
    slit = r.slit
    # the tops' stripes lean 72-80 degrees from the vertical
    lean = []
    for k in np.unique(slit[top & (slit >= 0)]):
        ys, xs = np.nonzero(top & (slit == k))
        if xs.size >= 20:
            lean.append(np.degrees(np.arctan2(1.0, abs(np.polyfit(xs, ys, 1)[0]))))
    assert len(lean) >= 15 and 70 <= min(lean) and max(lean) <= 82
    ex = extract_slits(r.image)
    lk = ex.segment >= 0
    # away from the tops' outlines (where a stripe is cut, the middle of what is left of it is
    # no centre), and over the whole tops; measured on render seeds 1, 2, 3: 90.2, 93.0,
    # 95.5 % and 85.4, 84.8, 88.0 %
    inner = cv2.erode(top.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    for mask, least in ((inner, 0.90), (top, 0.82)):
        near = _near_centres(ex.u[lk], ex.v[lk], _centres_in(slit, mask), h, w)
        assert np.mean([len(i) > 0 for i in near]) >= least
    # what is found there is on the stripes, and by the column pass
    r_, c_ = np.rint(ex.v).astype(int).clip(0, h - 1), np.rint(ex.u).astype(int).clip(0, w - 1)
    on = lk & top[r_, c_]
    assert ex.by_column[on].mean() >= 0.97
    hit = np.zeros(on.sum(), bool)
    for d in (-1, 0, 1):
        hit |= slit[np.clip(r_[on] + d, 0, h - 1), c_[on]] >= 0
    assert hit.mean() >= 0.99


def test_the_column_pass_can_be_left_out():
    img, _, _ = _leaning(75.0)
    assert extract_slits(img).by_column.sum() > 1000
    ex = extract_slits(img, leaning=False)
    assert not ex.by_column.any() and np.all(ex.v == np.rint(ex.v))
    ext = ExtractionOptions(leaning=False)
    assert not extract_slits(img, **ext.kwargs()).by_column.any()
    with pytest.raises(SlitExtractionError, match="leaning must be True or False"):
        extract_slits(img, leaning="yes")


def test_a_line_across_upright_stripes_is_no_leaning_region():
    """A thin bright line along a row, across upright stripes (an edge, a row of dots): the
    quick look along the columns sees a run there, but it runs through the row pass's
    stripes, so no region is searched again."""
    img, _, _ = _leaning(0.0, dots=0, seed=9)
    img = img.astype(float)
    img[118:121, :] += np.array([20.0, 45.0, 20.0])[:, None]
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    ex = extract_slits(img)
    lk = ex.segment >= 0
    link = {"max_du": 1.5, "max_gap": 2, "min_length": 10}
    _, alone = leaning_regions(img, 1.3 * 2.355, 8.0, link)
    assert alone, "the quick look sees the line"
    _, boxes = leaning_regions(img, 1.3 * 2.355, 8.0, link, (ex.v[lk], ex.u[lk]))
    assert boxes == []
    assert not ex.by_column.any()
