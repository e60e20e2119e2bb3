"""Every benchmark script starts: its imports resolve and its command line is read (``--help``)."""

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("bench_*.py"))


@pytest.mark.slow  # a fresh interpreter per script
@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_the_benchmark_starts(script):
    run = subprocess.run(
        [sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stderr[-500:]
    assert "usage" in run.stdout.lower()


@pytest.mark.slow  # a fresh interpreter
def test_the_zoo_benchmark_refuses_a_confidence_out_of_range():
    script = SCRIPTS[0].parent / "bench_zoo.py"
    run = subprocess.run(
        [sys.executable, str(script), "--confidence", "0.9", "1.5"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2
    last = run.stderr.strip().splitlines()[-1]
    assert "--confidence" in last and "[0, 1]" in last and "1.5" in last, run.stderr
    assert "Traceback" not in run.stderr


@pytest.mark.slow  # a fresh interpreter
def test_the_zoo_benchmark_refuses_a_file_to_keep_its_captures_in(tmp_path):
    script = SCRIPTS[0].parent / "bench_zoo.py"
    not_a_folder = tmp_path / "captures.txt"
    not_a_folder.write_text("kept\n")
    run = subprocess.run(
        [sys.executable, str(script), "--keep", str(not_a_folder)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2
    assert "is not a folder" in run.stderr.strip().splitlines()[-1], run.stderr
    assert "Traceback" not in run.stderr
    assert not_a_folder.read_text() == "kept\n"
