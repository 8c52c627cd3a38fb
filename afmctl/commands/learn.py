"""``afmctl learn``: iterative learning of a scan's voltages from its measured motion.

Subcommands live in :data:`SUBCOMMANDS` (name → register function); ``step`` is one
iteration from files. A device loop (``afmctl learn --config RUN.toml``) is to be added
beside it as another entry.
"""
from __future__ import annotations

import argparse
import logging
from collections.abc import Callable

from ..errors import AfmctlError
from .learn_defaults import CENTRAL_PCT

log = logging.getLogger(__name__)

HELP = "iterative learning: the next voltages from the target, the voltages sent and the motion measured"

DESCRIPTION = """\
Learn the voltages of a repetitive scan (a raster, a force-curve ramp) from the motion a
sensor measured while they played: every model is wrong somewhere, and the measured
motion teaches the feedforward what the model missed.

  afmctl learn step ...   one iteration from files (an external sensor, a DAQ, a script)
  afmctl learn --config RUN.toml --iterations N --out LEARNED.afmwave
                          on a device with a data recorder: play, record, learn, repeat

See 'afmctl learn step --help' and docs/LEARNING.md.
"""

STEP_HELP = "one learning iteration from files: target + sent + measured -> next voltages"

STEP_DESCRIPTION = """\
One iteration of iterative learning control from files.

Input:
  --target TARGET.csv     columns t,y: time (s, uniformly spaced) and the desired
                          motion (nm) — the same file every iteration
  --sent VOLTS.csv        columns t,u: the voltages (V) that were played, one row per
                          target row (the first iteration: e.g. the output of
                          'afmctl compensate', or a linear calibration)
  --measured MEAS.csv     columns t,y: the motion (nm) recorded while they played. Its
                          t column says when each sample was taken on the table's clock
                          (a recording that started late has a later first t); it is
                          interpolated onto the target's rows and must cover them.
  --model MODEL.json      the identified model (a chain from 'afmctl identify', or any
                          hysteresis model): its inverse is the learning filter. Without
                          it the frequency response is estimated from the iteration
                          itself (model-free; start from a linear calibration).
Output:
  --out NEXT.csv          columns t,u: the voltages to play next, same rows as the target,
                          within --limits and --slew-V-per-s
  --state STATE.json      keeps the history between iterations (created if missing): the
                          divergence guard (error rising twice in a row stops learning and
                          writes the best table) needs it. Use one state file per target.

The law (docs/LEARNING.md):  u_next = u + Q·ρ·Ĝ⁻¹·(W·e),  e = target − measured,
per frequency (per harmonic for a periodic table). W weights the central part of the
judged raster lines (found in the target): by default every line but the first, which
the scanner starts from rest (--judge-lines names others); the turnarounds the amplifier
cannot follow do not pull the learning off. Each play measures the scanner's response at
the harmonics it excites: where the model is off, the measured response corrects it, and
the Q-filter reaches as high as the plays measured the response above the sensor's noise
(estimated from the repeating lines, and not counted as error). A stop names its floor:
the range, the slew limit, the noise, or what the line rate permits.

Printed: the sent table's error (max / RMS % of the span over the whole file, over the
central 80 % of each line, and over the judged lines in % and nm of the line), the
sensor's noise, the recording's lag behind the prediction, the step size and Q cut-off,
what changed, and whether learning stopped and on which floor.

Example (iterate: play NEXT.csv, record, repeat with --sent NEXT.csv):
  afmctl compensate --model chain.json --target line.csv --out u0.csv --slew-V-per-s 1e4 --clip
  afmctl learn step --target line.csv --sent u0.csv --measured y0.csv --model chain.json \\
      --out u1.csv --limits 0 150 --slew-V-per-s 1e4 --state learn.json
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    from .learn_device import DEVICE_HELP, add_device_arguments, run_device
    p = subparsers.add_parser("learn", help=HELP, description=DESCRIPTION + "\n" + DEVICE_HELP,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    add_device_arguments(p)
    sub = p.add_subparsers(dest="learn_verb", metavar="SUBCOMMAND")
    for reg in SUBCOMMANDS.values():
        reg(sub)
    # without a subcommand, learn runs on the device ('afmctl learn --config RUN.toml ...')
    p.set_defaults(func=lambda args: run_device(args) if args.config else _no_subcommand(p))


def _no_subcommand(p: argparse.ArgumentParser) -> int:
    """``afmctl learn`` without a subcommand nor ``--config``: its help."""
    p.print_help()
    return 0


def register_step(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("step", help=STEP_HELP, description=STEP_DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--target", required=True, metavar="TARGET.csv", help="CSV with columns t,y (s, nm)")
    p.add_argument("--sent", required=True, metavar="VOLTS.csv", help="CSV with columns t,u (s, V): what was played")
    p.add_argument("--measured", required=True, metavar="MEAS.csv", help="CSV with columns t,y (s, nm): what moved")
    p.add_argument("--out", required=True, metavar="NEXT.csv", help="output CSV, columns t,u (s, V)")
    p.add_argument("--model", metavar="MODEL.json", help="model file (chain or hysteresis kind); none: model-free")
    p.add_argument("--axis", choices=("x", "y", "z"), help="axis of a scanner model file (kind scanner)")
    p.add_argument("--limits", nargs=2, type=float, metavar=("LO", "HI"),
                   help="voltage range [V] (default: the model's range, else 0..150 V)")
    p.add_argument("--slew-V-per-s", type=float, metavar="S", help="amplifier slew limit [V/s]")
    p.add_argument("--state", metavar="STATE.json", help="iteration state file (created if missing)")
    p.add_argument("--step-size", type=float, metavar="RHO",
                   help="largest step size ρ, 0 < ρ ≤ 2 (default 1 with --model: a full inverse step, sized down "
                        "per harmonic from the model's measured error; 0.7 without)")
    p.add_argument("--q-cutoff-Hz", type=float, metavar="HZ",
                   help="Q-filter cut-off [Hz] (default: the model's band limit; model-free: what the data excite)")
    p.add_argument("--central-pct", type=float, default=CENTRAL_PCT, metavar="P",
                   help="weighted central share of each raster line [%%] (default 80: the part the error is judged "
                        "on and an AFM images; the rest of each line is the turnaround, rounded; 100: no weighting)")
    p.add_argument("--lines-only", action="store_true", help="weight only the lines' central parts (rests count 0)")
    p.add_argument("--judge-lines", metavar="LIST",
                   help="raster lines (1-based; trace and retrace make one) the error is judged and learned on, "
                        "e.g. 2-6 or 1,3,5-8 (default: every line but the first, which starts from rest; all of a "
                        "one-line target)")
    p.add_argument("--periodic", action="store_true",
                   help="the table plays cyclically and was recorded in steady state (learning per harmonic)")
    p.add_argument("--align", action="store_true",
                   help="treat the estimated lag of the recording as a trigger offset and shift it back")
    p.set_defaults(func=run_step)


#: learn's subcommands: name → function adding its parser
SUBCOMMANDS: dict[str, Callable[[argparse._SubParsersAction], None]] = {"step": register_step}


def run_step(args: argparse.Namespace) -> int:

    from ..data.datafiles import write_csv
    from ..data.learnfiles import load_inputs, load_state, save_state, settings_from_args
    from afmctl.compensators.learning import Learner

    inputs = load_inputs(args)
    settings, source = settings_from_args(args, inputs.model)
    from afmctl.compensators.base import ModelError
    try:
        learner = Learner(inputs.target_nm, inputs.dt_s, inputs.model, settings, load_state(args.state))
    except ModelError as err:
        if "judged line" in str(err):
            raise AfmctlError(f"--judge-lines: {err}") from None
        raise
    if learner.state.stopped:
        print(f"status           : already stopped ({learner.state.reason}); writing the best table again")
    res = learner.step(inputs.sent_V, inputs.measured_nm)
    _check_table(res.u_next_V, settings, inputs.dt_s)
    write_csv(args.out, {"t": inputs.t_s, "u": res.u_next_V})
    if args.state:
        save_state(args.state, learner.state)
    _print_result(res, settings, source, inputs, args)
    return 0


def _check_table(u, settings, dt_s: float) -> None:
    """The driver's own check of a whole table before anything is written: every sample
    inside the limits, every step within the slew limit."""
    from afmctl.drivers.base import VoltageLimits
    from afmctl.drivers.wave_check import check_table

    step = None if settings.slew_V_per_s is None else settings.slew_V_per_s * dt_s
    check_table("learned", u, VoltageLimits(settings.u_min_V, settings.u_max_V), max_step_V=step,
                wraps=settings.periodic)


def _print_result(res, settings, source: str, inputs, args) -> None:
    import math

    e = res.errors
    print(f"iteration        : {res.iteration} ({'model-based, ' + args.model if res.law == 'model' else 'model-free'})")
    print(f"error (sent)     : max {e['max_pct']:.3g} % / RMS {e['rms_pct']:.3g} % of the span (whole file)")
    if "central_max_pct" in e:
        print(f"error (lines)    : max {e['central_max_pct']:.3g} % / RMS {e['central_rms_pct']:.3g} % of the line "
              "(central 80 % of each line)")
    if "judged_max_pct" in e:
        line = e["line_nm"]
        print(f"judged           : {res.judged}")
        print(f"error (judged)   : max {e['judged_max_pct']:.3g} % ({e['judged_max_pct'] * line / 100:.4g} nm) / RMS "
              f"{e['judged_rms_pct']:.3g} % of the {line:.5g} nm line; without the noise max "
              f"{res.weighted_max_pct:.3g} %")
    if res.noise_nm > 0:
        print(f"sensor noise     : σ {res.noise_nm:.3g} nm (not counted as error)")
    lag_us = res.lag_samples * inputs.dt_s * 1e6
    print(f"recording lag    : {res.lag_samples:+.2f} samples ({lag_us:+.4g} µs) behind the "
          f"{'prediction' if res.law == 'model' else 'target'}" + ("; shifted back (--align)" if res.aligned else ""))
    if math.isfinite(res.q_cutoff_Hz):
        print(f"learning         : step size ρ median {res.rho_median:.3g}, Q-filter cut-off {res.q_cutoff_Hz:.4g} Hz "
              "(where the plays measured the response)"
              + (f", largest phase error {res.phase_error_deg:.0f}° at {res.phase_error_f_Hz:.4g} Hz"
                 if res.law == "model" else ""))
    print(f"changed          : max {res.du_max_V:.4g} V, RMS {res.du_rms_V:.4g} V; {res.clipped} samples clipped, "
          f"{res.slew_limited} slew-limited")
    print(f"limits           : {settings.u_min_V:g} .. {settings.u_max_V:g} V ({source})"
          + (f", slew {settings.slew_V_per_s:g} V/s" if settings.slew_V_per_s else ", no slew limit given"))
    if res.stopped:
        print(f"status           : stopped: {res.reason}")
    else:
        print("status           : learning")
    print(f"written          : {args.out} ({res.u_next_V.size} rows, u from {res.u_next_V.min():.6g} to "
          f"{res.u_next_V.max():.6g} V)")
