"""Hot loops of the Prandtl–Ishlinskii family, compiled with numba, and their plain-Python
references.

One PI kernel serves the forward operator *and* its inverse: the inverse of a PI operator
is again a PI operator (extended-PI paper, eqs. 6–11), only with other thresholds and
weights and with the offset on the input side instead of the output side.

A PI operator with thresholds ``r`` (input units), weights ``w`` and play states ``x``
computes, per sample ``v = input − in_off`` (eq. 3 without creep, eq. 4)::

    x_i ← max(v − r_i, min(v + r_i, x_i))
    y   = out_off + Σ_i w_i·x_i            (summed in the canonical order below)

The compiled kernels and the references perform the same floating-point operations in
the same order, so their results are bit-identical (tested).
"""
from __future__ import annotations

import numpy as np
from numba import njit

# --------------------------------------------------------------------------- PI ------
# Canonical order of operations (kernels and references follow it exactly):
#   1. every play state is clamped:  s_i = min(s_i, v + r_i); s_i = max(s_i, v − r_i)
#   2. the weighted sum uses four partial sums: a_j = Σ_{i ≡ j mod 4, i < m} w_i·s_i
#      (m = n rounded down to a multiple of 4, the remaining terms go into a_0 in index
#      order) and y = out_off + ((a_0 + a_1) + (a_2 + a_3)).
# Step 1 vectorises; step 2 breaks the add-latency chain (n = 64: ~2× faster than one sum).


@njit(cache=True, nogil=True, inline="always")
def _clamp_sum(v, r, w, state, out_off):  # pragma: no cover - compiled
    n = r.shape[0]
    for i in range(n):
        s = state[i]
        hi = v + r[i]
        lo = v - r[i]
        s = hi if s > hi else s
        s = lo if s < lo else s
        state[i] = s
    m = n - n % 4
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    for i in range(0, m, 4):
        a0 += w[i] * state[i]
        a1 += w[i + 1] * state[i + 1]
        a2 += w[i + 2] * state[i + 2]
        a3 += w[i + 3] * state[i + 3]
    for i in range(m, n):
        a0 += w[i] * state[i]
    return out_off + ((a0 + a1) + (a2 + a3))


@njit(cache=True, nogil=True, inline="always")
def _peek_sum(v, r, w, state, out_off):  # pragma: no cover - compiled
    n = r.shape[0]
    m = n - n % 4
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    for i in range(n):
        s = state[i]
        hi = v + r[i]
        lo = v - r[i]
        s = hi if s > hi else s
        s = lo if s < lo else s
        p = w[i] * s
        if i >= m:
            a0 += p
        elif i % 4 == 0:
            a0 += p
        elif i % 4 == 1:
            a1 += p
        elif i % 4 == 2:
            a2 += p
        else:
            a3 += p
    return out_off + ((a0 + a1) + (a2 + a3))


@njit(cache=True, nogil=True)
def pi_step(x, r, w, state, in_off, out_off):  # pragma: no cover - compiled
    """One sample through the PI operator; updates ``state`` in place."""
    return _clamp_sum(x - in_off, r, w, state, out_off)


@njit(cache=True, nogil=True)
def pi_step_packed(x, P, in_off, out_off):  # pragma: no cover - compiled
    """:func:`pi_step` with ``P = [r; w; state]`` in one (3, n) array: one array argument
    makes the call from Python cheaper (the per-sample step of a streaming operator)."""
    return _clamp_sum(x - in_off, P[0], P[1], P[2], out_off)


@njit(cache=True, nogil=True)
def pi_peek_packed(x, P, in_off, out_off):  # pragma: no cover - compiled
    """Like :func:`pi_step_packed` but leaves ``state`` unchanged."""
    return _peek_sum(x - in_off, P[0], P[1], P[2], out_off)


@njit(cache=True, nogil=True)
def pi_block(x, r, w, state, in_off, out_off, out):  # pragma: no cover - compiled
    """Run ``x`` through the PI operator into ``out``; ``state`` carried in place."""
    for k in range(x.shape[0]):
        out[k] = _clamp_sum(x[k] - in_off, r, w, state, out_off)


@njit(cache=True, nogil=True)
def play_outputs(x, r, state, out):  # pragma: no cover - compiled
    """Every play operator's output for every sample: ``out[k, i]`` (identification
    regressors, eq. 5). ``state`` carried in place."""
    n = r.shape[0]
    for k in range(x.shape[0]):
        v = x[k]
        for i in range(n):
            s = state[i]
            hi = v + r[i]
            lo = v - r[i]
            if s > hi:
                s = hi
            if s < lo:
                s = lo
            state[i] = s
            out[k, i] = s


def _sum_ref(w: list[float], s: list[float], out_off: float) -> float:
    n = len(w)
    m = n - n % 4
    acc = [0.0, 0.0, 0.0, 0.0]
    for i in range(m):
        acc[i % 4] += w[i] * s[i]
    for i in range(m, n):
        acc[0] += w[i] * s[i]
    return out_off + ((acc[0] + acc[1]) + (acc[2] + acc[3]))


def pi_step_ref(x: float, r: np.ndarray, w: np.ndarray, state: np.ndarray,
                in_off: float, out_off: float) -> float:
    """Plain-Python reference of :func:`pi_step` (same operations, same order)."""
    v = x - in_off
    for i in range(r.shape[0]):
        s = float(state[i])
        hi = v + float(r[i])
        lo = v - float(r[i])
        s = hi if s > hi else s
        s = lo if s < lo else s
        state[i] = s
    return _sum_ref(w.tolist(), state.tolist(), out_off)


def pi_block_ref(x: np.ndarray, r: np.ndarray, w: np.ndarray, state: np.ndarray,
                 in_off: float, out_off: float) -> np.ndarray:
    """Plain-numpy reference of :func:`pi_block`: the clamp vectorised over the operators
    with numpy, the weighted sum in the canonical order."""
    out = np.empty(x.shape[0])
    wl = w.tolist()
    for k in range(x.shape[0]):
        v = float(x[k]) - in_off
        np.minimum(state, v + r, out=state)
        np.maximum(state, v - r, out=state)
        out[k] = _sum_ref(wl, state.tolist(), out_off)
    return out


# ------------------------------------------------------------------- linear creep ------


@njit(cache=True, nogil=True)
def creep_block(x, a, c, z, out):  # pragma: no cover - compiled
    """Linear creep (bank of first-order lags), see :mod:`afmctl.compensators.creep`."""
    m = a.shape[0]
    for k in range(x.shape[0]):
        v = x[k]
        y = v
        for j in range(m):
            zj = a[j] * z[j] + (1.0 - a[j]) * v
            z[j] = zj
            y -= c[j] * (v - zj)
        out[k] = y


@njit(cache=True, nogil=True)
def creep_inv_block(y, a, c, z, out):  # pragma: no cover - compiled
    """Exact inverse of :func:`creep_block`."""
    m = a.shape[0]
    for k in range(y.shape[0]):
        num = y[k]
        den = 1.0
        for j in range(m):
            num -= c[j] * a[j] * z[j]
            den -= c[j] * a[j]
        v = num / den
        for j in range(m):
            z[j] = a[j] * z[j] + (1.0 - a[j]) * v
        out[k] = v


def creep_block_ref(x: np.ndarray, a: np.ndarray, c: np.ndarray, z: np.ndarray) -> np.ndarray:
    out = np.empty(x.shape[0])
    m = a.shape[0]
    for k in range(x.shape[0]):
        v = float(x[k])
        y = v
        for j in range(m):
            zj = float(a[j]) * float(z[j]) + (1.0 - float(a[j])) * v
            z[j] = zj
            y -= float(c[j]) * (v - zj)
        out[k] = y
    return out


def creep_inv_block_ref(y: np.ndarray, a: np.ndarray, c: np.ndarray, z: np.ndarray) -> np.ndarray:
    out = np.empty(y.shape[0])
    m = a.shape[0]
    for k in range(y.shape[0]):
        num = float(y[k])
        den = 1.0
        for j in range(m):
            num -= float(c[j]) * float(a[j]) * float(z[j])
            den -= float(c[j]) * float(a[j])
        v = num / den
        for j in range(m):
            z[j] = float(a[j]) * float(z[j]) + (1.0 - float(a[j])) * v
        out[k] = v
    return out


# ------------------------------------------------------------- extended PI (HC) -------
# Compiled twin of compensators.epi.CreepEpisodes / EPIForward / EPIInverse (which are the
# plain-Python reference). Same operations in the same order; tested bit-identical.
# Creep state ``cs`` (float64[15]):
#   0 u_prev, 1 last_dir, 2 active, 3 s, 4 u_d, 5 m_d, 6 band, 7 k, 8 sc,
#   9 fp, 10 fp_anchor, 11 fp_width, 12 fm, 13 fm_anchor, 14 fm_width
# Parameters ``prm`` (float64[6]): 0 a, 1 log b, 2 λ, 3 dt, 4 min slope, 5 band margin.

CS_SIZE = 15
#: most bracket doublings of the extended-PI inverse (1e-9 V · 2^2200 overflows any float):
#: a target that no finite voltage reaches holds the previous voltage instead of looping
BRACKET_DOUBLINGS = 2200


@njit(cache=True, nogil=True, inline="always")
def _fade(dist, width):  # pragma: no cover - compiled
    if dist <= 0.0:
        return 1.0
    if width <= 0.0:
        return 0.0
    g = 1.0 - dist / width
    return g if g > 0.0 else 0.0


@njit(cache=True, nogil=True)
def ep_advance(cs, prm):  # pragma: no cover - compiled
    if cs[2] != 0.0:
        cs[7] += 1.0
        cs[8] = cs[3] * (1.0 - np.exp(-prm[2] * (cs[7] * prm[3]))) * cs[5]
    else:
        cs[8] = 0.0


@njit(cache=True, nogil=True)
def ep_in_band(cs, d, u):  # pragma: no cover - compiled
    if cs[2] == 0.0 or d == 0:
        return False
    if d > 0:
        return cs[3] < 0.0 and u - cs[4] <= cs[6]
    return cs[3] > 0.0 and cs[4] - u <= cs[6]


@njit(cache=True, nogil=True)
def ep_term(cs, u):  # pragma: no cover - compiled
    up = cs[0]
    d = 1 if u > up else (-1 if u < up else 0)
    comp = ep_in_band(cs, d, u)
    tp = 0.0
    if cs[9] != 0.0 and (d <= 0 or comp):
        tp = cs[9] * _fade(cs[10] - u, cs[11])
    tm = 0.0
    if cs[12] != 0.0 and (d >= 0 or comp):
        tm = cs[12] * _fade(u - cs[13], cs[14])
    te = 0.0
    if cs[2] != 0.0:
        if d == 0 or comp:
            te = cs[8]
        elif d != cs[3]:
            te = cs[8] * _fade(cs[3] * (cs[4] - u) - cs[6], cs[6])
    return (tp + tm) + te


@njit(cache=True, nogil=True)
def ep_commit(cs, prm, u):  # pragma: no cover - compiled
    up = cs[0]
    d = 1 if u > up else (-1 if u < up else 0)
    if d == 0:
        if cs[2] == 0.0 and cs[1] != 0.0:
            cs[2] = 1.0
            cs[3] = cs[1]
            cs[4] = u
            e = u * prm[1]
            cs[5] = prm[0] * np.exp(e if e < 690.0 else 690.0)
            cs[6] = prm[5] * cs[5] / prm[4]
            cs[7] = 0.0
    elif ep_in_band(cs, d, u):
        cs[1] = d
    else:
        if d > 0:
            cs[9] = 0.0
            if cs[12] != 0.0 and _fade(u - cs[13], cs[14]) == 0.0:
                cs[12] = 0.0
        else:
            cs[12] = 0.0
            if cs[9] != 0.0 and _fade(cs[10] - u, cs[11]) == 0.0:
                cs[9] = 0.0
        if cs[2] != 0.0:
            if d != cs[3]:
                if cs[3] > 0.0:
                    cs[9] = cs[8]
                    cs[10] = cs[4] - cs[6]
                    cs[11] = cs[6]
                    if _fade(cs[10] - u, cs[11]) == 0.0:
                        cs[9] = 0.0
                else:
                    cs[12] = cs[8]
                    cs[13] = cs[4] + cs[6]
                    cs[14] = cs[6]
                    if _fade(u - cs[13], cs[14]) == 0.0:
                        cs[12] = 0.0
            cs[2] = 0.0
        cs[1] = d
    cs[0] = u


@njit(cache=True, nogil=True)
def epi_forward_step(x, P, out_off, cs, prm):  # pragma: no cover - compiled
    h = _clamp_sum(x, P[0], P[1], P[2], out_off)
    ep_advance(cs, prm)
    T = ep_term(cs, x)
    ep_commit(cs, prm, x)
    return h + T


@njit(cache=True, nogil=True)
def epi_forward_block(x, P, out_off, cs, prm, out):  # pragma: no cover - compiled
    for k in range(x.shape[0]):
        out[k] = epi_forward_step(x[k], P, out_off, cs, prm)


@njit(cache=True, nogil=True)
def _epi_Y(v, Pf, out_off, cs):  # pragma: no cover - compiled
    return _peek_sum(v, Pf[0], Pf[1], Pf[2], out_off) + ep_term(cs, v)


@njit(cache=True, nogil=True)
def _epi_solve(y, c0, Pi, in_off, Pf, out_off, cs):  # pragma: no cover - compiled
    up = cs[0]
    rising = c0 > up
    u = c0
    for _ in range(8):
        T = ep_term(cs, u)
        u_new = _peek_sum((y - T) - in_off, Pi[0], Pi[1], Pi[2], 0.0)
        if u_new == u:
            return u
        if (u_new > up) != rising:
            break
        u = u_new
    sgn = 1.0 if rising else -1.0
    step = max(0.25 * abs(c0 - up), 1e-9 * (1.0 + abs(up)))
    near = up
    for _ in range(BRACKET_DOUBLINGS + 1):
        far = up + sgn * step
        yf = _epi_Y(far, Pf, out_off, cs)
        if (yf >= y) if rising else (yf <= y):
            break
        near = far
        step *= 2.0
    else:
        return up  # no finite bracket (overflowing creep law): hold the voltage
    if rising:
        lo = near
        hi = far
    else:
        lo = far
        hi = near
    while True:
        mid = 0.5 * (lo + hi)
        if not (lo < mid < hi):
            return hi if rising else lo
        ym = _epi_Y(mid, Pf, out_off, cs)
        if rising:
            if ym >= y:
                hi = mid
            else:
                lo = mid
        elif ym <= y:
            lo = mid
        else:
            hi = mid


@njit(cache=True, nogil=True)
def epi_inverse_step(x, Pi, in_off, Pf, out_off, cs, prm):  # pragma: no cover - compiled
    ep_advance(cs, prm)
    up = cs[0]
    T0 = ep_term(cs, up)
    c0 = _peek_sum((x - T0) - in_off, Pi[0], Pi[1], Pi[2], 0.0)
    u = c0 if c0 == up else _epi_solve(x, c0, Pi, in_off, Pf, out_off, cs)
    _clamp_sum((x - ep_term(cs, u)) - in_off, Pi[0], Pi[1], Pi[2], 0.0)
    _clamp_sum(u, Pf[0], Pf[1], Pf[2], out_off)
    ep_commit(cs, prm, u)
    return u


@njit(cache=True, nogil=True)
def epi_inverse_block(y, Pi, in_off, Pf, out_off, cs, prm, out):  # pragma: no cover - compiled
    for k in range(y.shape[0]):
        out[k] = epi_inverse_step(y[k], Pi, in_off, Pf, out_off, cs, prm)


@njit(cache=True, nogil=True)
def epi_creep_block(u, cs, prm, out):  # pragma: no cover - compiled
    """Only the creep part of the extended-PI forward output (identification)."""
    for k in range(u.shape[0]):
        ep_advance(cs, prm)
        out[k] = ep_term(cs, u[k])
        ep_commit(cs, prm, u[k])
