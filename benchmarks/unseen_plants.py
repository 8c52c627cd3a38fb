"""The speed-ladder workflow on simulated scanners afmctl was never tuned on.

Per plant (x axis of a variant of the default scanner: other hysteresis, creep, amplifier
and structural modes, see :data:`PLANTS`) and recording, through the command line as a user
runs it:

1. the recording a position sensor would give of the plant: ``afmctl excite --kind all
   --rate-Hz 50000 --slew-V-per-s S`` (recording ``excite``), or what a lab records without
   afmctl's excitation (``user``, ``tests/plants.py: user_style_record``: nested triangles at 1 Hz, triangles at
   10 and 40 Hz, a 1 Hz → 2 kHz chirp around mid-range);
2. ``afmctl identify --model auto`` on that recording (the table it prints is kept);
3. 4 µm raster lines at 1, 4, 10 and 50 lines/s compensated by ``afmctl compensate --model
   auto.json --limits 0 150 --slew-V-per-s S --clip``, played through a fresh plant: max /
   RMS error over the central 80 % of every trace and retrace, % of the line.

    .venv/bin/python benchmarks/unseen_plants.py [--plants NAME ...] [--recordings excite user]
        [--rates 1 4 10 50] [--jobs 2] [--no-write]

Writes its section of docs/BENCHMARKS.md between ``<!-- bench:unseen_plants -->`` markers.
About 2 minutes per plant and recording. A figure marked † is slew-bound: the compensated
line needs the amplifier's whole slew rate, so no feedforward can follow it.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import speed_ladder as sl  # noqa: E402
from afmctl.data.datafiles import read_csv, write_csv  # noqa: E402
from afmctl.sim_backend.config import (AmplifierConfig, CreepConfig, DynamicsConfig,  # noqa: E402
                                       GaussianPreisachConfig, PreisachComponent, ScannerConfig)
from afmctl.sim_backend.scanner import Scanner, default_scanner_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

sys.path.insert(0, str(ROOT / "tests"))
from plants import user_style_record  # noqa: E402  (tests/plants.py: what a lab records)

NAME = "unseen_plants"


def _plant(hyst: GaussianPreisachConfig, creep: CreepConfig, amp: AmplifierConfig, modes: list[DynamicsConfig]
           ) -> ScannerConfig:
    cfg = default_scanner_config()
    cfg.x.hysteresis, cfg.x.creep, cfg.x.amplifier = hyst, creep, amp
    cfg.x.dynamics, cfg.x.extra_modes = modes[0], modes[1:]
    return cfg


def _gauss(linear: float, comps: list[tuple[float, float, float, float, float, float]]) -> GaussianPreisachConfig:
    return GaussianPreisachConfig(linear_nm_per_V=linear, components=[
        PreisachComponent(mass_nm=m, alpha_V=a, beta_V=b, sigma_alpha_V=sa, sigma_beta_V=sb, rho=r)
        for m, a, b, sa, sb, r in comps])


#: variant plants: name → (scanner config, description)
PLANTS = {
    "stiff": (_plant(_gauss(70.0, [(2500, 70, 40, 20, 20, 0.5), (1200, 120, 100, 15, 15, 0.6)]),
                     CreepConfig(fraction=0.06, tau_min_s=0.02, tau_max_s=50.0, n_lags=4),
                     AmplifierConfig(bandwidth_Hz=3000.0, slew_V_per_s=2.0e4),
                     [DynamicsConfig(resonance_Hz=1600.0, quality_factor=30.0)]),
              "narrower loop, 70 nm/V, creep 6 % (20 ms–50 s), 3 kHz amplifier, 1.6 kHz mode Q 30"),
    "soft": (_plant(_gauss(35.0, [(3000, 45, 10, 30, 15, 0.2), (2500, 100, 50, 30, 30, 0.3),
                                  (800, 140, 130, 10, 10, 0.8)]),
                    CreepConfig(fraction=0.03, tau_min_s=0.005, tau_max_s=200.0, n_lags=6),
                    AmplifierConfig(bandwidth_Hz=8000.0, slew_V_per_s=1.0e4),
                    [DynamicsConfig(resonance_Hz=700.0, quality_factor=15.0),
                     DynamicsConfig(resonance_Hz=2500.0, quality_factor=40.0)]),
             "wide loop (≈ 18 %), 35 nm/V, creep 3 % (5 ms–200 s), 8 kHz amplifier, modes 0.7 kHz Q 15 + 2.5 kHz Q 40"),
    "capacitive": (_plant(_gauss(45.0, [(2800, 85, 35, 35, 25, 0.4), (900, 125, 95, 12, 18, 0.7)]),
                          CreepConfig(fraction=0.04, tau_min_s=0.01, tau_max_s=100.0, n_lags=5),
                          AmplifierConfig(bandwidth_Hz=None, slew_V_per_s=2.0e4, load_capacitance_F=1.0e-6,
                                          output_resistance_ohm=120.0),
                          [DynamicsConfig(resonance_Hz=2200.0, quality_factor=60.0)]),
                   "smooth asymmetric loop, 45 nm/V, creep 4 % (10 ms–100 s), amplifier bandwidth set by the "
                   "piezo's capacitance (120 Ω × 1 µF: 1.3 kHz), one lightly damped mode 2.2 kHz Q 60 (#24)"),
    "rate-dependent": (_plant(default_scanner_config().x.hysteresis.model_copy(update={"rate_lag_s": 2e-4}),
                              CreepConfig(), AmplifierConfig(bandwidth_Hz=5000.0, slew_V_per_s=1.0e4),
                              [DynamicsConfig(resonance_Hz=1000.0, quality_factor=20.0)]),
                       "the default x axis with rate-dependent hysteresis (the Preisach part lags the "
                       "voltage by 0.2 ms: the loop 41 % wider at 100 Hz than at 1 Hz)"),
}


def play_x(cfg: ScannerConfig, u_V: np.ndarray, dt_s: float) -> np.ndarray:
    U = np.zeros((u_V.size, 3))
    U[:, 0] = u_V
    return Scanner(cfg).run(U, dt_s)[:, 0]


def raster_for(cfg: ScannerConfig, rate: float) -> tuple[np.ndarray, int, int, int]:
    """The speed ladder's raster scaled to this plant: 4 µm lines starting at a third of its
    0–150 V range."""
    lines = {1: 3, 4: 4, 10: 6, 16: 8, 50: 10}.get(int(rate), 4)
    span = float(np.ptp(play_x(cfg, np.linspace(0.0, 150.0, 20000), 1e-3)))
    tgt, start, n = sl.raster(rate, lines)
    x0 = span / 3.0
    out = tgt - sl.X0_NM + x0
    na = int(0.2 / sl.DT_S)                       # the approach from 0 nm (sl.raster)
    out[:na] = tgt[:na] * (x0 / sl.X0_NM)
    return out, start, n, lines


def recording(name: str, kind: str, cfg: ScannerConfig, slew: float, work: Path) -> Path:
    """The plant's recording of ``kind`` (``excite`` or ``user``) as a t,u,y CSV in ``work``."""
    if kind == "excite":
        exc = work / f"{name}_exc.csv"
        sl.cli("excite", "--kind", "all", "--u-min-V", "0", "--u-max-V", "150", "--rate-Hz", "50000",
               "--slew-V-per-s", f"{slew:g}", "--out", str(exc))
        u = read_csv(exc, ("t", "u"))["u"]
    else:
        u = user_style_record(slew)
    data = work / f"{name}_{kind}.csv"
    write_csv(data, {"t": np.arange(u.size) * 2e-5, "u": u, "y": play_x(cfg, u, 2e-5)})
    return data


def one_plant(name: str, cfg: ScannerConfig, rates: list[float], work: Path, params: tuple[str, ...] = (),
              kind: str = "excite") -> tuple[dict, str]:
    slew = cfg.x.amplifier.effective_slew_V_per_s() or 1e5
    data = recording(name, kind, cfg, slew, work)
    model = work / f"{name}_{kind}_auto.json"
    t0 = time.perf_counter()
    out = sl.cli("identify", "--model", "auto", "--data", str(data), "--out", str(model),
                 *[a for p in params for a in ("--param", p)])
    print(out[out.index("held-out prediction error"):out.index("selected ")], flush=True)
    ident_s = time.perf_counter() - t0
    selected = next(ln.split(":", 1)[1].strip() for ln in out.splitlines() if ln.startswith("selected"))
    row = {}
    for r in rates:
        tgt, start, n, lines = raster_for(cfg, r)
        target, volts = work / f"{name}_{kind}_target.csv", work / f"{name}_{kind}_volts.csv"
        write_csv(target, {"t": np.arange(tgt.size) * sl.DT_S, "y": tgt})
        slew_args = ("--slew-V-per-s", f"{slew:g}") if "dynamics" in selected else ()
        sl.cli("compensate", "--model", str(model), "--target", str(target), "--out", str(volts),
               "--limits", "0", "150", *slew_args, "--clip")
        u = read_csv(volts, ("t", "u"))["u"]
        row[r] = sl.line_error_pct(play_x(cfg, u, sl.DT_S), tgt, start, n, lines)
        row[r]["slew_bound"] = float(np.max(np.abs(np.diff(u[start:start + 2 * lines * n])))) / sl.DT_S >= 0.99 * slew
        print(f"{name} {kind} {r:g} lines/s: {row[r]['max_error_pct']:.2f} / {row[r]['rms_error_pct']:.2f} %"
              + (" (slew-bound)" if row[r]["slew_bound"] else ""), flush=True)
    row["found"] = found_parameters(model)
    return row, f"{selected} (identify {ident_s:.0f} s)"


def true_parameters(cfg: ScannerConfig) -> dict[str, str]:
    """The plant's x axis as the identified chain would state it: modes (Hz, ζ), the
    amplifier's lag [Hz], the creep's fraction."""
    ax = cfg.x
    modes = [ax.dynamics, *ax.extra_modes]
    lag = ax.amplifier.effective_bandwidth_Hz()
    return {"modes": ", ".join(f"{m.resonance_Hz:.4g} Hz ζ {0.5 / m.quality_factor:.2g}" for m in modes),
            "lag": f"{lag:.4g} Hz" if lag else "none", "creep": f"{ax.creep.fraction:.3g}"}


def found_parameters(model_path: Path) -> dict[str, str]:
    """The same figures read from an identified model file (a chain; "–" for a stage it
    has not)."""
    import json

    d = json.loads(model_path.read_text())
    out = {"modes": "–", "lag": "–", "creep": "–"}
    dyn = d.get("dynamics")
    if dyn:
        poles = [complex(re, im) for re, im in dyn["poles_rad_per_s"]]
        modes = sorted((abs(q) / (2 * np.pi), -q.real / abs(q)) for q in poles if q.imag > 0)
        lags = sorted(-q.real / (2 * np.pi) for q in poles if q.imag == 0)
        out["modes"] = ", ".join(f"{f:.4g} Hz ζ {z:.2g}" for f, z in modes) or "none"
        out["lag"] = ", ".join(f"{f:.4g} Hz" for f in lags) or "none"
        if dyn.get("delay_s"):
            out["lag"] += f" + {1e6 * float(dyn['delay_s']):.3g} µs"
    if d.get("creep"):
        out["creep"] = f"{sum(d['creep']['creep_weights']):.3g}"
    return out


def _cell(v: dict) -> str:
    return f"{v['max_error_pct']:.2f} / {v['rms_error_pct']:.2f}" + (" †" if v.get("slew_bound") else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plants", nargs="+", choices=sorted(PLANTS), default=sorted(PLANTS))
    ap.add_argument("--recordings", nargs="+", choices=["excite", "user"], default=["excite", "user"])
    ap.add_argument("--rates", type=float, nargs="+", default=[1, 4, 10, 50], help="line rates [lines/s]")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    ap.add_argument("--jobs", type=int, default=1, help="plants and recordings run in parallel (processes)")
    ap.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                    help="passed to identify, e.g. 'dynamics_options={\"from\": \"static\"}'")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    jobs = [(name, kind) for name in args.plants for kind in args.recordings]
    with tempfile.TemporaryDirectory(prefix="unseen-") as tmp, ProcessPoolExecutor(max(1, args.jobs)) as pool:
        futures = {job: pool.submit(one_plant, job[0], PLANTS[job[0]][0], args.rates, Path(tmp), tuple(args.param),
                                    job[1]) for job in jobs}
        rows = {job: futures[job].result() for job in jobs}
    head = ("| plant | recording | selected by `auto` | " + " | ".join(f"{r:g} lines/s" for r in args.rates)
            + " |\n|---|---|---|" + "---|" * len(args.rates) + "\n")
    body = "".join(f"| {n} | {k} | {sel} | " + " | ".join(_cell(v[r]) for r in args.rates) + " |\n"
                   for (n, k), (v, sel) in rows.items())
    tab = head + body
    ptab = ("\n| plant | recording | modes: true → found | amplifier lag: true → found | creep fraction: true → found |"
            "\n|---|---|---|---|---|\n")
    for (n, k), (v, _) in rows.items():
        tp, fp = true_parameters(PLANTS[n][0]), v["found"]
        ptab += f"| {n} | {k} | " + " | ".join(f"{tp[q]} → {fp[q]}" for q in ("modes", "lag", "creep")) + " |\n"
    tab += ptab
    print(tab)
    if not args.no_write:
        plants = "".join(f"- `{n}`: {PLANTS[n][1]}\n" for n in args.plants)
        write_section(NAME, "## The speed-ladder workflow on plants afmctl was not tuned on\n\n"
                      f"`.venv/bin/python benchmarks/unseen_plants.py{f' --jobs {args.jobs}' if args.jobs > 1 else ''}` "
                      f"({time.perf_counter() - t0:.0f} s). "
                      "Variants of the default scanner's x axis; per plant and recording, through the CLI: the "
                      "recording (`excite`: `excite --kind all` at 50 kHz; `user`: nested 1 Hz triangles, "
                      "triangles at 10 and 40 Hz, a 1 Hz → 2 kHz chirp, no afmctl excitation) → the plant → "
                      "`identify --model auto` → `compensate --limits 0 150 --slew-V-per-s S --clip` → the "
                      "plant. 4 µm lines from a third of the plant's range; max / RMS error over the central "
                      "80 % of every trace and retrace, % of the line; † slew-bound (the compensated line uses "
                      "the amplifier's whole slew rate). The second table: what the selected model states "
                      "against the plant's true figures (– : the model has no such stage).\n\n" + plants + "\n" + tab)
    return 0


if __name__ == "__main__":
    sys.exit(main())
