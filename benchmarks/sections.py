"""What the benchmark scripts share: writing one benchmark's section of docs/BENCHMARKS.md,
and the median wall time of a call.

Each benchmark script owns the text between ``<!-- bench:NAME -->`` and
``<!-- /bench:NAME -->``: the section is replaced if present, appended if missing, and
nothing else in the file is touched.
"""
from __future__ import annotations

import re
import statistics
import time
from collections.abc import Callable
from pathlib import Path

DOC = Path(__file__).resolve().parent.parent / "docs" / "BENCHMARKS.md"


def write_section(name: str, body: str, path: Path = DOC) -> Path:
    """Put ``body`` between the markers of section ``name`` in ``path``; return the path."""
    start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    block = f"{start}\n{body.strip(chr(10))}\n{end}"
    text = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n"
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _m: block, text)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text, encoding="utf-8")
    return path


def median_s(fn: Callable[[], object], repeats: int, warm_up: bool = False) -> float:
    """The median wall time [s] of ``repeats`` calls of ``fn`` (``warm_up``: one call first,
    not timed: numba compilation or its cache load)."""
    if warm_up:
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)
