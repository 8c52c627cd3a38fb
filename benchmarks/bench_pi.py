"""Throughput of the PI operator and its closed-form inverse (compensators.pi).

Measures, for n = 13 and n = 64 play operators:

* block throughput (samples/s) of the forward operator and of the inverse (which is the
  same compiled PI kernel with the inverse parameters, eqs. 8–11);
* the per-sample ``step()`` call as a Python caller sees it (µs/call);
* the extended-PI inverse (compiled creep state machine) on a staircase with dwells.

Targets (one core): inverse block ≥ 40 M samples/s at n = 13, ≥ 12 M samples/s at
n = 64; step ≤ 3 µs. Medians over repeats. Writes its section of docs/BENCHMARKS.md
between ``<!-- bench:pi -->`` markers.

    .venv/bin/python benchmarks/bench_pi.py [--repeats 7] [--samples 2000000] [--no-write]
"""
from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from compensators.epi import EPIModel  # noqa: E402
from compensators.pi import PIModel  # noqa: E402

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


def time_block(op, x: np.ndarray, repeats: int) -> float:
    op.reset()
    op.block(x[:1000])                    # compile / warm caches
    rates = []
    for _ in range(repeats):
        op.reset()
        t0 = time.perf_counter()
        op.block(x)
        rates.append(x.size / (time.perf_counter() - t0))
    return statistics.median(rates)


def time_step(op, x: np.ndarray, repeats: int) -> float:
    xs = x[:50_000].tolist()
    step = op.step
    step(xs[0])
    per = []
    for _ in range(repeats):
        op.reset()
        t0 = time.perf_counter()
        for v in xs:
            step(v)
        per.append((time.perf_counter() - t0) / len(xs))
    return statistics.median(per) * 1e6


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
        print(f"n={n:3d}: forward block {rows[-1]['fwd_block'] / 1e6:7.1f} M samples/s, inverse block "
              f"{rows[-1]['inv_block'] / 1e6:7.1f} M samples/s, step fwd {rows[-1]['fwd_step']:.2f} µs, "
              f"inv {rows[-1]['inv_step']:.2f} µs", flush=True)
    # extended PI inverse (compiled creep state machine), on a staircase with dwells
    e = EPIModel(**{**make_model(13).model_dump(), "kind": "epi"}, creep_a_nm=20.0, creep_b=1.005,
                 creep_lambda_per_s=3.0)
    ys = np.repeat(np.linspace(500, 8000, 400), 500)
    einv = e.inverse(1e-3)
    epi_rate = time_block(einv, ys, args.repeats)
    epi_step = time_step(einv, ys, args.repeats)
    print(f"extended PI inverse (n=13, staircase with dwells): block {epi_rate / 1e6:.1f} M samples/s, "
          f"step {epi_step:.2f} µs")

    cmd = "`.venv/bin/python benchmarks/bench_pi.py`"
    lines = [
        "## PI operator and inverse (compensators.pi)",
        "",
        f"Command: {cmd} (median of {args.repeats} runs; {args.samples:,} samples of a multi-loop "
        "signal with small reversals; one core; "
        f"{platform.python_implementation()} {platform.python_version()}, {os.cpu_count()} CPUs visible, "
        f"{time.strftime('%Y-%m-%d')}).",
        "",
        "| plays n | forward block [M samples/s] | inverse block [M samples/s] | step forward [µs/call] | step inverse [µs/call] |",
        "|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['n']} | {r['fwd_block'] / 1e6:.1f} | {r['inv_block'] / 1e6:.1f} | "
                     f"{r['fwd_step']:.2f} | {r['inv_step']:.2f} |")
    lines += [
        "",
        "Targets: inverse block ≥ 40 M samples/s (n = 13) and ≥ 12 M samples/s (n = 64); step ≤ 3 µs. "
        "The inverse is the same numba kernel as the forward operator (the inverse of a PI "
        "operator is a PI operator, eqs. 8–11); `step` calls a scalar kernel on one "
        "preallocated (3, n) array.",
        f"Extended-PI inverse (n = 13, compiled creep state machine, staircase of 400 levels with 0.5 s "
        f"dwells at 1 kHz): block {epi_rate / 1e6:.1f} M samples/s, step {epi_step:.2f} µs/call.",
    ]
    if not args.no_write:
        write_section("\n".join(lines))
    return 0


def write_section(body: str) -> None:
    path = ROOT / "docs" / "BENCHMARKS.md"
    text = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n"
    start, end = f"<!-- bench:{NAME} -->", f"<!-- /bench:{NAME} -->"
    block = f"{start}\n{body}\n{end}"
    if start in text and end in text:
        text = re.sub(re.escape(start) + r".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(text, encoding="utf-8")
    print(f"updated {path.relative_to(ROOT)} section {NAME}")


if __name__ == "__main__":
    sys.exit(main())
