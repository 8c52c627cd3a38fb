"""Drift prediction cost: block path per 3-axis sample (target ≤ 2 µs), per-sample step,
Kalman predict, phase correlation of a 64×64 frame. Rewrites the ``drift`` section of
docs/BENCHMARKS.md.

    .venv/bin/python benchmarks/bench_drift.py [--repeats N]
"""
from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from afmctl.compensators.drift import DriftParams  # noqa: E402
from afmctl.compensators.drift_kalman import DriftKalman  # noqa: E402
from afmctl.compensators.phase_correlation import phase_correlation  # noqa: E402
from sections import median_s, write_section as _write_section  # noqa: E402  (benchmarks/sections.py)

COMMAND = ".venv/bin/python benchmarks/bench_drift.py"


def measure(repeats: int = 7, n_block: int = 200_000, n_step: int = 5_000) -> list[tuple[str, str, float, str]]:
    rows = []
    rng = np.random.default_rng(0)
    T = 20.0 + np.cumsum(rng.normal(0, 1e-4, n_block))
    U = rng.uniform(0, 150, size=(n_block, 3))
    for name in ("physical_tube", "table_a1"):
        for dt in (1e-3, 1e-4):
            pred = DriftParams.named(name).predictor(dt)
            pred.block(T[:100], U[:100])  # compile / warm up
            s = median_s(lambda: pred.block(T, U), repeats) / n_block
            states = pred.system.n_states + pred.system.n_slow * pred.system.kmax
            rows.append((f"predictor.block, {name}", f"{1 / dt:g} Hz, {states} states", s * 1e6,
                         "µs / 3-axis sample"))
        pred = DriftParams.named(name).predictor(1e-3)
        pred.step(20.0, U[0])

        def steps():
            for i in range(n_step):
                pred.step(T[i], U[i])
        rows.append((f"predictor.step, {name}", "1000 Hz", median_s(steps, max(3, repeats // 2)) / n_step * 1e6,
                     "µs / call"))
    kf = DriftKalman(1e-3)
    m = np.zeros(3)

    def kpred():
        for _ in range(n_step):
            kf.predict(m)
    rows.append(("DriftKalman.predict", "3 axes, bias + rate", median_s(kpred, 3) / n_step * 1e6, "µs / call"))
    a = rng.normal(size=(64, 64))
    b = np.roll(a, 2, axis=1)
    rows.append(("phase_correlation", "64×64, upsample 100, refine",
                 median_s(lambda: phase_correlation(a, b), repeats) * 1e3, "ms / frame pair"))
    return rows


def write_section(rows, repeats: int) -> str:
    lines = ["", "## Drift prediction", "",
             f"Command: `{COMMAND}` (median of {repeats} runs; block of 200 000 samples; "
             f"{platform.python_implementation()} {platform.python_version()}, {platform.machine()}). "
             "Target: ≤ 2 µs per 3-axis sample in the block path.", "",
             "| what | conditions | median | unit |", "|---|---|---|---|"]
    for what, cond, val, unit in rows:
        lines.append(f"| {what} | {cond} | {val:.3g} | {unit} |")
    section = "\n".join(lines[1:])
    _write_section("drift", section)
    return section


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/BENCHMARKS.md alone")
    args = ap.parse_args(argv)
    rows = measure(args.repeats)
    if args.no_write:
        for row in rows:
            print("| {} | {} | {:.3g} | {} |".format(*row))
    else:
        print(write_section(rows, args.repeats))
    block = [val for what, _, val, _ in rows if what.startswith("predictor.block")]
    ok = max(block) <= 2.0
    print(f"target ≤ 2 µs per 3-axis sample in the block path met: {ok} (worst {max(block):.3g} µs)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
