"""``afmctl excite``: write the excitation voltages a user plays to identify a scanner."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)

HELP = "write identification excitation voltages (static loops, creep dwells, small-signal multisine)"

DESCRIPTION = """\
Write the voltages to play through your amplifier while recording the displacement, so
that 'afmctl identify' can fit hysteresis, creep and dynamics from the recording.

Kinds:
  static    the major loop, then first-order reversal curves (descending from several
            turning points, ascending from several): they reveal the inside of the
            Preisach plane, which full-range cycles alone cannot.
  creep     a staircase up and down the range with --dwell-s holds: creep shows while
            the voltage rests.
  dynamics  a small-signal multisine (±--amplitude-pct of the range) around mid-range,
            every frequency line from --f-min-Hz to --f-max-Hz, --periods periods:
            for the amplifier's bandwidth, the structural modes and the delay.
  all       the three in that order, separated by --gap-s holds.

Play the file at --rate-Hz: the dynamics part needs a rate well above the scanner's
first resonance (e.g. 50 kHz for a 1 kHz mode); static and creep are slow (a full-range
sweep per second by default, --sweep-V-per-s). Give --slew-V-per-s (your amplifier's
slew limit) and no sample will change faster than half of it.

Output: --out EXC.csv with columns t,u (s, V), starting at --u-min-V (scanner at rest).
Record the displacement y (nm) beside it and fit with
  afmctl identify --model ... --data DATA.csv   (columns t,u,y)

Example:
  afmctl excite --kind all --u-min-V 0 --u-max-V 150 --rate-Hz 50000 --slew-V-per-s 10000 --out exc.csv
  afmctl amp stream ... exc.csv      # play it, record y
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("excite", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kind", required=True, choices=("static", "creep", "dynamics", "all"), help="what to excite")
    p.add_argument("--u-min-V", required=True, type=float, metavar="LO", help="lowest voltage [V]")
    p.add_argument("--u-max-V", required=True, type=float, metavar="HI", help="highest voltage [V]")
    p.add_argument("--rate-Hz", required=True, type=float, metavar="R", help="sample rate you will play at [Hz]")
    p.add_argument("--out", required=True, metavar="EXC.csv", help="output CSV, columns t,u (s, V)")
    p.add_argument("--slew-V-per-s", type=float, metavar="V_PER_S", help="amplifier slew limit [V/s]; samples stay within half of it")
    p.add_argument("--sweep-V-per-s", type=float, metavar="V_PER_S", help="ramp speed of static/creep [V/s] (default: the range per s)")
    p.add_argument("--dwell-s", type=float, metavar="S", default=2.0, help="creep dwell per level [s] (default 2)")
    p.add_argument("--gap-s", type=float, metavar="S", default=1.0, help="settling hold between parts [s] (default 1)")
    p.add_argument("--amplitude-pct", type=float, metavar="PCT", default=2.0,
                   help="multisine peak, %% of the range (default 2)")
    p.add_argument("--f-min-Hz", type=float, metavar="HZ", default=5.0, help="lowest multisine line [Hz] (default 5)")
    p.add_argument("--f-max-Hz", type=float, metavar="HZ", help="highest multisine line [Hz] (default 40 %% of the rate)")
    p.add_argument("--periods", type=int, metavar="N", default=8, help="multisine periods after one settling period (default 8)")
    p.add_argument("--seed", type=int, metavar="N", default=0, help="multisine phases seed (default 0)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..data.datafiles import write_csv
    from ..data.excitation import ExcitationSpec, excitation

    spec = ExcitationSpec(u_min_V=args.u_min_V, u_max_V=args.u_max_V, rate_Hz=args.rate_Hz,
                          sweep_V_per_s=args.sweep_V_per_s, slew_V_per_s=args.slew_V_per_s, dwell_s=args.dwell_s,
                          gap_s=args.gap_s, amplitude_frac=args.amplitude_pct / 100.0, f_min_Hz=args.f_min_Hz,
                          f_max_Hz=args.f_max_Hz, periods=args.periods, seed=args.seed)
    u = excitation(args.kind, spec)
    t = np.arange(u.size) / spec.rate_Hz
    write_csv(args.out, {"t": t, "u": u})
    slew = float(np.max(np.abs(np.diff(u)))) * spec.rate_Hz if u.size > 1 else 0.0
    print(f"written          : {args.out} ({u.size} rows, {t[-1]:.6g} s at {spec.rate_Hz:g} Hz)")
    print(f"voltage          : {u.min():.6g} … {u.max():.6g} V, fastest change {slew:.6g} V/s")
    return 0
