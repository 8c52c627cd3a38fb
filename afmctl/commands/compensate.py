"""``afmctl compensate``: offline feedforward — desired positions to amplifier voltages
through the inverse of any model kind."""
from __future__ import annotations

import argparse
import logging

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
                       and rate-limited, and reported. A chain model with a dynamics
                       stage (e.g. preisach+creep+dynamics) is inverted the same way,
                       within --limits (default: the model's range) and --slew-V-per-s.
  --slew-V-per-s S     the amplifier's slew limit [V/s] (with --dynamics or a chain
                       model with a dynamics stage)

The model's operator starts from the state stored in the model file (a scanner at rest)
and runs through the whole file. A preisach model clamps targets it cannot reach to the
ends of its grid range u_min_V..u_max_V and logs a warning.

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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..data.datafiles import read_csv, uniform_period, write_csv
    from ..errors import AfmctlError
    from afmctl.compensators.base import ModelError
    from afmctl.compensators.models import load_model

    if args.limits and not (np.isfinite(args.limits).all() and args.limits[0] < args.limits[1]):
        raise AfmctlError(f"--limits: {args.limits[0]} {args.limits[1]}; need finite LO < HI (V)")
    model = _axis_model(load_model(args.model), args)
    if model.kind == "dynamics":
        raise AfmctlError(f"{args.model}: field kind: a 'dynamics' model maps nm to nm, not to volts; give it as "
                          "--dynamics beside a --model that maps volts (pi, epi, creep, preisach, bouc-wen, chain)")
    if args.dynamics is not None and getattr(model, "dynamics", None) is not None:
        raise AfmctlError(f"--dynamics: {args.model} already holds a dynamics stage ({model.structure}); drop --dynamics")
    with_dynamics = args.dynamics is not None or getattr(model, "dynamics", None) is not None
    if args.slew_V_per_s is not None and not with_dynamics:
        raise AfmctlError("--slew-V-per-s: only used with --dynamics DYN.json or a chain model with a dynamics stage")
    data = read_csv(args.target, ("t", "y"), min_rows=1)
    t, y = data["t"], data["y"]
    timed = getattr(model, "time_dependent", False) or with_dynamics
    dt = uniform_period(t, str(args.target)) if timed else None
    if with_dynamics:
        def invert(target):
            return _with_dynamics(args, model, target, dt)
    else:
        invert = _inverter(model, dt, args)
    try:
        u = invert(y)
    except ModelError as err:
        raise ModelError(f"{args.target}: {err}") from None
    if not np.all(np.isfinite(u)):
        raise AfmctlError(f"{args.model}: the inverse produced non-finite voltages for {args.target}; "
                          "is the target inside the model's range?")
    lo, hi, source = _limits(args.limits, model)
    print(f"limits           : {lo:g} .. {hi:g} V ({source})")
    bad = (u < lo) | (u > hi)
    if np.any(bad):
        if not args.clip:
            i = int(np.flatnonzero(bad)[0])
            raise AfmctlError(f"{args.target}: row {i + 2} needs {u[i]:.6g} V, outside the limits {lo:g}..{hi:g} V "
                              f"({source}; {int(bad.sum())} samples); give --limits LO HI, "
                              "or add --clip to clip them")
        print(f"clipped          : {int(bad.sum())} of {u.size} samples to [{lo:g}, {hi:g}] V")
        u = np.clip(u, lo, hi)
    write_csv(args.out, {"t": t, "u": u})
    print(f"written          : {args.out} ({u.size} rows, u from {u.min():.6g} to {u.max():.6g} V)")
    return 0


def _inverter(model, dt, args: argparse.Namespace):
    """target [nm] → voltages [V] for a model without dynamics: its inverse streams
    (chunked). A model that cannot be inverted is blamed on the model file."""
    from afmctl.compensators.base import ModelError
    try:
        inverse = model.inverse(dt)
    except ModelError as err:  # e.g. a Bouc–Wen model that is not invertible
        raise ModelError(f"{args.model}: {err}") from None
    return lambda y: _run_chunked(inverse, y)


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


CHUNK = 200_000
#: limits when neither --limits nor the model file gives a voltage range [V]
FALLBACK_LIMITS_V = (0.0, 150.0)


def _limits(given, model) -> tuple[float, float, str]:
    """``(lo, hi, where from)`` [V]: --limits, else the model's voltage range, else 0..150 V."""
    if given:
        return float(given[0]), float(given[1]), "--limits"
    known = model.voltage_range_V()
    if known is not None:
        return float(known[0]), float(known[1]), "the model's voltage range"
    return (*FALLBACK_LIMITS_V, "the model file records no voltage range; give --limits")


def _with_dynamics(args, model, y, dt):
    """The offline inverse within --limits/--slew-V-per-s: a chain model's own dynamics
    stage (:meth:`ChainModel.inverse_within_limits`), or --dynamics then ``model``'s
    inverse — the same :func:`invert_within_limits` either way."""
    import math

    from ..errors import AfmctlError
    from afmctl.compensators.dynamics_limits import invert_within_limits
    from afmctl.compensators.models import load_model

    slew = args.slew_V_per_s
    if slew is not None and not (math.isfinite(slew) and slew > 0):
        raise AfmctlError(f"--slew-V-per-s: {slew}; need a finite rate > 0 V/s")
    lo, hi, _ = _limits(args.limits, model)
    if args.dynamics is None:
        res = model.inverse_within_limits(y, dt, lo, hi, slew)
    else:
        dyn = load_model(args.dynamics, expect=("dynamics",))
        res = invert_within_limits(dyn, y, dt, lambda: model.inverse(dt), lo, hi, slew)
    print(f"dynamics         : {res.report()}")
    if res.clipped and not args.clip:
        raise AfmctlError(f"{args.target}: {res.clipped} samples need voltages outside the limits {lo:g}..{hi:g} V "
                          "even with the lowest band limit; add --clip to clip them")
    return res.u_V


def _run_chunked(op, y):
    """``op.block(y)`` in chunks (state carries over, so the result is identical) with a
    progress bar on long files when stderr is a terminal."""
    import numpy as np

    if y.size <= CHUNK:
        return op.block(y)
    from tqdm import tqdm

    out = np.empty_like(y)
    with tqdm(total=y.size, unit="sample", unit_scale=True, desc="compensate", disable=None) as bar:
        for start in range(0, y.size, CHUNK):
            seg = y[start:start + CHUNK]
            out[start:start + seg.size] = op.block(seg)
            bar.update(seg.size)
    return out
