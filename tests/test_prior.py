"""The previous frame's labels as a prior (``identify(..., previous=...)``) and the simulated
sequences of moving objects (:func:`multislit.sim.simulate_sequence`)."""

from dataclasses import replace

import numpy as np
import pytest

from multislit.errors import IdentificationError, MultislitError
from multislit.identify import identify_template as identify
from multislit.identify import prepare_reference
from multislit.identify.prior import prior_slits
from multislit.io import Capture
from multislit.sim import RigSpec, identification_metrics, simulate_sequence


@pytest.fixture(scope="module")
def steps_scan(scenes_capture, scenes_reference):
    """The half-size steps scan (boxes that shift slits by several spacings), its full
    identification and its truth."""
    cap = Capture.open(scenes_capture)
    img = cap.image(next(p for p in cap.scans if p.stem == "steps"))
    truth = np.load(scenes_capture / "truth" / "steps.npz")["slit"]
    return img, identify(img, scenes_reference), truth


def _differ(a, b):
    """(K,) bool: points both identifications label, with different slits."""
    return (a.slit >= 0) & (b.slit >= 0) & (a.slit != b.slit)


def test_a_prior_that_holds_gives_the_full_identifications_slits(steps_scan, scenes_reference):
    img, full, truth = steps_scan
    ex = full.extraction
    prior = prior_slits(ex.u, ex.v, full.segment, full, scenes_reference.spacing_px)
    assert np.sum(prior >= 0) >= 0.5 * full.num_identified  # the prior is used
    with_prior = identify(img, scenes_reference, previous=full, extraction=ex)
    assert np.array_equal(with_prior.u, full.u)
    assert not _differ(with_prior, full).any()
    assert np.mean(with_prior.slit == full.slit) >= 0.995
    m_full = identification_metrics(full, truth)
    m_prior = identification_metrics(with_prior, truth)
    assert m_prior["correct"] >= m_full["correct"] - 1e-3
    assert m_prior["coverage"] >= m_full["coverage"] - 0.005


@pytest.mark.parametrize("shift", [1, -1, 2])
def test_a_wrong_prior_is_not_accepted(steps_scan, scenes_reference, shift):
    """Previous labels off by one or two slits: every segment is searched again (or left out);
    none takes the prior's wrong slit."""
    img, full, _ = steps_scan
    n = scenes_reference.num_slits
    k = full.slit + shift
    wrong = replace(full, slit=np.where((full.slit >= 0) & (k >= 0) & (k < n), k, -1))
    got = identify(img, scenes_reference, previous=wrong, extraction=full.extraction)
    took_wrong = (got.slit >= 0) & (got.slit == wrong.slit) & (got.slit != full.slit)
    assert took_wrong.sum() == 0
    assert not _differ(got, full).any()
    assert np.sum(got.slit >= 0) >= 0.99 * np.sum(full.slit >= 0)


def test_bad_previous_is_named(steps_scan, scenes_reference):
    img, full, _ = steps_scan
    with pytest.raises(IdentificationError, match="previous must be the Identification"):
        identify(img, scenes_reference, previous={"slit": full.slit})
    small = replace(full, extraction=replace(full.extraction, dots=np.zeros((64, 80), np.float32)))
    with pytest.raises(IdentificationError, match=r"previous is an identification of a 80x64"):
        identify(img, scenes_reference, previous=small)
    beyond = replace(full, slit=np.where(full.slit >= 0, full.slit + 100, -1))
    with pytest.raises(IdentificationError, match="previous has slit numbers beyond"):
        identify(img, scenes_reference, previous=beyond)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"frames": 0}, "frames must be a positive integer"),
        ({"frames": 2.5}, "frames must be a positive integer"),
        ({"step_mm": (1.0, 2.0)}, "step_mm must be one or three finite numbers"),
        ({"step_mm": float("nan")}, "step_mm must be one or three finite numbers"),
    ],
)
def test_simulate_sequence_checks_its_arguments(kwargs, match):
    with pytest.raises(MultislitError, match=match):
        simulate_sequence(RigSpec().scaled(0.5), **kwargs)


@pytest.fixture(scope="module")
def short_sequence():
    """Four half-size frames, the objects moving 6 mm to the right per frame."""
    seq = simulate_sequence(RigSpec().scaled(0.5), frames=4, step_mm=6.0, seed=5)
    ref = prepare_reference(seq.references, seq.spec.slits.num_slits, seq.reference_names)
    return seq, ref


@pytest.mark.slow
def test_sequence_truth_follows_the_moving_objects(short_sequence):
    seq, _ = short_sequence
    assert len(seq) == 4 and seq.offsets[-1, 0] == pytest.approx(18.0)
    cols = [np.nonzero(o)[1].mean() for o in seq.truth_object]
    # the objects fill a part of the image, not all of it
    assert all(1000 < o.sum() < 0.3 * o.size for o in seq.truth_object)
    # 6 mm at ~0.9 m with a 900 px focal length: ~6 px to the right per frame
    assert np.all(np.diff(cols) > 3) and np.all(np.diff(cols) < 9)
    assert all((t >= 0).sum() > 10000 for t in seq.truth_slit)


@pytest.mark.slow
def test_sequence_with_prior_gives_the_same_slits(short_sequence):
    seq, ref = short_sequence
    prev = None
    for img, truth in zip(seq.images, seq.truth_slit, strict=True):
        full = identify(img, ref)
        got = identify(img, ref, previous=prev, extraction=full.extraction)
        assert not _differ(got, full).any()
        assert np.mean(got.slit == full.slit) >= 0.99
        m_got, m_full = identification_metrics(got, truth), identification_metrics(full, truth)
        assert m_got["correct"] >= m_full["correct"] - 1e-3
        assert m_got["coverage"] >= m_full["coverage"] - 0.01
        prev = got
