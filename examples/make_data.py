"""Make measurement-like CSV files from the simulated scanner, for trying the offline
commands without hardware.

    .venv/bin/python examples/make_data.py OUTDIR

writes into OUTDIR:

* ``x_excitation.csv`` — columns ``t,u,y`` (s, V, nm): a decaying 0.5 Hz triangle on the
  x axis of the default simulated scanner (asymmetric Preisach hysteresis, creep,
  resonance), sampled at 1 kHz, with the x position a sensor would read. Feed it to
  ``afmctl identify``.
* ``target.csv`` — columns ``t,y`` (s, nm): a 1 Hz triangle over 10…90 % of the x range,
  the trajectory you want. Feed it to ``afmctl compensate``.

``--check VOLTS.csv`` runs the voltages that ``afmctl compensate`` wrote through the same
simulated scanner and prints the tracking error.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from afmctl.data.datafiles import read_csv, write_csv
from afmctl.sim_backend.scanner import Scanner, default_scanner_config

DT_S = 1e-3          # sample period of the files [s]
SUB = 10             # the plant is simulated at 10 kHz and averaged to 1 kHz
SETTLE_S = 0.5       # --check ignores the start-up transient before this time [s]


def _simulate_x(u_V: np.ndarray) -> np.ndarray:
    """x position [nm] of the default scanner for x voltages u_V [V] at DT_S (y, z at 0 V)."""
    scanner = Scanner(default_scanner_config())
    u = np.zeros((u_V.shape[0] * SUB, 3))
    u[:, 0] = np.repeat(u_V, SUB)
    pos = scanner.run(u, dt_s=DT_S / SUB)
    return pos[:, 0].reshape(-1, SUB).mean(axis=1)


def _triangle(t_s: np.ndarray, f_Hz: float) -> np.ndarray:
    """Unit triangle 0 → 1 → 0 with frequency f_Hz."""
    ph = (t_s * f_Hz) % 1.0
    return np.where(ph < 0.5, 2 * ph, 2 - 2 * ph)


def make(outdir: Path) -> None:
    outdir.mkdir(parents=True, exist_ok=True)
    t = np.arange(int(16 / DT_S)) * DT_S
    amp = 150.0 * np.clip(1.0 - np.floor(t * 0.5) / 8.0, 0.1, 1.0)      # 150 V, then decaying
    u = amp * _triangle(t, 0.5)
    y = _simulate_x(u)
    write_csv(outdir / "x_excitation.csv", {"t": t, "u": u, "y": y})
    lo, hi = float(y.min()), float(y.max())
    tt = np.arange(int(3 / DT_S)) * DT_S
    target = lo + (hi - lo) * (0.1 + 0.8 * _triangle(tt, 1.0))
    write_csv(outdir / "target.csv", {"t": tt, "y": target})
    print(f"wrote {outdir / 'x_excitation.csv'} and {outdir / 'target.csv'} "
          f"(x range {lo:.0f}…{hi:.0f} nm)")


def check(volts_csv: Path, target_csv: Path) -> float:
    """Run compensated voltages through the scanner; print and return max |error| [% range]."""
    v = read_csv(volts_csv, ["t", "u"])
    tg = read_csv(target_csv, ["t", "y"])
    y = _simulate_x(v["u"])
    rng = float(np.ptp(tg["y"])) / 0.8
    settled = v["t"] >= SETTLE_S       # the first sample jumps from 0 V: let the mode ring out
    err = 100.0 * np.abs(y - tg["y"])[settled] / rng
    print(f"tracking error after {SETTLE_S:g} s: max {err.max():.2f} %, "
          f"rms {np.sqrt(np.mean(err**2)):.2f} % of range")
    return float(err.max())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("outdir", type=Path)
    p.add_argument("--check", type=Path, metavar="VOLTS.csv",
                   help="instead: simulate VOLTS.csv (t,u) and compare with OUTDIR/target.csv")
    a = p.parse_args(argv)
    if a.check:
        check(a.check, a.outdir / "target.csv")
    else:
        make(a.outdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
