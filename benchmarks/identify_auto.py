"""Time of ``afmctl identify --model auto`` with the Preisach fit's normal equations formed
as before #38's change (numpy's cumsum over the reversed and transposed Gram matrix, the
dense ``DᵀD`` of the smoothness penalty) and as now (the compiled corner prefix sums of
``compensators/_corner_kernels.py``, the sparse ``DᵀD``), on the same recording, interleaved.

    .venv/bin/python benchmarks/identify_auto.py --recording REC.csv [--reps 3]

Without ``--recording``: ``afmctl excite --kind all`` at 50 kHz played through the default
simulated scanner (benchmarks/speed_ladder.py ``record``). Prints the medians, their ratio
and whether the two models are the same to the last bit (they must be).
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import fit_recording  # noqa: E402
from afmctl.api.identify import identify  # noqa: E402
from afmctl.compensators import preisach_identify as pid  # noqa: E402

NOW = {"_corner_prefix_fast": pid._corner_prefix_fast, "_smoothness_gram": pid._smoothness_gram}


def _dense_gram(L: int):
    D = pid._smoothness(L)
    return D.T @ D


BEFORE = {"_corner_prefix_fast": lambda M, L: pid._corner_prefix(M, L), "_smoothness_gram": _dense_gram}
VARIANTS = {"numpy (before)": BEFORE, "compiled (now)": NOW}


def _with(funcs: dict, recording: Path):
    """``identify auto`` with the Preisach fit's functions ``funcs`` in place: its model."""
    for attr, f in funcs.items():
        setattr(pid, attr, f)
    return identify("auto", recording).model


def main(argv: list[str] | None = None) -> int:
    args = fit_recording.parse_args(__doc__.split("\n\n")[0], argv)
    with tempfile.TemporaryDirectory() as tmp:
        fit_recording.recording(args, Path(tmp))
        identify("auto", args.recording)            # compile/load every kernel outside the timing
        times, models = fit_recording.interleaved({name: (lambda funcs=funcs: _with(funcs, args.recording))
                                                   for name, funcs in VARIANTS.items()}, args.reps)
        for attr, f in NOW.items():
            setattr(pid, attr, f)
    fit_recording.report(f"identify --model auto on {args.recording}", times, models, args.reps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
