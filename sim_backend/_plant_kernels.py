"""Sample loops of the simulated plant: plain-Python references and their numba twins.

Each ``*_py`` function is the reference; ``*_nb`` is the same source compiled with
``numba.njit(cache=True, nogil=True)`` (the loops release the GIL). Tests run both on the
same input and require equal output.
All loops carry their state in small arrays passed in and updated in place, so that a
signal run in blocks of any size gives exactly the per-sample result.

Units: voltages in V, displacements in nm, time in s.
"""
from __future__ import annotations

import math
import types

import numba

from afmctl.compensators._preisach_kernels import _memory_update as _memory_update_nb


# --------------------------------------------------------------------------- amplifier
def amplifier_py(u, out, state, u_min, u_max, lsb, max_step, a_lp):
    """Amplifier: clip to [u_min, u_max] → quantise to ``lsb`` V (0 = off) → slew limit of
    ``max_step`` V per sample → first-order low-pass ``f ← a_lp·f + (1 − a_lp)·s``
    (a_lp = exp(−2π·f_c·dt), exact for a held input). ``state`` = [slewed, filtered] V."""
    s = state[0]
    f = state[1]
    for k in range(u.shape[0]):
        q = u[k]
        if q < u_min:
            q = u_min
        elif q > u_max:
            q = u_max
        if lsb > 0.0:
            q = u_min + math.floor((q - u_min) / lsb + 0.5) * lsb
            if q > u_max:
                q = u_max
        d = q - s
        if d > max_step:
            d = max_step
        elif d < -max_step:
            d = -max_step
        s = s + d
        f = a_lp * f + (1.0 - a_lp) * s
        out[k] = f
    state[0] = s
    state[1] = f


# --------------------------------------------------------------------------- Preisach
def _everett_py(E, lo, h, n, a, b):
    """Everett function E(α=a, β=b) [nm] by bilinear interpolation on the node table ``E``
    (image-based paper, eq. 7)."""
    ta = (a - lo) / h
    ia = int(ta)
    if ia > n - 2:
        ia = n - 2
    if ia < 0:
        ia = 0
    fa = ta - ia
    tb = (b - lo) / h
    ib = int(tb)
    if ib > n - 2:
        ib = n - 2
    if ib < 0:
        ib = 0
    fb = tb - ib
    e00 = E[ia, ib]
    e01 = E[ia, ib + 1]
    e10 = E[ia + 1, ib]
    e11 = E[ia + 1, ib + 1]
    return (1.0 - fa) * ((1.0 - fb) * e00 + fb * e01) + fa * ((1.0 - fb) * e10 + fb * e11)


def _segment_py(E, lo, h, n, p, q):
    """Output change of a monotone input segment p → q: +E(q, p) rising, −E(p, q) falling."""
    if q > p:
        return _everett(E, lo, h, n, q, p)
    if q < p:
        return -_everett(E, lo, h, n, p, q)
    return 0.0


def preisach_py(u, out, E, lo, hi, lin, s, P, ist):
    """Classical Preisach operator by its memory of dominant extrema with wiping-out
    (image-based paper, eqs. 3 and 8): y = lin·(u − lo) + Σ ±E over the pairs of the
    memory. The memory is the one of :mod:`afmctl.compensators._preisach_kernels` and is updated
    by its ``_memory_update`` (one piece of code for both): ``s[0] = lo`` (negative
    saturation), ``s[1..K]`` the alternating dominant extrema, ``s[K]`` the current input,
    ``ist = [K]``; at ``K = len(s) − 1`` the innermost loop is forgotten. ``P[j]`` is the
    sum of the segments of the first j finished pairs, so a step costs O(1) amortised."""
    n = E.shape[0]
    h = (hi - lo) / (n - 1)
    cap = s.shape[0] - 1
    K = ist[0]
    for k in range(u.shape[0]):
        x = u[k]
        if x < lo:
            x = lo
        elif x > hi:
            x = hi
        K0 = K
        K = _memory_update(x, s, K0, cap)
        if K == K0 + 1 and K0 >= 1:
            # a reversal finished pair K0 and wiped nothing: s[K0-1], s[K0] are its ends
            P[K0] = P[K0 - 1] + _segment(E, lo, h, n, s[K0 - 1], s[K0])
        if K == 0:
            out[k] = lin * (x - lo)
        else:
            out[k] = lin * (x - lo) + P[K - 1] + _segment(E, lo, h, n, s[K - 1], x)
    ist[0] = K


# --------------------------------------------------------------------------- creep + mode
def creep_dynamics_py(h, out, a_c, g_c, x_c, ad, bd, z, use_dyn):
    """Creep lag bank then one structural mode.

    Creep (nonlinearities paper, eq. 21): x_k ← a_k·x_k + (1 − a_k)·h, r = h − Σ g_k·(h − x_k)
    with a_k = exp(−dt/τ_k). Mode: [p, v] ← ad·[p, v] + bd·r (exact zero-order-hold
    discretisation), output p. ``z`` = [p, v] state (nm, nm/s)."""
    nl = a_c.shape[0]
    for k in range(h.shape[0]):
        hk = h[k]
        r = hk
        if nl > 0:
            acc = 0.0
            for i in range(nl):
                x_c[i] = a_c[i] * x_c[i] + (1.0 - a_c[i]) * hk
                acc += g_c[i] * (hk - x_c[i])
            r = hk - acc
        if use_dyn:
            p = ad[0, 0] * z[0] + ad[0, 1] * z[1] + bd[0] * r
            v = ad[1, 0] * z[0] + ad[1, 1] * z[1] + bd[1] * r
            z[0] = p
            z[1] = v
            out[k] = p
        else:
            out[k] = r


# --------------------------------------------------------------------------- drift
def expansion_drift_py(T_amb, out, coef, a, T_state, T_ref):
    """First-order thermal expansion drift: T_s ← a·T_s + (1 − a)·T_amb (a = exp(−dt/τ)),
    drift_i = coef_i·(T_s − T_ref) [nm] for the three axes. ``T_state`` = [T_s] °C."""
    Ts = T_state[0]
    for k in range(T_amb.shape[0]):
        Ts = a * Ts + (1.0 - a) * T_amb[k]
        d = Ts - T_ref
        out[k, 0] = coef[0] * d
        out[k, 1] = coef[1] * d
        out[k, 2] = coef[2] * d
    T_state[0] = Ts


# --------------------------------------------------------------------------- numba twins
_everett = _everett_py
_segment = _segment_py
#: the plain-Python source of the compensators' memory update, for the reference path
_memory_update = _memory_update_nb.py_func


def _rebind(func, **names):
    """A copy of ``func`` whose global names ``names`` point to other objects (the
    numba twins of the helpers), so one source serves the reference and the fast path."""
    g = dict(func.__globals__)
    g.update(names)
    return types.FunctionType(func.__code__, g, func.__name__, func.__defaults__, func.__closure__)


#: ``nogil=True``: the compiled loops release the GIL, so a scanner simulated in-process
#: (simulated amplifier thread → Scanner.apply) does not stall other Python threads such
#: as a controller's real-time loop while it computes.
_njit = numba.njit(cache=True, nogil=True)

amplifier_nb = _njit(amplifier_py)
_everett_nb = _njit(_everett_py)
_segment_nb = _njit(_rebind(_segment_py, _everett=_everett_nb))
# Note: numba's cache does not track the callee in another file; after editing
# compensators/_preisach_kernels._memory_update, delete sim_backend/__pycache__/*.nbi.
preisach_nb = _njit(_rebind(preisach_py, _segment=_segment_nb, _memory_update=_memory_update_nb))
creep_dynamics_nb = _njit(creep_dynamics_py)
expansion_drift_nb = _njit(expansion_drift_py)
