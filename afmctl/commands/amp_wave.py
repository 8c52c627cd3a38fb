"""``afmctl amp ... wave``: play a file of voltages on the amplifier's own clock, ``--cycles``
times, and report what the amplifier says it played: through the CAN amplifier's stream
FIFO, or as wave tables uploaded whole to a PI GCS controller and played by its wave
generator on its servo clock."""
from __future__ import annotations

import logging
import math
import time

log = logging.getLogger(__name__)

#: FIFO level the host keeps ahead of the amplifier [s of samples]
WAVE_LOW_S, WAVE_HIGH_S = 0.1, 0.3


def add_parser(actions, add_max_step) -> None:
    """The ``wave`` action; ``add_max_step(parser)`` adds ``afmctl amp``'s ``--max-step`` to it."""
    w = actions.add_parser(
        "wave", help="play a CSV of voltages on the amplifier's clock (drivers can, gcs, nv200)",
        description="Play the rows of VOLTS.csv (columns t,u with --axis, or t,ux,uy,uz [V]; the t column "
                    "is not used) at --rate-Hz on the amplifier's own clock, --cycles times, through its "
                    "stream FIFO: host delays do not reach the output while the FIFO holds samples. "
                    "Every row, the wrap from the last row to the first and the step from the present "
                    "output are checked against the limits and --max-step before anything is sent. "
                    "--driver can streams through the FIFO; --driver gcs uploads each column as a wave "
                    "table and plays it on the controller's servo clock — there --rate-Hz must be the "
                    "servo rate over a whole number (refused otherwise, naming the nearest rates). "
                    "--driver nv200 does the same with its 1024-sample waveform buffer (20 kHz clock).")
    w.add_argument("--file", required=True, metavar="VOLTS.csv")
    w.add_argument("--axis", choices=["x", "y", "z"], default="x", help="axis of a t,u file (default x)")
    w.add_argument("--rate-Hz", dest="rate_Hz", type=float, required=True, metavar="R",
                   help="samples per second, 1..1000000 (can: a whole number; gcs, nv200: the device "
                        "clock over a whole number, e.g. 20000/3 = 6666.666667 on an E-727)")
    w.add_argument("--cycles", type=int, default=1, metavar="N", help="play the file N times (default 1)")
    w.add_argument("--record", metavar="MOTION.csv", default=None,
                   help="record the motion with the device's data recorder while it plays (one point per "
                        "played sample, from the first: the position sensor [nm] and the output [V] of the "
                        "file's axes, as many points as the recorder holds) and write it as t,y,u (one "
                        "axis) or t,x,y,z,ux,uy,uz — the format afmctl reads an external sensor's motion "
                        "in; refused on a device without a recorder (mdt693b)")
    add_max_step(w)


def check_args(args) -> None:
    from ..errors import AfmctlError
    r = args.rate_Hz
    whole = getattr(args, "driver", "can") == "can"  # device clocks (gcs, nv200) check their own divider
    if not (math.isfinite(r) and (r == round(r) or not whole) and 1 <= r <= 1_000_000):
        raise AfmctlError(f"--rate-Hz: {r:g} must be a {'whole ' if whole else ''}number of Hz in 1..1000000")
    if not 1 <= args.cycles <= 1_000_000:
        raise AfmctlError(f"--cycles: {args.cycles} must be in 1..1000000")


def _rows(amp, loaded, args):
    """The whole wave as rows x, y, z [V] (axes not in the file hold their present output)."""
    import numpy as np

    from .amp_checks import check_wrap
    axes, values, columns, _ = loaded
    step = getattr(amp, "max_step_V", None)
    if args.cycles > 1 and step is not None:
        check_wrap(values[0].tolist(), values[-1].tolist(), columns, step, args.file)
    held = amp.last_output
    full = np.column_stack([values[:, axes.index(a)] if a in axes else np.full(len(values), held.get(a, 0.0))
                            for a in amp.axes])
    return np.tile(full, (args.cycles, 1))


def play(amp, loaded, args, check_file_limits, fmt) -> None:
    """Stream the wave, keeping the FIFO between WAVE_LOW_S and WAVE_HIGH_S; print a summary.
    ``check_file_limits(amp, loaded, path)`` and ``fmt(volts)`` are ``afmctl amp``'s."""
    from ..errors import AfmctlError
    if args.record is not None and not amp.has_recorder:
        amp.recorder_capacity()          # raises RecorderUnavailable: one line on what to do instead
    if hasattr(amp, "upload_wave"):
        return play_table(amp, loaded, args, check_file_limits, fmt)
    if not hasattr(amp, "start_stream"):
        raise AfmctlError(f"--driver {amp.name}: no buffered stream in this driver yet; "
                          "wave works with --driver can, gcs or nv200")
    check_file_limits(amp, loaded, args.file)
    rows = _rows(amp, loaded, args)
    rate = args.rate_Hz
    low, high = max(1, int(WAVE_LOW_S * rate)), max(2, int(WAVE_HIGH_S * rate))
    amp.start_stream(rate, prefill=int(min(high, len(rows))))
    setup = _arm_recorder(amp, loaded[0], len(rows), 1, args)
    queued, t0 = 0, time.perf_counter()
    while queued < len(rows):
        st = amp.latest_buffer_status()
        played = 0
        if st is not None and st.state != "armed":  # SEQ of the last played, unwrapped
            played = queued - ((queued - ((st.played_seq + 1) & 0xFFFF)) & 0xFFFF)
        if queued - played < low or queued == 0:
            n = min(high - (queued - played), len(rows) - queued)
            amp.queue(rows[queued:queued + n].tolist())
            queued += n
        time.sleep(min(low / rate / 4, 0.05))
    amp.drain_stream()
    while (st := amp.buffer_status()).state not in ("idle", "fault"):
        time.sleep(0.01)
    elapsed = time.perf_counter() - t0
    print(f"played {queued} samples ({args.cycles} cycle(s)) at {rate:g} Hz on the amplifier clock: "
          f"{st.underruns} underrun(s), {st.overflows} overflow(s); host time {elapsed:.3f} s "
          f"(schedule {len(rows) / rate:.3f} s)")
    if st.state == "fault":
        raise AfmctlError("the amplifier stopped the stream (fault); see the error above")
    _write_recording(amp, setup, args)
    print("final: " + fmt(amp.get_voltages()))


def play_table(amp, loaded, args, check_file_limits, fmt) -> None:
    """Upload every column of the file as the wave table of its axis, play them together
    ``--cycles`` times on the controller's servo clock, wait for the end, print a summary."""
    from afmctl.drivers import codec_gcs_wave as wcodec

    from ..errors import AfmctlError
    axes, values, columns, _ = loaded
    check_file_limits(amp, loaded, args.file)
    _rows(amp, loaded, args)  # the wrap check (--cycles > 1) on the file's rows
    cycle_s = amp.servo_cycle_s()
    try:
        divider = wcodec.divider_for(args.rate_Hz, cycle_s)
    except ValueError as err:
        raise AfmctlError(f"--rate-Hz: {err}; nothing was sent") from None
    for k, axis in enumerate(axes):
        amp.upload_wave(axis, values[:, k])
    setup = _arm_recorder(amp, axes, len(values) * args.cycles, divider, args)
    st = amp.start_wave(divider=divider, cycles=args.cycles, axes=axes)
    duration_s = len(values) * args.cycles / st.rate_Hz
    t0 = time.perf_counter()
    try:
        while any(st.running.values()):
            if time.perf_counter() - t0 > duration_s + 5.0:
                raise AfmctlError(f"the wave generator still runs {duration_s + 5.0:.1f} s after its start; stopped")
            time.sleep(min(0.05, max(duration_s / 20, 0.005)))
            st = amp.wave_status()
    finally:
        if any(st.running.values()):
            amp.stop_wave()
    print(f"played {len(values)} points x {args.cycles} cycle(s) on {', '.join(axes)} at {st.rate_Hz:g} Hz on the "
          f"device's clock (every {divider} tick(s) of {cycle_s * 1e6:g} us): "
          f"{duration_s:.4f} s; host waited {time.perf_counter() - t0:.3f} s")
    _write_recording(amp, setup, args)
    print("final: " + fmt(amp.get_voltages()))


def _arm_recorder(amp, axes, samples: int, divider: int, args):
    """With ``--record``: arm the recorder for one point per played sample of ``axes`` (as
    many as it holds); None without."""
    if args.record is None:
        return None
    capacity = amp.recorder_capacity(list(axes))
    if samples > capacity:
        log.warning("--record: the recorder holds %d points per signal; the first %d of %d samples are recorded",
                    capacity, capacity, samples)
    return amp.configure_recorder(list(axes), points=min(samples, capacity), divider=divider)


def _write_recording(amp, setup, args) -> None:
    if setup is None:
        return
    from ..data.motion_files import write_motion_csv
    rec = amp.read_recording(timeout_s=10.0 + setup.points * setup.period_s)
    write_motion_csv(args.record, rec)
    span = {a: float(v.max() - v.min()) for a, v in rec.y_nm.items()}
    print(f"recorded {len(rec)} points every {rec.period_s * 1e6:g} us ({rec.source}) -> {args.record}; "
          "measured span " + ", ".join(f"{a} {s:.1f} nm" for a, s in span.items()))
