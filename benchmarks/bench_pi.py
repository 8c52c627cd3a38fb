"""Throughput of the PI operator and its closed-form inverse (compensators.pi).

Measures, for n = 13 and n = 64 play operators:

* block throughput (samples/s) of the forward operator and of the inverse (which is the
  same compiled PI kernel with the inverse parameters, eqs. 8–11);
* the per-sample ``step()`` call as a Python caller sees it (µs/call);
* the extended-PI inverse (compiled creep state machine) on a staircase with dwells;
* the rate-dependent PI (``rate-pi``, n = 13) forward and inverse blocks, as a ratio to PI's
  in the same run (its inverse solves a piecewise-linear equation per sample).

Targets (one core): inverse block ≥ 40 M samples/s at n = 13, ≥ 12 M samples/s at
n = 64; step ≤ 3 µs. Medians over repeats. Writes its section of docs/BENCHMARKS.md
between ``<!-- bench:pi -->`` markers.

    .venv/bin/python benchmarks/bench_pi.py [--repeats 7] [--samples 2000000] [--no-write]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from afmctl.compensators.epi import EPIModel  # noqa: E402
from afmctl.compensators.pi import PIModel  # noqa: E402
from afmctl.compensators.rate_pi import RatePIModel  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "pi"


def multiloop(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0.0, 150.0, n // 500 + 2)
    x = np.interp(np.arange(n), np.linspace(0, n - 1, pts.size), pts)
    return x + rng.normal(0.0, 0.05, n)   # many small reversals too


def make_model(n: int) -> PIModel:
    rng = np.random.default_rng(n)
    r = np.arange(n) * (75.0 / n)
    w = np.concatenate(([60.0], rng.uniform(-1.0, 6.0, n - 1)))
    return PIModel(thresholds=r.tolist(), weights=w.tolist(), offset_nm=-100.0)


def time_block(op, x: np.ndarray, repeats: int) -> tuple[float, float]:
    """Median block throughput (wall clock, CPU time of this process) [samples/s]."""
    op.reset()
    op.block(x[:1000])                    # compile / load the numba cache before timing
    wall, cpu = [], []
    for _ in range(repeats):
        op.reset()
        c0, t0 = time.process_time(), time.perf_counter()
        op.block(x)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return x.size / statistics.median(wall), x.size / max(statistics.median(cpu), 1e-9)


def time_step(op, x: np.ndarray, repeats: int) -> tuple[float, float]:
    """Median cost of one ``step()`` call from Python (wall clock, CPU time) [µs]."""
    xs = x[:50_000].tolist()
    step = op.step
    step(xs[0])
    wall, cpu = [], []
    for _ in range(repeats):
        op.reset()
        c0, t0 = time.process_time(), time.perf_counter()
        for v in xs:
            step(v)
        wall.append((time.perf_counter() - t0) / len(xs))
        cpu.append((time.process_time() - c0) / len(xs))
    return statistics.median(wall) * 1e6, statistics.median(cpu) * 1e6


def _fmt(pair: tuple[float, float], scale: float, digits: int) -> str:
    return f"{pair[0] * scale:.{digits}f} ({pair[1] * scale:.{digits}f})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--samples", type=int, default=2_000_000)
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/BENCHMARKS.md")
    args = ap.parse_args(argv)
    x = multiloop(args.samples)
    rows = []
    for n in (13, 64):
        m = make_model(n)
        fwd, inv = m.forward(), m.inverse()
        y = fwd.block(x)
        rows.append(dict(n=n,
                         fwd_block=time_block(fwd, x, args.repeats),
                         inv_block=time_block(inv, y, args.repeats),
                         fwd_step=time_step(fwd, x, args.repeats),
                         inv_step=time_step(inv, y, args.repeats)))
        r = rows[-1]
        print(f"n={n:3d}: forward block {_fmt(r['fwd_block'], 1e-6, 1)} M samples/s, inverse block "
              f"{_fmt(r['inv_block'], 1e-6, 1)} M samples/s, step fwd {_fmt(r['fwd_step'], 1, 2)} µs, "
              f"inv {_fmt(r['inv_step'], 1, 2)} µs  [wall clock (CPU time)]", flush=True)
    # extended PI inverse (compiled creep state machine), on a staircase with dwells
    e = EPIModel(**{**make_model(13).model_dump(), "kind": "epi"}, creep_a_nm=20.0, creep_b=1.005,
                 creep_lambda_per_s=3.0)
    ys = np.repeat(np.linspace(500, 8000, 400), 500)
    einv = e.inverse(1e-3)
    epi_rate = time_block(einv, ys, args.repeats)
    epi_step = time_step(einv, ys, args.repeats)
    print(f"extended PI inverse (n=13, staircase with dwells): block {_fmt(epi_rate, 1e-6, 1)} M samples/s, "
          f"step {_fmt(epi_step, 1, 2)} µs")

    # rate-dependent PI beside PI (n = 13), 10 kHz samples
    rp = RatePIModel(**make_model(13).model_dump(exclude={"kind", "direction"}), rate_gain_s_per_V=2e-4,
                     rate_tau_s=0.01)
    yr = rp.forward(1e-4).block(x)
    rate_rows = {"forward": time_block(rp.forward(1e-4), x, args.repeats),
                 "inverse": time_block(rp.inverse(1e-4), yr, args.repeats)}
    pi_rows = {"forward": rows[0]["fwd_block"], "inverse": rows[0]["inv_block"]}
    rate_text = ", ".join(f"{k} block {_fmt(v, 1e-6, 1)} M samples/s ({v[0] / pi_rows[k][0]:.2f}× PI's)"
                          for k, v in rate_rows.items())
    print(f"rate-dependent PI (n=13): {rate_text}")

    cmd = "`" + " ".join([".venv/bin/python benchmarks/bench_pi.py"] + list(sys.argv[1:] if argv is None else argv)) + "`"
    lines = [
        "## PI operator and inverse (compensators.pi)",
        "",
        f"Command: {cmd} (median of {args.repeats} runs; {args.samples:,} samples of a multi-loop "
        "signal with small reversals; one core; "
        f"{platform.python_implementation()} {platform.python_version()}, {os.cpu_count()} CPUs visible, "
        f"{time.strftime('%Y-%m-%d')}).",
        "",
        "Each figure: median wall clock (median CPU time of this single-threaded process, the fairer "
        "one-core figure on a shared machine).",
        "",
        "| plays n | forward block [M samples/s] | inverse block [M samples/s] | step forward [µs/call] | step inverse [µs/call] |",
        "|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['n']} | {_fmt(r['fwd_block'], 1e-6, 1)} | {_fmt(r['inv_block'], 1e-6, 1)} | "
                     f"{_fmt(r['fwd_step'], 1, 2)} | {_fmt(r['inv_step'], 1, 2)} |")
    lines += [
        "",
        "Targets: inverse block ≥ 40 M samples/s (n = 13) and ≥ 12 M samples/s (n = 64); step ≤ 3 µs. "
        "The inverse is the same numba kernel as the forward operator (the inverse of a PI "
        "operator is a PI operator, eqs. 8–11); `step` calls a scalar kernel on one "
        "preallocated (3, n) array.",
        f"Extended-PI inverse (n = 13, compiled creep state machine, staircase of 400 levels with 0.5 s "
        f"dwells at 1 kHz): block {_fmt(epi_rate, 1e-6, 1)} M samples/s, step {_fmt(epi_step, 1, 2)} µs/call.",
        f"Rate-dependent PI (`rate-pi`, n = 13, at 10 kHz; the inverse solves the piecewise-linear "
        f"equation of each sample by bisection over the plays' corners): {rate_text}.",
    ]
    if not args.no_write:
        path = write_section(NAME, "\n".join(lines))
        print(f"updated {path.relative_to(ROOT)} section {NAME}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
