"""Sample loops of the amplifier stage: plain-Python references and numba twins.

* :func:`amp_forward_py` — a first-order voltage amplifier with a slew (current) limit
  (:mod:`afmctl.compensators.amplifier`).
* :func:`amp_inverse_py` — its exact inverse, the piezo voltage asked for kept within the
  slew limit.

Each ``*_py`` function is the reference; ``*_nb`` is the same source compiled with
``numba.njit(cache=True, nogil=True)``: the same floating-point operations in the same
order, so the results are bit-identical (tested). The state (``state[0]`` the piezo voltage
[V], ``state[1]`` 1.0 once the first sample has set it) is updated in place, so a signal run
in blocks of any size gives exactly the per-sample result.
"""
from __future__ import annotations

import numba


def amp_forward_py(u, out, a, max_step, state):
    """``v_k = v_{k−1} + clip((1 − a)·(u_k − v_{k−1}), ±max_step)``; the first sample settles
    the stage (``v_0 = u_0``). ``a = exp(−2π·f_c·dt)``, ``max_step`` the slew limit times dt [V]."""
    x = state[0]
    started = state[1]
    g = 1.0 - a
    for k in range(u.shape[0]):
        if started == 0.0:
            x = u[k]
            started = 1.0
        else:
            d = g * (u[k] - x)
            if d > max_step:
                d = max_step
            elif d < -max_step:
                d = -max_step
            x = x + d
        out[k] = x
    state[0] = x
    state[1] = started


def amp_inverse_py(v, out, a, max_step, state, limited):
    """The command ``u_k`` that brings the stage from ``v_{k−1}`` to ``v_k``:
    ``u_k = v_{k−1} + (v_k − v_{k−1})/(1 − a)``, the step first kept within ±max_step (the
    stage cannot follow more; ``limited[0]`` counts those samples). The first sample settles
    the stage (``u_0 = v_0``)."""
    x = state[0]
    started = state[1]
    g = 1.0 - a
    for k in range(v.shape[0]):
        if started == 0.0:
            x = v[k]
            started = 1.0
            out[k] = x
            continue
        d = v[k] - x
        if d > max_step:
            d = max_step
            limited[0] += 1
        elif d < -max_step:
            d = -max_step
            limited[0] += 1
        out[k] = x + d / g
        x = x + d
    state[0] = x
    state[1] = started


amp_forward_nb = numba.njit(cache=True, nogil=True)(amp_forward_py)
amp_inverse_nb = numba.njit(cache=True, nogil=True)(amp_inverse_py)
