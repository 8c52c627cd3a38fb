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

import statistics
import sys
import tempfile
import time
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


def main(argv: list[str] | None = None) -> int:
    args = fit_recording.parse_args(__doc__.split("\n\n")[0], argv)
    with tempfile.TemporaryDirectory() as tmp:
        fit_recording.recording(args, Path(tmp))
        identify("auto", args.recording)            # compile/load every kernel outside the timing
        times: dict[str, list[float]] = {v: [] for v in VARIANTS}
        models: dict[str, str] = {}
        for _ in range(args.reps):
            for name, funcs in VARIANTS.items():
                for attr, f in funcs.items():
                    setattr(pid, attr, f)
                t0 = time.perf_counter()
                fit = identify("auto", args.recording)
                times[name].append(time.perf_counter() - t0)
                models[name] = fit.model.model_dump_json()
        for attr, f in NOW.items():
            setattr(pid, attr, f)
    a, b = (statistics.median(times[v]) for v in VARIANTS)
    print(f"identify --model auto on {args.recording}: before {a:.1f} s, now {b:.1f} s "
          f"(medians of {args.reps}, interleaved); ratio {a / b:.2f}x")
    print("the two models are " + ("the same to the last bit" if len(set(models.values())) == 1 else "DIFFERENT"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
