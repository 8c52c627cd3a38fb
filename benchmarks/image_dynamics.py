"""Sensorless chains: preisach[+creep]+dynamics identified from grating images (slow
scans and scans at several line rates) vs the same chains identified with a position
sensor.

On the default simulated scanner (x axis):

* **images** — slow grating scans (15 ranges at 1 line/s, :func:`scan_grating_lines`) for
  the Preisach stage (and the creep stage, :mod:`afmctl.compensators.image_creep`), and
  scans at 10…100 lines/s (:func:`scan_grating_rates`) for the dynamics
  (:mod:`afmctl.compensators.image_dynamics`); no sensor;
* **sensor** — the demo's quick static + creep excitation (1 kHz sensor) for the Preisach
  (and creep) stage and its small-signal multisine at 10 kHz for the dynamics (what
  ``afmctl identify`` fits), preisach+dynamics and preisach+creep+dynamics.

Each chain compensates 4 µm raster lines offline (:func:`afmctl.reports.speed_ladder.offline_errors_nm`,
the chain's offline inverse within 0…150 V); the table gives the x error over the central
80 % of every trace and retrace, % of the line.

    .venv/bin/python benchmarks/image_dynamics.py [--rates 1 4 16 50] [--no-write]

Writes its section of docs/BENCHMARKS.md between ``<!-- bench:image_dynamics -->`` markers.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.sim_backend.scanner import Scanner, ScannerConfig, default_scanner_config  # noqa: E402

#: the true mode of the default scanner's x axis: 1 kHz, Q 20
TRUE_MODE = (1000.0, 1.0 / (2 * 20.0))


def image_chain(cfg: ScannerConfig, creep: bool = False) -> Any:
    """preisach[+creep]+dynamics from simulated grating images only (x axis)."""
    from afmctl.compensators.image_chain import identify_from_rate_scans
    from afmctl.sim_backend.image_scans import scan_grating_lines
    from afmctl.sim_backend.rate_scans import scan_grating_rates
    sc = Scanner(cfg)
    slow = scan_grating_lines(sc, lines_per_range=4, keep_truth=False)
    sc.reset()
    fast = scan_grating_rates(sc, keep_truth=False)
    structure = "preisach+creep+dynamics" if creep else "preisach+dynamics"
    return identify_from_rate_scans([slow.arrays(), fast.arrays()], structure, n_operators=15)


def sensor_chain(cfg: ScannerConfig, creep: bool = False) -> Any:
    """preisach[+creep]+dynamics from position-sensor recordings: the demo's quick static
    and creep excitation (a 1 kHz sensor) for the static stages, its small-signal
    multisine at 10 kHz for the dynamics."""
    from afmctl.compensators.chain import ChainModel
    from afmctl.compensators.models import model_class
    from afmctl.reports.demo import EXCITE_DECIMATE, EXCITE_SIM_DT_S, excitation_voltage
    from afmctl.data.excitation import ExcitationSpec, excitation
    dt, m = EXCITE_SIM_DT_S, EXCITE_DECIMATE
    u1 = excitation_voltage(dt * m, True)
    u = np.zeros((u1.size * m, 3))
    u[:, 0] = np.repeat(u1, m)
    y = Scanner(cfg).run(u, dt).reshape(u1.size, m, 3).mean(axis=1)[:, 0]
    ud = excitation("dynamics", ExcitationSpec(u_min_V=0.0, u_max_V=150.0, rate_Hz=1.0 / dt, periods=4))
    v = np.zeros((ud.size, 3))
    v[:, 0] = ud
    yd = Scanner(cfg).run(v, dt)[:, 0]
    t1 = np.arange(u1.size) * dt * m
    if creep:
        static = ChainModel.identify(t1, u1, y, structure="preisach+creep")
        hyst, creep_stage = static.hysteresis, static.creep
    else:
        static = hyst = model_class("preisach").identify(t1, u1, y)
        creep_stage = None
    x = static.forward(dt).block(np.ascontiguousarray(ud))
    dynamics = model_class("dynamics").identify(np.arange(ud.size) * dt, x, yd)
    return ChainModel(hysteresis=hyst, creep=creep_stage, dynamics=dynamics)


def x_errors_pct(cfg: ScannerConfig, chain: Any, rate_Hz: float) -> dict[str, float]:
    """Max / RMS x error [% of the 4 µm line] of raster lines at ``rate_Hz`` compensated
    offline by ``chain`` on x (y: the linear calibration)."""
    from afmctl.reports.speed_ladder import error_pct, offline_errors_nm

    def make(dt: float):
        lo, gain = Scanner(cfg).voltage_limits_V()[:, 0], Scanner(cfg).nominal_gain_nm_per_V()

        def volts(targets: np.ndarray) -> np.ndarray:
            u = lo + targets / gain
            u[:, 0] = chain.inverse_within_limits(np.ascontiguousarray(targets[:, 0]), dt, 0.0, 150.0).u_V
            return u
        return volts
    return error_pct(offline_errors_nm(lambda: Scanner(cfg), make, rate_Hz)[:, 0])


def mode_of(chain: Any) -> tuple[float, float]:
    """(f [Hz], ζ) of the chain's mode nearest the true one."""
    p = [q for q in chain.dynamics.poles() if q.imag > 0]
    q = min(p, key=lambda z: abs(abs(z) / (2 * np.pi) - TRUE_MODE[0]))
    return float(abs(q) / (2 * np.pi)), float(-q.real / abs(q))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 4.0, 16.0, 50.0])
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args(argv)
    cfg = default_scanner_config()
    rows = []
    for name, build in (("images, preisach+dynamics (no sensor)", image_chain),
                        ("images, preisach+creep+dynamics (no sensor)", lambda c: image_chain(c, creep=True)),
                        ("sensor, preisach+dynamics", sensor_chain),
                        ("sensor, preisach+creep+dynamics", lambda c: sensor_chain(c, creep=True))):
        t0 = time.perf_counter()
        chain = build(cfg)
        took = time.perf_counter() - t0
        f, z = mode_of(chain)
        errs = {r: x_errors_pct(cfg, chain, r) for r in a.rates}
        rows.append((name, f, z, took, errs))
        print(name, f"mode {f:.1f} Hz ζ {z:.4f}", f"{took:.1f} s", errs, flush=True)
    head = "| chain identified from | mode found | " + " | ".join(
        f"{r:g} lines/s max / RMS %" for r in a.rates) + " |"
    lines = [head, "|" + "---|" * (2 + len(a.rates))]
    for name, f, z, took, errs in rows:
        lines.append(f"| {name} | {f:.1f} Hz, ζ {z:.4f} | " + " | ".join(
            f"{errs[r]['max_error_pct']:.2f} / {errs[r]['rms_error_pct']:.2f}" for r in a.rates) + " |")
    body = ("Default simulated scanner, x axis (true mode 1000 Hz, ζ 0.025; amplifier 5 kHz), 4 µm raster "
            "lines compensated offline, error over the central 80 % of each line, % of the line. "
            "Reproduce: `.venv/bin/python benchmarks/image_dynamics.py`.\n\n" + "\n".join(lines) + "\n")
    print(body)
    if not a.no_write:
        from sections import write_section
        write_section("image_dynamics", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
