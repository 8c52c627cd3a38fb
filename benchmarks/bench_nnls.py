"""Nonnegative least squares of the Preisach fit: block principal pivoting
(``compensators/nnls_gram.py``) against Lawson–Hanson (``scipy.optimize.nnls`` on the
Cholesky factor, the reference), on the normal equations of real fits — the default scanner's
``afmctl excite --kind static`` record at 32 and 64 grid levels — and a whole
``afmctl identify --model preisach+creep`` run with each solver.

Medians of ``--repeats`` runs, both solvers alternated in one run (ratios, not absolute
figures: the machines are noisy). Rewrites the ``bench:nnls`` section of docs/BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_nnls.py [--repeats N] [--no-write]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from sections import median_s, write_section  # noqa: E402  (benchmarks/sections.py)
COMMAND = ".venv/bin/python benchmarks/bench_nnls.py"


def _record(folder: Path) -> Path:
    from afmctl.cli import main
    from afmctl.data.datafiles import read_csv, write_csv
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    exc = folder / "exc.csv"
    with contextlib.redirect_stdout(io.StringIO()):
        main(["excite", "--kind", "all", "--u-min-V", "0", "--u-max-V", "150", "--rate-Hz", "2000", "--out", str(exc)])
    u = read_csv(exc, ("t", "u"))["u"]
    y = Scanner(default_scanner_config()).run(np.column_stack([u, 0 * u, 0 * u]), 5e-4)[:, 0]
    write_csv(folder / "data.csv", {"t": np.arange(u.size) * 5e-4, "u": u, "y": y})
    return folder / "data.csv"


def _normal_equations(data: Path, levels: int) -> tuple[np.ndarray, np.ndarray]:
    from afmctl.compensators import preisach_identify as pid
    from afmctl.compensators.preisach import PreisachModel
    from afmctl.data.datafiles import read_csv
    d = read_csv(data, ("t", "u", "y"))
    seen: dict[str, np.ndarray] = {}
    solve = pid.nnls_gram

    def spy(H, b):
        seen["H"], seen["b"] = H.copy(), b.copy()
        return solve(H, b)
    pid.nnls_gram = spy
    try:
        PreisachModel.identify(d["t"], d["u"], d["y"], n_operators=levels, method="nnls")
    finally:
        pid.nnls_gram = solve
    return seen["H"], seen["b"]


def _identify_s(data: Path, out: Path, reference: bool) -> float:
    from afmctl.cli import main
    from afmctl.compensators import nnls_gram as ng
    from afmctl.compensators import preisach_identify as pid
    pid.nnls_gram = ng.reference_nnls if reference else ng.nnls_gram
    try:
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            main(["identify", "--model", "preisach+creep", "--data", str(data), "--out", str(out)])
        return time.perf_counter() - t0
    finally:
        pid.nnls_gram = ng.nnls_gram


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    from afmctl.compensators.nnls_gram import nnls_gram, reference_nnls
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = _record(Path(tmp))
        for levels in (32, 64):
            H, b = _normal_equations(data, levels)
            x, ref = nnls_gram(H, b), reference_nnls(H, b)
            diff = float(np.abs(x - ref).max() / np.abs(ref).max())
            t_bpp = median_s(lambda: nnls_gram(H, b), args.repeats)
            t_lh = median_s(lambda: reference_nnls(H, b), args.repeats)
            rows.append((f"{levels} levels ({b.size} unknowns, {np.count_nonzero(x)} > 0)", t_lh, t_bpp, diff))
        whole = {ref: [] for ref in (True, False)}
        for _ in range(args.repeats):
            for ref in (True, False):
                whole[ref].append(_identify_s(data, Path(tmp) / "m.json", ref))
        rows.append(("`identify --model preisach+creep` (64 levels, joint)", statistics.median(whole[True]),
                     statistics.median(whole[False]), float("nan")))
    lines = [f"Command: `{COMMAND}` ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
             f"medians of {args.repeats}, the two solvers alternated in one run).", "",
             "| problem | Lawson–Hanson [s] | block pivoting [s] | ratio | largest difference in x, relative |",
             "|---|---:|---:|---:|---:|"]
    for name, lh, bpp, diff in rows:
        lines.append(f"| {name} | {lh:.3f} | {bpp:.3f} | {lh / bpp:.1f}× | "
                     + ("–" if diff != diff else f"{diff:.1e}") + " |")
    body = "## Preisach NNLS: block principal pivoting vs Lawson–Hanson\n\n" + "\n".join(lines)
    print(body)
    if not args.no_write:
        write_section("nnls", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
