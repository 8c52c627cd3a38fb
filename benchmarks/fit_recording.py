"""The command line the fit benchmarks share (``dynamics_fit.py``, ``bouc_wen_fit.py``): a
recording to fit, or one simulated from the default scanner (``excite --kind all`` at
50 kHz through ``speed_ladder.record``), and the repetitions per variant."""
from __future__ import annotations

import argparse
from pathlib import Path


def parse_args(description: str, argv: list[str] | None = None) -> argparse.Namespace:
    """``--recording CSV`` (t,u,y) and ``--reps N``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--recording", type=Path, help="CSV with columns t,u,y (default: simulate one)")
    ap.add_argument("--reps", type=int, default=3, help="repetitions per Jacobian (median)")
    return ap.parse_args(argv)


def recording(args: argparse.Namespace, tmp: Path) -> Path:
    """``args.recording``, or a simulated one written into ``tmp`` (kept in ``args``)."""
    if args.recording is None:
        import speed_ladder as sl
        args.recording = sl.record("all", 50_000, tmp)
    return args.recording


def interleaved(variants: dict, reps: int) -> tuple[dict, dict]:
    """Each of ``variants`` (name → a function returning a fitted model) timed ``reps``
    times, the variants interleaved (a noisy machine loads them alike): the times [s] per
    variant and each variant's last model as JSON."""
    import time
    times: dict = {v: [] for v in variants}
    models: dict = {}
    for _ in range(reps):
        for name, fit in variants.items():
            t0 = time.perf_counter()
            model = fit()
            times[name].append(time.perf_counter() - t0)
            models[name] = model.model_dump_json()
    return times, models


def report(what: str, times: dict, models: dict, reps: int) -> None:
    """Print the two variants' medians, their ratio (first / second) and whether their
    models are the same to the last bit."""
    import statistics
    (a_name, a), (b_name, b) = ((v, statistics.median(t)) for v, t in times.items())
    print(f"{what}: {a_name} {a:.1f} s, {b_name} {b:.1f} s (medians of {reps}, interleaved); ratio {a / b:.2f}x")
    print("the two models are " + ("the same to the last bit" if len(set(models.values())) == 1 else "DIFFERENT"))
