"""The allocator setting that lets a frame reuse the last frame's buffers (multislit._memory)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="the setting is glibc's (Linux)"
)

#: Frame-like work: arrays of a few MB alive together, touched, freed; page faults counted over
#: the rounds after the first.
_WORK = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    if sys.argv[1] == "multislit":
        import multislit
        from multislit._memory import keep_freed_buffers
        print(int(keep_freed_buffers()))
    else:
        print(-1)
    def rounds(n):
        for _ in range(n):
            arrays = [np.empty(int(mb * 2**20) // 8) for mb in (5, 4, 4, 3, 5, 2, 10)]
            for a in arrays:
                a[:] = 1.0
            del arrays
    rounds(1)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    rounds(3)
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def _faults(which: str, **env: str) -> tuple[int, int]:
    """(whether the setting was made (-1: not asked), page faults) of the work in a new
    process."""
    full = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith("MALLOC_") and k != "MULTISLIT_ALLOCATOR"
    }
    full.update(env)
    out = subprocess.run(
        [sys.executable, "-c", _WORK, which],
        capture_output=True,
        text=True,
        env=full,
        timeout=120,
        check=True,
    ).stdout.split()
    return int(out[0]), int(out[1])


def test_frames_reuse_their_buffers_after_import():
    _, plain = _faults("numpy")
    made, kept = _faults("multislit")
    assert made == 1
    assert plain > 1000  # the allocator's own thresholds: each round faults its arrays in
    assert kept < 0.25 * plain, (kept, plain)


def test_a_users_own_allocator_setting_stands():
    made, faults = _faults("multislit", MALLOC_MMAP_THRESHOLD_="131072")
    assert made == 0
    assert faults > 1000  # every block mapped afresh, as the user asked


def test_the_setting_can_be_left_out():
    _, plain = _faults("numpy")
    made, faults = _faults("multislit", MULTISLIT_ALLOCATOR="system")
    assert made == 0
    assert faults > 0.5 * plain, (faults, plain)  # as without multislit


def test_an_unknown_choice_is_named_and_taken_as_the_default():
    out = subprocess.run(
        [sys.executable, "-c", "import multislit"],
        capture_output=True,
        text=True,
        env={**os.environ, "MULTISLIT_ALLOCATOR": "sytem"},
        timeout=120,
        check=True,
    )
    assert "UserWarning: MULTISLIT_ALLOCATOR must be one of frames, system, got 'sytem'" in (
        out.stderr
    )
    assert out.stderr.count("\n") == 1, out.stderr  # one line
