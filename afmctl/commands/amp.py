"""``afmctl amp``: talk to a piezo amplifier from the shell (bench use)."""
from __future__ import annotations

import argparse
import logging
import math
import time
from typing import Any

from . import amp_checks, amp_wave

log = logging.getLogger(__name__)

#: --max-step for ``stream`` when none is given [V]
DEFAULT_STREAM_STEP_V = 10.0
#: a stream that ends later than its schedule by more than this fraction (plus
#: STREAM_SLACK_S) is reported as not kept
STREAM_LATE_FRACTION = 0.05
STREAM_SLACK_S = 0.05

HELP = "talk to a piezo amplifier: info, read back, set voltages, stream a file"

DESCRIPTION = """\
Talk to a piezo amplifier from the shell, through the same drivers afmctl uses.

Drivers: mdt693b, mdt694b (Thorlabs), gcs (PI, open loop), nv200 (piezosystem jena) over a
serial port (device path, pty path or any pyserial URL such as socket://host:4001), and
can (afmctl's CAN frames, docs/DRIVERS.md) with --port INTERFACE:CHANNEL (virtual:afm0,
socketcan:can0). Voltages are in volts. Every value is checked against the device's own
limits (read at connect) and your --limit before anything is sent; a file with any value
outside them is refused as a whole.

Actions:
  info                      identity, limits, connection state
  get                       read back the applied output voltages
  set x=V [y=V z=V]         set some axes, then read back
  wave --file VOLTS.csv --rate-Hz R [--cycles N] [--record MOTION.csv]
                            play the rows on the amplifier's own clock: through its
                            stream FIFO (driver can), as wave tables on the servo
                            clock (gcs) or through the waveform buffer (nv200), N times
  stream --file VOLTS.csv   send every row in order at the times of its t column (or
                            at --rate HZ rows per second), print the rate achieved and
                            warn when the link could not keep that timing. Columns t,u
                            (one axis, chosen with --axis) or t,ux,uy,uz (s, V).

--max-step V (before or after the action) refuses any step over V volts from one output
to the next — for stream and wave (default 10 V there) from the present output to the
file's first row and between rows — and names the largest step it found. A serial line
limits stream: at 115200 baud an MDT693B takes about 770 one-axis (380 three-axis)
setpoints/s, so a file of 1 kHz rows takes longer than its t column says (3000 rows:
about 3.9 s for 3 s); --rate sets a steady rate the link keeps. Over TCP (socket://) no
baud rate applies.

Examples:
  afmctl amp --driver mdt693b --port /dev/ttyUSB0 info
  afmctl amp --driver mdt693b --port /dev/pts/5 --limit 0:100 set x=10 y=20
  afmctl amp --driver mdt693b --port /dev/pts/5 stream --file volts.csv --axis x --max-step 15
  afmctl amp --driver gcs --port socket://192.168.0.10:50000 info     # E-727 over Ethernet
  afmctl amp --driver nv200 --port /dev/ttyUSB1 stream --file ramp.csv --rate 500
  afmctl amp --driver can --port virtual:afm0 wave --file scan.csv --rate-Hz 5000 --cycles 10
"""


STREAM_DESCRIPTION = f"""\
Send every row of VOLTS.csv in order at the times of its t column [s] (row i at t_i - t_0
after the start), or at --rate HZ. Columns t,u (one axis, --axis) or t,ux,uy,uz [V].

Before anything is sent every row is checked against the limits (the device's, read at
connect, narrowed by --limit) and every step against --max-step (default
{DEFAULT_STREAM_STEP_V:g} V): the step from the present output to the first row, then from
each row to the next. A refusal names the row, what it measured and the fix.

A serial line sets the pace: at 115200 baud an MDT693B carries about 770 one-axis
setpoints/s, so 3000 rows at 1 ms (3.00 s) take about 3.9 s (longer on a busy host), and
the command warns, naming a --rate the link kept. Over TCP (socket://) no baud rate applies.

Example (after afmctl amp ... set x=10; volts.csv starts at 21.6 V):
  afmctl amp --driver mdt693b --port /dev/pts/3 stream --file volts.csv --axis x --max-step 15
"""


def add_max_step(parser) -> None:
    """``--max-step`` after the action too (SUPPRESS: an absent one keeps the value given before it)."""
    parser.add_argument("--max-step", type=float, default=argparse.SUPPRESS, metavar="V",
                        help="refuse any step over V volts: from the present output to the first row, "
                             f"and between rows (default {DEFAULT_STREAM_STEP_V:g} V)")


def _limit(text: str) -> tuple[str | None, float, float]:
    axis: str | None
    axis, sep, rng = text.partition("=")
    if not sep:
        axis, rng = None, text
    lo, sep2, hi = rng.partition(":")
    try:
        lo_v, hi_v = float(lo), float(hi)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--limit {text!r}: expected MIN:MAX or AXIS=MIN:MAX in volts, e.g. x=0:100") from None
    if not sep2 or not (math.isfinite(lo_v) and math.isfinite(hi_v)) or lo_v > hi_v:
        raise argparse.ArgumentTypeError(f"--limit {text!r}: expected MIN:MAX with MIN <= MAX (V)")
    if axis is not None and axis not in ("x", "y", "z"):
        raise argparse.ArgumentTypeError(f"--limit {text!r}: axis must be x, y or z")
    return axis, lo_v, hi_v


def _assignment(text: str) -> tuple[str, float]:
    axis, sep, val = text.partition("=")
    axis = axis.strip().lower()
    try:
        v = float(val)
    except ValueError:
        v = math.nan
    if not sep or axis not in ("x", "y", "z") or not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r}: expected AXIS=VOLTS with AXIS x, y or z and a finite number, e.g. x=12.5")
    return axis, v


def register(subparsers) -> None:
    p = subparsers.add_parser("amp", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--driver", required=True, choices=["mdt693b", "mdt694b", "gcs", "nv200", "can"],
                   help="amplifier protocol")
    p.add_argument("--port", required=True, help="serial device/URL, or INTERFACE:CHANNEL for can")
    p.add_argument("--baud", type=int, default=None, help="serial baud rate (default: the protocol's, 115200)")
    p.add_argument("--timeout", type=float, default=0.5, metavar="S", help="read/write timeout in s (default 0.5)")
    p.add_argument("--limit", type=_limit, action="append", default=[], metavar="[AXIS=]MIN:MAX",
                   help="host voltage limits in V, narrowing the device's; repeat per axis")
    p.add_argument("--max-step", type=float, default=None, metavar="V",
                   help="refuse any step larger than this many volts from the last output "
                        f"(stream, wave: default {DEFAULT_STREAM_STEP_V:g} V)")
    p.add_argument("--restore-settings", action="store_true",
                   help="nv200: write back the stored settings (cl, modsrc) this command had to change, "
                        "at its end (off by default: restoring closed loop or the analog input moves the "
                        "actuator once afmctl lets go)")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("info", help="identity, limits, state")
    actions.add_parser("get", help="read back the applied voltages")
    s = actions.add_parser("set", help="set voltages, e.g. set x=10 y=20.5")
    s.add_argument("values", nargs="+", type=_assignment, metavar="AXIS=V")
    st = actions.add_parser("stream", help="stream a CSV of voltages (t,u or t,ux,uy,uz)",
                            formatter_class=argparse.RawDescriptionHelpFormatter,
                            description=STREAM_DESCRIPTION)
    st.add_argument("--file", required=True, metavar="VOLTS.csv")
    st.add_argument("--axis", choices=["x", "y", "z"], default="x", help="axis of a t,u file (default x)")
    st.add_argument("--rate", type=float, default=None, metavar="HZ",
                    help="send HZ rows per second, ignoring the t column (default: the t column's timing)")
    add_max_step(st)
    amp_wave.add_parser(actions, add_max_step)
    p.set_defaults(func=run)


def _host_limits(limits: list[tuple[str | None, float, float]] | None) -> dict[str, tuple[float, float]] | None:
    """``--limit`` options as the driver's host limits (axis -> (lo, hi) V; "*" every axis)."""
    if not limits:
        return None
    out: dict[str, tuple[float, float]] = {}
    for a, lo, hi in limits:
        out["*" if a is None else a] = (lo, hi)  # "*": every axis of the unit
    return out


def _fmt(volts) -> str:
    return "  ".join(f"{a}={v:.4f} V" for a, v in volts.items())


def run(args) -> int:
    from ..errors import AfmctlError
    from afmctl.drivers.registry import open_amplifier

    if args.timeout <= 0 or not math.isfinite(args.timeout):
        raise AfmctlError(f"--timeout: {args.timeout} s must be a positive number of seconds")
    if getattr(args, "rate", None) is not None and not (args.rate > 0 and math.isfinite(args.rate)):
        raise AfmctlError(f"--rate: {args.rate} Hz must be a positive number")
    rows = None
    if args.action == "wave":
        amp_wave.check_args(args)
        args.rate = args.rate_Hz
    if args.action in ("stream", "wave"):
        rows = _load_stream(args)  # file problems are reported before connecting
    options: dict[str, Any] = {}
    host = _host_limits(args.limit)
    if host is not None:
        options["host_limits"] = host
    if args.max_step is not None and not (args.max_step > 0 and math.isfinite(args.max_step)):
        raise AfmctlError(f"--max-step: {args.max_step} V must be a positive number of volts")
    if args.max_step is not None:
        options["max_step_V"] = args.max_step
    elif args.action in ("stream", "wave"):
        options["max_step_V"] = DEFAULT_STREAM_STEP_V
    if args.restore_settings:
        if args.driver != "nv200":
            raise AfmctlError(f"--restore-settings: only --driver nv200 changes stored settings (got {args.driver})")
        options["restore_settings"] = True
    amp = open_amplifier(args.driver, args.port, baudrate=args.baud, timeout_s=args.timeout, **options)
    with amp:
        _say_changed_settings(amp, args)
        if args.action == "info":
            for key, value in amp.info().items():
                print(f"{key}: {value}")
        elif args.action == "get":
            print(_fmt(amp.get_voltages()))
        elif args.action == "set":
            amp_checks.check_set(amp, dict(args.values))
            amp.set_voltages(dict(args.values))
            print(_fmt(amp.get_voltages()))
        elif args.action == "wave":
            amp_wave.play(amp, rows, args, amp_checks.check_rows, _fmt)
        else:
            _stream(amp, rows, args)
    return 0


def _say_changed_settings(amp, args) -> None:
    """An NV200 whose stored settings the driver changed (it warns which): the option that
    writes them back (stderr)."""
    import sys
    changed = getattr(amp, "changed_settings", None)
    if changed and not args.restore_settings:
        was = ", ".join(f"{k}={v}" for k, v in changed.items())
        print(f"afmctl amp: add --restore-settings to write {was} back at the end", file=sys.stderr)


def _load_stream(args) -> tuple[list[str], "object", list[str], "object"]:
    """``(axes, volts (n, axes) [V], columns, send times from the start (n,) [s])``."""
    import numpy as np

    from ..data.datafiles import read_csv
    from ..errors import AfmctlError
    data = read_csv(args.file, ["t"], optional=["u", "ux", "uy", "uz"])
    n = data["t"].shape[0]
    times = np.arange(n) / args.rate if args.rate else data["t"] - data["t"][0]
    if all(c in data for c in ("ux", "uy", "uz")):
        return ["x", "y", "z"], np.column_stack([data["ux"], data["uy"], data["uz"]]), ["ux", "uy", "uz"], times
    if "u" in data:
        return [args.axis], data["u"][:, None], ["u"], times
    raise AfmctlError(f"{args.file}: needs columns t,u (one axis) or t,ux,uy,uz (three axes)")


def _stream(amp, loaded, args) -> None:
    """Send row i at ``times[i]`` [s] after the start (never earlier), then report the rate
    achieved and warn (stderr) when the schedule was not kept."""
    import sys

    from tqdm import tqdm
    amp_checks.check_rows(amp, loaded, args.file)
    axes, values, _, times = loaded
    n = values.shape[0]
    t0 = time.perf_counter()
    with tqdm(total=n, unit="pt", desc="stream", disable=None, mininterval=0.5) as bar:
        for i in range(n):
            wait = t0 + times[i] - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            amp.set_voltages(dict(zip(axes, values[i].tolist())))
            if i % 256 == 255:
                bar.update(256)
        bar.update(n - bar.n)
        amp.flush()
    elapsed = time.perf_counter() - t0
    planned = float(times[-1])
    print(f"sent {n} setpoints ({len(axes)} axis/axes) in {elapsed:.3f} s: {n / elapsed:.1f} setpoints/s "
          f"(schedule {planned:.3f} s)")
    if elapsed > planned * (1 + STREAM_LATE_FRACTION) + STREAM_SLACK_S:
        wanted = f"--rate {args.rate:g} Hz" if args.rate else f"the t column of {args.file}"
        print(f"afmctl amp stream: warning: {wanted} was not kept: the link reached {n / elapsed:.1f} "
              f"setpoints/s and the file took {elapsed:.3f} s instead of {planned:.3f} s; --rate "
              f"{max(1, math.floor(0.9 * n / elapsed))} sends at a steady rate this link keeps", file=sys.stderr)
    print("final: " + _fmt(amp.get_voltages()))
