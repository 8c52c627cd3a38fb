"""``afmctl identify``: fit a hysteresis/creep model to measured data (generic over the
model kinds registered in :data:`afmctl.compensators.models.KINDS`)."""
from __future__ import annotations

import argparse
import json
import logging
from typing import Any

log = logging.getLogger(__name__)

HELP = "fit a hysteresis/creep model (pi, epi, creep, preisach, bouc-wen) to measured data"

DESCRIPTION = """\
Fit a model of the scanner to measured data and write it as a JSON model file.

Input:
  --data DATA.csv   header row and columns t,u,y: time (s, strictly increasing), the
                    voltage sent to the amplifier (V) and the measured displacement (nm).
                    Extra columns are ignored. Excite the scanner over the range you will
                    use: a decaying triangle (nested loops) for hysteresis models, and
                    holds/staircases of a few seconds for the creep-aware kinds (epi,
                    creep), which also need uniformly spaced samples.
Model kinds (--model):
  pi        Prandtl-Ishlinskii: play operators, constrained least squares (always invertible)
  epi       extended PI: PI + inflexion creep C(u,t) = (1-exp(-lambda t)) a b^u, needs dwells
  creep     linear creep (bank of first-order lags), no hysteresis
  preisach  classical Preisach on an (alpha, beta) grid: asymmetric loops, exact inverse
  bouc-wen  Bouc-Wen differential model, nonlinear least squares
  dynamics  linear dynamics (amplifier bandwidth, structural modes, delay), unit DC gain,
            from a small-signal recording ('afmctl excite --kind dynamics'): frequency
            response (Welch) fitted by modes + lags + delay; the gain is printed
  KIND+creep[+dynamics]
            a chain (kind chain): hysteresis KIND (pi, epi, preisach, bouc-wen), then
            linear creep, then linear dynamics, identified jointly (Hammerstein);
            needs uniformly spaced samples
  auto      fit every candidate chain on the first 70 % of the data, score each by its
            prediction error on the last 30 % (held out), print the table and keep
            the best (re-fitted on all the data); the table is stored in the model
            file. Excite the full voltage range in the first 70 %.
Options:
  --operators N     pi/epi: play operators (default 13, max 1000); creep: lags (default 4);
                    preisach: grid levels (default 32; nnls up to 64, for up to 512);
                    bouc-wen: ignored
  --param KEY=VALUE model-specific options, VALUE parsed as JSON when possible:
                    pi, epi: thresholds=[0,10,...] (V), min_slope_fraction (1e-3), max_rows
                    epi: min_dwell_samples (10), dwell_tol_V (0)
                    creep: tau_min_s, tau_max_s (time-constant range, s)
                    preisach: u_min_V, u_max_V (grid range, default the data range),
                      method=auto|for|nnls, smoothing (1e-4), max_rows, memory_depth
                    bouc-wen: n (fix the exponent), max_rows (20000), u0_V
                    dynamics: n_modes (1), n_lags (1), segment=auto|all, nperseg,
                      f_min_Hz, f_max_Hz, min_coherence (0.9)
                    e.g. --param min_slope_fraction=1e-3 --param 'thresholds=[0,10,20,30]'
Output:
  --out MODEL.json  the fitted model (a 'kind' field plus its parameters); a summary and
                    the fit residual are printed. --plot FIT.png draws data and fit.

Examples:
  afmctl identify --model pi --data sweep.csv --out pi.json --operators 13
  afmctl identify --model preisach --data sweep.csv --out pre.json --param u_min_V=0 --param u_max_V=150
  afmctl compensate --model pi.json --target path.csv --out volts.csv
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("identify", help=HELP, description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, metavar="KIND",
                   help="model kind: pi, epi, creep, preisach, bouc-wen, dynamics, a chain KIND+creep[+dynamics], "
                        "or auto")
    p.add_argument("--data", metavar="DATA.csv", help="CSV with columns t,u,y (s, V, nm)")
    p.add_argument("--from-images", metavar="SCANS.npz",
                   help="instead of --data: identify without a position sensor from AFM images of a "
                        "calibration grating (npz of line images + voltage ramps, format in docs/SIM.md)")
    p.add_argument("--out", required=True, metavar="MODEL.json", help="where to write the fitted model")
    p.add_argument("--operators", type=int, default=None, metavar="N",
                   help="number of operators (PI plays, creep lags, ...); default depends on the kind")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="model-specific option (repeatable); VALUE is parsed as JSON when possible")
    p.add_argument("--plot", metavar="FIT.png", help="also draw the data and the model's output")
    p.set_defaults(func=run)


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


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..datafiles import read_csv, uniform_period
    from ..errors import AfmctlError
    from afmctl.compensators.base import ModelError
    from afmctl.compensators.models import model_class, save_model

    if args.model == "auto" or "+" in args.model:
        from .identify_chain import run_chain
        return run_chain(args)
    cls = model_class(args.model)
    if getattr(args, "from_images", None) is not None:  # image-based identification, docs/SIM.md
        from afmctl.sim_backend.image_scans import identify_from_scan_file

        model = identify_from_scan_file(args.from_images, args.model, n_operators=args.operators,
                                        **parse_params(args.param))
        try:
            save_model(model, args.out)
        except OSError as err:
            raise AfmctlError(f"--out: cannot write {args.out} ({err.strerror})") from None
        print(model.summary())
        print(f"written          : {args.out}")
        return 0
    if args.data is None:
        raise AfmctlError("--data: required; give a CSV with columns t,u,y (s, V, nm)")
    if args.operators is not None and args.operators < 1:
        raise AfmctlError(f"--operators: {args.operators} must be ≥ 1")
    params = parse_params(args.param)
    data = read_csv(args.data, ("t", "u", "y"), min_rows=2)
    t, u, y = data["t"], data["u"], data["y"]
    dt = uniform_period(t, str(args.data)) if getattr(cls, "time_dependent", False) else None
    try:
        model = cls.identify(t, u, y, n_operators=args.operators, **params)
    except TypeError as err:  # an option the kind does not know
        raise AfmctlError(f"--param: not accepted by kind {args.model!r} ({err})") from None
    except ModelError as err:
        raise ModelError(f"{args.data}: {err}") from None
    except np.linalg.LinAlgError as err:
        raise ModelError(f"{args.data}: the fit failed ({err}); is the input excited over its range?") from None
    except ValueError as err:  # a --param value of the wrong type that a kind did not check itself
        raise AfmctlError(f"--param: a value is not accepted by kind {args.model!r} ({err})") from None
    predict = getattr(model, "predict_linear", None)  # dynamics: its fitted segment, with its gain
    y_fit = predict(t, u, y, dt) if predict is not None else model.forward(dt).block(u)
    seen = np.isfinite(y_fit)
    rms = float(np.sqrt(np.mean((y_fit[seen] - y[seen]) ** 2)))
    peak = float(np.max(np.abs(y_fit[seen] - y[seen])))
    span = float(np.ptp(y[seen])) or 1.0
    try:
        save_model(model, args.out)
    except OSError as err:
        raise AfmctlError(f"--out: cannot write {args.out} ({err.strerror})") from None
    print(model.summary())
    print(f"fit residual     : rms {rms:.4g} nm, max {peak:.4g} nm ({100 * peak / span:.3g} % of the {span:.4g} nm span)")
    print(f"written          : {args.out}")
    if args.plot:
        _plot(args.plot, t, u, y, y_fit, args.model)
        print(f"plot             : {args.plot}")
    return 0


def _plot(path: str, t, u, y, y_fit, kind: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..errors import AfmctlError

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
    try:
        fig.savefig(path, dpi=110)
    except OSError as err:
        raise AfmctlError(f"--plot: cannot write {path} ({err.strerror})") from None
    finally:
        plt.close(fig)
