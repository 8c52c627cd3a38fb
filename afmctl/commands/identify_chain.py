"""``afmctl identify --model auto`` and ``--model KIND+creep[+dynamics]``: the chain
branch of ``identify`` (kept apart so that identify.py stays about single kinds)."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)


def _read(args: argparse.Namespace):
    """The recording conditioned as for single kinds (units, spikes, uniform sampling, the
    estimated sensor delay applied), whole: ``(t, u, y, delay_s, fit_from)``; the samples
    before ``fit_from`` (the burn-in) only set the models' memory."""
    from ..errors import AfmctlError
    from ..data.identdata import delayed
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
    return c.t_s, u, c.y_nm, c.delay_s, k


def _fit(args: argparse.Namespace, t, u, y, fit_from: int):
    from afmctl.compensators.chain import ChainModel, format_table, parse_structure
    from afmctl.compensators.selection import CRITERIA, select_model

    from ..errors import AfmctlError
    from .identify_io import parse_params
    params = parse_params(args.param)
    if args.operators is not None:
        params["n_operators"] = args.operators
    if args.model == "auto":
        holdout = float(params.pop("holdout_fraction", 0.3))
        candidates = params.pop("candidates", None)
        criterion = params.pop("criterion", "rms")
        with_dynamics = params.pop("with_dynamics", True)
        if not isinstance(with_dynamics, bool):
            raise AfmctlError(f"--param with_dynamics: {with_dynamics!r}; allowed true or false")
        if criterion not in CRITERIA:
            raise AfmctlError(f"--param criterion: {criterion!r}; allowed {', '.join(CRITERIA)} (held-out error)")
        kwargs = {"candidates": tuple(candidates)} if candidates else {}
        model, table = select_model(t, u, y, holdout_fraction=holdout, options=params, fit_from_index=fit_from,
                                    criterion=criterion, with_dynamics=with_dynamics, **kwargs)
        print(f"held-out prediction error (last {holdout:.0%} of {args.data} after the burn-in; % of its span; "
              f"ranked by {criterion}" + ("; the leading candidates also on earlier blocks, fitted on what precedes "
                                          "each; the simplest adequate model wins" if criterion == "rms" else "")
              + "):")
        print(format_table(table))
        print(f"selected         : {model.structure}")
        return model
    parse_structure(args.model)
    return ChainModel.identify(t, u, y, structure=args.model, fit_from_index=fit_from, **params)


def run_chain(args: argparse.Namespace) -> int:
    """Identify a chain (or select one), print the summary and the fit residual, save."""
    import numpy as np

    from afmctl.compensators.base import ModelError
    from afmctl.compensators.models import save_model

    from ..errors import AfmctlError
    from .identify_io import _plot
    t, u, y, delay_s, k = _read(args)
    try:
        model = _fit(args, t, u, y, k)
    except TypeError as err:
        raise AfmctlError(f"--param: not accepted by --model {args.model} ({err})") from None
    except ModelError as err:
        raise ModelError(f"{args.data}: {err}") from None
    except np.linalg.LinAlgError as err:
        raise ModelError(f"{args.data}: the fit failed ({err}); is the input excited over its range?") from None
    dt = float(np.median(np.diff(t)))
    y_fit = model.forward(dt).block(np.ascontiguousarray(u))
    res = (y_fit - y)[k:]               # the burn-in only set the memory
    rms = float(np.sqrt(np.mean(res ** 2)))
    peak = float(np.max(np.abs(res)))
    span = float(np.ptp(y[k:])) or 1.0
    from .identify_io import _refuse_failed
    _refuse_failed(args, model, y, u, y_fit, k)
    model.delay_s = delay_s
    if model.u_range_V is None:        # compensate's default --limits
        model.u_range_V = (float(np.min(u)), float(np.max(u)))
    try:
        save_model(model, args.out)
    except OSError as err:
        raise AfmctlError(f"--out: cannot write {args.out} ({err.strerror})") from None
    print(model.summary())
    print(f"fit residual     : rms {rms:.4g} nm, max {peak:.4g} nm ({100 * peak / span:.3g} % of the {span:.4g} nm span)"
          + (f", from t = {float(t[k]):.4g} s" if k else ""))
    print(f"written          : {args.out}")
    if args.plot:
        _plot(args.plot, t[k:], u[k:], y[k:], y_fit[k:], model.structure)
        print(f"plot             : {args.plot}")
    return 0
