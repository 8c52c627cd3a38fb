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
  excites; averaged with the one kept where a bin is measured again, :func:`averaged`),
  and past the model's band the play's own ``Y/Ŷ``. Inside the band the model stands
  unless two measurements agree that its own step would not converge
  (:func:`trusted_ratio`); every measurement may size a bin's real step down to the one
  that minimises ``|1 − ρR|``, ``ρ = cos θ / |R|`` (clipped to ``[0, ρ_max]``; 0 where
  ``|θ| ≥ 90°``: such a bin is not learned until its ``R`` is trusted); a trusted ``R``
  corrects the model from 30° of phase error on (:func:`corrected_step`).
* :func:`model_free_increment` — no model: ``Ĝ_k = Y_k / U_k`` from this iteration's own
  sent voltages and measured motion (Kim & Zou, "Model-less inversion-based iterative
  control", IEEE/ASME Trans. Mechatronics 2013; here the smoothed H1 ratio of the
  differenced signals), replaced from the second iteration on, wherever the last change
  of the table excites a bin, by the secant

      Ĝ_k(jω) = (y_k − y_{k−1})(jω) / (u_k − u_{k−1})(jω)                               (3)

  — the response to a *change*, which is what the learning relies on: the harmonics that
  hysteresis adds to ``Y_k`` are no response of a linear system to ``U_k`` at that
  frequency, but to a small change they respond nearly linearly (the local slope of the
  branch); a bin measured again is averaged with the one kept. The DC gain comes from a straight-line fit of the motion on the voltages (the
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
#: past the model's band the law probes up to where the model's dynamics still respond
#: with at least this fraction of their DC gain (:func:`probe_top_Hz`)
PROBE_GAIN = 0.25
#: the step on the probed bins no play has measured yet: small, so that a model whose phase
#: is off there makes those bins at most 1 + PROBE_STEP·|R| worse for one play
PROBE_STEP = 0.3
#: only bins whose error holds more power than the recording's noise there are probed
#: (around each bin, as :func:`~afmctl.compensators.learning_spectra.smoothed_ratio` sums)
PROBE_SNR = 1.0


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
    #: the model's error the step was computed with (``ratio`` where it is trusted, else 1; None: ``ratio``)
    applied: np.ndarray | None = None


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
                          known: tuple[np.ndarray, np.ndarray] | None = None,
                          noise_psd_nm2: np.ndarray | None = None,
                          play: tuple[np.ndarray, np.ndarray] | None = None,
                          full_step: float | None = None) -> Increment:
    """Law (1) with the chain ``chain`` (a :class:`~afmctl.compensators.chain.ChainModel`
    or any static hysteresis model: ``forward``/``inverse`` u [V] ↔ y [nm]) as ``Ĝ``,
    applied to the table ``base = (u [V], y [nm])`` with its weighted error ``werr_nm``.
    ``secant = (u_a, y_a, u_b, y_b)``: two tables and their recordings, from which the
    model's error ``R`` is measured (2) where their difference excites a bin; ``known =
    (R, mask)``: what earlier iterations measured; ``play = (u, y)``: this play, whose own
    response ``Y/Ŷ`` measures ``R`` for a model without a dynamics stage (which claims no
    band: all of it); ``noise_psd_nm2``: the recording's
    noise per bin [nm²] (a bin is measured only where it stands above it); ``full_step``:
    the law's step before the guard halved it (None: ``rho_max``).

    What the step relies on is :func:`trusted_ratio`'s: the model inside its band unless
    repeated measurements say its own step would not converge, past it repeated secants
    (and a static model's play). One play's ``Y/Ŷ = 1 + E/Ŷ`` takes every error at a bin
    for the response's; past the band of a model with a dynamics stage the error there is
    mostly what is not the response (the hysteresis model's misfit at the line's
    harmonics, the creep after the approach), and learning on it took the simulated E-727
    at 200 lines/s from 8.7 % to 2.7–3.2 % of the line in the first step (5 runs; without
    it 1.1–1.5 %, main's law 1.7 %). Past what the plays measured the law probes with a
    small step (:data:`PROBE_STEP`, where the error stands above the noise) up to where
    the model's dynamics still respond (:func:`probe_top_Hz`); the Q-filter's cut-off is
    the highest of the model's band, the measured band and the probe's top. The returned
    ``ratio`` and ``reliable`` are the knowledge to keep (every measurement, trusted or
    not); ``applied`` the error the step was computed with."""
    dyn = getattr(chain, "dynamics", None)
    static_fwd, static_inv = static_ops(chain, dt_s)
    periodic = grid.periodic
    f = grid.f_Hz

    def predict(u: np.ndarray) -> np.ndarray:
        return _predict(dyn, periodic_run(static_fwd, u, periodic), dt_s, periodic)

    if dyn is not None:
        d_hat = dyn.discrete(dt_s).frequency_response(f)
        band = float(dyn.inverse_bandwidth_Hz(dt_s))
    else:
        d_hat = np.ones(f.size, dtype=complex)
        band = 0.0                                   # a static model claims no band of its own
    past = f > band
    noise = None if noise_psd_nm2 is None else grid.diff_noise(noise_psd_nm2)
    ratio = np.ones(f.size, dtype=complex)
    reliable = np.zeros(f.size, dtype=bool)
    repeated = np.zeros(f.size, dtype=bool)
    if known is not None:
        ratio[known[1]], reliable = known[0][known[1]], known[1].copy()
    if secant is not None:
        u_a, y_a, u_b, y_b = secant
        r, rel = smoothed_ratio(grid.diff_spectrum(y_a - y_b), grid.diff_spectrum(predict(u_a) - predict(u_b)),
                                f, threshold=SECANT_RELIABLE, noise_power=None if noise is None else 2 * noise)
        again = rel & reliable
        repeated[again] = repeats(r[again], ratio[again])
        ratio[rel], reliable = averaged(ratio, reliable, r, rel), reliable | rel
    played = np.zeros(f.size, dtype=bool)
    if play is not None and dyn is None:
        r, rel = smoothed_ratio(grid.diff_spectrum(play[1]), grid.diff_spectrum(predict(play[0])), f,
                                threshold=SECANT_RELIABLE, noise_power=noise)
        played = rel & past
        ratio[played], reliable = r[played], reliable | played
    trusted = trusted_ratio(ratio, reliable, repeated, played, past, rho_max if full_step is None else full_step)
    top = float(f[np.flatnonzero(trusted & past)[-1]]) if np.any(trusted & past) else 0.0
    settled = max(band, top)                         # the model's band, or what the plays measured past it
    reach = max(settled, probe_top_Hz(f, d_hat, band) if dyn is not None else 0.0)
    cutoff = reach if q_cutoff_Hz is None else q_cutoff_Hz
    if cutoff <= 0:
        cutoff = 0.45 / dt_s
    applied = _fill_between(np.where(trusted, ratio, 1.0 + 0j), trusted, f, band)
    learned = (f <= reach) if q_cutoff_Hz is None else np.ones(f.size, dtype=bool)
    # every measurement may size a bin's real step down (cos θ/|R|: at 90° and beyond, not learned), a trusted
    # one also corrects the model (corrected_step); past what the plays measured, a small probing step
    measured = _fill_between(np.where(reliable, ratio, 1.0 + 0j), reliable, f, band)
    rho = step_size(applied, rho_max)
    rho = np.where(trusted, rho, np.minimum(rho, step_size(measured, rho_max)))
    beyond = f > settled
    rho = np.where(beyond, np.minimum(rho, PROBE_STEP), rho)
    if noise is not None:           # where the error is the noise's a probe would only add it
        e = grid.diff_spectrum(werr_nm)
        above = smoothed_ratio(e, e, f, threshold=0.0, noise_power=noise, min_snr=PROBE_SNR)[1]
        rho = np.where(beyond & ~above, 0.0, rho)
    step = corrected_step(rho, applied, trusted, rho_max) * learned
    filt = zero_phase_q(f, cutoff) * step * _regularised_inverse(d_hat)
    x = periodic_run(static_fwd, base[0], periodic)
    dx = grid.apply(filt, werr_nm, smooth_ends=True)
    du = periodic_run(static_inv, x + dx, periodic) - periodic_run(static_inv, x, periodic)
    return Increment(du, np.abs(step), ratio, reliable, float(cutoff), _predict(dyn, x, dt_s, periodic), applied)


def probe_top_Hz(f_Hz: np.ndarray, d_hat: np.ndarray, band_Hz: float) -> float:
    """The top [Hz] of the bins past the model's band ``band_Hz`` that the law probes: up
    to the first bin where the model's dynamics ``d_hat`` (their response per bin, unit DC
    gain) fall below :data:`PROBE_GAIN` (``band_Hz`` when none). No play measures a bin
    its tables never change, so without a probe the band stops the learning for good: a
    50 lines/s raster's triangle keeps 2.6 nm of its harmonics above 1.5 × a 1 kHz mode,
    the whole error left on the simulated E-727 (0.055 % of a 4 µm line)."""
    past = f_Hz > band_Hz
    weak = past & (np.abs(d_hat) < PROBE_GAIN)
    ends = float(f_Hz[np.flatnonzero(weak)[0]]) if np.any(weak) else math.inf
    inside = past & (f_Hz < ends)
    return float(f_Hz[np.flatnonzero(inside)[-1]]) if np.any(inside) else band_Hz


def trusted_ratio(ratio: np.ndarray, reliable: np.ndarray, repeated: np.ndarray, played: np.ndarray,
                  past: np.ndarray, full_step: float) -> np.ndarray:
    """The bins whose measured model error ``ratio`` the step relies on. Past the model's
    band (``past``): those this play measured (``played``), or where a secant repeated an
    earlier measurement (``repeated``, :func:`repeats`). Inside it: only where the model's
    own full step ``ρ`` (``full_step``, before any halving by the guard) would not converge
    on the measurement (``|1 − ρ R| ≥ 1``: a phase error of 60° or more at ``|R| = 1``) and
    the measurement repeated; elsewhere the model stands. A hysteretic scanner's response
    to a small change of the table is no fixed linear response, and its secants scatter
    where the model's own step converges anyway: on the in-house 300 Hz plant a secant at
    7 Hz, 119° off and repeated, turned 0.075 % into 0.12 % where the model's step went on
    to 0.07 %; a model whose mode is 30 % off fails by |R| ≈ 8 at its resonance, and there
    the repeated secants carry the learning."""
    fails = np.abs(1.0 - full_step * ratio) >= 1.0
    return reliable & (played | (repeated & (past | fails)))


def _fill_between(ratio: np.ndarray, reliable: np.ndarray, f_Hz: np.ndarray, band_Hz: float) -> np.ndarray:
    """``R`` on the bins not measured: 1 (the model) inside its band, interpolated between
    the measured bins past it."""
    out = ratio.copy()
    past = (f_Hz > band_Hz) & ~reliable
    if np.any(past) and np.any(reliable):
        out[past] = interpolate_unreliable(ratio, reliable, fill=1.0)[past]
    return out


#: share of ``ρ_max`` the corrected step takes where the measured phase error is
#: :data:`CORRECT_FROM_DEG` or more
CORRECTED_STEP = 0.8
#: the largest step per bin, a multiple of ``ρ_max``
MAX_STEP = 2.0
#: from this measured phase error [°] on, a trusted measurement corrects the model (the real
#: step ``cos θ/|R|`` shrinks the error by only ``|sin θ|`` per iteration: 0.5 at 30°)
CORRECT_FROM_DEG = 30.0


def corrected_step(rho: np.ndarray, ratio: np.ndarray, trusted: np.ndarray, rho_max: float) -> np.ndarray:
    """The step per bin: the real ``ρ`` of :func:`step_size`, except where the trusted
    measured model error ``R`` turns the phase by :data:`CORRECT_FROM_DEG` or more (beyond
    90° no real step converges, from 30° on it is slow): there the model corrected by it,
    ``Ĝ·R``, is the filter (the secant method per bin, Li & Bechhoefer), with the complex
    step ``CORRECTED_STEP·ρ_max / R``, at most :data:`MAX_STEP`·ρ_max in magnitude.
    A model whose phase is that wrong where most of the error lies is still stopped by the
    convergence check (:mod:`afmctl.compensators.learning`)."""
    step = rho.astype(complex)
    fix = trusted & (np.abs(np.angle(ratio)) >= np.radians(CORRECT_FROM_DEG)) & (np.abs(ratio) > 1e-12)
    step[fix] = CORRECTED_STEP * rho_max / ratio[fix]
    big = np.abs(step) > MAX_STEP * rho_max                  # a response measured far smaller than the model's
    step[big] *= MAX_STEP * rho_max / np.abs(step[big])
    return step


def repeats(r_new: np.ndarray, r_old: np.ndarray) -> np.ndarray:
    """Per bin, whether two measurements of the model's error agree: the corrected step of
    one (:func:`corrected_step`, ``CORRECTED_STEP / R_old``) also converges on the other,
    ``|1 − CORRECTED_STEP · R_new / R_old| < 1``. A hysteretic scanner's response to a
    small change of the table is no fixed linear response: its secants scatter from one
    iteration to the next (on the in-house plant their phase at one bin went 96°, 71°,
    83°, 180° over four), and a correction built on one of them pulls the table off."""
    old = np.where(np.abs(r_old) > 1e-12, r_old, 1e-12)
    return np.abs(1.0 - CORRECTED_STEP * np.asarray(r_new) / old) < 1.0


def averaged(old: np.ndarray, known: np.ndarray, new: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """The response on the bins ``measured`` anew: the new measurement ``new``, averaged
    with the one kept (``old``) where there was one (``known``) — each play is a
    measurement, and the mean of two scatters less than either (a hysteretic scanner's
    secants scatter from play to play: the model-free law without the mean ended on the
    two-modes reference scanner at 0.58 % of the line at 100 lines/s, with it at 0.33 %)."""
    out = np.asarray(new, dtype=complex)[measured].copy()
    both = known[measured]
    out[both] = 0.5 * (out[both] + np.asarray(old)[measured][both])
    return out


def _predict(dyn, x: np.ndarray, dt_s: float, periodic: bool) -> np.ndarray:
    """The dynamics stage's response to the static output ``x`` (``x`` without one)."""
    if dyn is None:
        return x
    x0 = float(x[0])
    return periodic_run(lambda: dyn.forward(dt_s, initial_nm=x0), x, periodic)


def model_free_increment(grid: Grid, base: tuple[np.ndarray, np.ndarray], werr_nm: np.ndarray, rho_max: float,
                         q_cutoff_Hz: float | None,
                         secant: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
                         known: tuple[np.ndarray, np.ndarray] | None = None,
                         noise_psd_nm2: np.ndarray | None = None) -> Increment:
    """Law (1) with ``Ĝ_k`` estimated from the iterations themselves (module docstring),
    applied to the table ``base = (u [V], y [nm])``: the secant (3) between the two
    tables and recordings of ``secant = (u_a, y_a, u_b, y_b)`` where their difference
    excites a bin above the noise (``noise_psd_nm2`` [nm²] per bin), else what earlier
    secants measured (``known = (Ĝ, mask)``), else the base's own ``Y/U``; the DC gain
    from the linear calibration. The returned ``ratio``/``reliable`` are the secants'
    knowledge (to keep); the Q-filter's cut-off is where no measurement knows ``Ĝ``
    (or where it has rolled off)."""
    f = grid.f_Hz
    sent_V, measured_nm = base
    noise = None if noise_psd_nm2 is None else grid.diff_noise(noise_psd_nm2)
    g, reliable = smoothed_ratio(grid.diff_spectrum(measured_nm), grid.diff_spectrum(sent_V), f, noise_power=noise)
    measured = np.zeros(f.size, dtype=bool)
    g_known = np.ones(f.size, dtype=complex)
    if known is not None:
        g_known[known[1]], measured = known[0][known[1]], known[1].copy()
    if secant is not None:
        u_a, y_a, u_b, y_b = secant
        g_sec, rel_sec = smoothed_ratio(grid.diff_spectrum(y_a - y_b), grid.diff_spectrum(u_a - u_b), f,
                                        threshold=SECANT_RELIABLE, noise_power=None if noise is None else 2 * noise)
        g_known[rel_sec], measured = averaged(g_known, measured, g_sec, rel_sec), measured | rel_sec
    g = np.where(measured, g_known, g)
    reliable = reliable | measured
    gain, offset = calibration(sent_V, measured_nm)
    g[0], reliable[0] = gain, True
    top = float(f[np.flatnonzero(reliable)[-1]])
    g = interpolate_unreliable(g, reliable)
    cutoff = min(top, roll_off_Hz(f, g, reliable)) if q_cutoff_Hz is None else min(q_cutoff_Hz, top)
    q = zero_phase_q(f, cutoff) * (f <= top)
    rho = np.full(f.size, float(rho_max))
    du = grid.apply(q * rho * _regularised_inverse(g), werr_nm, smooth_ends=True)
    return Increment(du, rho, g_known, measured, cutoff, gain * np.asarray(sent_V) + offset)


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


def static_ops(chain, dt_s: float):
    """Factories of the static part's forward (V → nm) and inverse (nm → V) operators."""
    if hasattr(chain, "static_inverse"):
        return (lambda: chain.static_forward(dt_s)), (lambda: chain.static_inverse(dt_s))
    return (lambda: chain.forward(dt_s)), (lambda: chain.inverse(dt_s))
