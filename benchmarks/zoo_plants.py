"""The reference scanners from outside (``../shared/plants``): the command-line workflow, scored.

``../shared/plants/zoo.py`` holds scanner axes built differently from afmctl's simulator
(the amplifier before the hysteresis with its slew limit, an asymmetric generalised PI,
rate-dependent Bouc–Wen loops, two modes behind a zero pair, a lumpy Preisach plane, a noisy
low-pass sensor); ``../shared/plants/check.py`` runs afmctl's command line on them as a user
would and scores the true tip. This script runs ``check.py --only speed`` for every plant and
recording — ``excite`` (``afmctl excite --kind all``, recorded with the piezo voltage as
column ``v``), ``lab`` (a lab's own recording: nested slow triangles, interior loops, fast
triangles, a chirp; with ``v``) and ``lab-no-v`` (the same without ``v``) — ``--jobs`` at a
time, and prints the max / RMS error at 1 / 10 / 50 lines/s (% of the line, central 80 %
of every line after the first two).

    .venv/bin/python benchmarks/zoo_plants.py [--plants amp-first ...] [--recordings excite lab lab-no-v]
        [--jobs 2] [--keep DIR] [--no-write]

Writes its section of docs/BENCHMARKS.md between ``<!-- bench:zoo_plants -->`` markers. About
5–10 minutes per plant and recording on a quiet 2-core machine (``identify --model auto``).
The plants are an outside check: no constant of afmctl is tuned to them.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "plants"
sys.path.insert(0, str(ROOT / "benchmarks"))

from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "zoo_plants"
PLANTS = ("amp-first", "two-modes", "lumpy-noisy")
RECORDINGS = ("excite", "lab", "lab-no-v")
GOALS = {"excite": "0.5 / 0.5 / 1.0", "lab": "1 / 1 / 2", "lab-no-v": "1 / 1 / 2"}
ROW = re.compile(r"^(\S+)\s+speed \((\S+)\), max / RMS % at 1 \| 10 \| 50 lines/s: (.*)$")


def run_one(plant: str, recording: str, keep: Path | None) -> tuple[str, str, str, float]:
    """``check.py --only speed`` for one plant and recording: (plant, recording, cells, seconds)."""
    cmd = [sys.executable, str(SHARED / "check.py"), "--only", "speed", "--plants", plant,
           "--recording", recording]
    if keep is not None:
        cmd += ["--keep", str(keep / recording)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    for line in p.stdout.splitlines():
        m = ROW.match(line.strip())
        if m:
            return plant, recording, m.group(3), seconds
    last = (p.stderr or p.stdout).strip().splitlines()
    return plant, recording, f"failed: {last[-1] if last else p.returncode}", seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plants", nargs="+", default=list(PLANTS))
    ap.add_argument("--recordings", nargs="+", default=list(RECORDINGS), choices=RECORDINGS)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", type=Path, help="keep every file (check.py --keep) under this folder")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/BENCHMARKS.md alone")
    a = ap.parse_args()
    if not (SHARED / "check.py").exists():
        raise SystemExit(f"zoo_plants: {SHARED / 'check.py'} not found (the shared reference plants)")
    jobs = [(p, r) for r in a.recordings for p in a.plants]
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, a.jobs)) as pool:
        rows = list(pool.map(lambda job: run_one(*job, a.keep), jobs))
    lines = [f"`{' '.join(['.venv/bin/python', 'benchmarks/zoo_plants.py', '--jobs', str(a.jobs)])}` "
             f"({time.perf_counter() - t0:.0f} s wall, {a.jobs} at a time). Max / RMS error of the true tip, "
             "% of the line, central 80 % of every line after the first two:", "",
             "| plant | recording | 1 line/s | 10 lines/s | 50 lines/s | goal (max) | s |", "|---|---|---|---|---|---|---|"]
    for plant, rec, cells, seconds in rows:
        parts = [c.strip() for c in cells.split("|")]
        cols = parts if len(parts) == 3 else [cells, "", ""]
        lines.append(f"| {plant} | {rec} | {' | '.join(cols)} | {GOALS[rec]} | {seconds:.0f} |")
    body = "\n".join(lines)
    print(body)
    if not a.no_write:
        write_section(NAME, "## Reference scanners from outside (`../shared/plants`)\n\n" + body)


if __name__ == "__main__":
    main()
