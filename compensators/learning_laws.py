"""The two learning laws of :mod:`afmctl.compensators.learning`, one iteration each.

Both are iterative inversion (Zou & Devasia; Kim & Zou 2008): on every frequency bin ω of
the iteration's grid (:class:`~afmctl.compensators.learning_spectra.Grid`; on a periodic
table, exactly its harmonics),

    u_{k+1}(jω) = u_k(jω) + Q(ω) · ρ(ω) · Ĝ⁻¹(jω) · (W e_k)(jω),        e_k = y_d − y_k     (1)

with ``W`` the error weight (:mod:`~afmctl.compensators.learning_weights`), ``Q`` a
zero-phase Q-filter and ``ρ`` the step size. With the true response ``G = Ĝ·R``
(``R = |R|e^{jθ}`` the model's error), the error of bin ω shrinks by
``|1 − Qρ R|`` per iteration: it converges iff ``0 < Qρ < 2 cos θ / |R|``, which needs
``|θ| < 90°`` (Wu & Zou, IEEE TCST 17(1), 2009, eq. 12; Zou & Devasia, Automatica 2004).

* :func:`model_based_increment` — ``Ĝ`` the identified chain ``dynamics ∘ static``: the
  filter is the dynamics' inverse, then the static (hysteresis, creep) inverse along the
  present table, incrementally: ``Δu = S⁻¹(x_k + Δx) − S⁻¹(x_k)`` with ``x_k = S(u_k)``
  and ``Δx = Q ρ D̂⁻¹ W e_k`` — the local slope of the hysteresis branch the table is on.
  ``R`` — what the learning relies on, the plant's response to a *change* of the table
  against the model's — is measured from the last two iterations as the secant ratio
  (Li & Bechhoefer's secant iteration, here per frequency bin)

      R(ω) = Δy(jω) / Δŷ(jω),   Δy = y_k − y_{k−1},  Δŷ = Ĝ(u_k) − Ĝ(u_{k−1})           (2)

  (:func:`~afmctl.compensators.learning_spectra.smoothed_ratio`, on the bins the change
  excites; 1 elsewhere and on the first iteration), and the step size is the one that
  minimises ``|1 − ρR|`` for a real ρ, ``ρ = cos θ / |R|`` (clipped to ``[0, ρ_max]``;
  0 where ``|θ| ≥ 90°``: such a bin is not learned).
* :func:`model_free_increment` — no model: ``Ĝ_k = Y_k / U_k`` from this iteration's own
  sent voltages and measured motion (Kim & Zou, "Model-less inversion-based iterative
  control", IEEE/ASME Trans. Mechatronics 2013; here the smoothed H1 ratio of the
  differenced signals), replaced from the second iteration on, wherever the last change
  of the table excites a bin, by the secant

      Ĝ_k(jω) = (y_k − y_{k−1})(jω) / (u_k − u_{k−1})(jω)                               (3)

  — the response to a *change*, which is what the learning relies on: the harmonics that
  hysteresis adds to ``Y_k`` are no response of a linear system to ``U_k`` at that
  frequency, but to a small change they respond nearly linearly (the local slope of the
  branch). The DC gain comes from a straight-line fit of the motion on the voltages (the
  linear calibration); bins above the highest excited one are not learned.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .learning_spectra import Grid, interpolate_unreliable, smoothed_ratio, zero_phase_q

#: a secant bin is measured when its windowed change is at least this fraction of the peak
SECANT_RELIABLE = 1e-3
#: the model-free Q-filter cuts where |Ĝ| has rolled off to this fraction of its DC gain
ROLL_OFF = 0.3
#: regularisation of Ĝ⁻¹: |Ĝ|² + (λ·|Ĝ(0)|)² in the denominator
REGULARISATION = 1e-3


@dataclass(frozen=True)
class Increment:
    """One law's proposal: the voltage change ``du_V`` [V], the step size per bin, the
    measured model error ``R`` per bin and which bins it was measured on, the Q-filter
    cut-off [Hz] and the prediction the alignment is judged against [nm]."""

    du_V: np.ndarray
    rho: np.ndarray
    ratio: np.ndarray
    reliable: np.ndarray
    q_cutoff_Hz: float
    prediction_nm: np.ndarray


def periodic_run(op_factory, x: np.ndarray, periodic: bool, periods: int = 3) -> np.ndarray:
    """A fresh operator from ``op_factory()`` over ``x``; a periodic table is run
    ``periods`` times and the last period returned (its steady state)."""
    if not periodic:
        return op_factory().block(np.ascontiguousarray(x))
    out = op_factory().block(np.ascontiguousarray(np.tile(x, periods)))
    return out[-x.size:]


def step_size(ratio: np.ndarray, rho_max: float) -> np.ndarray:
    """``ρ = clip(cos θ / |R|, 0, ρ_max)`` per bin (module docstring)."""
    mag = np.maximum(np.abs(ratio), 1e-12)
    return np.clip(np.cos(np.angle(ratio)) / mag, 0.0, rho_max)


def model_based_increment(grid: Grid, chain, dt_s: float, base: tuple[np.ndarray, np.ndarray], werr_nm: np.ndarray,
                          rho_max: float, q_cutoff_Hz: float | None,
                          secant: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
                          known: tuple[np.ndarray, np.ndarray] | None = None) -> Increment:
    """Law (1) with the chain ``chain`` (a :class:`~afmctl.compensators.chain.ChainModel`
    or any static hysteresis model: ``forward``/``inverse`` u [V] ↔ y [nm]) as ``Ĝ``,
    applied to the table ``base = (u [V], y [nm])`` with its weighted error ``werr_nm``.
    ``secant = (u_a, y_a, u_b, y_b)``: two tables and their recordings, from which the
    model's error ``R`` is measured (2) where their difference excites a bin; ``known =
    (R, mask)``: what earlier iterations measured (kept where not measured anew). Bins
    never measured take ``R = 1`` (the model trusted). The returned ``ratio`` and
    ``reliable`` are the updated knowledge."""
    dyn = getattr(chain, "dynamics", None)
    static_fwd, static_inv = _static_ops(chain, dt_s)
    periodic = grid.periodic

    def predict(u: np.ndarray) -> np.ndarray:
        return _predict(dyn, periodic_run(static_fwd, u, periodic), dt_s, periodic)

    if dyn is not None:
        d_hat = dyn.discrete(dt_s).frequency_response(grid.f_Hz)
        cutoff = dyn.inverse_bandwidth_Hz(dt_s) if q_cutoff_Hz is None else q_cutoff_Hz
    else:
        d_hat = np.ones(grid.f_Hz.size, dtype=complex)
        cutoff = 0.45 / dt_s if q_cutoff_Hz is None else q_cutoff_Hz
    ratio = np.ones(grid.f_Hz.size, dtype=complex)
    reliable = np.zeros(grid.f_Hz.size, dtype=bool)
    if known is not None:
        ratio[known[1]], reliable = known[0][known[1]], known[1].copy()
    if secant is not None:
        u_a, y_a, u_b, y_b = secant
        r, rel = smoothed_ratio(grid.diff_spectrum(y_a - y_b), grid.diff_spectrum(predict(u_a) - predict(u_b)),
                                grid.f_Hz, threshold=SECANT_RELIABLE)
        ratio[rel], reliable = r[rel], reliable | rel
    rho = step_size(ratio, rho_max)
    step = corrected_step(rho, ratio, reliable, rho_max)
    filt = zero_phase_q(grid.f_Hz, cutoff) * step * _regularised_inverse(d_hat)
    x = periodic_run(static_fwd, base[0], periodic)
    dx = grid.apply(filt, werr_nm)
    du = periodic_run(static_inv, x + dx, periodic) - periodic_run(static_inv, x, periodic)
    return Increment(du, np.abs(step), ratio, reliable, float(cutoff), _predict(dyn, x, dt_s, periodic))


#: share of ``ρ_max`` the corrected step takes where the model's phase error is 90° or more
CORRECTED_STEP = 0.5


def corrected_step(rho: np.ndarray, ratio: np.ndarray, reliable: np.ndarray, rho_max: float) -> np.ndarray:
    """The step per bin: the real ``ρ`` of :func:`step_size`, except where the measured
    model error ``R`` turns the phase by 90° or more — no real step converges there — and
    ``R`` was measured: there the model corrected by it, ``Ĝ·R``, is the filter (the secant
    method per bin, Li & Bechhoefer), with the complex step ``CORRECTED_STEP·ρ_max / R``.
    A model whose phase is that wrong where most of the error lies is still stopped by the
    convergence check (:mod:`afmctl.compensators.learning`)."""
    step = rho.astype(complex)
    fix = reliable & (np.abs(np.angle(ratio)) >= 0.5 * math.pi) & (np.abs(ratio) > 1e-12)
    step[fix] = CORRECTED_STEP * rho_max / ratio[fix]
    return step


def _predict(dyn, x: np.ndarray, dt_s: float, periodic: bool) -> np.ndarray:
    """The dynamics stage's response to the static output ``x`` (``x`` without one)."""
    if dyn is None:
        return x
    x0 = float(x[0])
    return periodic_run(lambda: dyn.forward(dt_s, initial_nm=x0), x, periodic)


def model_free_increment(grid: Grid, base: tuple[np.ndarray, np.ndarray], werr_nm: np.ndarray, rho_max: float,
                         q_cutoff_Hz: float | None,
                         secant: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None) -> Increment:
    """Law (1) with ``Ĝ_k`` estimated from the iterations themselves (module docstring),
    applied to the table ``base = (u [V], y [nm])``: the secant (3) between the two
    tables and recordings of ``secant = (u_a, y_a, u_b, y_b)`` where their difference
    excites a bin, else the base's own ``Y/U``; the DC gain from the linear calibration."""
    f = grid.f_Hz
    sent_V, measured_nm = base
    g, reliable = smoothed_ratio(grid.diff_spectrum(measured_nm), grid.diff_spectrum(sent_V), f)
    if secant is not None:
        u_a, y_a, u_b, y_b = secant
        g_sec, rel_sec = smoothed_ratio(grid.diff_spectrum(y_a - y_b), grid.diff_spectrum(u_a - u_b), f,
                                        threshold=SECANT_RELIABLE)
        g = np.where(rel_sec, g_sec, g)
        reliable = reliable | rel_sec
    gain, offset = calibration(sent_V, measured_nm)
    g[0], reliable[0] = gain, True
    top = float(f[np.flatnonzero(reliable)[-1]])
    g = interpolate_unreliable(g, reliable)
    cutoff = min(top, roll_off_Hz(f, g, reliable)) if q_cutoff_Hz is None else min(q_cutoff_Hz, top)
    q = zero_phase_q(f, cutoff) * (f <= top)
    rho = np.full(f.size, float(rho_max))
    du = grid.apply(q * rho * _regularised_inverse(g), werr_nm)
    ratio = np.ones(f.size, dtype=complex)
    return Increment(du, rho, ratio, reliable, cutoff, gain * np.asarray(sent_V) + offset)


def roll_off_Hz(f_Hz: np.ndarray, g: np.ndarray, reliable: np.ndarray) -> float:
    """The model-free Q cut-off: the first reliable frequency above the response's peak
    where ``|Ĝ|`` falls below :data:`ROLL_OFF` of its DC value — above it the scanner
    barely responds, a learning step there needs large voltages, and the estimate of a
    small response is the least certain (inf when it never does)."""
    mag = np.abs(g)
    idx = np.flatnonzero(reliable & (f_Hz > 0))
    if idx.size == 0:
        return math.inf
    peak = idx[int(np.argmax(mag[idx]))]
    below = idx[(idx > peak) & (mag[idx] < ROLL_OFF * mag[0])]
    return float(f_Hz[below[0]]) if below.size else math.inf


def calibration(u_V: np.ndarray, y_nm: np.ndarray) -> tuple[float, float]:
    """Straight-line fit ``y ≈ gain·u + offset`` (nm/V, nm); gain 1 for constant u."""
    u = np.asarray(u_V, dtype=float)
    y = np.asarray(y_nm, dtype=float)
    if np.ptp(u) <= 0:
        return 1.0, float(np.mean(y) - np.mean(u))
    gain, offset = np.polyfit(u, y, 1)
    if not (math.isfinite(gain) and abs(gain) > 0):
        gain = 1.0
    return float(gain), float(offset)


def _regularised_inverse(g: np.ndarray) -> np.ndarray:
    """``conj(Ĝ) / (|Ĝ|² + (λ|Ĝ(0)|)²)``: ``1/Ĝ`` where ``Ĝ`` is not tiny."""
    lam = REGULARISATION * max(abs(complex(g[0])), 1e-12)
    return np.conj(g) / (np.abs(g) ** 2 + lam * lam)


def _static_ops(chain, dt_s: float):
    """Factories of the static part's forward (V → nm) and inverse (nm → V) operators."""
    if hasattr(chain, "static_inverse"):
        return (lambda: chain.static_forward(dt_s)), (lambda: chain.static_inverse(dt_s))
    return (lambda: chain.forward(dt_s)), (lambda: chain.inverse(dt_s))
