"""Hot loops of the rate-dependent Prandtl–Ishlinskii operator, compiled with numba, and
their plain-Python references (same operations in the same order: bit-identical, tested).

Per sample ``k`` with input ``v`` [V] (:mod:`afmctl.compensators.rate_pi`)::

    g    = 1 + c·min(ρ, ρ_max)           (ρ: the input's smoothed rate up to sample k−1)
    x_i ← max(v − g·r_i, min(v + g·r_i, x_i))
    y    = out_off + Σ_i w_i·x_i
    s'   = s + a·(v − s);  ρ ← ρ + a·(|s' − s|/dt − ρ);  s ← s'

``aux = [ρ, s]`` is the rate state: ``s`` the input through a first-order low-pass, ρ its
|slope| through the same low-pass. Smoothing the input before its slope is taken keeps ρ
the same at any sample rate: a step of ΔV gives at most ΔV/τ, a small fast wiggle of
amplitude A about A/τ, where the raw |Δv|/dt would grow with the sample rate. The thresholds of sample ``k`` depend only on the
inputs before it, so the inverse solves one piecewise-linear equation per sample exactly.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _advance(v, aux, dt, a):  # pragma: no cover - compiled
    s = aux[1] + a * (v - aux[1])
    aux[0] = aux[0] + a * (abs(s - aux[1]) / dt - aux[0])
    aux[1] = s


@njit(cache=True, nogil=True, inline="always")
def _play(s, v, h):  # pragma: no cover - compiled
    """One play's new state: ``s`` clamped to ``[v − h, v + h]``."""
    if s > v + h:
        s = v + h
    if s < v - h:
        s = v - h
    return s


@njit(cache=True, nogil=True)
def _clamp_sum(v, r, w, g, state, out_off):  # pragma: no cover - compiled
    acc = 0.0
    for i in range(r.shape[0]):
        s = _play(state[i], v, g * r[i])
        state[i] = s
        acc += w[i] * s
    return out_off + acc


@njit(cache=True, nogil=True)
def _peek(v, r, w, g, state):  # pragma: no cover - compiled
    acc = 0.0
    for i in range(r.shape[0]):
        acc += w[i] * _play(state[i], v, g * r[i])
    return acc


@njit(cache=True, nogil=True)
def _solve(target, r, w, g, state, knots):  # pragma: no cover - compiled
    n = r.shape[0]
    for i in range(n):
        knots[2 * i] = state[i] - g * r[i]
        knots[2 * i + 1] = state[i] + g * r[i]
    knots.sort()
    lo = 0
    hi = 2 * n - 1
    f_lo = _peek(knots[lo], r, w, g, state)
    f_hi = _peek(knots[hi], r, w, g, state)
    slope = 0.0
    for i in range(n):
        slope += w[i]
    if target <= f_lo:
        return knots[lo] - (f_lo - target) / slope
    if target >= f_hi:
        return knots[hi] + (target - f_hi) / slope
    while hi - lo > 1:
        mid = (lo + hi) // 2
        f_mid = _peek(knots[mid], r, w, g, state)
        if f_mid <= target:
            lo = mid
            f_lo = f_mid
        else:
            hi = mid
            f_hi = f_mid
    if f_hi == f_lo:
        return knots[lo]
    return knots[lo] + (target - f_lo) * (knots[hi] - knots[lo]) / (f_hi - f_lo)


@njit(cache=True, nogil=True)
def forward_block(x, r, w, c, rmax, a, dt, state, aux, out_off, out):  # pragma: no cover - compiled
    """``x`` [V] through the operator into ``out`` [nm]; ``state``, ``aux`` carried in place."""
    for k in range(x.shape[0]):
        out[k] = _clamp_sum(x[k], r, w, 1.0 + c * min(aux[0], rmax), state, out_off)
        _advance(x[k], aux, dt, a)


@njit(cache=True, nogil=True)
def inverse_block(y, r, w, c, rmax, a, dt, state, aux, out_off, out):  # pragma: no cover - compiled
    """The voltages [V] whose output is ``y`` [nm] into ``out``; state carried in place."""
    knots = np.empty(2 * r.shape[0])
    for k in range(y.shape[0]):
        g = 1.0 + c * min(aux[0], rmax)
        v = _solve(y[k] - out_off, r, w, g, state, knots)
        _clamp_sum(v, r, w, g, state, 0.0)
        _advance(v, aux, dt, a)
        out[k] = v


@njit(cache=True, nogil=True)
def play_outputs(x, r, c, rmax, a, dt, state, aux, out):  # pragma: no cover - compiled
    """Every play's output for every sample, ``out[k, i]`` (identification regressors)."""
    for k in range(x.shape[0]):
        g = 1.0 + c * min(aux[0], rmax)
        v = x[k]
        for i in range(r.shape[0]):
            state[i] = _play(state[i], v, g * r[i])
            out[k, i] = state[i]
        _advance(v, aux, dt, a)


@njit(cache=True, nogil=True)
def rates(x, a, dt, aux, out):  # pragma: no cover - compiled
    """ρ [V/s] before every sample of ``x`` into ``out``; ``aux`` carried in place."""
    for k in range(x.shape[0]):
        out[k] = aux[0]
        _advance(x[k], aux, dt, a)


# ------------------------------------------------------------------ references -------

def _advance_ref(v: float, aux: np.ndarray, dt: float, a: float) -> None:
    s = aux[1] + a * (v - aux[1])
    aux[0] = aux[0] + a * (abs(s - aux[1]) / dt - aux[0])
    aux[1] = s


def _plays_ref(v: float, r: np.ndarray, g: float, state: np.ndarray) -> np.ndarray:
    h = g * r
    return np.maximum(np.minimum(state, v + h), v - h)


def _sum_ref(w: np.ndarray, s: np.ndarray) -> float:
    acc = 0.0
    for wi, si in zip(w.tolist(), s.tolist()):
        acc += wi * si
    return acc


def forward_block_ref(x: np.ndarray, r: np.ndarray, w: np.ndarray, c: float, rmax: float, a: float, dt: float,
                      state: np.ndarray, aux: np.ndarray, out_off: float) -> np.ndarray:
    """Plain-numpy reference of :func:`forward_block` (returns ``out``)."""
    out = np.empty(x.shape[0])
    for k, v in enumerate(x.tolist()):
        state[:] = _plays_ref(v, r, 1.0 + c * min(aux[0], rmax), state)
        out[k] = out_off + _sum_ref(w, state)
        _advance_ref(v, aux, dt, a)
    return out


def _solve_ref(target: float, r: np.ndarray, w: np.ndarray, g: float, state: np.ndarray) -> float:
    knots = np.sort(np.concatenate([np.stack([state - g * r, state + g * r], axis=1).ravel()]))

    def f(v: float) -> float:
        return _sum_ref(w, _plays_ref(v, r, g, state))

    lo, hi = 0, knots.size - 1
    f_lo, f_hi, slope = f(knots[lo]), f(knots[hi]), _sum_ref(w, np.ones_like(w))
    if target <= f_lo:
        return float(knots[lo] - (f_lo - target) / slope)
    if target >= f_hi:
        return float(knots[hi] + (target - f_hi) / slope)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        f_mid = f(knots[mid])
        if f_mid <= target:
            lo, f_lo = mid, f_mid
        else:
            hi, f_hi = mid, f_mid
    if f_hi == f_lo:
        return float(knots[lo])
    return float(knots[lo] + (target - f_lo) * (knots[hi] - knots[lo]) / (f_hi - f_lo))


def inverse_block_ref(y: np.ndarray, r: np.ndarray, w: np.ndarray, c: float, rmax: float, a: float, dt: float,
                      state: np.ndarray, aux: np.ndarray, out_off: float) -> np.ndarray:
    """Plain-numpy reference of :func:`inverse_block` (returns ``out``)."""
    out = np.empty(y.shape[0])
    for k, target in enumerate(y.tolist()):
        g = 1.0 + c * min(aux[0], rmax)
        v = _solve_ref(target - out_off, r, w, g, state)
        state[:] = _plays_ref(v, r, g, state)
        _advance_ref(v, aux, dt, a)
        out[k] = v
    return out


def smoothing_factor(dt_s: float, tau_s: float) -> float:
    """The rate filter's ``a = 1 − exp(−dt/τ)`` (a first-order low-pass of time constant
    ``tau_s`` [s] sampled every ``dt_s`` [s])."""
    return -math.expm1(-dt_s / tau_s)
