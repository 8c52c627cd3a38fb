"""``afmctl run --config FILE.toml``: the controller service."""
from __future__ import annotations

import argparse

HELP = """\
Run the feedforward controller: read the configuration (TOML, see `afmctl schema` and
examples/), open the amplifier (or serve a simulated amplifier + scanner in this process
with [simulation] enabled = true), start the zenoh API if [zenoh] enabled = true (in a
child process, so that it cannot delay the loop), and stream the configured trajectory
through drift prediction, the inverse models and the safety layer to the amplifier at
loop.rate_Hz. Every setpoint is written to a crash-safe
run log (runlog.dir; read it with `afmctl log show`).

How the voltages reach the amplifier ([amplifier] output): "setpoints" (default) sends
one per loop tick on the host's timing; "stream" (driver can) keeps the amplifier's FIFO
filled ahead and the samples play on its clock; "wave" (drivers gcs, nv200, can)
compensates the whole trajectory before the run, as `afmctl compensate` does, and the
device plays it (wave table, waveform buffer or FIFO) — for line rates the host cannot
carry (e.g. 50 lines/s at 20 kHz).

Ctrl-C or SIGTERM ramps the output to the safe value and stops cleanly; a second Ctrl-C
is an emergency stop (ramp at the slew limit).

With --serve (needs [zenoh] enabled = true) the service starts idle and stays up: an
operator starts and stops the scanner over zenoh (`cmd start` {{"configured": true}} runs the
configured trajectory, `cmd stop` ends it), as often as wanted, each run with its own run
log, until Ctrl-C or SIGTERM. The scanner's presence (its zenoh liveliness token
<prefix>/<scanner>/alive) lasts as long as the process: a lab of scanners behind one
`afmctl router` (docs/ZENOH.md, "A lab").

Examples:
  afmctl run --config examples/sim_inprocess.toml
  afmctl run --config examples/sim_wave_gcs.toml        # 50 lines/s on a GCS wave table
  afmctl run --config examples/mdt693b_serial.toml --log runs/scan1.afmlog
  AFMCTL_AMPLIFIER__PORT=/dev/ttyUSB1 afmctl run --config examples/mdt693b_serial.toml
  afmctl run --config examples/lab/stage1.toml --port socket://127.0.0.1:50000 --serve

Environment: AFMCTL_<SECTION>__<KEY>=value overrides the file (e.g. AFMCTL_LOOP__RATE_HZ=500).

Exit status:
  0  the run ended cleanly (end of the trajectory, --seconds, Ctrl-C or SIGTERM)
  1  the run ended in a fault (amplifier link lost or a setpoint refused); the device holds
     its output
  2  bad input: configuration, arguments (--seconds), a trajectory file that is missing or
     has a bad sample (one line names the file and the field; nothing or only a ramp to
     the safe value was sent)
  3  the run log could not be written (disk full, its directory removed): the output was
     ramped to the safe value and the run stopped; the log keeps every record written
     before the error

A configuration (every key: `afmctl schema`; units in the names: _V, _nm, _s, _Hz):

{example}"""


def _help() -> str:
    from .schema import EXAMPLE_TOML
    return HELP.format(example="\n".join("  " + line for line in EXAMPLE_TOML.splitlines()))


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("run", help="run the controller service", description=_help(),
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, metavar="FILE.toml", help="configuration file (TOML)")
    p.add_argument("--log", metavar="FILE.afmlog", help="run log path (default: runlog.dir/<scanner>-<time>.afmlog)")
    p.add_argument("--port", metavar="URL", help="override amplifier.port")
    p.add_argument("--seconds", type=float, metavar="S",
                   help=f"stop after S seconds, 0 < S <= {MAX_SECONDS:g} (default: end of trajectory)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--serve", action="store_true",
                   help="start idle and serve zenoh commands (cmd start / stop, again and again) until Ctrl-C or "
                        "SIGTERM; needs [zenoh] enabled = true")
    p.add_argument("--drift-images", metavar="DIR",
                   help="watch DIR for new AFM frames of one area (.gwy/.gsf/.tif/.ibw, Nanoscope .spm/.000–.999) while "
                        "scanning and feed "
                        "their drift (phase correlation) to the Kalman filter (compensation.drift.kalman = true)")
    p.add_argument("--drift-image-std-nm", type=float, default=0.5, metavar="NM",
                   help="1-sigma of a frame's drift measurement (default 0.5 nm)")
    p.add_argument("--drift-frame-period-s", type=float, default=None, metavar="S",
                   help="time to scan one frame (default: lines / line rate from the frame's metadata)")
    p.set_defaults(func=run)


#: longest --seconds [s] (about 115 days)
MAX_SECONDS = 1e7
#: exit status (see HELP)
EXIT_OK, EXIT_FAULT, EXIT_BAD_INPUT, EXIT_RUNLOG = 0, 1, 2, 3



def link_warning(config) -> str | None:
    """A warning when loop.rate_Hz exceeds what the amplifier link carries."""
    from ..control.path_delay import LINK_CEILING_PER_S
    driver = config.amplifier.driver
    ceiling = LINK_CEILING_PER_S.get(driver)
    if ceiling is None or str(config.amplifier.port or "").startswith("socket://"):
        return None      # CAN and TCP links carry more than the loop's rate limit
    if config.amplifier.output == "wave" and driver != "can":
        return None      # the table is uploaded before it plays on the device's clock
    if config.amplifier.output in ("stream", "wave") and config.amplifier.options.get("fd"):
        return None      # CAN FD: 10 samples per frame
    if driver != "can":
        baud = config.amplifier.options.get("baudrate") or (config.simulation.baud if config.simulation.enabled
                                                            else 115200)
        ceiling *= float(baud) / 115200.0
    if config.loop.rate_Hz > ceiling:
        return (f"loop.rate_Hz {config.loop.rate_Hz:g} exceeds what the {driver} link carries (about "
                f"{ceiling:.0f} setpoints/s): the link will block and the loop run late")
    return None


def _summary(ctl, config, scanner, recorder=None) -> dict:
    from ..control.runlog import RunLogReader
    from ..simulation.link import replay_positions_nm
    st = ctl.stats()
    out = {"state": st["state"], "samples": st["samples"], "ticks": st["ticks"], "rate_Hz": st["rate_Hz"],
           "lateness_p50_s": st["lateness_p50_s"], "lateness_p99_s": st["lateness_p99_s"],
           "lateness_max_s": st["lateness_max_s"], "missed_deadlines": st["missed_deadlines"],
           "overruns": st["overruns"], "errors": st["errors"], "faults": st["faults"],
           "reconnects": st["reconnects"], "watchdog_trips": st["watchdog_trips"],
           "slew_limited": st["slew_limited"], "clamped": st["clamped"], "last_error": st["last_error"],
           "latency_samples": st["latency_samples"], "latency_s": st["latency_s"], "path_delay": st["path_delay"],
           "output": st["output"], "stream": st["stream"], "wave": st["wave"],
           "runlog": str(ctl.runlog_path) if ctl.runlog_path else None,
           "runlog_error": ctl.runlog_error, "trajectory_error": ctl.trajectory_error,
           "watchdog": ctl.watchdog_report()}
    if (scanner is not None or recorder is not None) and ctl.runlog_path is not None and ctl.runlog_error is None:
        reader = RunLogReader(ctl.runlog_path)
        ev = reader.events()
        sp = reader.setpoints()
        start = max([e["seq"] for e in ev if e.get("event") == "ramp-done"] or [0])
        ends = [e["seq"] for e in ev if e.get("event") in ("end", "stop", "estop")]
        end = min(ends) if ends else len(sp)
        if end > start:
            replayed = replay_positions_nm(config, sp, ctl.path_delay.advance) if scanner is not None else None
            out["tracking"] = replayed_tracking(config, sp, (start, end), replayed) if scanner is not None else {}
            if recorder is not None:
                measured = recorder.errors()
                out["tracking"]["recorded"] = measured.as_dict() if measured is not None else None
                out["tracking"]["recorded_why_not"] = recorder.why_not
            out["tracking"]["lag"] = lag_summary(config, ctl, sp, (start, end), scanner, recorder, replayed)
    return out


def lag_summary(config, ctl, setpoints, seq_range: tuple[int, int], scanner=None, recorder=None,
                replayed=None) -> dict:
    """The lag of the motion behind its target per axis (:func:`afmctl.data.lag.measure_lags`)
    over the tracked setpoints of ``seq_range``: as the device's recorder measured it (a wave
    run) and as the voltages replayed through a fresh simulated scanner give it; beside the
    output path's delay known in advance and the ticks the loop advanced the setpoints by to
    take it out, and for host-timed setpoints to a simulated amplifier in this process how
    late each reached the simulated scanner (:func:`afmctl.simulation.link.arrival_delays_s`).
    ``replayed``: the replayed positions (N, 3) [nm] of every setpoint, when there is a scanner."""
    import numpy as np

    from ..data.lag import measure_lags
    from ..simulation.link import arrival_delays_s
    sel = (setpoints["seq"] >= seq_range[0]) & (setpoints["seq"] < seq_range[1])
    tgt, dt = setpoints["target_nm"][sel], config.dt_s
    axes = "".join(a for a in "xyz" if a in config.scanner.axes)
    out: dict = {"path_delay": ctl.path_delay.as_dict(), "dt_s": dt}
    rec = getattr(recorder, "recorded", None)
    if rec is not None:
        target, pos, rec_axes = rec
        out["recorded"] = [g.as_dict() for g in measure_lags(target, pos, dt, rec_axes)]
    if scanner is None or replayed is None:
        return out
    out["replayed"] = [g.as_dict() for g in measure_lags(tgt, replayed[sel], dt, axes)]
    deadlines = ctl.tick_deadlines_s(np.round(setpoints["t_s"] / dt))
    if config.amplifier.output == "setpoints" and deadlines is not None and hasattr(scanner, "applied"):
        late = arrival_delays_s(scanner, deadlines, setpoints["u_V"])[sel]
        late = late[np.isfinite(late)]
        if late.size:
            out["arrival"] = {"median_s": float(np.median(late)), "p99_s": float(np.percentile(late, 99)),
                              "max_s": float(late.max()), "matched": int(late.size), "sent": int(np.count_nonzero(sel))}
    return out


def replayed_tracking(config, setpoints, seq_range: tuple[int, int], replayed=None) -> dict:
    """The tracking error of a simulated run: the voltages sent replayed through a fresh
    simulated scanner (:func:`afmctl.simulation.link.replay_positions_nm`), over the setpoints
    of ``seq_range`` (those that track the trajectory). ``axes``, ``max_abs_nm``, ``rms_nm``
    over all of them, and ``judged``: per axis in nm and % of its line or step over the
    central part of a raster's lines (:func:`afmctl.data.axis_errors.axis_errors`).
    ``replayed``: those positions already replayed (N, 3) [nm]."""
    import numpy as np

    from ..data.axis_errors import axis_errors
    from ..simulation.link import replay_positions_nm
    sel = (setpoints["seq"] >= seq_range[0]) & (setpoints["seq"] < seq_range[1])
    if replayed is None:
        replayed = replay_positions_nm(config, setpoints)
    pos, tgt = replayed[sel], setpoints["target_nm"][sel]
    axes = [a for a in "xyz" if a in config.scanner.axes]
    idx = ["xyz".index(a) for a in axes]
    err = pos - tgt
    return {"axes": axes, "max_abs_nm": [float(np.abs(err[:, i]).max()) for i in idx],
            "rms_nm": [float(np.sqrt(np.mean(err[:, i] ** 2))) for i in idx],
            "judged": axis_errors(tgt, pos, "".join(axes)).as_dict()}


def _check_seconds(seconds: float | None) -> None:
    import math

    from ..errors import AfmctlError
    if seconds is not None and not (math.isfinite(seconds) and 0.0 < seconds <= MAX_SECONDS):
        raise AfmctlError(f"--seconds {seconds:g}: outside the allowed range 0 < S <= {MAX_SECONDS:g} s")


def _install_signals(stack, ctl, stops: dict) -> None:
    """Ctrl-C / SIGTERM: first a stop (ramp to the safe value), then an emergency stop."""
    import signal
    import sys
    import threading

    def on_signal(signum, frame) -> None:  # noqa: ARG001
        stops["n"] += 1
        if stops["n"] == 1:
            print("afmctl: stopping (ramping to the safe value); again for an emergency stop",
                  file=sys.stderr)
            ctl.stop()
        else:
            ctl.estop()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old = signal.signal(sig, on_signal)
            stack.callback(signal.signal, sig, old)


def _wait_for_run(ctl, args: argparse.Namespace, stops: dict) -> None:
    """Wait for the run to end; stop it after --seconds; a progress line every 2 s."""
    import sys
    import time
    t0 = time.monotonic()
    next_report = t0 + 2.0
    while not ctl.wait(0.05):
        now = time.monotonic()
        if args.seconds is not None and now - t0 >= args.seconds and stops["n"] == 0:
            stops["n"] = 1
            ctl.stop()
        if not args.quiet and now >= next_report:
            next_report = now + 2.0
            print(_progress(ctl.stats()), file=sys.stderr)


def _progress(s: dict) -> str:
    """The progress line every 2 s: the host loop's lateness, or for a device-timed table
    how much of it played."""
    if s.get("wave"):
        w = s["wave"]
        return (f"afmctl: {s['state']:8s} samples {s['samples']:>9d}  table {w['played']} of {w['samples']} played "
                "on the device's clock")
    return (f"afmctl: {s['state']:8s} samples {s['samples']:>9d}  p99 lateness "
            f"{s['lateness_p99_s'] * 1e6:7.1f} us  missed {s['missed_deadlines']}")


def _serve(ctl, args: argparse.Namespace, stops: dict) -> None:
    """--serve: runs are started and stopped over zenoh; wait for Ctrl-C / SIGTERM (the
    first stops a running run), then for the run to end."""
    import sys
    import time
    next_report = time.monotonic() + 2.0
    while stops["n"] == 0:
        time.sleep(0.05)
        if not args.quiet and time.monotonic() >= next_report:
            next_report = time.monotonic() + 2.0
            print(_progress(ctl.stats()), file=sys.stderr)
    if ctl.running:
        ctl.wait(30.0)


def _print_summary(summary: dict) -> None:
    print(f"state             {summary['state']}")
    print(f"samples           {summary['samples']} at {summary['rate_Hz']:g} Hz")
    if summary.get("wave"):
        _print_device_timing(summary)
    else:
        print(f"lateness          p50 {summary['lateness_p50_s'] * 1e6:.1f} us  p99 "
              f"{summary['lateness_p99_s'] * 1e6:.1f} us  max {summary['lateness_max_s'] * 1e6:.1f} us")
        print(f"missed deadlines  {summary['missed_deadlines']} (> half a period late); overruns {summary['overruns']}")
    print(f"errors            {summary['errors']} (faults {summary['faults']}, reconnects {summary['reconnects']}, "
          f"watchdog trips {summary['watchdog_trips']})")
    if summary.get("watchdog"):
        print(f"watchdog          {summary['watchdog']}")
    print(f"safety            slew-limited {summary['slew_limited']} samples, clamped {summary['clamped']}"
          + ("; a late tick's catch-up (missed setpoints sent back to back) is held back by the slew limit: "
             "loop.resync_periods = 2 restarts the schedule instead" if summary["slew_limited"] and summary["overruns"]
             and summary.get("output") == "setpoints" else ""))
    if summary.get("stream"):
        st = summary["stream"]
        print(f"stream            {st['queued']} samples queued; device underruns {st['underruns']}, lowest FIFO "
              f"level {st['lowest_level']} samples (marks {st['low_water']}..{st['high_water']}); the host's lateness "
              "is the producer's wake-ups")
    if summary.get("wave"):
        w = summary["wave"]
        print(f"wave              {w['played']} of {w['samples']} table samples played on the {w['player']}"
              + "".join(f"; {r}" for r in w["inverse"]))
    if summary.get("latency_samples"):
        print(f"preview latency   {summary['latency_samples']} samples = {summary['latency_s'] * 1e3:.3g} ms "
              "(the output lags the trajectory read)")
    if summary.get("last_error"):
        print(f"last error        {summary['last_error']}")
    if summary.get("tracking"):
        _print_tracking(summary["tracking"])
    print(f"run log           {summary['runlog']}")


def _print_device_timing(summary: dict) -> None:
    """A device-timed run (output = "wave"): the table played on the device's clock, which the
    host's timing does not reach; the host only ticked the approach, settle and finish ramps
    (a late tick there slows a ramp, it never moves the tip faster or off the table)."""
    w = summary["wave"]
    host = summary["samples"] - w["played"]
    print(f"timing            device-timed: the table's {w['played']} samples played on the device's clock "
          f"({w['player']}); the host's timing does not reach the tip")
    print(f"host ramps        {host} ticks before and after the table (approach, settle hold, finish): lateness p99 "
          f"{summary['lateness_p99_s'] * 1e6:.1f} us, {summary['missed_deadlines']} late by over half a period "
          "(a late ramp tick slows the ramp; not a missed deadline of the scan)")


def _print_tracking(t: dict) -> None:
    """The tracking error: per axis over the judged part (nm and % of its line or step) as
    the device's recorder measured it (a wave run on a device with one), else as the
    simulated scanner replays the voltages sent; then the replay over the whole tracked
    record in nm."""
    from ..data.axis_errors import AxisError
    if t.get("recorded"):
        j, how = t["recorded"], "measured by the device's recorder during the play (as afmctl learn measures)"
    elif t.get("judged"):
        j, how = t["judged"], "the voltages sent replayed through a fresh simulated scanner"
    else:
        print(f"tracking error    not measured: {t.get('recorded_why_not')}")
        return
    print(f"tracking error    per axis over {j['part']}, {how}:")
    for a in j["axes"].values():
        print("                    " + AxisError(a["axis"], a["max_nm"], a["rms_nm"], a["reference"],
                                                 a["reference_nm"]).text())
    if "recorded" in t and not t["recorded"]:
        print(f"                  (the device's recorder: {t.get('recorded_why_not')})")
    if t.get("lag"):
        _print_lag(t["lag"])
    if t.get("max_abs_nm") and not t.get("recorded"):
        print("                  replayed, whole tracked record (turnarounds included): max |e| "
              + ", ".join(f"{a} {v:.2f}" for a, v in zip(t["axes"], t["max_abs_nm"]))
              + " nm;  rms " + ", ".join(f"{a} {v:.2f}" for a, v in zip(t["axes"], t["rms_nm"])) + " nm")


#: the lag's sources, most direct first: (key in the summary's tracking.lag, in words)
LAG_SOURCES = (("recorded", "the device's recorder"), ("replayed", "the voltages replayed"))


def lag_lines(lag: dict) -> list[str]:
    """Per axis: ``x: lag measured X ms (N samples) by ..., Y ms taken out (path: ...)``, from
    the most direct measurement there is, the others beside it."""
    from ..control.path_delay import PathDelay, describe
    p = lag["path_delay"]
    taken_ms = p["advance_samples"] * lag["dt_s"] * 1e3
    lines = []
    found = [(key, words, {g["axis"]: g for g in lag[key]}) for key, words in LAG_SOURCES if lag.get(key)]
    for axis in (found[0][2] if found else {}):
        key, words, first = found[0]
        g = first[axis]
        if g["lag_samples"] is None:
            lines.append(f"{axis}: no lag measured ({g['why']})")
            continue
        others = "; ".join(f"{w}: {o[axis]['lag_ms']:.3g} ms" for _, w, o in found[1:]
                           if o.get(axis, {}).get("lag_samples") is not None)
        lines.append(f"{axis}: lag measured {g['lag_ms']:.3g} ms ({g['lag_samples']:.3g} samples) by {words}, "
                     f"{taken_ms:.3g} ms taken out (path: {p['path']}); after it max {g['rest_max_nm']:.3g} nm / "
                     f"RMS {g['rest_rms_nm']:.3g} nm" + (f" [{others}]" if others else ""))
    lines.append("path delay: " + describe(PathDelay(p["delay_s"], p["advance_samples"], p["path"]), lag["dt_s"]))
    if lag.get("arrival"):
        a = lag["arrival"]
        lines.append(f"arrival: the setpoints reached the simulated scanner {a['median_s'] * 1e3:.3g} ms (median), "
                     f"{a['p99_s'] * 1e3:.3g} ms (p99) after their ticks' deadlines ({a['matched']} of {a['sent']} "
                     "matched; host lateness and the in-process simulator's own backlog, which the replay leaves out)")
    return lines


def _print_lag(lag: dict) -> None:
    for i, line in enumerate(lag_lines(lag)):
        print(("lag               " if i == 0 else "                  ") + line)


def _exit_status(ctl, summary: dict) -> int:
    """The exit status of a finished run (see HELP); the reason goes to stderr as one line."""
    import sys

    from ..control.controller import State
    if ctl.runlog_error is not None:
        print(f"afmctl: error: {ctl.runlog_error}; the run was stopped (ramped to the safe value)",
              file=sys.stderr)
        return EXIT_RUNLOG
    if ctl.trajectory_error is not None:
        print(f"afmctl: error: trajectory: {ctl.trajectory_error}; the run was stopped", file=sys.stderr)
        return EXIT_BAD_INPUT
    return EXIT_OK if summary["state"] in (State.STOPPED.value, State.IDLE.value) else EXIT_FAULT


def run(args: argparse.Namespace) -> int:
    import contextlib
    import sys

    from ..control import cpu_pinning
    from ..config import load_config
    from ..control.controller import Controller
    from ..control.rate_check import mode_warnings
    from ..control.run_recording import RunRecorder
    from ..errors import AfmctlError

    _check_seconds(args.seconds)
    config = load_config(args.config, overrides={"amplifier": {"port": args.port}} if args.port else None)
    scanner = None
    if getattr(args, "serve", False) and not config.zenoh.enabled:
        raise AfmctlError(f"--serve: {args.config} has [zenoh] enabled = false; runs are started over zenoh")
    # this thread, the in-process simulator and the zenoh process: off the loop's CPU
    cpu_pinning.pin_this_thread(cpu_pinning.plan_for(config.loop).others)
    warning = link_warning(config)
    if warning:
        print(f"afmctl: warning: {warning}", file=sys.stderr)
    with contextlib.ExitStack() as stack:
        if config.simulation.enabled:
            from ..simulation.link import simulated_amplifier
            amp, scanner = stack.enter_context(simulated_amplifier(config))
        else:
            from ..control.hardware import open_driver
            amp = open_driver(config, config.amplifier.port)
            stack.callback(amp.close)
        ctl = Controller(config, amp)
        stack.callback(ctl.close)
        recorder = None
        if RunRecorder.available(config, amp) and not getattr(args, "serve", False):
            recorder = RunRecorder(config, amp, ctl)     # the table's motion, as afmctl learn measures it
            ctl.before_wave_start = recorder.hook
        if config.zenoh.enabled:   # in its own process: the loop's timing does not depend on it
            from ..zenoh_api.process import ZenohBridgeProcess
            bridge = ZenohBridgeProcess(ctl, config.zenoh, scanner_name=config.scanner.name)
            stack.callback(bridge.close)
        if args.drift_images:
            from ..inputs.drift_watch import DriftImageWatcher
            watcher = DriftImageWatcher(ctl, args.drift_images, args.drift_image_std_nm, args.drift_frame_period_s)
            stack.callback(watcher.close)

        stops = {"n": 0}
        _install_signals(stack, ctl, stops)
        if getattr(args, "serve", False):
            print(f"afmctl: serving {config.scanner.name} over zenoh ({config.zenoh.mode}); an operator starts "
                  "and stops it (cmd start / stop); stop the service with Ctrl-C or SIGTERM", file=sys.stderr)
            _serve(ctl, args, stops)
            ctl.close()
            summary = _summary(ctl, config, scanner)
            return _finish(args, summary, ctl)
        ctl.start(config.trajectory, runlog_path=args.log)
        # always, --quiet included: which axes are compensated, by which model, from which file
        print(f"afmctl: compensation {ctl.pipeline.describe()}", file=sys.stderr)
        simulated = scanner.config if scanner is not None else None     # the link's simulated scanner
        for line in mode_warnings(config, list(getattr(ctl.pipeline, "models", [])), simulated):
            print(f"afmctl: warning: {line}", file=sys.stderr)
        if config.amplifier.output == "wave":
            print("afmctl: wave: the whole trajectory is computed before it plays (as `afmctl compensate` "
                  "does) and played on the amplifier's clock; the output does not lag it", file=sys.stderr)
        elif ctl.latency_samples:   # always: the output lags the trajectory the loop reads
            print(f"afmctl: preview: the loop reads the trajectory {ctl.latency_samples} samples "
                  f"({ctl.latency_s * 1e3:.3g} ms) ahead; the output lags it by latency_s = {ctl.latency_s:.6g} s",
                  file=sys.stderr)
        if not args.quiet:
            print(f"afmctl: running {config.trajectory.kind} on {config.amplifier.driver} "
                  f"{'(simulated) ' if scanner is not None else ''}at {config.loop.rate_Hz:g} Hz; "
                  f"{ctl.cpu_plan.why}; run log {ctl.runlog_path}", file=sys.stderr)
        _wait_for_run(ctl, args, stops)
        ctl.close()
        summary = _summary(ctl, config, scanner, recorder)
    return _finish(args, summary, ctl)


def _finish(args: argparse.Namespace, summary: dict, ctl) -> int:
    """Print the summary (text or --json); the exit status."""
    import json
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        _print_summary(summary)
    return _exit_status(ctl, summary)
