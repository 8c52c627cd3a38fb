"""``afmctl calibrate``: excite the scanner on its device, record through the device's own
recorder, identify, validate on a second play, write the model (:mod:`afmctl.api.calibrate`)."""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
from typing import Any

log = logging.getLogger(__name__)

HELP = "calibrate the scanner on its device in one command: excite, record, identify, validate, write the model"

DESCRIPTION = """\
Calibrate a scanner on the device that drives it, in one command, then hand the model to
afmctl learn and afmctl run:

  afmctl calibrate --config RUN.toml --out scanner.json          # excite, record, identify, validate
  afmctl learn --config RUN.toml --iterations 6 --out line.afmwave   # RUN.toml: [compensation] scanner_model = "scanner.json"
  afmctl run --config RUN.toml

The device must play tables on its own clock and record its motion (amplifier.output =
"wave"): a PI GCS controller such as the E-727, a sensored NV200, the CAN amplifier — or
their simulators (afmctl sim, or [simulation] enabled = true). For each axis (--axes,
default the scanner's), afmctl calibrate

  1. plays what 'afmctl excite --kind all' writes for the configured amplifier (the axis's
     voltage limits, loop.rate_Hz, the slew limit): major and reversal loops, a creep
     staircase, a small-signal multisine, large fast triangles and steps — about a minute. The device's wave table and
     recorder hold a few thousand points, so it plays in pieces; between pieces the output
     holds its last voltage (the scanner's hysteresis memory runs on) and the holds go back
     into the joined recording, their positions not measured (column measured 0: left out
     of the fit, their creep the model's). A device whose recorder cannot hold one multisine period is
     refused in one line before anything moves. Only the calibrated axis plays; the others
     hold their safe value;
  2. reads the position back through the device's recorder, and the piezo voltage where the
     device records it: column v of the recording CSV (t,u,y,v);
  3. identifies a model from that recording as 'afmctl identify --model KIND --data' does
     (--kind, default auto: the held-out selection table is printed), in a process of its
     own that starts as soon as the excitation is recorded, while the validation plays
     (auto fits in two worker processes: --param jobs=N or AFMCTL_FIT_JOBS=N to change);
  4. validates it on a second, different play: triangles across the range at the
     configuration's line rate (trajectory.line_rate_Hz) and nested minor loops; prints the
     held-out error in % of the measured span;
  5. writes the model with its provenance (device, identity *IDN?, recorder rate, settle
     hold, date, afmctl version): a one-axis scanner's model, or for a scanner of several
     axes a scanner file holding the calibrated ones (for [compensation] scanner_model).

Safe as afmctl run: every table is checked against the limits and the slew limit before it
is sent; the settle hold (amplifier.settle_s, unset: 2 s) before the first piece. Ctrl-C,
SIGTERM or 'stop' on zenoh ([zenoh] enabled = true: the scanner's cmd key answers stop,
estop and status) stops the piece playing at once (generator stopped / FIFO flushed), cancels
a read-back, ramps every axis to its safe value and exits 130; during the identification it
interrupts it (the recording is kept). A lost link ends with exit 1 and keeps what was
recorded as OUT.<axis>-excite-partial.csv. A progress bar shows the piece and the time to go.

Files (beside --out, or in --report DIR): OUT.<axis>-recording.csv (t,u,y[,v]: s, V, nm, V),
OUT.<axis>-validation.csv; with --report also the selection table and the validation figures
(calibration.json); with --plot a figure of the validation.

Shorter excitations (a first look, tests): --dwell-s, --gap-s, --periods, --f-min-Hz,
--f-max-Hz, --sweep-V-per-s as in afmctl excite.

Example, the README's tour on the simulated E-727 over TCP (examples/tour.toml):
  afmctl sim --protocol gcs --tcp 127.0.0.1:50000 &
  afmctl calibrate --config examples/tour.toml --axes x --out scanner.json
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("calibrate", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, metavar="RUN.toml", help="run configuration (amplifier.output = 'wave')")
    p.add_argument("--out", required=True, metavar="SCANNER.json", help="the model file to write")
    p.add_argument("--axes", metavar="x,y", help="axes to calibrate, comma-separated (default: the scanner's)")
    p.add_argument("--kind", default="auto", metavar="KIND",
                   help="model kind: auto (default), a chain such as preisach+creep+dynamics, or pi, preisach, ...")
    p.add_argument("--plot", metavar="VAL.png", help="plot the validation: measured and predicted")
    p.add_argument("--report", metavar="DIR", help="write the recordings, the selection table and the figures here")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="the kind's option, as in afmctl identify (repeatable)")
    g = p.add_argument_group("excitation (as afmctl excite; defaults: its defaults)")
    g.add_argument("--sweep-V-per-s", type=float, metavar="V_PER_S", help="ramp speed of the static and creep parts")
    g.add_argument("--dwell-s", type=float, metavar="S", help="creep dwell per level [s]")
    g.add_argument("--gap-s", type=float, metavar="S", help="settling hold between the parts [s]")
    g.add_argument("--periods", type=int, metavar="N", help="multisine periods")
    g.add_argument("--f-min-Hz", type=float, metavar="HZ", help="lowest multisine line [Hz]")
    g.add_argument("--f-max-Hz", type=float, metavar="HZ", help="highest multisine line [Hz]")
    p.set_defaults(func=run)


def _excitation(args: argparse.Namespace) -> dict[str, Any]:
    names = ("sweep_V_per_s", "dwell_s", "gap_s", "periods", "f_min_Hz", "f_max_Hz")
    return {n: getattr(args, n) for n in names if getattr(args, n) is not None}


class ProgressBar:
    """A tqdm bar on stderr over the excitation's seconds: which piece, how long to go."""

    def __init__(self) -> None:
        self.bar: Any = None
        self.last: Any = None

    def status(self) -> dict[str, Any]:
        """Where the calibration is (for zenoh ``status``)."""
        p = self.last
        if p is None:
            return {"what": "starting"}
        return {"what": p.what, "piece": p.k + 1, "pieces": p.n, "left_s": round(p.left_s, 1)}

    def __call__(self, p: Any) -> None:
        from tqdm import tqdm
        self.last = p
        if self.bar is None:
            self.total = p.left_s
            self.bar = tqdm(total=round(p.left_s, 1), unit="s", file=sys.stderr, desc="afmctl calibrate",
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of excitation")
        self.bar.set_description_str(f"afmctl calibrate: {p.what} piece {p.k + 1}/{p.n}, {p.left_s:.0f} s to go")
        self.bar.n = round(max(self.total - p.left_s, 0.0), 1)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.n = self.bar.total
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    from ..api.calibrate import Calibration
    from ..control.calibrate_run import CalibrationFault, CalibrationStopped
    from .identify_io import parse_params
    bar = ProgressBar()
    axes = [a.strip() for a in args.axes.split(",")] if args.axes else None
    cal = Calibration(args.config, args.out, axes=axes, kind=args.kind, report_dir=args.report,
                      excitation=_excitation(args), on_progress=bar, **parse_params(args.param))
    try:
        with contextlib.ExitStack() as stack:
            _install_stop(stack, cal)
            if cal.config.zenoh.enabled:
                from .calibrate_zenoh import CalibrationCommands
                stack.enter_context(CalibrationCommands(cal.config.zenoh, cal.config.scanner.name, cal.stop,
                                                        bar.status))
            result = cal.run()
    except CalibrationStopped as err:
        bar.close()
        print(f"afmctl: {err}; the output was ramped to the safe value, no model written"
              + _partial(cal), file=sys.stderr)
        return 130
    except CalibrationFault as err:
        bar.close()
        print(f"afmctl: {err}; no model written" + _partial(cal), file=sys.stderr)
        return 1
    bar.close()
    _print(result)
    if args.report:
        _report(args.report, result)
    if args.plot:
        _plot(args.plot, result)
        print(f"plot             : {args.plot}")
    return 0


def _partial(cal: Any) -> str:
    return "; recorded so far: " + ", ".join(map(str, cal.partial)) if cal.partial else ""


def _install_stop(stack: contextlib.ExitStack, cal: Any) -> None:
    """Ctrl-C / SIGTERM: stop (the piece stops, the output ramps to the safe value)."""
    import signal
    import threading

    def on_signal(signum: int, frame: Any) -> None:  # noqa: ARG001
        if cal.device_done:             # the output is safe already: stop the identification now
            raise KeyboardInterrupt
        print("\nafmctl: stopping (the output ramps to the safe value)", file=sys.stderr)
        cal.stop()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old = signal.signal(sig, on_signal)
            stack.callback(signal.signal, sig, old)


#: a recording whose share of holds between pieces is above this gets a note
MOSTLY_HELD = 0.5


def _print(result: Any) -> None:
    from afmctl.compensators.chain import format_table
    for axis, r in result.axes.items():
        fit = r.identified
        held = r.recording.held_share
        print(f"axis {axis}          : {len(r.recording.t_s)} samples from {r.pieces} piece(s), {held:.0%} of them "
              f"holds between the pieces; recording {r.csv}")
        if held > MOSTLY_HELD:
            print(f"note             : {held:.0%} of the recording are holds between the pieces: their positions are "
                  "not measured (column measured 0) and are left out of the fit, their creep is the model's: the "
                  "link or the recorder's size sets them (docs/DRIVERS.md, 'Calibrating on the device')")
        if fit.table is not None:
            print(f"held-out prediction error of the candidates (last {fit.holdout_fraction:.0%} of the recording; "
                  f"% of its span; ranked by {fit.criterion}):")
            print(format_table(fit.table))
        print(f"selected         : {getattr(fit.model, 'structure', fit.model.kind)}")
        print(f"fit residual     : {fit.residual()}")
        for part, e in r.validation.items():
            print(f"validation {part:<12}: max {e['max_pct']:.3f} %, RMS {e['rms_pct']:.3f} % of the "
                  f"{e['span_nm']:.4g} nm span (held out: a second play)")
    played = result.excitation_s + result.validation_s
    over = 100.0 * (result.recording_s / played - 1.0) if played else 0.0
    print(f"time             : on the device {result.recording_s:.1f} s for {result.excitation_s:.1f} s of excitation "
          f"and {result.validation_s:.1f} s of validation ({over:+.0f} %); {result.elapsed_s:.1f} s in all")
    dev = result.provenance["device"]
    print(f"device           : {dev['driver']} {dev.get('identity', '')}".rstrip())
    if result.path is not None:
        print(f"written          : {result.path}")


def _report(folder: str, result: Any) -> None:
    from pathlib import Path

    from afmctl.compensators.chain import format_table
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    summary = {"provenance": result.provenance, "excitation_s": result.excitation_s, "elapsed_s": result.elapsed_s,
               "axes": {a: {"validation": r.validation, "recording": str(r.csv), "pieces": r.pieces,
                            "held_share": round(r.recording.held_share, 4), "fit_rms_nm": r.identified.rms_nm, "fit_max_nm": r.identified.max_nm}
                        for a, r in result.axes.items()}}
    (d / "calibration.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    for a, r in result.axes.items():
        if r.identified.table is not None:
            (d / f"selection-{a}.txt").write_text(format_table(r.identified.table) + "\n", encoding="utf-8")
    print(f"report           : {d}")


def _plot(path: str, result: Any) -> None:
    """Per axis the validation play: measured and predicted position, and their difference."""
    import numpy as np

    from ..data.prediction import predict_nm
    from ..figures import pyplot, save_figure
    plt = pyplot()
    fig, axs = plt.subplots(2, len(result.axes), figsize=(6.4 * len(result.axes), 5.0), squeeze=False)
    for j, (a, r) in enumerate(result.axes.items()):
        rec, val = r.recording, r.validation_record
        u = np.concatenate([rec.u_V, val.u_V])
        y_hat = predict_nm(r.identified.model, np.arange(len(u)) * (rec.t_s[1] - rec.t_s[0]), u, "plot")[len(rec.u_V):]
        axs[0, j].plot(val.t_s, val.y_nm, label="measured")
        axs[0, j].plot(val.t_s, y_hat, "--", label="model")
        axs[0, j].set_title(f"axis {a}: validation (held out)")
        axs[0, j].set_ylabel("position [nm]")
        axs[0, j].legend()
        axs[1, j].plot(val.t_s, val.y_nm - y_hat - np.mean((val.y_nm - y_hat)[val.measured]))
        axs[1, j].set_xlabel("t [s]")
        axs[1, j].set_ylabel("measured - model [nm]")
    fig.tight_layout()
    save_figure(fig, path, "--plot")
