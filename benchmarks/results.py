"""Writing a benchmark's section of benchmarks/RESULTS.md.

Each benchmark that records its figures owns one section, between the markers
``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``; running it again replaces that section
whole (the file is written to a temporary name, then renamed), or appends it if missing.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from multislit.io import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def command_line(script: str, argv: list[str] | None = None) -> str:
    """The command that repeats a run: ``.venv/bin/python benchmarks/SCRIPT ARGS``."""
    args = argv if argv is not None else sys.argv[1:]
    return " ".join([".venv/bin/python", f"benchmarks/{script}", *args]).strip()


def write_section(name: str, title: str, text: str, command: str, path: Path = RESULTS) -> None:
    """Replace (or append) section ``name`` of RESULTS.md with ``title``, command, date, text."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    date = subprocess.run(["date", "-u"], capture_output=True, text=True).stdout.strip()
    block = f"{begin}\n## {title}\n\nCommand: `{command}`  \nDate: {date}\n\n{text}\n{end}"
    old = path.read_text() if path.exists() else "# Benchmark results\n"
    if begin in old and end in old:
        new = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: block, old, flags=re.S)
    else:
        new = old.rstrip("\n") + "\n\n" + block + "\n"
    write_text_atomic(path, new)
