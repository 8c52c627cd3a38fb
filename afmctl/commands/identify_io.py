"""What ``afmctl identify`` shares between single kinds (identify.py) and chains
(identify_chain.py): ``--param`` parsing, reading conditioned data, saving, the fit plot."""
from __future__ import annotations

import argparse
import json
import logging
from typing import Any

log = logging.getLogger(__name__)


def parse_params(items: list[str]) -> dict[str, Any]:
    """``["a=1", "b=[1,2]", "c=text"]`` → ``{"a": 1, "b": [1, 2], "c": "text"}``."""
    from ..errors import AfmctlError

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


def _read_conditioned(args: argparse.Namespace, uniform: bool):
    from ..data.datafiles import read_csv
    from ..errors import AfmctlError
    from ..data.identdata import Y_UNITS, condition

    if args.y_unit not in Y_UNITS:
        raise AfmctlError(f"--y-unit: {args.y_unit!r} is not known; allowed: nm, um")
    data = read_csv(args.data, ("t", "u", "y"), min_rows=2)
    return condition(data["t"], data["u"], data["y"] * Y_UNITS[args.y_unit], str(args.data),
                     burn_in=args.burn_in, delay=args.delay, despike=not args.keep_spikes, uniform=uniform)


def _save(model, path: str) -> None:
    from ..errors import AfmctlError
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


def _refuse_failed(args: argparse.Namespace, model, y, u, y_fit, k: int) -> None:
    """A failed fit (:mod:`afmctl.compensators.fit_health`) is not written without
    ``--force``: one line with the reason, exit status 2. ``y_fit`` is the model's output on
    ``u``; samples from ``k`` on were fitted (NaN: not predicted, the dynamics kind)."""
    import numpy as np

    from ..errors import AfmctlError
    from afmctl.compensators.fit_health import failure_reason, linear_fit_rms

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
