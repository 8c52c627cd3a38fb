"""``afmctl compensate``: offline feedforward — desired positions to amplifier voltages
through the inverse of any model kind."""
from __future__ import annotations

import argparse
import contextlib
import logging
from collections.abc import Callable, Iterator

log = logging.getLogger(__name__)

HELP = "offline feedforward: target positions (nm) -> voltages (V) through a model's inverse"

DESCRIPTION = """\
Compute the voltages that make the scanner follow a target path, using the inverse of a
fitted model (hysteresis and, for epi/creep models, creep).

Input:
  --model MODEL.json   a model file written by 'afmctl identify' (any kind, a chain such
                       as preisach+creep included; a PI file written by 'afmctl model
                       invert' works too), or a scanner model (kind scanner) with --axis
  --axis x|y|z         which axis of a scanner model to use (its coupling matrix is not
                       applied: one axis at a time)
  --target TARGET.csv  header row and columns t,y: time (s, strictly increasing) and the
                       desired displacement (nm). Time-dependent kinds (epi, creep) need
                       uniformly spaced rows.
Output:
  --out VOLTS.csv      columns t,u (s, V), one row per target row.
  --limits LO HI       voltage range (V): any voltage outside it is an error unless
                       --clip is given, which clips and reports how many samples.
                       Default: the range the model was identified on (a preisach
                       model: its grid), else 0..150 V; the limits used are printed.
  --dynamics DYN.json  also invert the scanner's linear dynamics (a 'dynamics' model from
                       'afmctl identify --model dynamics'): the target first goes through
                       the stable non-causal inverse of the dynamics over the whole file
                       (delay and resonance compensated, no latency), then through
                       --model's inverse. Needs uniformly spaced rows; the path should
                       start and end at rest. With --slew-V-per-s (and --limits) the
                       inverse's band limit is lowered until the voltages fit (the
                       turnarounds get rounder); what is still out of reach is clipped
                       and rate-limited, and reported. When even the static (hysteresis,
                       creep) inverse alone changes faster than S, the report says the
                       target itself is too fast for the amplifier and at what share of
                       its speed it would fit: scan slower there. A chain model with a
                       dynamics stage (e.g. preisach+creep+dynamics) is inverted the same way,
                       within --limits (default: the model's range) and --slew-V-per-s.
  --slew-V-per-s S     the amplifier's slew limit [V/s], with every model: with dynamics
                       as above; otherwise the voltages are rate-limited to it and the
                       report says how many samples that took (and when the target
                       itself is too fast). A chain with an amplifier stage also keeps
                       the piezo voltage within the stage's own identified slew limit.
The largest voltage step per sample the voltages make is printed: a step the amplifier and
the scanner's first mode would turn into ringing shows there.

The scanner is taken to have rested at the target's first point (--start rest, the
default): a creep stage starts settled there, and the hysteresis from the memory stored in
the model file. --start model takes every stage as stored (the scanner at rest where the
identification's recording began, usually the bottom of the range, and moved to the first
point at once, its creep still running): use it for a table played right after such a move.
(`afmctl run` plans its wave tables from the stored state: it ramps from the safe value and
plays after a settle hold of seconds, which leaves most of the creep still running.)
The operators then run through the whole file. A preisach model clamps targets it cannot
reach to the ends of its grid range u_min_V..u_max_V and logs a warning.

Example:
  afmctl compensate --model pi.json --target raster_x.csv --out volts_x.csv --limits 0 150
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("compensate", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, metavar="MODEL.json", help="model JSON file (any kind)")
    p.add_argument("--target", required=True, metavar="TARGET.csv", help="CSV with columns t,y (s, nm)")
    p.add_argument("--out", required=True, metavar="VOLTS.csv", help="output CSV with columns t,u (s, V)")
    p.add_argument("--axis", choices=("x", "y", "z"), help="axis of a scanner model file (kind scanner)")
    p.add_argument("--limits", nargs=2, type=float, metavar=("LO", "HI"), help="allowed voltage range [V]")
    p.add_argument("--clip", action="store_true", help="clip to --limits instead of failing")
    p.add_argument("--dynamics", metavar="DYN.json", help="dynamics model to invert first (offline stable inverse)")
    p.add_argument("--slew-V-per-s", type=float, metavar="S", help="slew limit [V/s] for --dynamics")
    p.add_argument("--start", choices=("rest", "model"), default="rest",
                   help="the scanner's state before the first row: rest (default: it has rested at the "
                        "target's first point, its creep settled) or model (as stored in the model file)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..api.compensation import compensate
    from ..api.models import LimitsExceeded
    from ..data.datafiles import read_csv, write_csv
    from ..errors import AfmctlError
    from afmctl.compensators.models import load_model

    if args.limits and not (np.isfinite(args.limits).all() and args.limits[0] < args.limits[1]):
        raise AfmctlError(f"--limits: {args.limits[0]} {args.limits[1]}; need finite LO < HI (V)")
    model = _axis_model(load_model(args.model), args)
    _check_flags(args, model)
    data = read_csv(args.target, ("t", "y"), min_rows=1)
    t, y = data["t"], data["y"]
    dyn = load_model(args.dynamics, expect=("dynamics",)) if args.dynamics is not None else None
    lo, hi, source = _limits(args.limits, model)
    limits_line = f"limits           : {lo:g} .. {hi:g} V ({source})"
    try:
        with _progress(y.size) as progress:
            res = compensate(model, y, t_s=t, limits_V=(lo, hi), clip=args.clip, dynamics=dyn,
                             slew_V_per_s=args.slew_V_per_s, model_name=str(args.model), where=str(args.target),
                             progress=progress, start=args.start)
    except LimitsExceeded as err:
        if err.index < 0:
            raise AfmctlError(f"{args.target}: {err.count} samples need voltages outside the limits {lo:g}..{hi:g} V "
                              "even with the lowest band limit; add --clip to clip them") from None
        print(limits_line)
        raise AfmctlError(f"{args.target}: row {err.index + 2} needs {err.value_V:.6g} V, outside the limits "
                          f"{lo:g}..{hi:g} V ({source}; {err.count} samples); give --limits LO HI, "
                          "or add --clip to clip them") from None
    if res.dynamics_report is not None:
        label = "dynamics" if dyn is not None or getattr(model, "dynamics", None) is not None else "slew"
        print(f"{label:<17}: {res.dynamics_report}")
    print(limits_line)
    if res.clipped:
        print(f"clipped          : {res.clipped} of {res.u_V.size} samples to [{lo:g}, {hi:g}] V")
    u = res.u_V
    if u.size > 1:
        k = int(np.argmax(np.abs(np.diff(u))))
        step = float(u[k + 1] - u[k])
        print(f"largest step     : {step:+.4g} V per sample, from {u[k]:.6g} V at row {k + 2} "
              f"({abs(step) / float(t[k + 1] - t[k]):.4g} V/s)")
    write_csv(args.out, {"t": t, "u": u})
    print(f"written          : {args.out} ({u.size} rows, u from {u.min():.6g} to {u.max():.6g} V)")
    return 0


def _check_flags(args: argparse.Namespace, model) -> None:
    """The flags that do not fit this model, one line naming the flag."""
    import math

    from ..errors import AfmctlError
    if model.kind == "dynamics":
        raise AfmctlError(f"{args.model}: field kind: a 'dynamics' model maps nm to nm, not to volts; give it as "
                          "--dynamics beside a --model that maps volts (pi, epi, creep, preisach, bouc-wen, rate-pi, rate-bouc-wen, chain)")
    if args.dynamics is not None and getattr(model, "dynamics", None) is not None:
        raise AfmctlError(f"--dynamics: {args.model} already holds a dynamics stage ({model.structure}); drop --dynamics")
    slew = args.slew_V_per_s
    if slew is not None and not (math.isfinite(slew) and slew > 0):
        raise AfmctlError(f"--slew-V-per-s: {slew}; need a finite rate > 0 V/s")


def _axis_model(model, args: argparse.Namespace):
    """The model itself, or axis ``--axis`` of a scanner model (one line naming the file
    when that axis or the option is missing)."""
    from ..errors import AfmctlError
    if model.kind != "scanner":
        if args.axis:
            raise AfmctlError(f"--axis: {args.model} is a single-axis model (kind {model.kind}); drop --axis")
        return model
    if not args.axis:
        raise AfmctlError(f"--axis: {args.model} is a scanner model; choose the axis with --axis x|y|z")
    axis_model = model.axis(args.axis)
    if axis_model is None:
        raise AfmctlError(f"--axis: {args.model} has no model for axis {args.axis}")
    return axis_model


def _limits(given, model) -> tuple[float, float, str]:
    """``(lo, hi, where from)`` [V]: --limits, else the model's voltage range, else 0..150 V."""
    from ..api.models import model_limits_V
    lo, hi, source = model_limits_V(model, tuple(given) if given else None)
    if given:
        return lo, hi, "--limits"
    return lo, hi, source.replace("give limits", "give --limits")


@contextlib.contextmanager
def _progress(n: int) -> Iterator[Callable[[int], None] | None]:
    """A progress bar on long targets when stderr is a terminal (tqdm): its ``update``."""
    from ..api.models import CHUNK
    if n <= CHUNK:
        yield None
        return
    from tqdm import tqdm
    with tqdm(total=n, unit="sample", unit_scale=True, desc="compensate", disable=None) as bar:
        yield bar.update
