"""Time of the dynamics' frequency-response fits with the analytic Jacobian against scipy's
2-point finite differences (the fit's Jacobian before), on the same measured response.

The response is the one :func:`afmctl.compensators.dynamics_identify.fit_dynamics` fits for
``--model dynamics`` on the recording (the recording conditioned as ``afmctl identify`` does;
the frequency response caught where ``fit_dynamics`` hands it to ``fit_mode_count``). Per
repetition, interleaved: ``fit_mode_count`` (0…3 modes, each grown from the last, as
``n_modes=auto``) and ``fit_frf`` with the count it selects, once per Jacobian. Prints the
medians, their ratio, and what each fit found (modes [Hz], ζ, RMS log error).

    .venv/bin/python benchmarks/dynamics_fit.py [--recording REC.csv] [--reps 3]

Without ``--recording``: ``afmctl excite --kind all`` at 50 kHz played through the default
simulated scanner (benchmarks/speed_ladder.py ``record``).
"""
from __future__ import annotations

import copy
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import afmctl.compensators.dynamics_identify as di  # noqa: E402
import fit_recording  # noqa: E402
from afmctl.api.identify import prepare  # noqa: E402

JACOBIANS: tuple[di.Jacobian, ...] = ("2-point", "analytic")


def fitted_frf(recording: Path) -> tuple[di.FRF, int, float]:
    """The frequency response, lag count and sample period [s] ``fit_dynamics`` fits on
    ``recording`` (caught at its call of ``fit_mode_count``; that fit is not timed)."""
    c, _ = prepare("dynamics", recording)
    caught: list[tuple[di.FRF, int, float]] = []
    fit_mode_count = di.fit_mode_count

    def catch(frf: di.FRF, n_lags: int, dt_s: float, jac: di.Jacobian = "analytic") -> tuple[int, np.ndarray, float]:
        caught.append((copy.deepcopy(frf), n_lags, dt_s))
        return fit_mode_count(frf, n_lags, dt_s, jac)

    di.fit_mode_count = catch
    try:
        di.fit_dynamics(c.t_s, c.u_V, c.y_nm)
    finally:
        di.fit_mode_count = fit_mode_count
    return caught[0]


def found(x: np.ndarray, n_modes: int, n_lags: int, rms: float) -> str:
    _, fm, zeta, fl, tau = di._unpack(x, n_modes, n_lags)
    modes = ", ".join(f"{f:.6g} Hz ζ {z:.5g}" for f, z in zip(fm, zeta)) or "none"
    lags = ", ".join(f"{f:.6g} Hz" for f in fl) or "none"
    return f"modes {modes}; lags {lags}; τ {tau * 1e6:.4g} µs; RMS log error {rms:.6g}"


def main(argv: list[str] | None = None) -> int:
    args = fit_recording.parse_args(__doc__.split("\n\n")[0], argv)
    with tempfile.TemporaryDirectory() as tmp:
        fit_recording.recording(args, Path(tmp))
        frf, n_lags, dt = fitted_frf(args.recording)
    print(f"recording {args.recording}: {frf.f_Hz.size} bins {frf.f_Hz[0]:.4g}–{frf.f_Hz[-1]:.4g} Hz, "
          f"{n_lags} lag(s), {1 / dt:g} Hz samples")
    times: dict[str, dict[str, list[float]]] = {j: {"fit_mode_count": [], "fit_frf": []} for j in JACOBIANS}
    result: dict[str, Any] = {}
    for _ in range(args.reps):
        for j in JACOBIANS:
            f = copy.deepcopy(frf)
            t0 = time.perf_counter()
            n, x, rms = di.fit_mode_count(f, n_lags, dt, jac=j)
            times[j]["fit_mode_count"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            x1, rms1 = di.fit_frf(copy.deepcopy(frf), n, n_lags, dt, jac=j)
            times[j]["fit_frf"].append(time.perf_counter() - t0)
            result[j] = (n, x, rms, f.trials, x1, rms1)
    for what in ("fit_mode_count", "fit_frf"):
        a, b = (statistics.median(times[j][what]) for j in JACOBIANS)
        print(f"{what}: 2-point {a:.3f} s, analytic {b:.3f} s (medians of {args.reps}); ratio {a / b:.2f}×")
    for j in JACOBIANS:
        n, x, rms, trials, x1, rms1 = result[j]
        print(f"{j}: {n} mode(s) kept: {found(x, n, n_lags, rms)}")
        print(f"{j}:   trials: {'; '.join(trials)}")
        print(f"{j}:   fit_frf({n} modes) alone: {found(x1, n, n_lags, rms1)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
