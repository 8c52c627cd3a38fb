"""Sample loops of the linear-dynamics operators: plain-Python references and numba twins.

* :func:`lti_block_py` — a discrete state-space system with an input delay line
  (:mod:`afmctl.compensators.lti`).
* :func:`fir_block_py` — an FIR filter on a ring buffer (the preview inverse of
  :mod:`afmctl.compensators.dynamics_inverse`).

Each ``*_py`` function is the reference; ``*_nb`` is the same source compiled with
``numba.njit(cache=True, nogil=True)``: the same floating-point operations in the same
order, so the results are bit-identical (tested). State lives in small arrays updated in
place, so a signal run in blocks of any size gives exactly the per-sample result.
"""
from __future__ import annotations

import numba


def lti_block_py(u, out, Ad, B1, B2, C, D0, D1, x, buf, pos):
    """Discrete LTI system with a delay of ``d`` whole samples plus a fraction (zero-order
    hold)::

        w_k     = u_{k-d}                          (ring buffer ``buf``, length d + 2)
        y_k     = C·x_k + D0·w_k + D1·w_{k-1}
        x_{k+1} = Ad·x_k + B1·w_k + B2·w_{k-1}

    ``x`` (n,) is the state, ``pos`` = [index of the newest sample in ``buf``]."""
    n = x.shape[0]
    m = buf.shape[0]
    p = pos[0]
    xn = x.copy()
    for k in range(u.shape[0]):
        p = p + 1
        if p == m:
            p = 0
        buf[p] = u[k]
        i0 = p - (m - 2)  # index of u_{k-d}, d = m - 2
        if i0 < 0:
            i0 += m
        i1 = i0 - 1
        if i1 < 0:
            i1 += m
        w0 = buf[i0]
        w1 = buf[i1]
        y = D0 * w0 + D1 * w1
        for i in range(n):
            y += C[i] * x[i]
        out[k] = y
        for i in range(n):
            acc = B1[i] * w0 + B2[i] * w1
            for j in range(n):
                acc += Ad[i, j] * x[j]
            xn[i] = acc
        for i in range(n):
            x[i] = xn[i]
    pos[0] = p


def fir_block_py(u, out, h, buf, pos):
    """FIR filter ``y_k = Σ_j h_j·u_{k−j}`` (j = 0 … len(h) − 1), ring buffer ``buf`` of
    len(h) past inputs, ``pos`` = [index of the newest sample]."""
    m = h.shape[0]
    p = pos[0]
    for k in range(u.shape[0]):
        p = p + 1
        if p == m:
            p = 0
        buf[p] = u[k]
        acc = 0.0
        i = p
        for j in range(m):
            acc += h[j] * buf[i]
            i -= 1
            if i < 0:
                i = m - 1
        out[k] = acc
    pos[0] = p


_njit = numba.njit(cache=True, nogil=True)
lti_block_nb = _njit(lti_block_py)
fir_block_nb = _njit(fir_block_py)
