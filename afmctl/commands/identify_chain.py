"""``afmctl identify --model auto`` and ``--model KIND+creep[+dynamics]``: the chain
branch of ``identify`` (kept apart so that identify.py stays about single kinds)."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)


def _read(args: argparse.Namespace):
    """The recording conditioned as for single kinds (units, spikes, uniform sampling, the
    estimated sensor delay applied), from the end of the burn-in on: ``(t, u, y, delay_s)``."""
    from ..errors import AfmctlError
    from ..identdata import delayed
    from .identify_io import _read_conditioned

    if getattr(args, "from_images", None) is not None:
        raise AfmctlError(f"--model {args.model}: chains and auto are identified from --data (t,u,y); "
                          "--from-images takes a single kind")
    if args.data is None:
        raise AfmctlError("--data: required; give a CSV with columns t,u,y (s, V, nm)")
    if args.operators is not None and args.operators < 1:
        raise AfmctlError(f"--operators: {args.operators} must be ≥ 1")
    c = _read_conditioned(args, uniform=True)
    k = c.fit_from
    for note in c.notes:
        print(f"data             : {note}")
    u = delayed(c.t_s, c.u_V, c.delay_s)
    return c.t_s[k:], u[k:], c.y_nm[k:], c.delay_s


def _fit(args: argparse.Namespace, t, u, y):
    from afmctl.compensators.chain import ChainModel, parse_structure
    from afmctl.compensators.chain import format_table
    from afmctl.compensators.selection import select_model

    from .identify_io import parse_params
    params = parse_params(args.param)
    if args.operators is not None:
        params["n_operators"] = args.operators
    if args.model == "auto":
        holdout = float(params.pop("holdout_fraction", 0.3))
        candidates = params.pop("candidates", None)
        kwargs = {"candidates": tuple(candidates)} if candidates else {}
        model, table = select_model(t, u, y, holdout_fraction=holdout, options=params, **kwargs)
        print(f"held-out prediction error (last {holdout:.0%} of {args.data}; % of its span):")
        print(format_table(table))
        print(f"selected         : {model.structure}")
        return model
    parse_structure(args.model)
    return ChainModel.identify(t, u, y, structure=args.model, **params)


def run_chain(args: argparse.Namespace) -> int:
    """Identify a chain (or select one), print the summary and the fit residual, save."""
    import numpy as np

    from afmctl.compensators.base import ModelError
    from afmctl.compensators.models import save_model

    from ..errors import AfmctlError
    from .identify_io import _plot
    t, u, y, delay_s = _read(args)
    try:
        model = _fit(args, t, u, y)
    except TypeError as err:
        raise AfmctlError(f"--param: not accepted by --model {args.model} ({err})") from None
    except ModelError as err:
        raise ModelError(f"{args.data}: {err}") from None
    except np.linalg.LinAlgError as err:
        raise ModelError(f"{args.data}: the fit failed ({err}); is the input excited over its range?") from None
    dt = float(np.median(np.diff(t)))
    y_fit = model.forward(dt).block(np.ascontiguousarray(u))
    rms = float(np.sqrt(np.mean((y_fit - y) ** 2)))
    peak = float(np.max(np.abs(y_fit - y)))
    span = float(np.ptp(y)) or 1.0
    model.delay_s = delay_s
    if model.u_range_V is None:        # compensate's default --limits
        model.u_range_V = (float(np.min(u)), float(np.max(u)))
    try:
        save_model(model, args.out)
    except OSError as err:
        raise AfmctlError(f"--out: cannot write {args.out} ({err.strerror})") from None
    print(model.summary())
    print(f"fit residual     : rms {rms:.4g} nm, max {peak:.4g} nm ({100 * peak / span:.3g} % of the {span:.4g} nm span)")
    print(f"written          : {args.out}")
    if args.plot:
        _plot(args.plot, t, u, y, y_fit, model.structure)
        print(f"plot             : {args.plot}")
    return 0
