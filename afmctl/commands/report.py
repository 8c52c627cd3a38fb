"""``afmctl report RUN``: plots of a run log (see afmctl.reports.report)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "turn a run log (.afmlog) into plots and a summary"

DESCRIPTION = """\
Read a run log written by `afmctl run` and write into OUT:

  report_loops.png     voltage sent [V] vs target [nm] per axis (the compensator's loops)
  report_tracking.png  target, corrected target [nm] and voltages [V] over time [s]
  report_errors.png    histograms, in % of the target range, of the drift correction
                       applied (corrected - target) and of the tracking error (tip -
                       target) of the simulated scanner driven by the logged voltages:
                       shown for runs on the simulator, and for any run with --simulate
  report_drift.png     drift estimate [nm] and temperature [°C] over time (if logged)
  report_summary.json  counts, duration, voltage ranges, states, error numbers

Printed: the errors in % of the target range over the samples that track the trajectory
(ramps left out), and the tracking error per axis in nm and in % of that axis's line (the
fast axis of a raster) or step (its slow axis: the move per line) over the central 80 % of
each line, or in % of the axis's range over the whole record when the target is no raster
(as `afmctl run` prints it for a run on the simulator). The replay holds each logged voltage
for one loop period from rest: for a device-timed run (output = "wave") the host's approach
ramp and settle hold took longer than their rows' loop periods, and the replay reads the
tip at the end of each period where a recorder reads it as the next sample starts, so there
the figure `afmctl run` measured with the device's recorder is the one to go by.

A log torn by a crash is read up to the last intact chunk.
"""

EPILOG = """\
examples:
  afmctl report runs/scan-001.afmlog --out runs/scan-001-report
  afmctl report runs/scan-001.afmlog --simulate
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("report", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path, metavar="RUN", help="run log file (.afmlog)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output directory (default: RUN without suffix + '-report')")
    p.add_argument("--simulate", action="store_true", default=None,
                   help="replay the voltages through the simulated scanner for the tracking error "
                        "(default for runs that drove the simulator)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..reports.report import run_report
    out = args.out if args.out is not None else args.run.with_name(args.run.stem + "-report")
    files, summary = run_report(args.run, out, simulate=args.simulate)
    print(f"{summary['samples']} setpoints, {summary.get('duration_s', 0.0):.3f} s, states: "
          f"{' -> '.join(summary['states']) or '-'}")
    from ..reports.report import QUANTITIES, TRACKING_ERROR
    errors = summary.get("errors_pct_of_range", {})
    span = summary.get("range_nm", 0.0)
    for name, e in errors.items():
        print(f"{name} ({QUANTITIES[name]}): max {e['max']:.3f} %, rms {e['rms']:.3f} % "
              f"of the {span:.6g} nm target range")
    per_axis = summary.get("tracking_per_axis")
    if per_axis:
        from ..data.axis_errors import AxisError
        print(f"{TRACKING_ERROR} per axis, over {per_axis['part']}:")
        for a in per_axis["axes"].values():
            print("  " + AxisError(a["axis"], a["max_nm"], a["rms_nm"], a["reference"], a["reference_nm"]).text())
    if summary.get("lag"):
        from .run import lag_lines
        print("lag per axis, the voltages replayed:")
        for line in lag_lines(summary["lag"]):
            print("  " + line)
    if TRACKING_ERROR not in errors:
        print(f"{TRACKING_ERROR}: not known (the run did not drive the simulator and the log holds no "
              "tip positions; --simulate estimates it with the simulated scanner)")
    for f in files:
        print(f"wrote {f}")
    return 0
