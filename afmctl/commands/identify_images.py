"""``afmctl identify --from-images`` for the chains and the linear dynamics (``dynamics``,
``preisach+dynamics``, ``preisach+creep``, ``preisach+creep+dynamics``): slow grating
scans for the static stages, scans at several line rates for the dynamics, no position
sensor (:mod:`afmctl.compensators.image_dynamics`, :mod:`afmctl.compensators.image_creep`;
file convention in docs/SIM.md)."""
from __future__ import annotations

import argparse
import logging

log = logging.getLogger(__name__)

#: --param keys of the dynamics part (the rest go to the Preisach identification)
DYNAMICS_PARAMS = ("static_max_Hz", "gain_nm_per_V", "n_modes", "n_lags", "f_max_Hz", "static_error_nm")


def wants_rates(args: argparse.Namespace) -> bool:
    """True when ``identify`` should take this path: ``--from-images`` with a chain or a
    model with linear dynamics (``--model auto`` is refused by the chain path)."""
    parts = str(args.model).split("+")
    return getattr(args, "from_images", None) is not None and ("dynamics" in parts or len(parts) > 1)


def _options(args: argparse.Namespace) -> tuple[dict, dict]:
    from afmctl.compensators.input_checks import number_option

    from .identify_io import parse_params
    params = parse_params(args.param)
    dyn = {k: params.pop(k) for k in DYNAMICS_PARAMS if k in params}
    limits = {"static_max_Hz": (1e-6, 1e4, False), "gain_nm_per_V": (1e-6, 1e6, False), "n_lags": (0, 4, True),
              "f_max_Hz": (1.0, 1e6, False), "static_error_nm": (1e-6, 1e4, False)}
    for k, (lo, hi, integer) in limits.items():
        if k in dyn:
            dyn[k] = number_option(k, dyn[k], lo=lo, hi=hi, integer=integer)
    if "n_modes" in dyn and dyn["n_modes"] == "auto":
        dyn["n_modes"] = None
    elif "n_modes" in dyn:
        dyn["n_modes"] = int(number_option("n_modes", dyn["n_modes"], lo=0, hi=6, integer=True))
    return dyn, params


def run_from_rate_images(args: argparse.Namespace) -> int:
    """Load the ``.npz`` scan files, identify, print the summary and the response per line
    rate, save."""
    from afmctl.compensators.base import ModelError
    from afmctl.compensators.image_chain import IMAGE_STRUCTURES, identify_from_rate_scans
    from afmctl.compensators.image_dynamics import STATIC_MAX_LINE_RATE_HZ, split_scans
    from afmctl.compensators.scan_files import load_scans_npz

    from ..errors import AfmctlError
    from .identify_io import _save
    if args.data is not None:
        raise AfmctlError("--data: give either --data DATA.csv or --from-images SCANS, not both")
    if args.model not in IMAGE_STRUCTURES:
        raise AfmctlError(f"--model {args.model}: from grating images the chains are {', '.join(IMAGE_STRUCTURES)} "
                          "(or a single kind: pi, epi, preisach, bouc-wen, creep)")
    bad = [p for p in args.from_images if not str(p).lower().endswith(".npz")]
    if bad:
        raise AfmctlError(f"{bad[0]}: the dynamics are identified from .npz scan files (pixel voltages and "
                          "line_rate_Hz; docs/SIM.md), not from image files")
    dyn, params = _options(args)
    parts = [load_scans_npz(p) for p in args.from_images]
    for path, part in zip(args.from_images, parts):
        try:
            split_scans(part, float(dyn.get("static_max_Hz", STATIC_MAX_LINE_RATE_HZ)))
        except ModelError as err:
            raise ModelError(f"{path}: {err}") from None
    where = ", ".join(str(p) for p in args.from_images)
    try:
        model = identify_from_rate_scans(parts, args.model, n_operators=args.operators, **dyn, **params)
    except TypeError as err:
        raise AfmctlError(f"--param: not accepted by --model {args.model} from images ({err})") from None
    except ModelError as err:
        raise ModelError(f"{where}: {err}") from None
    except (ValueError, ArithmeticError) as err:  # incl. numpy.linalg.LinAlgError
        raise ModelError(f"{where}: the image-based identification failed ({err})") from None
    _save(model, args.out)
    print(model.summary())
    print(f"written          : {args.out}")
    return 0
