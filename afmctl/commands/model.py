"""``afmctl model``: inspect model files and write inverse PI parameters."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)

HELP = "show a model file, run it on new voltages, validate it on held-out data, or invert a PI model"

DESCRIPTION = """\
Work with model JSON files written by 'afmctl identify'.

  afmctl model show --model MODEL.json
      a human summary: kind, parameters with units, invertibility.
  afmctl model predict --model MODEL.json --voltages V.csv --out Y.csv [--warm-start DATA.csv]
      run the model forward: V.csv has columns t,u (s, V); Y.csv gets t,y (s, nm), one
      row per input row. The model starts as its file says, or after running through the
      voltages of DATA.csv (columns t,u) when --warm-start is given.
  afmctl model validate --model MODEL.json --data HELDOUT.csv [--warm-start DATA.csv] [--plot FIG.png]
      predict a held-out recording (t,u,y in s, V, nm) and print the error: RMS and max,
      with and without the mean offset (a second recording sits on another sensor offset),
      for the whole record and per input cycle, in nm and % of the measured span. Without
      --warm-start, samples until the input has passed both its extremes only set the
      model's memory (the record's start is unknown) and are not scored.
  afmctl model invert --model MODEL.json --out INVERSE.json
      PI-family models (pi, epi): write the same model with the inverse operator's
      parameters at the top level (eqs. 8-11 of the extended-PI paper): 'thresholds'
      in nm, 'weights' in V/nm, 'initial_state' in nm, and "direction": "inverse".
      The file is still a valid model (compensate/identify treat it like the original);
      inverting it again gives the forward parameters back.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("model", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="model_cmd", metavar="ACTION")
    ps = sub.add_parser("show", help="print a human summary of a model file",
                        description="Print a human summary of a model file.\n\nExample:\n  afmctl model show --model pi.json",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ps.add_argument("--model", required=True, metavar="MODEL.json", help="model JSON file")
    ps.set_defaults(func=run_show)
    pi = sub.add_parser("invert", help="write the inverse operator's parameters (pi, epi)",
                        description="Write the inverse PI operator's parameters (thresholds in nm, weights in "
                                    "V/nm) at the top level.\n\nExample:\n"
                                    "  afmctl model invert --model pi.json --out pi_inverse.json",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pi.add_argument("--model", required=True, metavar="MODEL.json", help="PI-family model file (kind pi or epi)")
    pi.add_argument("--out", required=True, metavar="INVERSE.json", help="where to write the inverse")
    pi.set_defaults(func=run_invert)
    _register_predict(sub)
    _register_validate(sub)
    p.set_defaults(func=lambda args: _usage(p))


def _register_predict(sub: argparse._SubParsersAction) -> None:
    pp = sub.add_parser("predict", help="run a model forward on voltages: t,u (s, V) -> t,y (s, nm)",
                        description="Run a model forward on new voltages.\n\nExample:\n"
                                    "  afmctl model predict --model pi.json --voltages volts.csv --out y.csv",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pp.add_argument("--model", required=True, metavar="MODEL.json", help="model JSON file (any kind)")
    pp.add_argument("--voltages", required=True, metavar="V.csv", help="CSV with columns t,u (s, V)")
    pp.add_argument("--out", required=True, metavar="Y.csv", help="where to write t,y (s, nm)")
    pp.add_argument("--warm-start", metavar="DATA.csv",
                    help="run the model through this recording's t,u first (the history before V.csv)")
    pp.set_defaults(func=run_predict)


def _register_validate(sub: argparse._SubParsersAction) -> None:
    pv = sub.add_parser("validate", help="score a model on a held-out recording t,u,y (s, V, nm)",
                        description="Predict a held-out recording and print RMS/max errors with and without the "
                                    "mean offset, whole record and per input cycle.\n\nExample:\n"
                                    "  afmctl model validate --model pi.json --data heldout.csv --plot val.png",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pv.add_argument("--model", required=True, metavar="MODEL.json", help="model JSON file (any kind)")
    pv.add_argument("--data", required=True, metavar="HELDOUT.csv", help="CSV with columns t,u,y (s, V, nm); an optional column measured (0/1): rows 0 are not scored")
    pv.add_argument("--warm-start", metavar="DATA.csv", help="run the model through this recording's t,u first")
    pv.add_argument("--y-unit", default="nm", metavar="nm|um", help="unit of the data's y column (default nm)")
    pv.add_argument("--plot", metavar="FIG.png", help="draw measured vs predicted and the error")
    pv.set_defaults(func=run_validate)


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def run_show(args: argparse.Namespace) -> int:
    from afmctl.compensators.models import load_model

    model = load_model(args.model)
    print(f"file             : {args.model}")
    print(model.summary())
    if getattr(model, "delay_s", 0.0):
        print(f"delay            : {model.delay_s:.6g} s (input-output delay; model predict/validate honour it)")
    return 0


def run_invert(args: argparse.Namespace) -> int:
    from ..errors import AfmctlError
    from afmctl.compensators.models import load_model, save_model

    from afmctl.compensators.pi import PIFamilyModel

    model = load_model(args.model, expect=("pi", "epi"))
    assert isinstance(model, PIFamilyModel)  # the kinds pi and epi
    inv = model.inverted()
    try:
        save_model(inv, args.out)
    except OSError as err:
        raise AfmctlError(f"--out: cannot write {args.out} ({err.strerror})") from None
    print(f"written          : {args.out} (direction {inv.direction}: thresholds/weights of the "
          f"{'inverse y[nm] -> u[V]' if inv.direction == 'inverse' else 'forward u[V] -> y[nm]'} operator)")
    return 0


def _warm(path: str | None):
    from ..data.datafiles import read_csv

    if path is None:
        return None
    d = read_csv(path, ("t", "u"), min_rows=1)
    return d["t"], d["u"]


def run_predict(args: argparse.Namespace) -> int:
    from ..api.models import predict
    from ..data.datafiles import read_csv, write_csv
    from afmctl.compensators.models import load_model

    model = load_model(args.model)
    v = read_csv(args.voltages, ("t", "u"), min_rows=1)
    y = predict(model, v["t"], v["u"], warm=_warm(args.warm_start), where=str(args.voltages))
    write_csv(args.out, {"t": v["t"], "y": y})
    print(f"model predict: {y.size} rows, y {float(y.min()):.6g} … {float(y.max()):.6g} nm -> {args.out}")
    return 0


def run_validate(args: argparse.Namespace) -> int:
    from ..api.models import validate
    from ..data.datafiles import read_csv
    from ..errors import AfmctlError
    from ..data.identdata import Y_UNITS
    from afmctl.compensators.models import load_model

    model = load_model(args.model)
    if args.y_unit not in Y_UNITS:
        raise AfmctlError(f"--y-unit: {args.y_unit!r} is not known; allowed: nm, um")
    d = read_csv(args.data, ("t", "u", "y"), min_rows=2, optional=("measured",))
    t, u = d["t"], d["u"]
    res = validate(model, t, u, d["y"], warm=_warm(args.warm_start), y_unit=args.y_unit, where=str(args.data),
                   measured=d.get("measured"))
    start, stats = res.start, res.stats
    print(f"model            : {args.model} (kind {model.kind})")
    print(f"data             : {args.data}, {t.size} rows"
          + (f"; scored from t = {float(t[start]):.4g} s (burn-in until the input passed both extremes)" if start else ""))
    print(f"errors [nm]      : model − measured; '-mean' with the mean offset removed; % of the {stats[0].span_nm:.4g} nm span")
    print(res.table())
    if args.plot:
        from ..data.prediction import plot_validation
        plot_validation(args.plot, t, u, d["y"] * Y_UNITS[args.y_unit], res.y_pred_nm, start,
                        f"{model.kind} model, {args.data}")
        print(f"plot             : {args.plot}")
    return 0
