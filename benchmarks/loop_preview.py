"""Speed ladder through ``afmctl run``: the controller with the preview horizon.

What a user meets: the demo's scanner model files (``afmctl demo --only KIND``: models
identified on the default simulated scanner, per-axis chains + x/y coupling) loaded by
``afmctl run`` (``[compensation] scanner_model``, a separate process, the real CLI) that
scans 4 µm raster lines (trace and retrace) on the simulated scanner behind the CAN
amplifier on python-can's virtual bus (hardware in the loop). With a dynamics stage the
controller reads the trajectory ``latency_s`` ahead. The run log's voltages are replayed
through the simulated scanner (:func:`afmctl.reports.speed_ladder.runlog_errors_nm`): error of x
and y over the central 80 % of each line after the first, % of the line.

Beside each figure: the loop's p99 lateness and missed deadlines (a shared machine: the
replay holds every voltage one loop period, so lateness shows here, not in the error), the
samples the safety layer slew-limited or clamped, and the preview latency.

    .venv/bin/python benchmarks/loop_preview.py [--loop-rates 5000 10000] [--rates 1 4 16]
        [--outputs setpoints stream wave-can wave-gcs] [--models DEMO_OUT/models] [--no-write] [--json OUT.json]

Outputs: ``setpoints`` (one per loop tick, the host's timing), ``stream`` (the live
producer into the CAN FD FIFO), ``wave-can`` (``output = "wave"``: the whole trajectory
computed before the run, played from the CAN FD FIFO), ``wave-gcs`` (the same table
uploaded to the simulated E-727 on a pty at 921600 baud and played by its wave generator
on the 50 µs servo clock).

Without ``--models`` it first runs ``afmctl demo --only preisach+creep+dynamics`` (≈ 1 min).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.reports import speed_ladder as sl  # noqa: E402
from afmctl.config import load_config  # noqa: E402
from afmctl.sim_backend.scanner import DriftConfig, Scanner, default_scanner_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "loop_preview"
KINDS = ("preisach+creep", "preisach+creep+dynamics")
LINES = {1.0: 3, 4.0: 4, 16.0: 8, 50.0: 12}
AFMCTL = [sys.executable, "-m", "afmctl"]


def demo_models(work: Path) -> Path:
    """Model files from ``afmctl demo`` (identification on the default scanner)."""
    out = work / "demo"
    cmd = AFMCTL + ["demo", "--out", str(out), "--size", "32", "--no-progress"]
    for k in KINDS:
        cmd += ["--only", k]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out / "models"


#: ``[amplifier]`` keys per output
OUTPUT_TOML = {"setpoints": "", "stream": sl.STREAM_FD_TOML, "wave-can": sl.WAVE_FD_TOML, "wave-gcs": 'output = "wave"\n'}


def run_cell(work: Path, scanner_json: Path, model: Path, rate: float, loop_Hz: float,
             gain: list[float], output: str = "setpoints") -> dict:
    """One ``afmctl run`` of raster lines; its error and loop figures."""
    tag = f"{model.stem}-{rate:g}-{loop_Hz:g}-{output}"
    channel = f"afmctl-bench-{tag}-{os.getpid()}"
    text = sl._config_text(work, scanner_json, model, rate, loop_Hz, LINES.get(rate, 3), channel, gain,
                           OUTPUT_TOML[output])
    if output == "wave-gcs":     # the simulated E-727 on a pty instead of the CAN amplifier
        text = text.replace('driver = "can"', 'driver = "gcs"').replace(f'port = "virtual:{channel}"', 'port = ""')
        text = text.replace("[simulation]\nenabled = true", "[simulation]\nenabled = true\nbaud = 921600")
    cfg_path = work / f"{tag}.toml"
    cfg_path.write_text(text, encoding="utf-8")
    log = work / f"{tag}.afmlog"
    res = subprocess.run(AFMCTL + ["run", "--config", str(cfg_path), "--log", str(log), "--json", "--quiet"],
                         capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        return {"error": (res.stderr.strip().splitlines() or ["?"])[-1], "rc": res.returncode}
    summary = json.loads(res.stdout)
    err = sl.runlog_errors_nm(load_config(cfg_path), log, rate)
    return {**sl.error_pct(err), "loop_rate_Hz": loop_Hz, "latency_s": summary["latency_s"],
            "lateness_p99_us": round(summary["lateness_p99_s"] * 1e6, 1),
            "missed_deadlines": summary["missed_deadlines"], "samples": summary["samples"],
            "slew_limited": summary["slew_limited"], "clamped": summary["clamped"],
            "output": summary["output"], "underruns": (summary["stream"] or {}).get("underruns"),
            "lowest_level": (summary["stream"] or {}).get("lowest_level")}


def table(results: dict) -> str:
    head = ("| model | output | loop | lines/s | max / RMS % | latency | p99 late | missed | slew-lim. | clamped |"
            " underruns / lowest FIFO |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    rows = []
    for (kind, out, loop_Hz, rate), v in results.items():
        if "error" in v:
            rows.append(f"| {kind} | {out} | {loop_Hz / 1e3:g} kHz | {rate:g} | failed: {v['error']} | | | | | | |")
            continue
        fifo = "—" if v["underruns"] is None else f"{v['underruns']} / {v['lowest_level']}"
        rows.append(f"| {kind} | {out} | {loop_Hz / 1e3:g} kHz | {rate:g} | {v['max_error_pct']:.2f} / "
                    f"{v['rms_error_pct']:.2f} | {v['latency_s'] * 1e3:.3g} ms | {v['lateness_p99_us']:.0f} µs | "
                    f"{v['missed_deadlines']} of {v['samples']} | {v['slew_limited']} | {v['clamped']} | {fifo} |")
    return head + "\n".join(rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--loop-rates", type=float, nargs="+", default=[5000.0, 10000.0], help="loop rates [Hz]")
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 4.0, 16.0], help="line rates [lines/s]")
    ap.add_argument("--outputs", nargs="+", default=["setpoints"], choices=list(OUTPUT_TOML),
                    help="how afmctl run reaches the amplifier (default setpoints; see above)")
    ap.add_argument("--models", type=Path, help="folder of scanner_KIND.json (default: run the demo)")
    ap.add_argument("--sim-dt-s", type=float, default=None,
                    help="the simulated scanner's integration step [s] (default its own, 1e-5); 1e-4 integrates "
                         "a 10 kHz output once per sample, so the in-process simulator keeps up with a 10 kHz stream")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    ap.add_argument("--json", type=Path, help="also write the results as JSON")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="loop-preview-") as tmp:
        work = Path(tmp)
        models = args.models or demo_models(work)
        scfg = default_scanner_config().model_copy(update={"drift": DriftConfig(kind="none")})
        if args.sim_dt_s:
            scfg = scfg.model_copy(update={"dt_s": args.sim_dt_s})
        scanner_json = sl.write_scanner_json(scfg, work / "scanner.json")
        gain = Scanner(scfg).nominal_gain_nm_per_V().tolist()
        results = {}
        for loop_Hz in args.loop_rates:
            for rate in args.rates:
                for kind in KINDS:
                    for out in args.outputs:
                        v = run_cell(work, scanner_json, models / f"scanner_{kind}.json", rate, loop_Hz, gain, out)
                        results[(kind, out, loop_Hz, rate)] = v
                        print(kind, out, f"{loop_Hz:g} Hz", f"{rate:g} lines/s", v, flush=True)
    tab = table(results)
    print(tab)
    if args.json:
        args.json.write_text(json.dumps({f"{k} {o} {lh:g} {r:g}": v for (k, o, lh, r), v in results.items()}, indent=2),
                             encoding="utf-8")
    if not args.no_write:
        body = ("## Speed ladder through `afmctl run` (preview horizon in the loop)\n\n"
                f"`.venv/bin/python benchmarks/loop_preview.py {' '.join(argv if argv is not None else sys.argv[1:])}` "
                f"({time.perf_counter() - t0:.0f} s, 2 shared cores). The demo's scanner models on the default "
                "simulated scanner (drift off), `afmctl run` over the virtual CAN bus, 4 µm raster lines; max / "
                "RMS error of x and y over the central 80 % of each line after the first, % of the line "
                "(run-log voltages replayed through the simulator, each held one loop period). `latency`: the "
                "preview horizon (the output lags the trajectory read by it); `slew-lim.`/`clamped`: samples the "
                "safety layer limited. `stream`: `output = \"stream\"` over CAN FD (10 samples per frame); "
                "its error is that of the queued samples played on time, so a cell with device underruns "
                "(the simulated amplifier, in the same process, did not keep up) is not what that run's tip "
                "did. `wave-can` / `wave-gcs`: `output = \"wave\"`, the whole trajectory computed before the "
                "run (as `afmctl compensate` does) and played from the CAN FD FIFO / by the simulated E-727's "
                "wave generator (pty, 921600 baud); latency 0 (the table is aligned with the target). "
                "`--sim-dt-s 1e-4` integrates the simulated scanner once per 10 kHz sample instead of ten "
                "times (the mode and the amplifier are discretised exactly at either step).\n\n" + tab)
        write_section(NAME, body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
