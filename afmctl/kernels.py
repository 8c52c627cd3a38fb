"""Compile afmctl's numba kernels into numba's on-disk cache, with a progress bar.

Every kernel is ``numba.njit(cache=True)``: the first use compiles it (about a minute for
all of them on a laptop, several on a busy machine) and later runs load it from the cache
in milliseconds. ``make demo`` / ``make test`` run ``python -m afmctl.kernels`` right after
installing, so that the compile happens once, visibly, at install (after a plain ``pip
install`` the first use compiles instead; ``afmctl demo`` shows its steps' progress then). The
cache lives beside the sources (``__pycache__``) or in ``NUMBA_CACHE_DIR``.

Warming up runs the simulated scanner on a short sweep, each model kind on that sweep
(identification, then the forward and inverse operators sample by sample and in blocks) and
the drift predictor on a few samples: the same calls, and so the same compiled signatures, as
real use.
"""
from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable

import numpy as np

log = logging.getLogger(__name__)

DT_S = 1e-3


@functools.lru_cache(maxsize=1)
def _sweep() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A short triangle sweep u [V], held at each turning point (creep fits need dwells),
    through the default simulated scanner's x axis: times t [s], u [V], y [nm]."""
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    legs = [np.concatenate([np.linspace(a, b, 60), np.full(40, float(b))])
            for a, b in ((0, 120), (120, 10), (10, 90), (90, 30), (30, 120), (120, 0))]
    u = np.concatenate(legs)
    volts = np.zeros((u.size, 3))
    volts[:, 0] = u
    y = Scanner(default_scanner_config()).run(volts, DT_S)[:, 0]
    return np.arange(u.size) * DT_S, u, y


#: kinds made of other kinds' stages: warming those stages compiles every kernel they use
COMPOSITE_KINDS = ("chain", "scanner")


def _model_kind(kind: str) -> Callable[[], None]:
    def run() -> None:
        from afmctl.compensators.base import ModelError
        from afmctl.compensators.models import model_class
        t, u, y = _sweep()
        if kind == "amplifier":     # fitted to a piezo voltage [V], not a displacement
            y = model_class(kind).from_lag(50.0, 2e4).forward(DT_S).block(u)  # type: ignore[attr-defined]
        model = model_class(kind).identify(t, u, y)
        dt = DT_S if getattr(model, "time_dependent", False) else None
        forward = model.forward(dt)
        y_fit = forward.block(u[:-1])
        forward.step(float(u[-1]))
        try:
            inverse = model.inverse(dt)
        except ModelError:        # e.g. a Bouc–Wen fit that is not invertible: nothing to compile
            return
        inverse.block(y_fit[:-1])
        inverse.step(float(y_fit[-1]))
    return run


def _drift() -> None:
    from afmctl.compensators.drift import DriftParams
    DriftParams.named("physical_tube").predictor(0.01).block(np.full(20, 22.0))


def warm_up_steps() -> list[tuple[str, Callable[[], object]]]:
    """``(name, callable)`` for every group of kernels."""
    from afmctl.compensators.models import KINDS
    kinds = [k for k in KINDS if k not in COMPOSITE_KINDS]
    steps: list[tuple[str, Callable[[], object]]] = [("simulated scanner", _sweep)]
    steps += [(f"model {kind}", _model_kind(kind)) for kind in kinds]
    steps.append(("drift predictor", _drift))
    return steps


def warm_up(progress: bool = True) -> None:
    """Run :func:`warm_up_steps`, with a tqdm bar on stderr when ``progress``. Errors are
    logged and skipped: a kernel that fails here fails again, visibly, where it is used."""
    from tqdm import tqdm
    steps = warm_up_steps()
    with tqdm(total=len(steps), disable=not progress, unit="group", file=sys.stderr,
              desc="numba kernels (compiled once, then cached)") as bar:
        for name, step in steps:
            bar.set_postfix_str(name)
            try:
                step()
            except Exception:  # noqa: BLE001 - warming up is an optimisation only
                log.exception("warming up %s failed", name)
            bar.update(1)


if __name__ == "__main__":
    print("afmctl: compiling numba kernels into the cache (first time only)...", file=sys.stderr, flush=True)
    warm_up()
