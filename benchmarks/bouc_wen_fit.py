"""Time of the Bouc–Wen least-squares fit with the Jacobian from the simulation's forward
sensitivities against scipy's 2-point finite differences (the fit's Jacobian before), on the
same record.

The record is conditioned as ``afmctl identify --model bouc-wen`` conditions it (burn-in,
delay) and fitted as that command fits it (:meth:`BoucWenModel.identify` with the burn-in as
``fit_from_index``), once per Jacobian per repetition, interleaved. Prints the medians, their
ratio, each fit's parameters, residual and evaluation count, and the largest relative
difference of the parameters between the two.

    .venv/bin/python benchmarks/bouc_wen_fit.py [--recording REC.csv] [--reps 3]

Without ``--recording``: ``afmctl excite --kind all`` at 50 kHz played through the default
simulated scanner (benchmarks/speed_ladder.py ``record``).
"""
from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.api.identify import prepare  # noqa: E402
import fit_recording  # noqa: E402
from afmctl.compensators.bouc_wen import BoucWenModel  # noqa: E402
from afmctl.data.identdata import delayed  # noqa: E402

JACOBIANS = ("2-point", "sensitivities")
FIELDS = ("d_nm_per_V", "A_nm_per_V", "beta", "gamma", "n", "offset_nm", "fit_residual_nm")


def main(argv: list[str] | None = None) -> int:
    args = fit_recording.parse_args(__doc__.split("\n\n")[0], argv)
    with tempfile.TemporaryDirectory() as tmp:
        fit_recording.recording(args, Path(tmp))
        c, _ = prepare("bouc-wen", args.recording)
    t, u, y = c.t_s, delayed(c.t_s, c.u_V, c.delay_s), c.y_nm
    print(f"recording {args.recording}: {u.size} rows, fit from row {c.fit_from}")
    BoucWenModel.identify(t[:2000], u[:2000], y[:2000])  # compile/load the kernels outside the timing
    times: dict[str, list[float]] = {j: [] for j in JACOBIANS}
    fits: dict[str, BoucWenModel] = {}
    for _ in range(args.reps):
        for j in JACOBIANS:
            t0 = time.perf_counter()
            fits[j] = BoucWenModel.identify(t, u, y, fit_from_index=c.fit_from, jacobian=j)
            times[j].append(time.perf_counter() - t0)
    a, b = (statistics.median(times[j]) for j in JACOBIANS)
    print(f"Bouc–Wen fit: 2-point {a:.3f} s, sensitivities {b:.3f} s (medians of {args.reps}); ratio {a / b:.2f}×")
    for j in JACOBIANS:
        m = fits[j]
        print(f"{j}: " + ", ".join(f"{f} {getattr(m, f):.10g}" for f in FIELDS))
    worst = max(abs(getattr(fits["sensitivities"], f) / getattr(fits["2-point"], f) - 1.0)
                for f in FIELDS if getattr(fits["2-point"], f))
    print(f"largest relative difference of the fitted figures: {worst:.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
