"""Time of ``identify("auto", …)`` in the calling process (``jobs=1``) and in two worker
processes (``jobs=2``, :mod:`afmctl.compensators.fit_pool`) on the same recording,
interleaved (#38).

    .venv/bin/python benchmarks/identify_jobs.py --recording REC.csv [--reps 3]

Without ``--recording``: ``afmctl excite --kind all`` at 50 kHz played through the default
simulated scanner (benchmarks/speed_ladder.py ``record``). Prints the medians, their ratio
and whether the two models are the same to the last bit (they must be). Run it with
``OPENBLAS_NUM_THREADS=1`` for that comparison: the workers use one BLAS thread each, and
BLAS rounds differently with two.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import fit_recording  # noqa: E402
from afmctl.api.identify import identify  # noqa: E402

JOBS = (1, 2)


def main(argv: list[str] | None = None) -> int:
    args = fit_recording.parse_args(__doc__.split("\n\n")[0], argv)
    with tempfile.TemporaryDirectory() as tmp:
        fit_recording.recording(args, Path(tmp))
        identify("auto", args.recording, candidates=["pi"])    # compile/load the kernels outside the timing
        times, models = fit_recording.interleaved(
            {j: (lambda j=j: identify("auto", args.recording, jobs=j).model) for j in JOBS}, args.reps)
    fit_recording.report(f"identify --model auto on {args.recording}", {f"jobs={j}": times[j] for j in JOBS},
                         models, args.reps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
