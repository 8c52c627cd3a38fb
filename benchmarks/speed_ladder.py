"""Speed ladder: raster accuracy at 1, 4, 16 and 50 lines/s on the default simulated scanner.

The workflow a user runs, through the command line (in-process ``afmctl.cli.main``):

1. ``afmctl excite --kind all --rate-Hz 50000`` (major loop and reversal curves, a creep
   staircase, a small-signal multisine; 54 s), played through the default simulated
   scanner's x axis (the recording a position sensor would give; the simulator has no CLI
   verb for offline playback);
2. on that one recording: ``afmctl identify --model preisach``, ``--model dynamics`` and
   ``--model preisach+creep+dynamics`` (the chain; its static stages alone, the chain
   without its dynamics stage, are the ``preisach+creep`` row — ``identify --model
   preisach+creep`` fits exactly those);
3. 4 µm raster lines (x from 4 to 8 µm, trace and retrace, after a smooth approach and a
   0.3 s rest) sampled at 100 kHz, compensated by ``afmctl compensate`` with
   ``--model pre.json`` (static) and with ``--dynamics dyn.json --limits 0 150
   --slew-V-per-s 10000`` (the amplifier's limits);
4. the voltages run through a fresh default scanner; the error of the true x position is
   taken over the central 80 % of every trace and retrace, in % of the 4 µm line.

Rows: ``none`` (nominal gain), ``preisach``, ``preisach+dynamics`` (``--dynamics``),
``preisach+creep`` and ``preisach+creep+dynamics`` (the chain files through
``afmctl compensate``, same limits: the chain's one offline inverse). Writes its section of
docs/BENCHMARKS.md between ``<!-- bench:speed_ladder -->`` markers and the table as JSON.

    .venv/bin/python benchmarks/speed_ladder.py [--rates 1 4 16 50] [--no-write] [--json OUT.json]

Takes about 3–4 minutes (the 2.7 M-row recording, three identifications, 100 kHz CSV files).
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.cli import main as afmctl  # noqa: E402
from afmctl.compensators.chain import ChainModel  # noqa: E402
from afmctl.compensators.models import load_model, save_model  # noqa: E402
from afmctl.data.datafiles import read_csv, write_csv  # noqa: E402
from afmctl.sim_backend.scanner import Scanner, default_scanner_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "speed_ladder"
DT_S = 1e-5                 # raster sample period [s]
X0_NM, WIDTH_NM = 4000.0, 4000.0
LIMITS_V = (0.0, 150.0)
SLEW_V_PER_S = 1.0e4        # the default scanner's amplifier
LINES = {1: 3, 4: 4, 16: 8, 50: 10}


def cli(*args: str) -> str:
    """Run ``afmctl ARGS`` in this process; its printed output; exit status must be 0."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = afmctl(list(args))
    if rc != 0:
        raise SystemExit(f"afmctl {' '.join(args)} exited {rc}:\n{buf.getvalue()}")
    return buf.getvalue()


def play_x(u_V: np.ndarray, dt_s: float) -> np.ndarray:
    """True x position [nm] of a fresh default scanner for x voltages ``u_V`` (y, z at 0 V)."""
    s = Scanner(default_scanner_config())
    U = np.zeros((u_V.size, 3))
    U[:, 0] = u_V
    return s.run(U, dt_s)[:, 0]


def record(kind: str, rate_Hz: float, work: Path) -> Path:
    """``afmctl excite`` → simulator → data CSV with columns t,u,y."""
    exc = work / f"exc_{kind}.csv"
    cli("excite", "--kind", kind, "--u-min-V", "0", "--u-max-V", "150", "--rate-Hz", f"{rate_Hz:g}",
        "--slew-V-per-s", f"{SLEW_V_PER_S:g}", "--out", str(exc))
    d = read_csv(exc, ("t", "u"))
    out = work / f"data_{kind}.csv"
    write_csv(out, {"t": d["t"], "u": d["u"], "y": play_x(d["u"], 1.0 / rate_Hz)})
    return out


def identify(work: Path) -> dict[str, Path]:
    data = record("all", 50_000, work)
    paths = {k: work / f"{k}.json" for k in ("pre", "dyn", "chain", "chain_dyn")}
    cli("identify", "--model", "preisach", "--data", str(data), "--out", str(paths["pre"]),
        "--param", "u_min_V=0", "--param", "u_max_V=150")
    print(cli("identify", "--model", "dynamics", "--data", str(data), "--out", str(paths["dyn"])))
    print(cli("identify", "--model", "preisach+creep+dynamics", "--data", str(data), "--out",
              str(paths["chain_dyn"]), "--param", "u_min_V=0", "--param", "u_max_V=150"))
    full = load_model(paths["chain_dyn"])
    save_model(ChainModel(hysteresis=full.hysteresis, creep=full.creep), paths["chain"])
    return paths


def raster(rate_Hz: float, lines: int) -> tuple[np.ndarray, int, int]:
    """x target [nm] at DT_S: approach, rest, ``lines`` trace+retrace lines, rest;
    returns (target, index of the first line, samples per half line)."""
    n = int(round(0.5 / rate_Hz / DT_S))
    ramp = np.arange(n) / n
    line = np.concatenate([X0_NM + WIDTH_NM * ramp, X0_NM + WIDTH_NM * (1 - ramp)])
    na = int(0.2 / DT_S)
    approach = X0_NM * (0.5 - 0.5 * np.cos(np.pi * np.arange(na) / na))
    rest = np.full(int(0.3 / DT_S), X0_NM)
    tgt = np.concatenate([approach, rest, np.tile(line, lines), np.full(int(0.05 / DT_S), X0_NM)])
    return tgt, approach.size + rest.size, n


def line_error_pct(y: np.ndarray, tgt: np.ndarray, start: int, n: int, lines: int) -> dict[str, float]:
    """Max and RMS error over the central 80 % of every half line, % of the line width."""
    e = np.concatenate([(y - tgt)[a + n // 10: a + n - n // 10] for a in start + n * np.arange(2 * lines)])
    e = 100.0 * e / WIDTH_NM
    return {"max_error_pct": float(np.max(np.abs(e))), "rms_error_pct": float(np.sqrt(np.mean(e * e)))}


def ladder_rate(rate_Hz: float, paths: dict[str, Path], work: Path) -> dict[str, dict[str, float]]:
    lines = LINES.get(int(rate_Hz), 4)
    tgt, start, n = raster(rate_Hz, lines)
    t = np.arange(tgt.size) * DT_S
    target_csv, volts = work / f"target_{rate_Hz:g}.csv", work / f"volts_{rate_Hz:g}.csv"
    write_csv(target_csv, {"t": t, "y": tgt})
    gain = float(Scanner(default_scanner_config()).nominal_gain_nm_per_V()[0])
    row = {"none": line_error_pct(play_x(tgt / gain, DT_S), tgt, start, n, lines)}
    cli("compensate", "--model", str(paths["pre"]), "--target", str(target_csv), "--out", str(volts))
    row["preisach"] = line_error_pct(play_x(read_csv(volts, ("t", "u"))["u"], DT_S), tgt, start, n, lines)
    out = cli("compensate", "--model", str(paths["pre"]), "--dynamics", str(paths["dyn"]), "--target",
              str(target_csv), "--out", str(volts), "--limits", *map(str, LIMITS_V),
              "--slew-V-per-s", f"{SLEW_V_PER_S:g}", "--clip")
    row["preisach+dynamics"] = line_error_pct(play_x(read_csv(volts, ("t", "u"))["u"], DT_S), tgt, start, n, lines)
    row["preisach+dynamics"]["note"] = out.strip().splitlines()[0]
    for label, model in (("preisach+creep", paths["chain"]), ("preisach+creep+dynamics", paths["chain_dyn"])):
        extra = ("--slew-V-per-s", f"{SLEW_V_PER_S:g}", "--clip") if label.endswith("dynamics") else ()
        out = cli("compensate", "--model", str(model), "--target", str(target_csv), "--out", str(volts),
                  "--limits", *map(str, LIMITS_V), *extra)
        row[label] = line_error_pct(play_x(read_csv(volts, ("t", "u"))["u"], DT_S), tgt, start, n, lines)
        if extra:
            row[label]["note"] = next(ln for ln in out.splitlines() if ln.startswith("dynamics"))
    return row


def table(results: dict[float, dict[str, dict[str, float]]]) -> str:
    comps = list(next(iter(results.values())))
    head = "| lines/s | " + " | ".join(comps) + " |\n|---|" + "---|" * len(comps) + "\n"
    rows = "".join(f"| {r:g} | " + " | ".join(f"{v[c]['max_error_pct']:.2f} / {v[c]['rms_error_pct']:.2f}"
                                               for c in comps) + " |\n" for r, v in results.items())
    return head + rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rates", type=float, nargs="+", default=[1, 4, 16, 50], help="line rates [lines/s]")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    ap.add_argument("--json", type=Path, help="also write the results as JSON")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ladder-") as tmp:
        work = Path(tmp)
        paths = identify(work)
        results = {}
        for r in args.rates:
            results[r] = ladder_rate(r, paths, work)
            print(f"{r:g} lines/s: " + ", ".join(f"{c} {v['max_error_pct']:.2f}/{v['rms_error_pct']:.2f} %"
                                                for c, v in results[r].items()), flush=True)
            for c, v in results[r].items():
                if "note" in v:
                    print(f"    {c}: {v['note']}")
    tab = table(results)
    print(tab)
    if args.json:
        args.json.write_text(json.dumps({f"{r:g}": v for r, v in results.items()}, indent=2), encoding="utf-8")
    if not args.no_write:
        body = ("## Speed ladder (raster accuracy vs line rate, offline)\n\n"
                "`.venv/bin/python benchmarks/speed_ladder.py` "
                f"({time.perf_counter() - t0:.0f} s). Default simulated scanner, x axis, 4 µm lines "
                "(4–8 µm), 100 kHz samples; max / RMS error over the central 80 % of every trace and "
                "retrace, % of the line. Workflow through the CLI (`excite --kind all` at 50 kHz → "
                "simulator → identify → compensate; the `+creep` rows are chain model files: "
                "`identify --model preisach+creep+dynamics` and its static stages). Amplifier limits "
                f"{LIMITS_V[0]:g}–{LIMITS_V[1]:g} V, {SLEW_V_PER_S:g} V/s.\n\n" + tab)
        write_section(NAME, body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
