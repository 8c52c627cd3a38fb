"""``afmctl identify --model auto`` and ``--model KIND+creep[+dynamics]``: the chain
branch of ``identify`` (kept apart so that identify.py stays about single kinds)."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)


def run_chain(args: argparse.Namespace) -> int:
    """Identify a chain (or select one: the held-out table is printed), print the summary
    and the fit residual, save. The steps are :func:`afmctl.api.identify.identify`'s; what
    conditioning did is printed before the fit."""
    from afmctl.compensators.chain import format_table

    from ..errors import AfmctlError
    from .identify_io import _fitted, _plot, _refuse_failed, _save
    if getattr(args, "from_images", None) is not None:
        raise AfmctlError(f"--model {args.model}: chains and auto are identified from --data (t,u,y); "
                          "--from-images takes a single kind")
    fitted = _fitted(args, show_notes=True)
    model, k = fitted.model, fitted.fit_from
    if fitted.table is not None:
        print(f"held-out prediction error (last {fitted.holdout_fraction:.0%} of {args.data} after the burn-in; % of "
              f"its span; ranked by {fitted.criterion}"
              + ("; the leading candidates also on earlier blocks, fitted on what precedes each; the simplest "
                 "adequate model wins" if fitted.criterion == "rms" else "") + "):")
        print(format_table(fitted.table))
        print(f"selected         : {model.structure}")
    _refuse_failed(args, fitted)
    _save(model, args.out)
    print(model.summary())
    print(f"fit residual     : {fitted.residual()}")
    print(f"written          : {args.out}")
    if args.plot:
        _plot(args.plot, fitted.t_s[k:], fitted.u_V[k:], fitted.y_nm[k:], fitted.y_fit_nm[k:], model.structure)
        print(f"plot             : {args.plot}")
    return 0
