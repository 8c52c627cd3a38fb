"""Learning on the simulated devices: ``afmctl learn --config`` on the simulated E-727 (GCS
wave table + data recorder), the simulated NV200 (waveform buffer + recorder, a sensored
unit) and the CAN amplifier (FIFO + recorder), the default simulated scanner with its
position sensor, then ``afmctl run`` playing the learned table.

Per device and raster (4 µm lines at 50 lines/s, 1 µm at 100 and 200 lines/s), through the
command line as a user runs it: the progress lines of ``afmctl learn`` (error of each table
measured by the device's recorder, max over the central 80 % of each line, % of the line),
the best iteration, the wall time per iteration (upload + play + read-back + learning), and
the error of the learned table when ``afmctl run`` has played it (exit 0) and the controller
plays it again with the device's recorder armed (the same sensor that learning used).
The configurations leave ``amplifier.settle_s`` unset, as a user would: learning holds 2 s
before each play, and ``afmctl run`` plays the learned table after the same hold.

    .venv/bin/python benchmarks/learn_devices.py --model MODEL.json [--devices gcs can nv200]
        [--rates 50 100 200] [--iterations 10] [--work DIR] [--no-write]

``MODEL.json``: a scanner model of the default simulated scanner (``afmctl demo --only
preisach+creep+dynamics`` writes ``demo-out/models/scanner_preisach+creep+dynamics.json``);
``--model none`` learns from the linear calibration. Writes its section of
docs/BENCHMARKS.md between ``<!-- bench:learn_devices -->`` markers.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.compensators.learning_weights import judged_max_pct  # noqa: E402
from afmctl.config import load_config  # noqa: E402
from afmctl.errors import AfmctlError  # noqa: E402
from afmctl.control.learn_run import play_recorded  # noqa: E402
from afmctl.control.learned_table import LearnedSource  # noqa: E402
from afmctl.simulation.link import simulated_amplifier  # noqa: E402
from sections import write_section  # noqa: E402

NAME = "learn_devices"
#: (line width [nm], lines) per line rate [lines/s]
RASTERS = {50: (4000.0, 4), 100: (1000.0, 4), 200: (1000.0, 4)}
#: loop rate per device [Hz] (the NV200's 1024-sample buffer holds the 4-line tables with a
#: shortened preview padding: afmctl.control.wave_plan.plan_table's max_rows)
RATES_HZ = {"gcs": 10000, "can": 10000, "nv200": 10000}
#: a progress line: iteration, x's max error over the central 80 % of the lines [nm] and [% of the line]
LINE = re.compile(r"afmctl: learn +(\d+): x max ([\d.e+-]+) nm \(([\d.e+-]+) %\)")

CONFIG = """
[scanner]
name = "learn-bench"
axes = {axes}
[amplifier]
driver = "{driver}"
output = "wave"
slew_V_per_s = 100000.0
[loop]
rate_Hz = {rate}
[safety]
slew_V_per_s = 100000.0
ramp_V_per_s = 5000.0
{compensation}
[trajectory]
{trajectory}
[runlog]
dir = "{dir}"
fsync = false
[simulation]
enabled = true
baud = 921600
{device}
"""


def config_text(driver: str, line_rate: int, model: str | None, work: Path, trajectory: str | None = None) -> str:
    width, lines = RASTERS[line_rate]
    raster = (f'kind = "raster"\nx0_nm = {6000.0 - width / 2:g}\ny0_nm = 3000.0\nwidth_nm = {width:g}\n'
              f'height_nm = 0.0\nlines = {lines}\nline_rate_Hz = {line_rate:g}')
    comp = f'[compensation]\nscanner_model = "{model}"' if model else ""
    device = '[simulation.device]\nsensor = "strain gauge"\nposmax_um = 12.0' if driver == "nv200" else ""
    axes = '["x"]' if driver == "nv200" else '["x", "y", "z"]'
    return CONFIG.format(axes=axes, driver=driver, rate=RATES_HZ[driver], compensation=comp,
                         trajectory=trajectory or raster, dir=work, device=device)


def afmctl(*args: str, timeout: float = 1800.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "afmctl", *args], capture_output=True, text=True, timeout=timeout)


def played_error(run_toml: Path, table_file: Path) -> float:
    """Central max [% of the line] of the learned table as ``afmctl run`` plays it, measured
    by the device's recorder (:func:`afmctl.control.learn_run.play_recorded`)."""
    config = load_config(run_toml)
    learned = LearnedSource.from_file(table_file)
    with simulated_amplifier(config) as (amp, _scanner):
        y = play_recorded(config, amp, learned, ["x"])["x"]
    return judged_max_pct(y, learned.learned.table.target_nm[:, 0])


def one(driver: str, line_rate: int, model: str | None, iterations: int, work: Path) -> dict:
    d = work / f"{driver}-{line_rate}"
    d.mkdir(parents=True, exist_ok=True)
    (d / "learn.toml").write_text(config_text(driver, line_rate, model, d))
    t0 = time.perf_counter()
    res = afmctl("learn", "--config", str(d / "learn.toml"), "--iterations", str(iterations),
                 "--out", str(d / "L.afmwave"))
    wall = time.perf_counter() - t0
    its = [(int(m[1]), float(m[3])) for m in LINE.finditer(res.stderr)]
    row = {"device": driver, "lines_per_s": line_rate, "exit": res.returncode, "iterations": len(its),
           "first_pct": its[0][1] if its else None, "s_per_iteration": wall / max(len(its), 1)}
    if res.returncode != 0 or not its:
        row["error"] = res.stderr.strip().splitlines()[-1][:200] if res.stderr.strip() else "?"
        return row
    best_it, best = min(its, key=lambda x: x[1])
    row.update(best_pct=best, best_iteration=best_it,
               reached=next((i for i, c in its if c <= (0.5 if line_rate >= 200 else 0.2)), None))
    (d / "run.toml").write_text(config_text(driver, line_rate, model, d,
                                            f'kind = "learned"\nfile = "{d / "L.afmwave"}"'))
    run = afmctl("run", "--config", str(d / "run.toml"), "--log", str(d / "run.afmlog"), "--quiet")
    row["run_exit"] = run.returncode
    if run.returncode == 0:
        try:
            row["run_pct"] = played_error(d / "run.toml", d / "L.afmwave")
        except AfmctlError as err:            # a link fault of the check's own play: said in the row
            row["run_exit"], row["error"] = 1, str(err)[:200]
    return row


def table_md(rows: list[dict], model: str | None, command: str) -> str:
    out = ["## Learning on the simulated devices (`afmctl learn --config`, #25)", "",
           f"`{command}`, model: {Path(model).name if model else 'none (linear calibration)'}; error = max over the "
           "central 80 % of each line, % of the line; 'recorded' = the device's recorder (sensor noise 0.2 nm "
           "RMS), 'run' = the learned table played again as `afmctl run` plays it, recorded the same way.", "",
           "| device | lines/s | first [%] | best [%] (iteration) | at goal by iteration | run [%] | s / iteration |",
           "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "best_pct" not in r:
            out.append(f"| {r['device']} | {r['lines_per_s']} | – | failed: {r.get('error', '?')} | | | |")
            continue
        run = f"{r['run_pct']:.2f}" if "run_pct" in r else f"exit {r['run_exit']}"
        out.append(f"| {r['device']} | {r['lines_per_s']} | {r['first_pct']:.2f} | {r['best_pct']:.2f} "
                   f"({r['best_iteration']}) | {r['reached'] if r['reached'] is not None else '—'} | {run} | "
                   f"{r['s_per_iteration']:.1f} |")
    return "\n".join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, help="scanner model JSON, or 'none'")
    ap.add_argument("--devices", nargs="+", default=["gcs", "can", "nv200"], choices=sorted(RATES_HZ))
    ap.add_argument("--rates", nargs="+", type=int, default=[50, 100, 200], choices=sorted(RASTERS))
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--work", type=Path, default=Path("/tmp/afmctl-learn-devices"))
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    model = None if args.model == "none" else str(Path(args.model).resolve())
    rows = []
    for driver in args.devices:
        for rate in args.rates:
            row = one(driver, rate, model, args.iterations, args.work)
            print(json.dumps(row), flush=True)
            rows.append(row)
    text = table_md(rows, model, "benchmarks/learn_devices.py " + " ".join(sys.argv[1:]))
    print(text)
    if not args.no_write:
        write_section(NAME, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
