"""``afmctl log show RUN``: read a run log (summary, events, CSV export)."""
from __future__ import annotations

import argparse

HELP = """\
Read a run log written by `afmctl run` (a crash-safe *.afmlog file: every setpoint sent,
drift estimate and state change, with sequence numbers).

  afmctl log show runs/stage1-20260101-120000.afmlog
  afmctl log show RUN --events              also list every state change
  afmctl log show RUN --csv setpoints.csv   export t,seq,target,corrected,voltages

CSV columns: seq, t (s), x_target, y_target, z_target, x_corrected, ... (nm),
ux, uy, uz (V), T (°C), dx, dy, dz (drift estimate, nm). A log torn by a crash reads up to
its last complete chunk (reported as 'torn').
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("log", help="read a run log", description=HELP,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="log_cmd", metavar="ACTION", required=True)
    s = sub.add_parser("show", help="summary of a run log (+ CSV export)", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("run", metavar="RUN", help="run log file (*.afmlog), or its name in --dir")
    s.add_argument("--dir", default="runs", help="directory to look for RUN in (default: runs)")
    s.add_argument("--csv", metavar="FILE", help="export setpoints and drift as CSV")
    s.add_argument("--events", action="store_true", help="list every event")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    s.set_defaults(func=run)


def resolve(run_arg: str, directory: str):
    from pathlib import Path

    from ..errors import AfmctlError
    p = Path(run_arg)
    for cand in (p, Path(directory) / p, Path(directory) / f"{run_arg}.afmlog", Path(f"{run_arg}.afmlog")):
        if cand.is_file():
            return cand
    raise AfmctlError(f"RUN: no run log {run_arg!r} (looked as a path and in {directory}/)")


def run(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from ..control.runlog import RunLogReader
    reader = RunLogReader(resolve(args.run, args.dir))
    summary = reader.summary()
    meta = reader.meta()
    if args.json:
        print(json.dumps({"meta": {k: v for k, v in meta.items() if k != "config"}, "summary": summary}, indent=2))
    else:
        print(f"run log   {summary['path']}")
        print(f"scanner   {meta.get('scanner', '?')}  driver {meta.get('driver', '?')}  "
              f"rate {meta.get('rate_Hz', '?')} Hz  axes {','.join(str(a) for a in meta.get('axes') or [])}")
        print(f"samples   {summary['samples']}  (seq {summary.get('seq_first', '-')}..{summary.get('seq_last', '-')}, "
              f"gaps {summary.get('seq_gaps', 0)})  duration {summary.get('duration_s', 0.0):.3f} s")
        if summary["samples"]:
            lo = ", ".join(f"{v:.3f}" for v in summary["u_min_V"])
            hi = ", ".join(f"{v:.3f}" for v in summary["u_max_V"])
            print(f"voltages  min [{lo}] V  max [{hi}] V")
        if "drift_max_abs_nm" in summary:
            print("drift     max |d| [" + ", ".join(f"{v:.3f}" for v in summary["drift_max_abs_nm"]) + "] nm")
        print(f"states    {' -> '.join(summary['states']) or '-'}")
        stats = [e for e in reader.events() if e.get("event") == "stats"]
        if stats and isinstance(stats[-1].get("detail"), dict):
            st = stats[-1]["detail"]

            def us(key: str) -> str:
                v = st.get(key)
                return f"{v * 1e6:.1f}" if isinstance(v, (int, float)) else "?"
            print(f"timing    lateness p50 {us('lateness_p50_s')} us  p99 {us('lateness_p99_s')} us  "
                  f"max {us('lateness_max_s')} us  missed {st.get('missed_deadlines', '?')}  "
                  f"errors {st.get('errors', '?')}")
        if reader.torn:
            integrity = f"TORN at byte {reader.valid_bytes} (crash?)"
        elif not reader.closed:
            integrity = "INCOMPLETE: no end record (the writer was killed, or a write failed)"
        else:
            integrity = "complete"
        print(f"integrity {integrity}")
    if args.events:
        for e in reader.events():
            if e.get("event") == "stats":
                continue
            detail = f"  {e['detail']}" if e.get("detail") else ""
            t = e.get("t_s")
            t_txt = f"{t:10.3f}" if isinstance(t, (int, float)) else f"{'?':>10}"
            print(f"  seq {e.get('seq', '?')!s:>8}  t {t_txt} s  {e.get('state', '?')!s:8s} {e.get('event')}{detail}")
    if args.csv:
        from ..data.datafiles import write_csv
        sp = reader.setpoints()
        dr = reader.drift()
        n = min(len(sp), len(dr)) if len(dr) else len(sp)
        cols = {"seq": sp["seq"][:n].astype(np.float64), "t": sp["t_s"][:n]}
        for j, a in enumerate("xyz"):
            cols[f"{a}_target"] = sp["target_nm"][:n, j]
        for j, a in enumerate("xyz"):
            cols[f"{a}_corrected"] = sp["corrected_nm"][:n, j]
        for j, a in enumerate("xyz"):
            cols[f"u{a}"] = sp["u_V"][:n, j]
        if len(dr):
            cols["T"] = dr["T_C"][:n]
            for j, a in enumerate("xyz"):
                cols[f"d{a}"] = dr["drift_nm"][:n, j]
        write_csv(args.csv, cols)
        print(f"wrote {n} rows to {args.csv}")
    return 0
