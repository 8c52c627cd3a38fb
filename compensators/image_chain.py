"""Chains from grating images, no position sensor: the ``--from-images`` path of
``afmctl identify`` for ``dynamics``, ``preisach+dynamics``, ``preisach+creep`` and
``preisach+creep+dynamics``. The static stages come from the slow scans (Preisach:
:mod:`afmctl.compensators.image_identify`; Preisach + creep:
:mod:`afmctl.compensators.image_creep`), the dynamics from the scans at several line rates
read through them (:mod:`afmctl.compensators.image_dynamics`)."""
from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .base import ModelError
from .image_dynamics import STATIC_MAX_LINE_RATE_HZ, StaticFn, identify_dynamics, split_scans

log = logging.getLogger(__name__)


def static_function(model: Any | None, gain_nm_per_V: float | None = None) -> StaticFn:
    """The static stage as :data:`StaticFn`: a hysteresis model's forward operator run over
    the voltages, or, without a model, the linear ``gain_nm_per_V`` [nm/V]."""
    if model is None:
        if gain_nm_per_V is None:
            raise ModelError("gain_nm_per_V: needed without slow scans for the static model (nm/V, > 0)")
        g = float(gain_nm_per_V)
        return lambda u, dt: g * np.asarray(u, dtype=np.float64)
    return lambda u, dt: model.forward(dt).block(np.ascontiguousarray(u, dtype=np.float64))


#: the --model structures identified from images (slow scans and/or scans at several rates)
IMAGE_STRUCTURES = ("dynamics", "preisach+dynamics", "preisach+creep", "preisach+creep+dynamics")


def identify_from_rate_scans(parts: Sequence[Mapping[str, Any]], structure: str = "preisach+dynamics",
                             n_operators: int | None = None, static_max_Hz: float = STATIC_MAX_LINE_RATE_HZ,
                             gain_nm_per_V: float | None = None, n_modes: int | None = None, n_lags: int = 1,
                             f_max_Hz: float = 3000.0, static_error_nm: float = 1.0, **options: Any) -> Any:
    """Scan files' arrays (one mapping per file; the slow ranges all in one) → a model of
    ``structure`` (:data:`IMAGE_STRUCTURES`):

    * the static stages from the ranges scanned at ≤ ``static_max_Hz`` lines/s: Preisach
      (:mod:`image_identify`), or Preisach + creep (:mod:`image_creep`);
    * the dynamics from the faster ranges (:func:`identify_dynamics`), read through the
      images' Preisach model (also for ``+creep``: through the joint Preisach + creep fit
      the reading failed on a plant with 6 % creep and a 1.6 kHz mode, Q 30 — 1606 Hz,
      ζ 0.032 against 1596 Hz, ζ 0.018 through the Preisach model; the true 1600 Hz,
      ζ 0.017); "dynamics" alone through that Preisach model when there are slow ranges,
      else through the linear ``gain_nm_per_V``.

    ``options`` go to the Preisach identification."""
    from .chain import ChainModel

    if structure not in IMAGE_STRUCTURES:
        raise ModelError(f"model: {structure!r}; from grating images: {', '.join(IMAGE_STRUCTURES)}")
    split = [split_scans(p, static_max_Hz) for p in parts]
    slows = [sl for sl, _ in split if sl is not None]
    if len(slows) > 1:
        raise ModelError(f"line_rate_Hz: {len(slows)} files hold slow scans (≤ {static_max_Hz:g} lines/s); "
                         "give the static scans in one file")
    static, reader = _static_stages(slows[0] if slows else None, structure, gain_nm_per_V, static_max_Hz,
                                    n_operators, options)
    dyn = None
    if structure.endswith("dynamics"):
        fast = [sc for _, fs in split for sc in fs]
        dyn, _ = identify_dynamics(fast, static_function(reader, gain_nm_per_V), n_modes=n_modes, n_lags=n_lags,
                                   f_max_Hz=f_max_Hz, static_error_nm=static_error_nm)
    if structure == "dynamics":
        return dyn
    if isinstance(static, ChainModel):
        return ChainModel(hysteresis=static.hysteresis, creep=static.creep, dynamics=dyn)
    return ChainModel(hysteresis=static, dynamics=dyn)


def _static_stages(slow: dict[str, Any] | None, structure: str, gain_nm_per_V: float | None, static_max_Hz: float,
                   n_operators: int | None, options: dict[str, Any]) -> tuple[Any, Any]:
    """The static model of :func:`identify_from_rate_scans` — None (linear gain), a
    Preisach model or a preisach+creep chain — and the model the fast scans are read
    through (None or the Preisach model)."""
    from .image_creep import identify_static_chain
    from .image_identify import identify_from_images

    if slow is None:
        if structure != "dynamics":
            raise ModelError(f"line_rate_Hz: no scan range at ≤ {static_max_Hz:g} lines/s for the static stages; "
                             "add slow scans (e.g. 1 line/s)")
        if gain_nm_per_V is None:
            raise ModelError(f"gain_nm_per_V: needed (nm/V, > 0) for the linear static part: no scan range at "
                             f"≤ {static_max_Hz:g} lines/s")
        return None, None
    if structure == "dynamics" and gain_nm_per_V is not None:
        return None, None
    pre = identify_from_images(slow, kind="preisach", n_operators=n_operators, **options)
    if "creep" in structure:
        return identify_static_chain(slow, n_operators=n_operators, first=pre, **options), pre
    return pre, pre
