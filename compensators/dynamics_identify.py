"""Identification of linear scanner dynamics from the fast parts of a recording.

1. Frequency response ``Ĝ(f) = P_uy(f) / P_uu(f)`` and coherence by Welch's method
   (:func:`scipy.signal.csd`, :func:`scipy.signal.welch`), the spectra averaged over every
   part of the record with fast content (:func:`fast_parts`: afmctl's multisine, a chirp of
   any amplitude, fast triangles, a PRBS; Pintelon & Schoukens' best linear approximation,
   with the nonlinear distortion showing as lost coherence).
2. Keep the bins the input excites (power above 1e-6 of its peak) whose coherence is at
   least ``min_coherence``, between ``f_min_Hz`` and ``f_max_Hz``.
3. Fit, with :func:`scipy.optimize.least_squares` (analytic Jacobian,
   :func:`log_response_jacobian`) on the complex log error
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
whose output is read after the command within the same sample (at the end of each hold
interval, as the simulated scanner reports positions) still fits. Such a record leads the
model's convention by ``dt/2 − τ``; that lead is kept in samples, up to one
(``lead_samples``, :func:`afmctl.compensators.lti.discretise`: the state read inside the
interval), since it is a convention of the sampling and scales with the sample period.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

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
    #: the output read this fraction of a period after each command (module docstring)
    lead_samples: float = 0.0


@dataclass
class FRF:
    """Measured frequency response at the kept bins."""

    f_Hz: np.ndarray
    G: np.ndarray
    coherence: np.ndarray
    #: mode counts whose least-squares fit spent its evaluation budget (did not converge)
    unconverged_modes: set[int] = field(default_factory=set)
    #: one clause per mode count :func:`fit_mode_count` tried (the fit's report:
    #: ``info["mode_trials"]``)
    trials: list[str] = field(default_factory=list)


#: function evaluations per start of the least-squares fit (a good start converges in < 100)
MAX_NFEV = 400
#: longest default Welch segment (65536 samples: 0.76 Hz bins at 50 kHz)
MAX_NPERSEG = 1 << 16
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


def is_uniform(t_s: np.ndarray) -> bool:
    """Whether ``t_s`` [s] is strictly increasing and uniformly sampled (:func:`uniform_dt`)."""
    try:
        uniform_dt(t_s)
    except ModelError:
        return False
    return True


def parts_mask(n: int, parts: list[tuple[int, int]], margin: int = 0) -> np.ndarray:
    """One boolean per sample of a record of ``n``: True inside each ``(start, stop)`` of
    ``parts`` and up to ``margin`` samples after it."""
    mask = np.zeros(n, dtype=bool)
    for a, b in parts:
        mask[a:min(n, b + margin)] = True
    return mask


#: ``segment`` values of :func:`fit_dynamics`
SEGMENTS: tuple[str, ...] = ("auto", "small-signal", "all")


def record_parts(u: np.ndarray, t: np.ndarray, segment: Any) -> list[tuple[int, int]]:
    """The parts of the record the frequency response is measured on, as ``(start, stop)``
    sample indices: ``segment="all"`` the whole record; ``"small-signal"`` the small-signal
    run (:func:`small_signal_bounds`, afmctl's multisine); ``"auto"`` every part that shows
    the dynamics (:func:`dynamics_parts`: the multisine, a chirp of any amplitude, fast
    triangles, a PRBS). Either falls back to the whole record when it finds nothing."""
    if segment not in SEGMENTS:
        raise ModelError(f"segment: {segment!r}; allowed: {', '.join(SEGMENTS)}")
    whole = [(0, int(u.size))]
    if segment == "all":
        return whole
    if segment == "small-signal":
        bounds = small_signal_bounds(u, t)
        return whole if bounds is None else [bounds]
    return small_signal_first(u, t, dynamics_parts(u, t)) or whole


#: a fast part whose input spans more than this fraction of the record's span is large-signal
LARGE_FRACTION = 0.2


def small_signal_first(u: np.ndarray, t: np.ndarray, parts: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """``parts`` without the large-signal ones (input over more than :data:`LARGE_FRACTION` of
    the span: the large fast triangles and steps of ``afmctl excite --kind fast``) when the
    record also has a small-signal run of at least :data:`FAST_MIN_S` (afmctl's multisine):
    that measures the best linear approximation cleanly, and the large parts' hysteresis
    harmonics would cost the coherence the high bins need (a 1.6 kHz mode lost behind a
    triangle part: kept bins up to 0.8 kHz instead of past the mode). A record without such
    a run, or whose small run is not stationary (a lab's chirp: :func:`stationary`), keeps
    every part."""
    small = small_signal_bounds(u, t)
    if small is None or (small[1] - small[0]) * float(t[1] - t[0]) < FAST_MIN_S:
        return parts
    if not stationary(u[small[0]:small[1]], 1024):
        return parts
    span = float(np.ptp(u))
    keep = [(a, b) for a, b in parts
            if (a <= small[0] and b >= small[1]) or float(np.ptp(u[a:b])) <= LARGE_FRACTION * span]
    return keep or parts


def dynamics_parts(u: np.ndarray, t: np.ndarray) -> list[tuple[int, int]]:
    """Every part of the record that shows the dynamics, in time order: the fast parts
    (:func:`fast_parts`) and the small-signal run (:func:`small_signal_bounds`: afmctl's
    multisine, whose few % of the span at a low sample rate need not count as fast; at least
    :data:`FAST_MIN_S` long), overlapping ones merged; empty when there is none."""
    small = small_signal_bounds(u, t)
    if small is not None and (small[1] - small[0]) * float(t[1] - t[0]) < FAST_MIN_S:
        small = None                           # a turnaround's top, not a multisine
    parts = sorted(fast_parts(u, t) + ([small] if small is not None else []))
    merged: list[tuple[int, int]] = []
    for a, b in parts:
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(b, merged[-1][1]))
        else:
            merged.append((a, b))
    return merged


#: ``fast_parts``: the input's content above ~10 Hz (its departure from a running mean over
#: :data:`FAST_MEAN_S`), RMS over :data:`FAST_WINDOW_S`, above this fraction of its span …
FAST_FRACTION = 0.01
FAST_MEAN_S, FAST_WINDOW_S = 0.05, 0.02
#: … for at least this long [s]
FAST_MIN_S = 0.25


def fast_parts(u: np.ndarray, t: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` sample indices of the runs where the input has fast content: its
    departure from its own running mean over :data:`FAST_MEAN_S` (what is left above ~10 Hz)
    has an RMS over :data:`FAST_WINDOW_S` above :data:`FAST_FRACTION` of the input's span, for
    at least :data:`FAST_MIN_S` and 256 samples. That is where a scanner's amplifier lag and
    structural modes show in the output: a chirp past ~10 Hz of a few % of the span,
    triangles at ~10 Hz and up, a PRBS. A ramp at any constant speed has none (a lag only
    delays it), nor have slow sweeps with a turnaround now and then."""
    from scipy.ndimage import uniform_filter1d

    if u.size < 256:
        return []
    dt = float(t[1] - t[0])
    span = float(np.ptp(u))
    if not span > 0:
        return []
    high = u - uniform_filter1d(u, max(3, int(round(FAST_MEAN_S / dt))), mode="nearest")
    power = uniform_filter1d(high * high, max(3, int(round(FAST_WINDOW_S / dt))), mode="nearest")
    rms = np.sqrt(np.maximum(power, 0.0))       # the running mean of squares may round below 0
    min_len = max(256, int(round(FAST_MIN_S / dt)))
    return [(a, b) for a, b in true_runs(rms > FAST_FRACTION * span) if b - a >= min_len]


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` sample indices of each run of True in ``mask`` (stop exclusive)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(mask).astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def parts_text(t: np.ndarray, parts: list[tuple[int, int]]) -> str:
    """``"8.5–10.5 s, 12–20 s"``: the parts of a record, for reports."""
    return ", ".join(f"{t[a]:.4g}–{t[b - 1]:.4g} s" for a, b in parts)


def small_signal_bounds(u: np.ndarray, t: np.ndarray) -> tuple[int, int] | None:
    """``(start, stop)`` sample indices of the longest run of samples whose input moves, but
    within 5 % of the input's span over 0.1 s windows and within :data:`LARGE_FRACTION` of it
    over the whole run (the small-signal part of an ``afmctl excite --kind all`` recording;
    large sweeps would show the hysteresis, dwells carry no information; slow triangles of
    tens of volts move little in 0.1 s but are large-signal: a lab's nested 0.5 Hz triangles
    were taken for the small-signal run, and the chirp beside them was dropped); None when
    the record has no such run of ≥ 256 samples, or is all one."""
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    dt = float(t[1] - t[0])
    w = max(3, int(round(0.1 / dt)))
    local = maximum_filter1d(u, w) - minimum_filter1d(u, w)
    span = float(np.ptp(u))
    ok = (local > 0) & (local <= 0.05 * span) if span > 0 else np.zeros(u.size, bool)
    if not np.any(ok) or np.all(ok):
        return None
    runs = [(a, b) for a, b in true_runs(ok) if float(np.ptp(u[a:b])) <= LARGE_FRACTION * span]
    if not runs:
        return None
    a, b = max(runs, key=lambda run: run[1] - run[0])
    return (a, b) if b - a >= 256 else None


#: Welch segment [s] when a part's input is not stationary (a sweep, triangles at changing
#: rates): the segment must not span much of the sweep — in a long one the output at a
#: resonance also holds the hysteresis harmonics of the sweep's earlier, slower part, which
#: the mode amplifies, and the coherence there collapses (0.001 at 1.55 kHz on a 1.6 kHz,
#: Q 30 plant with 1.3 s segments; the mode found to 0.02 % with 0.16 s)
SWEEP_SEGMENT_S = 0.16
#: ``stationary``: the two halves' input spectra (in dB, over the bins within 60 dB of the
#: peak) differ by less than this RMS [dB] — a periodic multisine repeats its spectrum, a
#: sweep does not
STATIONARY_DB = 6.0


def stationary(u: np.ndarray, nperseg: int) -> bool:
    """Whether the input ``u`` of one part has the same spectrum in its first and second
    half (Welch, ``nperseg`` samples, at most a quarter of a half): afmctl's multisine or a
    PRBS does, a chirp or triangles at changing rates do not."""
    from scipy.signal import welch

    half = u.size // 2
    n = min(nperseg, max(16, half // 4))
    if half < 4 * 16:
        return True
    _, p1 = welch(u[:half], nperseg=n, detrend="linear")
    _, p2 = welch(u[half:2 * half], nperseg=n, detrend="linear")
    peak = max(float(np.max(p1[1:])), float(np.max(p2[1:])))
    if not peak > 0:
        return True
    band = (np.maximum(p1, p2) > 1e-6 * peak)
    band[0] = False
    if not np.any(band):
        return True
    floor = 1e-9 * peak
    diff_db = 10.0 * np.log10((p1[band] + floor) / (p2[band] + floor))
    return float(np.sqrt(np.mean(diff_db ** 2))) < STATIONARY_DB


def measure_frf(u: np.ndarray, y: np.ndarray, dt_s: float, nperseg: int, f_min_Hz: float, f_max_Hz: float,
                min_coherence: float, parts: list[tuple[int, int]] | None = None) -> FRF:
    """Welch estimate of ``y/u`` at the excited, coherent bins in [f_min_Hz, f_max_Hz].

    With ``parts`` (``(start, stop)`` sample indices), the spectra are averaged over the
    Welch segments of every part at least ``nperseg`` long, each part's weighted by its
    number of segments (the parts are not joined: a join would be a step); the coherence
    ``|P_uy|²/(P_uu·P_yy)`` of the summed spectra weighs each bin by how linearly the
    output follows the input there, across all the parts."""
    from scipy.signal import csd, welch

    fs = 1.0 / dt_s
    kw = dict(fs=fs, nperseg=nperseg, detrend="linear", window="hann")
    spans = [(a, b) for a, b in (parts or [(0, u.size)]) if b - a >= nperseg]
    if not spans:
        raise ModelError(f"data: no part of the record is {nperseg} samples long (nperseg)")
    f = puu = pyy = puy = None
    for a, b in spans:
        n_seg = 1 + (b - a - nperseg) // (nperseg // 2)
        f, p_uu = welch(u[a:b], **kw)
        _, p_yy = welch(y[a:b], **kw)
        _, p_uy = csd(u[a:b], y[a:b], **kw)
        puu = n_seg * p_uu if puu is None else puu + n_seg * p_uu
        pyy = n_seg * p_yy if pyy is None else pyy + n_seg * p_yy
        puy = n_seg * p_uy if puy is None else puy + n_seg * p_uy
    assert f is not None and puu is not None and pyy is not None and puy is not None
    with np.errstate(invalid="ignore", divide="ignore"):  # a constant output has no coherence
        coh = np.nan_to_num(np.abs(puy) ** 2 / (puu * pyy), nan=0.0)
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


def log_response_jacobian(x: np.ndarray, f_Hz: np.ndarray, n_modes: int, n_lags: int) -> np.ndarray:
    """``∂ log G(j2πf) / ∂x`` of :func:`model_response`, complex, shape ``(f_Hz.size, x.size)``.

    ``log G = x₀ − sτ + Σ_i [2 log ω_i − log(s² + 2ζ_iω_i s + ω_i²)] + Σ_j [log p_j − log(s + p_j)]``
    with ``ω_i = 2π e^{x}`` (so ``∂ω/∂x = ω``): per mode ``∂/∂ log f = 2 − 2ω(ζs + ω)/D`` and
    ``∂/∂ζ = −2ωs/D`` (``D`` its denominator), per lag ``∂/∂ log f = s/(s + p)``, and
    ``∂/∂τ = −s``. The branch of the log does not matter: it is constant between jumps."""
    _, fm, zeta, fl, _ = _unpack(x, n_modes, n_lags)
    s = 2j * math.pi * np.asarray(f_Hz, dtype=float)
    J = np.empty((s.size, x.size), dtype=complex)
    J[:, 0] = 1.0
    for i, (f0, z) in enumerate(zip(fm, zeta)):
        w = 2 * math.pi * f0
        D = s * s + 2 * z * w * s + w * w
        J[:, 1 + i] = 2.0 - 2.0 * w * (z * s + w) / D
        J[:, 1 + n_modes + i] = -2.0 * w * s / D
    for j, f0 in enumerate(fl):
        J[:, 1 + 2 * n_modes + j] = s / (s + 2 * math.pi * f0)
    J[:, -1] = -s
    return J


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
    lb = [-np.inf] + [math.log(f_lo)] * n_modes + [ZETA_MIN] * n_modes + [math.log(f_lo)] * n_lags + [-2 * dt_s]
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


#: a mode added to a fitted structure (:func:`grown_starts`) starts either at the largest
#: misfit of the smaller structure with ζ :data:`ADDED_MODE_ZETA` [-], or this many times
#: above the measured band with ζ 0.5, where it barely changes the response inside the band:
#: the larger fit then starts close to where the smaller one ended
ADDED_MODE_ABOVE, ADDED_MODE_ZETA = 5.0, 0.05


def grown_starts(x: np.ndarray, frf: FRF, n_modes: int, n_lags: int) -> list[np.ndarray]:
    """Starting vectors for a fit with ``n_modes + 1`` modes from the parameters ``x`` of the
    fit with ``n_modes``: the new mode at the largest coherence-weighted misfit of ``x``, and
    far above the band (:data:`ADDED_MODE_ABOVE`). A start from nothing put the second mode
    of the demo's scanner where the response has no peak, and the fit wandered for 400
    evaluations into a minimum 500× worse than the one-mode fit it contains."""
    misfit = np.sqrt(frf.coherence) * np.abs(np.log(model_response(x, frf.f_Hz, n_modes, n_lags) / frf.G))
    f_new = [float(frf.f_Hz[int(np.argmax(misfit))]), ADDED_MODE_ABOVE * float(frf.f_Hz[-1])]
    zeta_new = [ADDED_MODE_ZETA, 0.5]
    k = 1 + n_modes                            # x: log K, log f (n), ζ (n), log lags, τ
    return [np.concatenate([x[:k], [math.log(f)], x[k:k + n_modes], [z], x[k + n_modes:]])
            for f, z in zip(f_new, zeta_new)]


#: how :func:`fit_frf` gets the residual's Jacobian: analytic, or scipy's finite differences
Jacobian = Literal["analytic", "2-point", "3-point"]


def fit_frf(frf: FRF, n_modes: int, n_lags: int, dt_s: float,
            grow_from: np.ndarray | None = None, jac: Jacobian = "analytic") -> tuple[np.ndarray, float]:
    """Least-squares fit of the structure to ``frf``; returns the best parameter vector and
    its RMS complex log error (≈ relative error). Started from a few lags and the response's
    peaks, and (``grow_from``: the parameters of the fit with one mode less) from that fit
    with one mode added (:func:`grown_starts`); the best end wins. A best start that spends :data:`MAX_NFEV`
    evaluations is continued once; one that still has not converged is recorded in
    ``frf.unconverged_modes``. ``jac``: "analytic" (:func:`log_response_jacobian`) or a
    finite-difference scheme of :func:`scipy.optimize.least_squares` ("2-point", the fit's
    Jacobian before the analytic one; benchmarks/dynamics_fit.py compares them)."""
    from scipy.optimize import least_squares

    w = np.sqrt(frf.coherence)

    def resid(x: np.ndarray) -> np.ndarray:
        r = w * np.log(model_response(x, frf.f_Hz, n_modes, n_lags) / frf.G)
        return np.concatenate([r.real, r.imag])

    def analytic(x: np.ndarray) -> np.ndarray:
        J = w[:, None] * log_response_jacobian(x, frf.f_Hz, n_modes, n_lags)
        return np.concatenate([J.real, J.imag])

    jacobian: Any = analytic if jac == "analytic" else jac
    f_hi = float(frf.f_Hz[-1])
    _, lb, ub = _initial(frf, n_modes, n_lags, f_hi, dt_s)
    starts = [_initial(frf, n_modes, n_lags, lag_Hz, dt_s)[0]
              for lag_Hz in ([0.3 * f_hi, f_hi, 3 * f_hi] if n_lags else [f_hi])]
    if grow_from is not None:
        starts = grown_starts(grow_from, frf, n_modes - 1, n_lags) + starts
    best = None
    for x0 in starts:
        x0 = np.clip(x0, lb + 1e-12, ub - 1e-12)
        sol = least_squares(resid, x0, jac=jacobian, bounds=(lb, ub), x_scale="jac", max_nfev=MAX_NFEV)
        if best is None or sol.cost < best.cost:
            best = sol
    assert best is not None  # the loop above runs at least once
    if best.status == 0:                       # the budget spent: go on from there, once
        more = least_squares(resid, best.x, jac=jacobian, bounds=(lb, ub), x_scale="jac", max_nfev=MAX_NFEV)
        best = more if more.cost <= best.cost else best
        if more.status == 0:
            frf.unconverged_modes.add(n_modes)
    rms = float(np.sqrt(2 * best.cost / frf.f_Hz.size))
    log.debug("dynamics fit: %d modes, RMS log error %.3g, %d evaluations (status %d)", n_modes, rms,
              best.nfev, best.status)
    return best.x, rms


#: lowest damping ratio the fit searches
ZETA_MIN = 1e-3
#: ``n_modes="auto"``: most modes tried, and the factor by which one more mode must lower
#: the fit's RMS log error to be kept
MAX_AUTO_MODES, MODE_GAIN = 3, 0.75


def unresolved_modes(x: np.ndarray, frf: FRF, n_modes: int, n_lags: int) -> list[str]:
    """The fitted modes the measured response does not resolve: damping on the search's
    lower bound :data:`ZETA_MIN` (the record does not show the peak's width), or a frequency
    outside the measured band; one clause each."""
    _, fm, zeta, _, _ = _unpack(x, n_modes, n_lags)
    lo, hi = float(frf.f_Hz[0]), float(frf.f_Hz[-1])
    out = []
    for f0, z in zip(fm, zeta):
        if z <= 1.01 * ZETA_MIN:
            out.append(f"dynamics: the mode at {f0:.4g} Hz has ζ on its lower bound {ZETA_MIN:g}")
        elif not lo <= f0 <= hi:
            out.append(f"dynamics: the mode at {f0:.4g} Hz lies outside the measured {lo:.4g}–{hi:.4g} Hz")
    return out


def fit_mode_count(frf: FRF, n_lags: int, dt_s: float, jac: Jacobian = "analytic") -> tuple[int, np.ndarray, float]:
    """Fit 0, 1, … :data:`MAX_AUTO_MODES` structural modes, each fit grown from the one
    before (:func:`grown_starts`); keep adding one while it lowers the RMS log error below
    :data:`MODE_GAIN` times the previous and the record resolves it (:func:`unresolved_modes`:
    a mode beyond the measured band, or one whose peak the record does not show, is a guess
    that rings in the inverse). Returns the count, its parameters, its RMS; each count tried
    leaves one clause in ``frf.trials`` (why it was kept or not). ``jac``: as :func:`fit_frf`."""
    n, (x, rms) = 0, fit_frf(frf, 0, n_lags, dt_s, jac=jac)
    frf.trials.append(_trial_text(frf, 0, rms))
    while n < MAX_AUTO_MODES:
        x2, rms2 = fit_frf(frf, n + 1, n_lags, dt_s, grow_from=x, jac=jac)
        unresolved = unresolved_modes(x2, frf, n + 1, n_lags)
        why = (f"not kept: not below {MODE_GAIN:g} × {rms:.3g} (one mode fewer)" if not rms2 < MODE_GAIN * rms
               else f"not kept: {unresolved[0].removeprefix('dynamics: ')}" if unresolved else "")
        frf.trials.append(_trial_text(frf, n + 1, rms2, why))
        if why:
            break
        n, x, rms = n + 1, x2, rms2
    return n, x, rms


def _trial_text(frf: FRF, n_modes: int, rms: float, why: str = "") -> str:
    """``"2 modes: RMS log error 0.0102, not kept: …"`` for ``frf.trials``."""
    text = f"{n_modes} mode{'' if n_modes == 1 else 's'}: RMS log error {rms:.3g}"
    if n_modes in frf.unconverged_modes:
        text += f", did not converge in {2 * MAX_NFEV} evaluations"
    return text + (f", {why}" if why else "")


def fit_dynamics(t_s: np.ndarray, u: np.ndarray, y_nm: np.ndarray, **options: Any) -> DynamicsFit:
    """Identify the dynamics; options (all optional): ``segment`` (the parts of the record
    measured, :func:`record_parts`: "auto" every part with fast content, "small-signal",
    "all"), ``n_modes`` ("auto": as many as the response shows, :func:`fit_mode_count`; or
    0…6), ``n_lags`` (1), ``nperseg`` (samples per Welch segment, default the largest power
    of two ≤ a quarter of the longest part, at most 65536, or :data:`SWEEP_SEGMENT_S` when a
    part's input is not :func:`stationary`; shorter parts are not used),
    ``f_min_Hz``, ``f_max_Hz`` (default 40 % of the sample rate), ``min_coherence`` (0.9).
    ``info["fit_parts"]`` says which parts were used."""
    t = check_finite("t_s", t_s).ravel()
    u = check_finite("u", u).ravel()
    y = check_finite("y_nm", y_nm).ravel()
    if not (t.size == u.size == y.size) or t.size < 256:
        raise ModelError("data: need equal-length columns t, u, y with at least 256 samples")
    dt = uniform_dt(t)
    fs = 1.0 / dt
    if options.pop("n_operators", None) is not None:
        raise ModelError("--operators: not used by the dynamics model; use --param n_modes=N / n_lags=N")
    modes_opt = options.pop("n_modes", "auto")
    n_modes = None if modes_opt == "auto" else int(number_option("n_modes", modes_opt, lo=0, hi=6, integer=True))
    n_lags = int(number_option("n_lags", options.pop("n_lags", 1), lo=0, hi=4, integer=True))
    used, frf = _measured(t, u, y, dt, options)
    frf = thinned(frf)
    if n_modes is None:
        n_modes, x, rms = fit_mode_count(frf, n_lags, dt)
    else:
        x, rms = fit_frf(frf, n_modes, n_lags, dt)
    poles, tau, K = poles_of(x, n_modes, n_lags)
    info: dict[str, float | str] = {
        "static_gain_y_per_u": K, "fit_rms_log": rms, "f_min_Hz": float(frf.f_Hz[0]),
        "f_max_Hz": float(frf.f_Hz[-1]), "bins": float(frf.f_Hz.size), "sample_rate_Hz": fs,
        "fitted_delay_s": tau, "fit_t0_s": float(t[used[0][0]]), "fit_t1_s": float(t[used[-1][1] - 1]),
        "fit_parts": parts_text(t, used),
        "fit_spans_s": " ".join(f"{float(t[a])!r} {float(t[b - 1])!r}" for a, b in used),
    }
    if frf.trials:
        info["mode_trials"] = "; ".join(frf.trials)
    problems = unresolved_modes(x, frf, n_modes, n_lags)
    if n_modes in frf.unconverged_modes:
        problems.insert(0, f"dynamics: the frequency-response fit did not converge ({2 * MAX_NFEV} evaluations)")
    if problems:
        info["problem"] = "; ".join(problems)
    log.info("dynamics fit: %d modes, %d lags, delay %.3g µs, RMS log error %.3g over %d bins",
             n_modes, n_lags, tau * 1e6, rms, frf.f_Hz.size)
    delay, lead = split_delay(tau, dt)
    return DynamicsFit(poles, np.zeros(0, complex), delay, info, lead)


def _measured(t: np.ndarray, u: np.ndarray, y: np.ndarray, dt: float, options: dict[str, Any]
              ) -> tuple[list[tuple[int, int]], FRF]:
    """The parts measured and the frequency response ``y/u`` there (:func:`fit_dynamics`'s
    options ``segment``, ``nperseg``, ``f_min_Hz``, ``f_max_Hz``, ``min_coherence``, popped
    from ``options``; anything left is an unknown option)."""
    fs = 1.0 / dt
    parts = record_parts(u, t, options.pop("segment", "auto"))
    longest = max(b - a for a, b in parts)
    nps = min(MAX_NPERSEG, 1 << int(math.floor(math.log2(max(16, longest // 4)))))
    if not all(stationary(u[a:b], nps) for a, b in parts):
        nps = min(nps, 1 << int(round(math.log2(SWEEP_SEGMENT_S * fs))))
    nperseg = int(number_option("nperseg", options.pop("nperseg", nps), lo=16, hi=longest, integer=True))
    f_max = number_option("f_max_Hz", options.pop("f_max_Hz", 0.4 * fs), lo=0, hi=fs / 2)
    f_min = number_option("f_min_Hz", options.pop("f_min_Hz", 0.0), lo=0, hi=f_max)
    min_coh = number_option("min_coherence", options.pop("min_coherence", 0.9), lo=0, hi=1)
    if options:
        raise ModelError(f"options: unknown option(s) {', '.join(sorted(options))}; allowed: segment, n_modes, n_lags, "
                         "nperseg, f_min_Hz, f_max_Hz, min_coherence")
    used = [(a, b) for a, b in parts if b - a >= nperseg]
    log.info("dynamics: measuring the frequency response on %s", parts_text(t, used))
    return used, measure_frf(u, y, dt, nperseg, f_min, f_max, min_coh, used)


def coherent_band_Hz(t_s: np.ndarray, u: np.ndarray, y_nm: np.ndarray, **options: Any) -> float:
    """The highest frequency [Hz] at which :func:`fit_dynamics` with ``options`` would
    measure ``y/u`` (excited, coherent bins); 0 when it measures none."""
    t = check_finite("t_s", t_s).ravel()
    try:
        _, frf = _measured(t, check_finite("u", u).ravel(), check_finite("y_nm", y_nm).ravel(), uniform_dt(t),
                           dict(options))
    except ModelError:
        return 0.0
    return float(frf.f_Hz[-1]) if frf.f_Hz.size else 0.0


def split_delay(tau_s: float, dt_s: float) -> tuple[float, float]:
    """The fitted delay ``τ`` [s] of sampled, held data at period ``dt_s`` [s] as the
    model's ``(delay_s, lead_samples)``: the hold's half sample taken off; what is left below
    zero is a lead of at most one sample (module docstring)."""
    d = tau_s - 0.5 * dt_s
    if d >= 0:
        return d, 0.0
    return 0.0, float(min(1.0, -d / dt_s))
