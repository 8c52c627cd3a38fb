"""The lag ``afmctl run`` measures and takes out, per shipped example on its simulator.

Each configuration of ``examples/`` that runs on a simulator in this process is run as a
user runs it (``afmctl run --config examples/X.toml --json``, its own process), with
``[simulation] enabled = true`` where the example talks to a real port
(``AFMCTL_SIMULATION__ENABLED=true``) and, with ``--model``, the demo's scanner model
(``AFMCTL_COMPENSATION__SCANNER_MODEL``). From the summary's ``tracking``: per axis the
error over the judged part (nm, % of the line/step/range), the lag measured (the device's
recorder for a wave run, else the voltages replayed through the simulated scanner) and what
is left after it, the output path's delay known in advance and the ticks taken out, and for
host-timed setpoints how late they reached the in-process simulated scanner (median / p99).

    .venv/bin/python benchmarks/run_lag.py [--model demo-out/models/scanner_preisach+creep+dynamics.json]
        [--examples sim_inprocess sim_wave_gcs ...] [--json OUT.json]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
AFMCTL = [sys.executable, "-m", "afmctl"]
#: the shipped examples that run on a simulator in this process (the others: sim_zenoh waits
#: for a zenoh client, tour/tour_learned need afmctl calibrate's model first)
EXAMPLES = ["sim_inprocess", "sim_wave_gcs", "can", "mdt693b_serial", "nv200_serial", "nv200_tcp", "e727_tcp"]


def run_example(name: str, model: str | None, runs: Path) -> dict:
    env = dict(os.environ, AFMCTL_SIMULATION__ENABLED="true", AFMCTL_RUNLOG__DIR=str(runs))
    if model:
        env["AFMCTL_COMPENSATION__SCANNER_MODEL"] = str(Path(model).resolve())
    cmd = AFMCTL + ["run", "--config", str(ROOT / "examples" / f"{name}.toml"), "--json", "--quiet"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    if res.returncode != 0 or not res.stdout.strip():
        return {"error": (res.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(res.stdout)


def rows(name: str, s: dict) -> list[str]:
    if "error" in s:
        return [f"| {name} | — | failed: {s['error'][:120]} | | | | |"]
    t = s.get("tracking") or {}
    lag = t.get("lag") or {}
    judged = t.get("recorded") or t.get("judged") or {"axes": {}}
    source = "recorder" if lag.get("recorded") else "replay"
    lags = {g["axis"]: g for g in lag.get("recorded") or lag.get("replayed") or []}
    p = lag.get("path_delay", {})
    arrival = lag.get("arrival")
    arr = f"{arrival['median_s'] * 1e3:.3g} / {arrival['p99_s'] * 1e3:.3g} ms" if arrival else "—"
    out = []
    for axis, e in judged["axes"].items():
        g = lags.get(axis, {})
        pct = f" ({e['max_pct']:.3g} %)" if e.get("max_pct") is not None else ""
        lag_txt = (f"{g['lag_ms']:.3g} ms ({g['lag_samples']:.3g}); rest {g['rest_max_nm']:.3g} nm"
                   if g.get("lag_samples") is not None else "— (" + str(g.get("why", "not measured")) + ")")
        out.append(f"| {name} | {axis} | {e['max_nm']:.3g} nm{pct} | {lag_txt}, {source} | "
                   f"{p.get('delay_s', 0) * 1e3:.3g} ms / {p.get('advance_samples', 0)} tick(s) | {arr} | "
                   f"{s['rate_Hz']:g} Hz {s['output']} |")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", help="scanner model for every example (e.g. the demo's)")
    ap.add_argument("--examples", nargs="+", default=EXAMPLES)
    ap.add_argument("--json", help="write the summaries here")
    args = ap.parse_args()
    out = {}
    print("| example | axis | max error (central part) | lag measured; left after it | path delay known / taken out "
          "| setpoints reached the simulator (median / p99) | loop |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.examples:
            out[name] = run_example(name, args.model, Path(tmp))
            print("\n".join(rows(name, out[name])), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
