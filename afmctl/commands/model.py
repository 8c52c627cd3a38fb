"""``afmctl model``: inspect model files and write inverse PI parameters."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)

HELP = "show a model file, or write the inverse operator of a PI-family model"

DESCRIPTION = """\
Work with model JSON files written by 'afmctl identify'.

  afmctl model show --model MODEL.json
      a human summary: kind, parameters with units, invertibility.
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
    p.set_defaults(func=lambda args: _usage(p))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def run_show(args: argparse.Namespace) -> int:
    from afmctl.compensators.models import load_model

    model = load_model(args.model)
    print(f"file             : {args.model}")
    print(model.summary())
    return 0


def run_invert(args: argparse.Namespace) -> int:
    from ..errors import AfmctlError
    from afmctl.compensators.models import load_model, save_model

    model = load_model(args.model, expect=("pi", "epi"))
    inv = model.inverted()
    try:
        save_model(inv, args.out)
    except OSError as err:
        raise AfmctlError(f"--out: cannot write {args.out} ({err.strerror})") from None
    print(f"written          : {args.out} (direction {inv.direction}: thresholds/weights of the "
          f"{'inverse y[nm] -> u[V]' if inv.direction == 'inverse' else 'forward u[V] -> y[nm]'} operator)")
    return 0
