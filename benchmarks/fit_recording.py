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
