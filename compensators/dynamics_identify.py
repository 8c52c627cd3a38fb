"""Identification of linear scanner dynamics from a small-signal excitation.

1. Frequency response ``Ĝ(f) = P_uy(f) / P_uu(f)`` and coherence by Welch's method
   (:func:`scipy.signal.csd`, :func:`scipy.signal.welch`, :func:`scipy.signal.coherence`).
2. Keep the bins the input excites (power above 1e-6 of its peak) whose coherence is at
   least ``min_coherence``, between ``f_min_Hz`` and ``f_max_Hz``.
3. Fit, with :func:`scipy.optimize.least_squares` on the complex log error
   ``√coh·log(G(f)/Ĝ(f))`` (log-magnitude and phase difference, no unwrapping), the
   structure

       G(s) = K · Π_i ω_i²/(s² + 2ζ_iω_i s + ω_i²) · Π_j p_j/(s + p_j) · e^{−sτ}

   (``n_modes`` lightly damped modes, ``n_lags`` first-order lags — an amplifier's
   bandwidth under the piezo's capacitance — and a delay). Every pole is stable by
   construction. ``K`` is the static small-signal gain (nm/V for a voltage input); it is
   reported and divided out (the dynamics model has unit DC gain).

The measured response of sampled, zero-order-held data carries the hold's half-sample
delay; the model's own discretisation adds it again, so it is taken off the fitted delay
(``delay_s = max(0, τ − dt/2)``). The fit lets ``τ`` go down to ``−2·dt`` so that data
whose output is sampled at the end of each hold interval (a simulator that answers in the
same sample) still fits; such a lead is reported in ``fit_info`` and not kept.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .base import ModelError, check_finite
from .input_checks import number_option

log = logging.getLogger(__name__)


@dataclass
class DynamicsFit:
    """Fitted poles and zeros [rad/s], delay [s] and a summary ``info``."""

    poles: np.ndarray
    zeros: np.ndarray
    delay_s: float
    info: dict[str, float | str] = field(default_factory=dict)


@dataclass
class FRF:
    """Measured frequency response at the kept bins."""

    f_Hz: np.ndarray
    G: np.ndarray
    coherence: np.ndarray
    #: mode counts whose least-squares fit spent its evaluation budget (did not converge)
    unconverged_modes: set[int] = field(default_factory=set)


#: function evaluations per start of the least-squares fit (a good start converges in < 100)
MAX_NFEV = 400
#: most frequency bins a fit uses (log-spaced beyond: a 50 kHz recording has > 10 000)
MAX_FIT_BINS = 1000


def thinned(frf: FRF, max_bins: int = MAX_FIT_BINS) -> FRF:
    """At most ``max_bins`` of the bins, nearest to a log-spaced grid over the measured band
    (each decade weighs alike in the fit; a mode of Q 100 at 1 kHz is still ≥ 3 bins wide)."""
    n = frf.f_Hz.size
    if n <= max_bins:
        return frf
    grid = np.geomspace(frf.f_Hz[0], frf.f_Hz[-1], max_bins)
    k = np.unique(np.clip(np.searchsorted(frf.f_Hz, grid), 0, n - 1))
    return FRF(frf.f_Hz[k], frf.G[k], frf.coherence[k])


def uniform_dt(t_s: np.ndarray) -> float:
    """The sample period of strictly increasing, uniformly sampled time [s]."""
    d = np.diff(t_s)
    dt = float(np.median(d)) if d.size else 0.0
    if dt <= 0 or np.max(np.abs(d - dt)) > 1e-3 * dt:
        raise ModelError("t_s: dynamics identification needs strictly increasing, uniformly sampled time")
    return dt


def small_signal_segment(u: np.ndarray, y: np.ndarray, t: np.ndarray, segment: Any
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The part of the record to fit: ``segment="all"`` everything; ``"auto"`` the
    small-signal part (:func:`small_signal_bounds`), or everything when there is none."""
    if segment == "all":
        return u, y, t
    if segment != "auto":
        raise ModelError(f"segment: {segment!r}; allowed: auto, all")
    bounds = small_signal_bounds(u, t)
    if bounds is None:
        return u, y, t
    a, b = bounds
    log.info("dynamics: fitting the small-signal part %.6g … %.6g s", t[a], t[b - 1])
    return u[a:b], y[a:b], t[a:b]


def small_signal_bounds(u: np.ndarray, t: np.ndarray) -> tuple[int, int] | None:
    """``(start, stop)`` sample indices of the longest run of samples whose input moves, but
    within 5 % of the input's span over 0.1 s windows (the small-signal part of an
    ``afmctl excite --kind all`` recording; large sweeps would show the hysteresis, dwells
    carry no information); None when the record has no such run of ≥ 256 samples, or is
    all one."""
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    dt = float(t[1] - t[0])
    w = max(3, int(round(0.1 / dt)))
    local = maximum_filter1d(u, w) - minimum_filter1d(u, w)
    span = float(np.ptp(u))
    ok = (local > 0) & (local <= 0.05 * span) if span > 0 else np.zeros(u.size, bool)
    if not np.any(ok) or np.all(ok):
        return None
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    starts, stops = edges[::2], edges[1::2]
    k = int(np.argmax(stops - starts))
    a, b = int(starts[k]), int(stops[k])
    return (a, b) if b - a >= 256 else None


def measure_frf(u: np.ndarray, y: np.ndarray, dt_s: float, nperseg: int, f_min_Hz: float, f_max_Hz: float,
                min_coherence: float) -> FRF:
    """Welch estimate of ``y/u`` at the excited, coherent bins in [f_min_Hz, f_max_Hz]."""
    from scipy.signal import coherence, csd, welch

    fs = 1.0 / dt_s
    kw = dict(fs=fs, nperseg=nperseg, detrend="linear", window="hann")
    f, puu = welch(u, **kw)
    _, puy = csd(u, y, **kw)
    with np.errstate(invalid="ignore", divide="ignore"):  # a constant output has no coherence
        _, coh = coherence(u, y, **kw)
    coh = np.nan_to_num(coh, nan=0.0)
    keep = (f >= f_min_Hz) & (f <= f_max_Hz) & (puu > 1e-6 * np.max(puu[1:])) & (coh >= min_coherence)
    keep[0] = False
    if np.count_nonzero(keep) < 8:
        raise ModelError(f"data: only {int(np.count_nonzero(keep))} frequency bins between {f_min_Hz:g} and "
                         f"{f_max_Hz:g} Hz are excited with coherence ≥ {min_coherence:g}; record a "
                         "small-signal chirp or multisine ('afmctl excite --kind dynamics')")
    return FRF(f[keep], puy[keep] / puu[keep], coh[keep])


def _unpack(x: np.ndarray, n_modes: int, n_lags: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, float]:
    K = math.exp(x[0])
    fm = np.exp(x[1:1 + n_modes])
    zeta = x[1 + n_modes:1 + 2 * n_modes]
    fl = np.exp(x[1 + 2 * n_modes:1 + 2 * n_modes + n_lags])
    return K, fm, zeta, fl, float(x[-1])


def model_response(x: np.ndarray, f_Hz: np.ndarray, n_modes: int, n_lags: int) -> np.ndarray:
    """``G(j2πf)`` of the fitted structure for the parameter vector ``x``."""
    K, fm, zeta, fl, tau = _unpack(x, n_modes, n_lags)
    s = 2j * math.pi * f_Hz
    g = K * np.exp(-s * tau)
    for f0, z in zip(fm, zeta):
        w = 2 * math.pi * f0
        g = g * w * w / (s * s + 2 * z * w * s + w * w)
    for f0 in fl:
        w = 2 * math.pi * f0
        g = g * w / (s + w)
    return g


def _initial(frf: FRF, n_modes: int, n_lags: int, lag_Hz: float, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from scipy.signal import find_peaks

    mag = np.abs(frf.G)
    peaks, props = find_peaks(mag / np.median(mag), prominence=0.05)
    order = peaks[np.argsort(props["prominences"])[::-1]][:n_modes] if peaks.size else np.zeros(0, int)
    f_lo, f_hi = float(frf.f_Hz[0]), float(frf.f_Hz[-1])
    below = frf.f_Hz < 0.2 * (float(np.min(frf.f_Hz[order])) if order.size else f_hi)
    K0 = float(np.median(mag[below] if np.count_nonzero(below) >= 3 else mag[:3]))
    fm = sorted(frf.f_Hz[order].tolist())
    # ζ from the peak height: |G(f_n)| ≈ K/(2ζ)
    zeta0 = sorted([float(np.clip(K0 / (2 * mag[i]), 2e-3, 0.5)) for i in order], key=lambda z: 0)
    zeta0 = [z for _, z in sorted(zip(frf.f_Hz[order].tolist(), zeta0))]
    while len(fm) < n_modes:
        fm.append(f_hi * (len(fm) + 1) / (n_modes + 1))
        zeta0.append(0.05)
    x0 = [math.log(K0)] + [math.log(f) for f in fm] + zeta0 + [math.log(lag_Hz)] * n_lags + [0.0]
    lb = [-np.inf] + [math.log(f_lo)] * n_modes + [1e-3] * n_modes + [math.log(f_lo)] * n_lags + [-2 * dt_s]
    ub = [np.inf] + [math.log(10 * f_hi)] * n_modes + [0.99] * n_modes + [math.log(100 * f_hi)] * n_lags + [10 / f_hi]
    return np.array(x0), np.array(lb), np.array(ub)


def poles_of(x: np.ndarray, n_modes: int, n_lags: int) -> tuple[np.ndarray, float, float]:
    """The fitted structure's poles [rad/s] (modes as conjugate pairs, then the lags),
    its delay τ [s] and static gain K for the parameter vector ``x``."""
    K, fm, zeta, fl, tau = _unpack(x, n_modes, n_lags)
    poles = []
    for f0, z in zip(fm, zeta):
        wn = 2 * math.pi * f0
        re, im = -z * wn, wn * math.sqrt(max(0.0, 1 - z * z))
        poles += [complex(re, im), complex(re, -im)]
    poles += [complex(-2 * math.pi * f0, 0.0) for f0 in fl]
    return np.array(poles, dtype=complex), tau, K


def fit_frf(frf: FRF, n_modes: int, n_lags: int, dt_s: float) -> tuple[np.ndarray, float]:
    """Least-squares fit of the structure to ``frf`` from a few starting lags; returns the
    best parameter vector and its RMS complex log error (≈ relative error)."""
    from scipy.optimize import least_squares

    w = np.sqrt(frf.coherence)

    def resid(x: np.ndarray) -> np.ndarray:
        r = w * np.log(model_response(x, frf.f_Hz, n_modes, n_lags) / frf.G)
        return np.concatenate([r.real, r.imag])

    best = None
    f_hi = float(frf.f_Hz[-1])
    for lag_Hz in ([0.3 * f_hi, f_hi, 3 * f_hi] if n_lags else [f_hi]):
        x0, lb, ub = _initial(frf, n_modes, n_lags, lag_Hz, dt_s)
        x0 = np.clip(x0, lb + 1e-12, ub - 1e-12)
        sol = least_squares(resid, x0, bounds=(lb, ub), x_scale="jac", max_nfev=MAX_NFEV)
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None  # the loop above runs at least once
    rms = float(np.sqrt(2 * best.cost / frf.f_Hz.size))
    if best.status == 0:
        log.warning("dynamics fit: least squares did not converge in %d evaluations", best.nfev)
        frf.unconverged_modes.add(n_modes)
    return best.x, rms


#: ``n_modes="auto"``: most modes tried, and the factor by which one more mode must lower
#: the fit's RMS log error to be kept
MAX_AUTO_MODES, MODE_GAIN = 3, 0.75


def fit_mode_count(frf: FRF, n_lags: int, dt_s: float) -> tuple[int, np.ndarray, float]:
    """Fit 1, 2, … :data:`MAX_AUTO_MODES` structural modes; keep adding one while it lowers
    the RMS log error below :data:`MODE_GAIN` times the previous (a further mode that does
    not explain the response is not kept). Returns the count, its parameters, its RMS."""
    n, (x, rms) = 1, fit_frf(frf, 1, n_lags, dt_s)
    while n < MAX_AUTO_MODES:
        x2, rms2 = fit_frf(frf, n + 1, n_lags, dt_s)
        if not rms2 < MODE_GAIN * rms:
            break
        n, x, rms = n + 1, x2, rms2
    return n, x, rms


def fit_dynamics(t_s: np.ndarray, u: np.ndarray, y_nm: np.ndarray, **options: Any) -> DynamicsFit:
    """Identify the dynamics; options (all optional): ``segment`` ("auto": the small-signal
    part, see :func:`small_signal_segment`; "all"), ``n_modes`` ("auto": as many as the
    response shows, :func:`fit_mode_count`; or 0…6), ``n_lags`` (1),
    ``nperseg`` (samples per Welch segment, default the largest power of two ≤ N/4),
    ``f_min_Hz``, ``f_max_Hz`` (default 40 % of the sample rate), ``min_coherence`` (0.9)."""
    t = check_finite("t_s", t_s).ravel()
    u = check_finite("u", u).ravel()
    y = check_finite("y_nm", y_nm).ravel()
    if not (t.size == u.size == y.size) or t.size < 256:
        raise ModelError("data: need equal-length columns t, u, y with at least 256 samples")
    dt = uniform_dt(t)
    fs = 1.0 / dt
    if options.pop("n_operators", None) is not None:
        raise ModelError("--operators: not used by the dynamics model; use --param n_modes=N / n_lags=N")
    u, y, t = small_signal_segment(u, y, t, options.pop("segment", "auto"))
    modes_opt = options.pop("n_modes", "auto")
    n_modes = None if modes_opt == "auto" else int(number_option("n_modes", modes_opt, lo=0, hi=6, integer=True))
    n_lags = int(number_option("n_lags", options.pop("n_lags", 1), lo=0, hi=4, integer=True))
    nps = 1 << int(math.floor(math.log2(max(16, t.size // 4))))
    nperseg = int(number_option("nperseg", options.pop("nperseg", nps), lo=16, hi=t.size, integer=True))
    f_max = number_option("f_max_Hz", options.pop("f_max_Hz", 0.4 * fs), lo=0, hi=fs / 2)
    f_min = number_option("f_min_Hz", options.pop("f_min_Hz", 0.0), lo=0, hi=f_max)
    min_coh = number_option("min_coherence", options.pop("min_coherence", 0.9), lo=0, hi=1)
    if options:
        raise ModelError(f"options: unknown option(s) {', '.join(sorted(options))}; allowed: segment, n_modes, n_lags, "
                         "nperseg, f_min_Hz, f_max_Hz, min_coherence")
    frf = thinned(measure_frf(u, y, dt, nperseg, f_min, f_max, min_coh))
    if n_modes is None:
        n_modes, x, rms = fit_mode_count(frf, n_lags, dt)
    else:
        x, rms = fit_frf(frf, n_modes, n_lags, dt)
    poles, tau, K = poles_of(x, n_modes, n_lags)
    info: dict[str, float | str] = {
        "static_gain_y_per_u": K, "fit_rms_log": rms, "f_min_Hz": float(frf.f_Hz[0]),
        "f_max_Hz": float(frf.f_Hz[-1]), "bins": float(frf.f_Hz.size), "sample_rate_Hz": fs,
        "fitted_delay_s": tau, "fit_t0_s": float(t[0]), "fit_t1_s": float(t[-1]),
    }
    if n_modes in frf.unconverged_modes:
        info["problem"] = f"dynamics: the frequency-response fit did not converge ({MAX_NFEV} evaluations per start)"
    log.info("dynamics fit: %d modes, %d lags, delay %.3g µs, RMS log error %.3g over %d bins",
             n_modes, n_lags, tau * 1e6, rms, frf.f_Hz.size)
    return DynamicsFit(poles, np.zeros(0, complex), max(0.0, tau - 0.5 * dt), info)
