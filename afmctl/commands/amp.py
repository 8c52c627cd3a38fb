"""``afmctl amp``: talk to a piezo amplifier from the shell (bench use)."""
from __future__ import annotations

import argparse
import logging
import math
import time

from . import amp_wave

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
  wave --file VOLTS.csv --rate-Hz R [--cycles N]
                            play the rows on the amplifier's own clock through its
                            stream FIFO (driver can) or as wave tables on the
                            controller's servo clock (driver gcs), N times
  stream --file VOLTS.csv   send every row in order at the times of its t column (or
                            at --rate HZ rows per second), print the rate achieved and
                            warn when the link could not keep that timing. Columns t,u
                            (one axis, chosen with --axis) or t,ux,uy,uz (s, V). Steps
                            between rows (and from the present output to the first
                            row) above --max-step (default 10 V when streaming) refuse
                            the whole file before anything is sent.

Examples:
  afmctl amp --driver mdt693b --port /dev/ttyUSB0 info
  afmctl amp --driver mdt693b --port /dev/pts/5 --limit 0:100 set x=10 y=20
  afmctl amp --driver nv200 --port /dev/ttyUSB1 stream --file ramp.csv --rate 500
  afmctl amp --driver can --port virtual:afm0 wave --file scan.csv --rate-Hz 5000 --cycles 10
"""


def _limit(text: str) -> tuple[str | None, float, float]:
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
                        f"(stream: default {DEFAULT_STREAM_STEP_V:g} V)")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("info", help="identity, limits, state")
    actions.add_parser("get", help="read back the applied voltages")
    s = actions.add_parser("set", help="set voltages, e.g. set x=10 y=20.5")
    s.add_argument("values", nargs="+", type=_assignment, metavar="AXIS=V")
    st = actions.add_parser("stream", help="stream a CSV of voltages (t,u or t,ux,uy,uz)",
                            description="Send every row of VOLTS.csv in order at the times of its t column "
                                        "[s] (row i at t_i - t_0 after the start). Columns t,u (one axis, "
                                        "--axis) or t,ux,uy,uz [V].")
    st.add_argument("--file", required=True, metavar="VOLTS.csv")
    st.add_argument("--axis", choices=["x", "y", "z"], default="x", help="axis of a t,u file (default x)")
    st.add_argument("--rate", type=float, default=None, metavar="HZ",
                    help="send HZ rows per second, ignoring the t column (default: the t column's timing)")
    amp_wave.add_parser(actions)
    p.set_defaults(func=run)


def _host_limits(limits):
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
    options = {}
    host = _host_limits(args.limit)
    if host is not None:
        options["host_limits"] = host
    if args.max_step is not None and not (args.max_step > 0 and math.isfinite(args.max_step)):
        raise AfmctlError(f"--max-step: {args.max_step} V must be a positive number of volts")
    if args.max_step is not None:
        options["max_step_V"] = args.max_step
    elif args.action in ("stream", "wave"):
        options["max_step_V"] = DEFAULT_STREAM_STEP_V
    amp = open_amplifier(args.driver, args.port, baudrate=args.baud, timeout_s=args.timeout, **options)
    with amp:
        if args.action == "info":
            for key, value in amp.info().items():
                print(f"{key}: {value}")
        elif args.action == "get":
            print(_fmt(amp.get_voltages()))
        elif args.action == "set":
            amp.set_voltages(dict(args.values))
            print(_fmt(amp.get_voltages()))
        elif args.action == "wave":
            amp_wave.play(amp, rows, args, _check_file_limits, _fmt)
        else:
            _stream(amp, rows, args)
    return 0


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


def _check_file_limits(amp, loaded, path) -> None:
    import numpy as np

    from ..errors import AfmctlError
    axes, values, columns, _ = loaded
    lim = amp.limits
    for k, (axis, col) in enumerate(zip(axes, columns)):
        if axis not in lim:
            raise AfmctlError(f"{path}: column {col}: axis {axis} is not driven by {amp.name} "
                              f"(axes: {', '.join(amp.axes)})")
        lo, hi = lim[axis].min_V, lim[axis].max_V
        bad = np.flatnonzero((values[:, k] < lo) | (values[:, k] > hi))
        if bad.size:
            i = int(bad[0])
            raise AfmctlError(f"{path}: row {i + 2}: column {col}: {values[i, k]:g} V is outside the limits "
                              f"[{lo:g}, {hi:g}] V of axis {axis} ({bad.size} row(s) outside); nothing was sent")
        step = getattr(amp, "max_step_V", None)
        if step is not None:
            start = amp.last_output.get(axis, values[0, k])
            steps = np.abs(np.diff(np.concatenate([[start], values[:, k]])))
            big = np.flatnonzero(steps > step)
            if big.size:
                i = int(big[0])
                raise AfmctlError(f"{path}: row {i + 2}: column {col}: step of {steps[i]:g} V on axis {axis} "
                                  f"exceeds --max-step {step:g} V; nothing was sent")


def _stream(amp, loaded, args) -> None:
    """Send row i at ``times[i]`` [s] after the start (never earlier), then report the rate
    achieved and warn (stderr) when the schedule was not kept."""
    import sys

    from tqdm import tqdm
    _check_file_limits(amp, loaded, args.file)
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
              f"setpoints/s and the file took {elapsed:.3f} s instead of {planned:.3f} s", file=sys.stderr)
    print("final: " + _fmt(amp.get_voltages()))
