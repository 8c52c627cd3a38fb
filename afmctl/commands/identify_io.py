"""What ``afmctl identify`` shares between single kinds (identify.py) and chains
(identify_chain.py): ``--param`` parsing, the fit through the Python API, saving, the fit
plot and the refusal of a failed fit."""
from __future__ import annotations

import argparse
import json
import logging
from typing import Any

from ..errors import AfmctlError

log = logging.getLogger(__name__)


def parse_params(items: list[str]) -> dict[str, Any]:
    """``["a=1", "b=[1,2]", "c=text"]`` → ``{"a": 1, "b": [1, 2], "c": "text"}``."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key or not key.isidentifier():
            raise AfmctlError(f"--param: {item!r} is not KEY=VALUE with KEY a name (e.g. min_slope_fraction=1e-3)")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _fitted(args: argparse.Namespace, show_notes: bool = False):
    """``--data`` through the Python API (:func:`afmctl.api.identify.prepare` then ``fit``),
    its errors naming the command's options; ``show_notes``: print what conditioning did
    before the fit (chains)."""
    from ..api.identify import OPTIONS, fit, prepare

    if args.data is None:
        raise AfmctlError("--data: required; give a CSV with columns t,u,y (s, V, nm)")
    c, where = prepare(args.model, args.data, n_operators=args.operators, y_unit=args.y_unit,
                       burn_in=args.burn_in, delay=args.delay, despike=not args.keep_spikes, names=OPTIONS)
    for note in c.notes if show_notes else ():
        print(f"data             : {note}")
    return fit(args.model, c, where, args.operators, parse_params(args.param), OPTIONS)


def _save(model, path: str) -> None:
    from afmctl.compensators.models import save_model

    try:
        save_model(model, path)
    except OSError as err:
        raise AfmctlError(f"--out: cannot write {path} ({err.strerror})") from None


def _plot(path: str, t, u, y, y_fit, kind: str) -> None:
    from ..figures import pyplot, save_figure
    plt = pyplot()

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    a1.plot(u, y, lw=0.8, label="measured")
    a1.plot(u, y_fit, lw=0.8, ls="--", label=f"{kind} model")
    a1.set_xlabel("u [V]")
    a1.set_ylabel("y [nm]")
    a1.legend()
    a2.plot(t, y_fit - y, lw=0.6)
    a2.set_xlabel("t [s]")
    a2.set_ylabel("model − measured [nm]")
    fig.tight_layout()
    save_figure(fig, path)


def _refuse_failed(args: argparse.Namespace, fitted) -> None:
    """A failed fit (:mod:`afmctl.compensators.fit_health`) is not written without
    ``--force``: one line with the reason, exit status 2. ``fitted.y_fit_nm`` is the model's
    output on ``fitted.u_V``; samples from ``fitted.fit_from`` on were fitted (NaN: not
    predicted, the dynamics kind)."""
    import numpy as np

    from afmctl.compensators.fit_health import failure_reason, linear_fit_rms

    model, y, u, y_fit, k = fitted.model, fitted.y_nm, fitted.u_V, fitted.y_fit_nm, fitted.fit_from
    seen = np.isfinite(y_fit[k:])
    if not np.any(seen):
        return
    r = (y_fit - y)[k:][seen]
    rms = float(np.sqrt(np.mean(r ** 2)))
    # the dynamics kind is a line with dynamics: the comparison with the line says nothing
    line = float("inf") if model.kind == "dynamics" else linear_fit_rms(u[k:][seen], y[k:][seen])
    reason = failure_reason(model, rms, line)
    if reason is None:
        return
    if not getattr(args, "force", False):
        raise AfmctlError(f"{args.data}: the {args.model} fit failed: {reason}; not written "
                          "(--force writes it anyway)")
    log.warning("the %s fit failed (%s); written because of --force", args.model, reason)
    print(f"warning          : the fit failed: {reason}; written because of --force")
