"""Joint fit of a Preisach hysteresis stage and the linear creep stage after it.

Chain (Hammerstein, :mod:`afmctl.compensators.chain`): ``h = y0 + Φ(u)·w`` [nm] (Preisach,
linear in the cell masses ``w ≥ 0``; image-based paper eq. 3), then creep
``y = h − Σ_k c_k·(h − x_k)``, ``x_k`` the first-order lag of ``h`` with time constant
``τ_k`` (nonlinearities paper eq. 21; ``c_k ≥ 0``). The product ``c_k·x_k(w)`` makes the
problem bilinear. Fitting the stages in turn (hysteresis on the creep-corrected output, then
creep on the hysteresis output) converges slowly: the rate-independent loop width and the
fast lags trade off against each other, and each half-step keeps the other's share.

Here both are fitted in one nonnegative least-squares problem per round, with the creep
corrections evaluated on the previous round's hysteresis output ``ĥ``:

    y ≈ y0 + Φ(u)·w − Σ_k c_k·(ĥ − x_k(ĥ))

which is linear in ``(y0, w, c)``. The first round takes the measured output itself for
``ĥ`` (it differs from ``h`` by the creep, a few % of a step), each further round the
previous round's hysteresis output; the rounds before the last fit a coarse grid (they only
supply ``ĥ``). The error of using ``ĥ`` for ``h`` in the correction is second order, so two
rounds (the default of :meth:`ChainModel.identify`) are enough. The lags start at rest at
``ĥ[0]``.
"""
from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from .creep import LinearCreepModel, log_spaced_time_constants

log = logging.getLogger(__name__)

#: rows of the joint least-squares problem (evenly spread over the record) unless
#: ``max_rows`` is given: the 64-level fit costs ≈ 5 s per round at 20 000 rows
JOINT_MAX_ROWS = 20_000
#: density smoothing of the joint fit unless ``smoothing`` is given. Chosen while the
#: penalty still tied the diagonal cells to their neighbours (speed ladder, static floor at
#: 16 lines/s: 0.65 % at 1e-4, 0.42 % at 1e-5; staircase 0.52 → 0.42 %). With the diagonal
#: out of the penalty (2026-11-26) the plain fit takes 1e-2; here 1e-2 measured 1.18 % vs
#: 1.31 % max on a user-style record's 1 line/s raster (stiff plant) and the same on afmctl's
#: excitation (speed ladder 0.05 / 0.07 / 0.13 / 0.23 % vs 0.05 / 0.08 / 0.15 / 0.22 % at
#: 1 / 4 / 16 / 50 lines/s): not worth changing every figure for, yet
JOINT_SMOOTHING = 1e-5
#: grid levels of the rounds before the last
COARSE_LEVELS = 24


def lag_corrections(h_nm: np.ndarray, dt_s: float, time_constants_s: np.ndarray) -> np.ndarray:
    """Columns ``−(h − x_k)`` [nm]: minus the part of ``h`` each lag has not yet followed
    (lag ``k`` exact for a zero-order-hold input, starting at rest at ``h[0]``)."""
    from scipy.signal import lfilter

    Z = np.empty((h_nm.size, len(time_constants_s)))
    for k, tau in enumerate(time_constants_s):
        a = math.exp(-dt_s / float(tau))
        x = lfilter([1.0 - a], [1.0, -a], h_nm, zi=[a * float(h_nm[0])])[0]
        Z[:, k] = x - h_nm
    return Z


def fit_preisach_creep(hcls: Any, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, *, rounds: int,
                       n_operators: int | None, options: dict[str, Any], creep_options: dict[str, Any],
                       fit_from_index: int = 0) -> tuple[Any, LinearCreepModel]:
    """Preisach model (``hcls``) and creep stage fitted jointly (module docstring).

    ``options`` go to the Preisach fit (grid range, smoothing, ...); ``creep_options``
    give the lags: ``n_operators``, ``tau_min_s``, ``tau_max_s`` [s]. ``rounds`` ≥ 1 joint
    fits. Data uniformly sampled."""
    from .preisach_identify import identify_preisach_with_regressors

    dt = float(np.median(np.diff(t_s)))
    tau = log_spaced_time_constants(float(creep_options["tau_min_s"]), float(creep_options["tau_max_s"]),
                                    int(creep_options["n_operators"]))
    # no PI-like prior in the joint fit (prior="none" unless asked): with its light smoothing
    # the prior's ridge dominated and the unseen-plant test went from <= 1 % to 3.1 % max at
    # 10 lines/s (#24; measured on this branch)
    opts = {"max_rows": JOINT_MAX_ROWS, "smoothing": JOINT_SMOOTHING, "prior": "none",
            **{k: v for k, v in options.items() if k != "method"}}
    if fit_from_index:
        opts["fit_from_index"] = fit_from_index
    from .fit_health import note_problem

    h = np.asarray(y_nm, dtype=float)     # first round: the output itself stands in for ĥ
    n_rounds = max(1, int(rounds))
    hyst: Any = None                      # the Preisach model of the previous round
    for r in range(n_rounds):
        if r:
            h = hyst.forward(dt).block(u_V)
        # rounds before the last only supply ĥ: a coarse grid does (and costs a tenth)
        levels = n_operators if r == n_rounds - 1 or n_operators is None else min(n_operators, COARSE_LEVELS)
        hyst, c = identify_preisach_with_regressors(hcls, t_s, u_V, y_nm, lag_corrections(h, dt, tau),
                                                    n_operators=levels, **opts)
        log.info("joint preisach+creep round %d: creep fractions %s, residual %.4g nm RMS", r + 1,
                 np.array2string(c, precision=4), hyst.fit_residual_nm)
    # (the rounds' residuals are not comparable: the first one's creep regressors are built
    # from the measured output itself, which flatters it; a diverged result shows in the
    # chain's training error against the straight line's, fit_health)
    if float(np.sum(c)) >= 1.0:
        note_problem(hyst, f"preisach+creep: the creep fractions sum to {float(np.sum(c)):.3g}, on their bound 1 "
                           "(the creep would take the whole step back); rescaled to 0.999")
        c = c * (0.999 / float(np.sum(c)))
    h0 = float(hyst.forward(dt).block(u_V[:1])[0])
    creep = LinearCreepModel(gain_nm_per_V=1.0, offset_nm=0.0, initial_V=h0, time_constants_s=tau.tolist(),
                             creep_weights=[float(v) for v in c])
    return hyst, creep
