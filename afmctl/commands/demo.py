"""``afmctl demo``: the simulated scanner with and without compensation (see afmctl.reports.demo)."""
from __future__ import annotations

import argparse
from pathlib import Path

HELP = "simulated scanner in-process: grating images with/without compensation, plots, metrics"

DESCRIPTION = """\
Run the whole job on a simulated scanner, in-process, in one to three minutes:

  1. build the default simulated 3-axis scanner (asymmetric Preisach hysteresis, creep,
     resonances, x/y cross-coupling, 0-150 V) with a drift scenario (the lab warms by a
     few kelvin during the scan);
  2. excite each lateral axis (reversal curves + decaying sine) and identify every
     available compensator model on the measured data (pi, epi, preisach, bouc-wen,
     preisach+creep: the chain model, Preisach followed by linear creep, and
     preisach+creep+dynamics: plus linear dynamics from a small-signal multisine) and
     write each as a scanner model file OUT/models/scanner_KIND.json (per-axis models
     + x/y coupling; usable in `afmctl run` as [compensation] scanner_model);
  3. raster-scan a 1.667 um calibration grating without compensation and with each
     compensator through afmctl's compensation pipeline (drift prediction,
     decoupling, inverse model per axis);
  4. write into OUT: demo_images.png, demo_hysteresis.png, demo_errors.png,
     demo_lines.png, demo_drift.png, demo_speed_ladder.png and metrics.json
     (max_error_pct / rms_error_pct per compensator, errors in % of the scan range;
     speed_ladder: 4 um raster lines at 1, 4, 16 and 50 lines/s for none, the static
     model, the chain and the chain with dynamics, central 80 % of each line, 1-16
     lines/s through the real controller (2 kHz; the chain with dynamics at 10 kHz,
     reading the trajectory its preview latency ahead) and the simulated CAN
     amplifier; 50 lines/s offline), and print the same tables.

Compensators that are not available in this installation are skipped with a message.
"""

EPILOG = """\
examples:
  afmctl demo --out demo-out
  afmctl demo --out /tmp/quick --size 64 --quick       # a fast, coarse run
  afmctl demo --out demo-out --no-drift --only preisach
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help=HELP, description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("demo-out"), metavar="DIR",
                   help="output directory for PNGs and metrics.json (default: demo-out)")
    p.add_argument("--size", type=int, default=256, metavar="PX",
                   help="image size in pixels per side, 8..1024 (default 256)")
    p.add_argument("--line-rate", type=float, default=5.0, metavar="HZ",
                   help="scan lines per second, trace + retrace (default 5)")
    p.add_argument("--quick", action="store_true", help="shorter identification excitation (for tests)")
    p.add_argument("--no-drift", action="store_true", help="switch the drift scenario off")
    p.add_argument("--only", action="append", metavar="KIND",
                   help="compensator to run (repeatable; a model kind or KIND+creep; "
                        "default: pi, epi, preisach, bouc-wen, preisach+creep, preisach+creep+dynamics)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--docs", type=Path, default=None, metavar="DIR",
                   help="also copy the PNGs into DIR (e.g. docs/img)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..reports.demo import DEFAULT_COMPENSATORS, DemoOptions, format_table, run_demo
    options = DemoOptions(out=args.out, size=args.size, line_rate_Hz=args.line_rate, quick=args.quick,
                          drift=not args.no_drift,
                          compensators=tuple(args.only) if args.only else DEFAULT_COMPENSATORS,
                          docs_dir=args.docs)
    if not args.no_progress:
        import sys
        print("afmctl demo: starting; the first run compiles numerical kernels (numba, cached for later "
              "runs), which can take a minute or two", file=sys.stderr, flush=True)
    ctx = run_demo(options, progress=not args.no_progress)
    print(format_table(ctx.metrics))
    print(f"wrote {len(ctx.files)} files to {options.out}")
    return 0
