"""The paper's template identification (``method="template"``) against the simulator's
ground truth.

The bars, per scene and for 25 and 49 slits: >= 99.5 % of output points correct, <= 0.1 %
wrong with confidence >= 0.5, >= 90 % of lit stripe-centre pixels with a point. 25 slits are
tested on half-size images; 49 slits at full size (``dense_scenes_capture``: at half size the
stripes keep their width but lie half as far apart, as dense as 98 slits at full size).
"""

import numpy as np
import pytest

import multislit.identify.labelling as identify_module
from multislit.errors import IdentificationError
from multislit.identify import (
    curve_u,
    intersect_line_curves,
    normalise_patches,
    sample_patches,
    split_at_brightness_steps,
)
from multislit.identify import (
    identify_template as identify,
)
from multislit.identify.labelling import _sampled_segments
from multislit.identify.matching import (
    score_candidates,
    template_col_scale,
    template_geometry,
    template_size,
)
from multislit.identify.segments import _sample_points, band_samples, near_segment_ends
from multislit.identify.votes import segment_votes
from multislit.io import Capture
from multislit.sim.evaluate import coverage_losses, identification_metrics
from multislit.stripes import extract_slits


def _identify_scans(capture, reference):
    """Per scan of a simulated capture: (its identification, its metrics against the truth)."""
    cap = Capture.open(capture)
    out = {}
    for p in cap.scans:
        ident = identify(cap.image(p), reference)
        truth = np.load(capture / "truth" / f"{p.stem}.npz")["slit"]
        out[p.stem] = (ident, identification_metrics(ident, truth))
    return out


@pytest.fixture(scope="module")
def results(scenes_capture, scenes_reference):
    return _identify_scans(scenes_capture, scenes_reference)


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["holes", "spheres", "steps", "freeform", "textured"])
def test_identified_points_carry_the_true_slit(results, scene):
    # half size, seed 11 (measured): holes 100, spheres 99.88, steps 99.89, freeform 99.95,
    # textured 100 %
    _, m = results[scene]
    assert m["points"] > 3000
    assert m["correct"] >= 0.995


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["holes", "spheres", "steps", "freeform", "textured"])
def test_few_confident_mistakes(results, scene):
    # half size, seed 11 (measured): 0 % on every scene
    assert results[scene][1]["wrong_confident"] <= 0.001


@pytest.mark.slow
@pytest.mark.parametrize(
    "scene",
    ["holes", "spheres", "steps", "freeform", "textured"],
)
def test_most_stripe_pixels_get_a_point(results, scene):
    # half size, seed 11 (measured): holes 94.6, spheres 91.7, steps 95.4, freeform 91.1,
    # textured 95.6 %
    assert results[scene][1]["coverage"] >= 0.90


@pytest.fixture(scope="module")
def dense_results(dense_scenes_capture, dense_scenes_reference):
    # the metrics only: five full-size identifications (with their extractions) held for the
    # whole module would cost memory for nothing
    scans = _identify_scans(dense_scenes_capture, dense_scenes_reference)
    return {name: m for name, (_, m) in scans.items()}


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["holes", "spheres", "steps", "freeform", "textured"])
def test_49_slits_meet_the_identification_bars(dense_results, scene):
    # full size, seed 11 (measured, correct / wrong conf >= 0.5 / coverage %): holes
    # 99.95/0.05/95.6, spheres 99.97/0.00/95.7, steps 100/0/97.6, freeform 99.93/0.03/94.0,
    # textured 100/0/98.9 (benchmarks/bench_identify.py --method template)
    m = dense_results[scene]
    assert m["points"] > 30000
    assert m["correct"] >= 0.995
    assert m["wrong_confident"] <= 0.001
    assert m["coverage"] >= 0.90


@pytest.mark.slow
def test_dropped_segments_are_counted(results):
    ident, _ = results["freeform"]
    assert ident.num_dropped > 0 and ident.num_identified > 0
    assert np.all(ident.confidence[~ident.identified] == 0)
    assert np.all(
        (ident.confidence[ident.identified] > 0) & (ident.confidence[ident.identified] <= 1)
    )


def test_image_without_slits_gives_empty_result(scenes_reference):
    rng = np.random.default_rng(0)
    img = rng.normal(20, 1.5, (512, 640)).clip(0, 255).astype(np.uint8)
    ident = identify(img, scenes_reference)
    assert ident.num_identified == 0 and not ident.identified.any()
    assert "no slits" in ident.message


def test_wrong_image_size_is_an_error(scenes_reference):
    with pytest.raises(IdentificationError, match="prepared for 640x512"):
        identify(np.zeros((100, 100), np.uint8), scenes_reference)


# --------------------------------------------------------------------------- fast scoring
def _straightforward_scores(ref, scan_dots, pu, pv, row_shift, col_scale, allowed=None):
    """The candidate scores computed the plain way: every reference patch sampled, normalised
    and dotted with the template (what the fast scoring must reproduce); the template is put
    together pixel by pixel, each row shifted sideways by ``row_shift`` and moved along the dot
    projector's epipolar line (its vertical motion per px sideways at most 1), its columns
    ``col_scale`` px apart; each slit compared in the reference where its candidate lies
    nearest the sample."""
    R, N = ref.curves.shape[:2]
    w, h = ref.image_size
    hw, hh = template_size(ref)
    uv = np.c_[pu, pv]
    M = len(uv)
    lines = ref.epipolar_lines(uv)
    direction = np.c_[lines[:, 1], -lines[:, 0]]
    rise = np.clip(direction[:, 1] / direction[:, 0], -1.0, 1.0)
    dx = np.arange(-hw, hw + 1)[None, None, :]
    dy = np.arange(-hh, hh + 1)[None, :, None]
    x = pu[:, None, None] + row_shift[:, :, None] + col_scale[:, None, None] * dx
    y = pv[:, None, None] + dy + (row_shift * rise[:, None])[:, :, None] + 0 * dx
    pix = sample_patches(scan_dots, np.c_[x.ravel(), y.ravel()], 0, 0)
    tmpl = normalise_patches(pix.reshape(M, 2 * hh + 1, 2 * hw + 1))
    uu_all = np.full((R, M, N), np.nan)
    vv_all = np.full((R, M, N), np.nan)
    for r in range(R):
        vv = intersect_line_curves(
            lines[:, None, :], ref.curves[r][None], np.broadcast_to(uv[:, 1:2], (M, N))
        )
        uu = curve_u(ref.curves[r][None], vv)
        ok = np.isfinite(vv)
        ok &= (vv >= ref.vrange[r, :, 0] - hh) & (vv <= ref.vrange[r, :, 1] + hh)
        ok &= (uu >= hw) & (uu <= w - 1 - hw) & (vv >= hh) & (vv <= h - 1 - hh)
        uu_all[r], vv_all[r] = np.where(ok, uu, np.nan), np.where(ok, vv, np.nan)
    valid = np.isfinite(vv_all).any(axis=0)
    disp = np.hypot(uu_all - uv[None, :, 0:1], vv_all - uv[None, :, 1:2])
    r_best = np.argmin(np.where(np.isfinite(disp), disp, np.inf), axis=0)
    best = np.full((M, N), -np.inf)
    for r in range(R):
        mask = valid & (r_best == r)
        ii, kk = np.nonzero(mask if allowed is None else mask & allowed)
        cand = np.c_[uu_all[r, ii, kk], vv_all[r, ii, kk]]
        pat = normalise_patches(sample_patches(ref.dots[r], cand, hw, hh))
        best[ii, kk] = np.einsum("ij,ij->i", pat, tmpl[ii])
    out = np.where(valid & np.isfinite(best), best, np.nan)
    out[~np.any(tmpl != 0, axis=1)] = np.nan
    return out


def test_band_samples_keep_templates_inside_the_image():
    # rows 0..99 of a 100-row image, band 20..79 (a template half height of 20, border_cut 1):
    # segment 0 crosses the top edge of the band, 1 the bottom, 2 lies in the top border only,
    # 3 inside the band, 4 crosses both edges
    spans = {0: (0, 50), 1: (40, 99), 2: (0, 15), 3: (30, 60), 4: (0, 99)}
    seg = np.concatenate([np.full(b - a + 1, k) for k, (a, b) in spans.items()])
    v = np.concatenate([np.arange(a, b + 1, dtype=float) for a, b in spans.values()])
    perm = np.random.default_rng(0).permutation(len(v))  # points in any order
    seg, v = seg[perm], v[perm]
    si = band_samples(seg, v, 6.0, 20.0, 79.0)
    assert np.all((v[si] >= 20) & (v[si] <= 79))
    # grouped by segment, rows increasing, no point twice
    assert np.all(np.diff(seg[si]) >= 0)
    same = np.diff(seg[si]) == 0
    assert np.all(np.diff(v[si])[same] > 0)
    rows = {k: v[si][seg[si] == k] for k in spans}
    assert rows[2].size == 0
    for k in (0, 4):
        assert rows[k][0] == 20  # sampling starts at the first row in the band
    for k in (1, 4):
        assert rows[k][-1] == 79  # and reaches the last row in the band
    assert rows[3][0] == 30 and np.all(np.diff(rows[3]) <= 6) and rows[3].size <= 31 // 6 + 1
    # every row between the band and the image edge is within a half height of a sample
    for k in (0, 1, 4):
        a, b = spans[k]
        gap = np.abs(np.arange(a, b + 1)[:, None] - rows[k][None, :]).min(axis=1)
        assert gap.max() <= 20


@pytest.fixture(scope="module")
def scene_samples(scenes_capture, scenes_reference):
    """The 'spheres' scan, its extraction and the sample points identification scores."""
    cap = Capture.open(scenes_capture)
    img = cap.image(next(p for p in cap.scans if p.stem == "spheres"))
    ex = extract_slits(
        img,
        stripe_width_px=scenes_reference.stripe_width_px,
        dot_size_px=scenes_reference.dot_size_px,
    )
    seg = split_at_brightness_steps(ex.segment.astype(np.int64), ex.v, ex.peak)
    si = _sample_points(seg, ex.v, max(2.0, 0.3 * scenes_reference.spacing_px))
    return img, ex, seg, si


@pytest.mark.parametrize("follow", [False, True])
def test_fast_scores_equal_sampled_patches(scenes_reference, scene_samples, follow):
    _, ex, seg, si = scene_samples
    si = si[::3]
    dots = ex.dots.astype(np.float32)
    hh = template_size(scenes_reference)[1]
    if follow:  # templates that follow their stripes' lean and spacing
        shift, scale = template_geometry(ex.u, ex.v, seg, si, scenes_reference, hh)
        assert np.any(shift != 0) and np.any(scale != 1)
    else:  # upright templates
        shift, scale = np.zeros((len(si), 2 * hh + 1)), np.ones(len(si))
    rng = np.random.default_rng(2)
    N = scenes_reference.num_slits
    allowed = rng.random((len(si), N)) < 0.7
    few = np.abs(np.arange(N)[None, :] - rng.integers(0, N, len(si))[:, None]) <= 1  # a prior
    for lim in (None, allowed, few):
        args = (scenes_reference, dots, ex.u[si], ex.v[si], shift, scale, lim)
        fast = score_candidates(*args)
        slow = _straightforward_scores(*args)
        assert np.array_equal(np.isnan(fast), np.isnan(slow))
        assert np.isfinite(fast).mean() > 0.5 * (1.0 if lim is None else lim.mean())
        assert np.nanmax(np.abs(fast - slow)) < 1e-4


@pytest.mark.slow
def test_fast_scoring_gives_the_same_slits(monkeypatch, scenes_reference, scene_samples):
    img, ex, _, _ = scene_samples
    fast = identify(img, scenes_reference, extraction=ex)
    monkeypatch.setattr(identify_module, "score_candidates", _straightforward_scores)
    slow = identify(img, scenes_reference, extraction=ex)
    assert fast.num_identified > 50
    assert np.array_equal(fast.slit, slow.slit)
    assert np.allclose(fast.confidence, slow.confidence, atol=1e-3)


def test_segment_votes_match_a_plain_loop():
    rng = np.random.default_rng(4)
    seg_of_sample = rng.integers(0, 30, 600)
    scores = rng.uniform(-0.5, 1.0, (600, 7))
    scores[rng.random(scores.shape) < 0.2] = np.nan
    scores[seg_of_sample == 3] = np.nan  # a segment without any candidate
    votes = segment_votes(seg_of_sample, scores)
    assert set(votes) == set(np.unique(seg_of_sample).tolist())
    for sid, (k, conf, m1, n) in votes.items():
        S = scores[seg_of_sample == sid]
        S = S[np.isfinite(S).any(axis=1)]
        if len(S) == 0:
            assert (k, conf, n) == (-1, 0.0, 0)
            continue
        Sz = np.where(np.isfinite(S), S, -0.2)
        mean = Sz.mean(axis=0)
        order = np.argsort(-mean, kind="stable")
        d = Sz[:, order[0]] - Sz[:, order[1]]
        se = d.std(ddof=1) / np.sqrt(len(S)) if len(S) > 1 else 0.3
        want = np.clip(max(0.0, mean[order[0]] - mean[order[1]] - se) / 0.3, 0, 1)
        assert (k, n) == (order[0], len(S))
        assert m1 == pytest.approx(mean[order[0]]) and conf == pytest.approx(want)


def _split_at_brightness_steps_loop(seg, v, peak, ratio=1.6, window=6):
    """Segment by segment, the plain way (what the vectorised split must reproduce)."""
    from numpy.lib.stride_tricks import sliding_window_view

    seg = seg.copy()
    next_id = int(seg.max()) + 1
    for sid in np.unique(seg[seg >= 0]):
        pts = np.flatnonzero(seg == sid)
        if pts.size < 2 * window + 2:
            continue
        pts = pts[np.argsort(v[pts])]
        med = np.median(sliding_window_view(np.log(np.maximum(peak[pts], 1e-3)), window), axis=1)
        step = np.abs(med[window:] - med[: len(med) - window])
        cut_at = []
        while step.size and step.max() > np.log(ratio):
            j = int(np.argmax(step))
            cut_at.append(j + window)
            step[max(0, j - window) : min(len(step), j + window + 1)] = 0
        for c in sorted(cut_at):
            seg[pts[c:]] = np.where(seg[pts[c:]] == seg[pts[c]], next_id, seg[pts[c:]])
            next_id += 1
    return seg


def test_brightness_steps_split_where_a_plain_loop_would():
    rng = np.random.default_rng(6)
    seg, v, peak = [], [], []
    layout = [(40, [20]), (30, []), (50, [10, 30]), (12, [6]), (60, [45]), (13, [7]), (9, [])]
    for sid, (length, steps) in enumerate(layout):
        pk = rng.uniform(90, 110, length)
        for at in steps:
            pk[at:] *= 3.0
        seg.append(np.full(length, sid))
        v.append(np.arange(length, dtype=float) + 100 * sid)
        peak.append(pk)
    seg.append(np.full(5, -1))  # unlinked points
    v.append(np.arange(5.0) + 1000)
    peak.append(np.full(5, 100.0))
    perm = rng.permutation(sum(len(s) for s in seg))
    seg, v, peak = (np.concatenate(a)[perm] for a in (seg, v, peak))
    out = split_at_brightness_steps(seg.astype(np.int64), v, peak)
    assert np.array_equal(out, _split_at_brightness_steps_loop(seg.astype(np.int64), v, peak))
    # the steps far enough from the ends cut their segments; short or even segments stay whole
    assert [len(np.unique(out[seg == s])) for s in range(len(layout))] == [2, 1, 3, 1, 2, 1, 1]
    assert np.all(out[seg == -1] == -1)


@pytest.fixture(scope="module")
def tilted_plate(small_rig):
    """A plate tilted 25 deg about the horizontal axis: its stripes lean ~0.2 px per row."""
    from multislit.sim import Polygon, Scene, constant
    from multislit.sim.render import render

    t = np.radians(25.0)
    plate = Polygon(
        (0.0, 0.0, 100.0),
        (0.0, np.sin(t), np.cos(t)),
        outline=np.array([[-180.0, -130.0], [180.0, -130.0], [180.0, 130.0], [-180.0, 130.0]]),
        texture=constant(0.75),
        name="plate",
    )
    wall = Polygon((0.0, 0.0, -150.0), (0.0, 0.0, 1.0), texture=constant(0.55), name="wall")
    return render(small_rig, Scene("plate_x25", [plate, wall], {}), np.random.default_rng(5))


def test_template_follows_a_leaning_stripe(scenes_reference, tilted_plate):
    # half size, seed 5 (measured): 92.1 % coverage, 99.78 % correct; the samples' best slit
    # is their true one on 92.6 % of them with templates that follow the stripes, 69.2 % upright
    full = identify(tilted_plate.image, scenes_reference)
    got = identification_metrics(full, tilted_plate.slit)
    assert got["correct"] >= 0.99
    assert got["coverage"] >= 0.90
    # the templates' own effect, sample by sample: the share of the samples whose best slit is
    # their true one, with templates that follow the stripes and with upright ones
    ex = full.extraction
    seg, si, _, hh = _sampled_segments(ex, scenes_reference)
    h, w = tilted_plate.slit.shape
    r = np.round(ex.v[si]).astype(int)
    c = np.round(ex.u[si]).astype(int)
    near = np.stack([tilted_plate.slit[r, np.clip(c + d, 0, w - 1)] for d in (0, -1, 1)])
    truth = np.max(near, axis=0)
    si, truth = si[truth >= 0], truth[truth >= 0]
    dots = ex.dots.astype(np.float32)
    shift, scale = template_geometry(ex.u, ex.v, seg, si, scenes_reference, hh)
    right = {}
    for mode, geometry in (
        ("follow", (shift, scale)),
        ("upright", (np.zeros_like(shift), np.ones_like(scale))),
    ):
        sc = score_candidates(scenes_reference, dots, ex.u[si], ex.v[si], *geometry)
        best = np.argmax(np.where(np.isfinite(sc), sc, -np.inf), axis=1)
        right[mode] = float(np.mean(best == truth))
    assert right["follow"] >= 0.90
    assert right["follow"] >= right["upright"] + 0.15


@pytest.mark.parametrize("bad", [float("nan"), -0.1, 1.5])
def test_min_confidence_is_checked(scenes_reference, bad):
    img = np.zeros(scenes_reference.image_size[::-1], np.uint8)
    with pytest.raises(IdentificationError, match="min_confidence"):
        identify(img, scenes_reference, min_confidence=bad)


def test_junctions_of_two_slits_are_trimmed_further():
    # three vertical segments: 0 (rows 0-49) runs into 1 (rows 50-99) at the same column, an
    # occlusion edge where slit 4 meets slit 9; segment 2 ends freely
    v = np.r_[np.arange(50), np.arange(50, 100), np.arange(0, 60)].astype(float)
    u = np.r_[np.full(50, 100.0), np.full(50, 100.5), np.full(60, 200.0)]
    seg = np.r_[np.zeros(50), np.ones(50), np.full(60, 2)].astype(np.int64)
    near = near_segment_ends(u, v, seg, np.array([4, 9, 4]), trim=2, junction=8)
    rows = {s: v[near & (seg == s)] for s in range(3)}
    assert set(rows[0]) == {0, 1} | set(range(42, 50))  # free start, junction end
    assert set(rows[1]) == set(range(50, 58)) | {98, 99}
    assert set(rows[2]) == {0, 1, 58, 59}
    # the same slit on both sides (a stripe broken by a gap) is no junction
    same = near_segment_ends(u, v, seg, np.array([4, 4, 4]), trim=2, junction=8)
    assert set(v[same & (seg == 0)]) == {0, 1, 48, 49}
    # an unidentified neighbour neither
    unk = near_segment_ends(u, v, seg, np.array([4, -1, 4]), trim=2, junction=8)
    assert set(v[unk & (seg == 0)]) == {0, 1, 48, 49}


@pytest.mark.slow
def test_coverage_losses_classify_every_stripe_pixel(results, scenes_capture):
    from types import SimpleNamespace

    # three rows, four stripes (slits 0..3, 3 px wide, centres at columns 6, 16, 26, 34; as
    # tall as wide, so their centres are taken along the rows); points in rows 0 and 1 only
    truth = np.full((3, 40), -1)
    for k, c in enumerate((6, 16, 26, 34)):
        truth[:, c - 1 : c + 2] = k
    ident = SimpleNamespace(
        u=np.array([6.2, 16.0, 26.0, 34.0, 6.0]),
        v=np.array([0.0, 0.0, 0.0, 0.0, 1.0]),
        slit=np.array([0, -1, -1, 2, -1]),
        segment=np.array([0, -1, 1, 2, 0]),
    )
    got = coverage_losses(ident, truth)
    assert got == pytest.approx(
        {
            "covered": 1 / 12,
            "unlinked": 1 / 12,
            "segment_unidentified": 1 / 12,
            "wrong": 1 / 12,
            "point_left_out": 1 / 12,
            "no_centre": 7 / 12,
        }
    )
    # on a scene: the shares sum to 1 and "covered" is the coverage
    ident, m = results["freeform"]
    truth = np.load(scenes_capture / "truth" / "freeform.npz")["slit"]
    loss = coverage_losses(ident, truth)
    assert sum(loss.values()) == pytest.approx(1.0)
    assert loss["covered"] == pytest.approx(m["coverage"])


def test_template_columns_follow_the_stripes_spacing(scenes_reference):
    """Stripes squeezed across (a surface turned away from the projector) give templates whose
    columns are as much closer together; a sample at an edge (gaps either side that disagree)
    or a lone stripe keeps 1."""
    ref = scenes_reference
    r = ref.curves.shape[0] // 2
    v0 = 0.5 * ref.image_size[1]
    u_ref = np.sort(curve_u(ref.curves[r], np.full(ref.num_slits, v0)))
    mid = u_ref[len(u_ref) // 2]
    inner = u_ref[len(u_ref) // 2 - 3 : len(u_ref) // 2 + 4]  # seven stripes about the middle
    for squeeze in (0.6, 1.0, 1.3):
        u = mid + squeeze * (inner - mid)
        v = np.full(len(u), v0)
        got = template_col_scale(u, v, np.arange(1, len(u) - 1), ref)
        assert np.allclose(got, squeeze, rtol=0.05), (squeeze, got)
    # the first and last stripes have a neighbour on one side only; at the fourth the gaps
    # either side (1 and 1.4 reference spacings) disagree
    u = np.r_[inner[:4], inner[3] + 1.4 * (inner[4:] - inner[3])]
    got = template_col_scale(u, np.full(len(u), v0), np.arange(len(u)), ref)
    assert got[0] == 1.0 and got[-1] == 1.0 and got[3] == 1.0
    assert np.allclose(got[1:3], 1.0, rtol=0.05) and np.allclose(got[4:6], 1.4, rtol=0.05)
    # samples in rows of their own: nothing to measure
    assert np.all(template_col_scale(u, np.arange(len(u)) * 3.0, np.arange(len(u)), ref) == 1.0)
    # the centres in any order give the same scales
    perm = np.random.default_rng(1).permutation(len(u))
    back = np.argsort(perm)
    again = template_col_scale(u[perm], np.full(len(u), v0), back, ref)
    assert np.array_equal(again, got)
