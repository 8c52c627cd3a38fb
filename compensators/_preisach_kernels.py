"""Compiled kernels of the discrete classical Preisach model (numba, ``cache=True``).

The model and the meaning of every array are described in :mod:`afmctl.compensators.preisach`;
this module only holds the hot loops. The plain-Python reference that the tests compare
against lives in :mod:`afmctl.compensators.preisach` (``reference_forward`` /
``reference_inverse``).

Memory representation (Mayergoyz; image-based paper eq. 8):

* ``s[0] = u_min`` (negative saturation), ``s[1..K]`` the alternating dominant extrema
  (``s[1]`` a maximum, ``s[2]`` a minimum, ...), ``s[K]`` the current input. Pair ``k``
  runs from ``s[k-1]`` to ``s[k]``; odd pairs ascend, even pairs descend.
* ``P[k] = y0 + sum_{j<=k} ±E(pair j)`` — prefix sums of Everett terms of the finished
  pairs, so one sample costs one or two Everett evaluations (output updated
  incrementally, only the top of the stack changes).
* ``ist = [K, n_clamped]``, ``fst = [y_current]``.

``E(α, β)`` is the Everett function ``f_α − f_αβ`` interpolated bilinearly inside each
grid cell (eq. 7) from the node matrix ``G`` (antisymmetric: ``G[j, i] = −G[i, j]`` so
that ``E(α, α) = 0`` inside diagonal cells too).

The stack holds at most ``cap`` pairs. A reversal that would exceed it first merges the
innermost loop (``s[K-1]`` is replaced by ``s[K]``), i.e. the smallest remembered loop is
forgotten; see :mod:`afmctl.compensators.preisach`.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def everett(G, u_min, inv_du, L, a, b):
    """E(a, b) [nm] by bilinear interpolation of node values ``G`` (eq. 7)."""
    x = (a - u_min) * inv_du
    i = int(x)
    if i > L - 1:
        i = L - 1
    fa = x - i
    z = (b - u_min) * inv_du
    j = int(z)
    if j > L - 1:
        j = L - 1
    fb = z - j
    return (G[i, j] * (1.0 - fa) * (1.0 - fb) + G[i + 1, j] * fa * (1.0 - fb)
            + G[i, j + 1] * (1.0 - fa) * fb + G[i + 1, j + 1] * fa * fb)


@njit(cache=True)
def _merge(s, ist):
    """Forget the innermost loop: s[K-1] := s[K], K -= 1 (used only on overflow)."""
    K = ist[0]
    s[K - 1] = s[K]
    ist[0] = K - 1


@njit(cache=True, inline="always")
def _memory_update(u, s, K, cap):
    """Apply the (clamped) input ``u`` to the memory ``s[0..K]``; return the new ``K``.

    A reversal starts a new pair (or, at the bound ``cap``, first merges the innermost
    loop away); then a new extremum wipes out every pair it dominates (wiping-out).
    Shared by :func:`fwd_update` and :func:`memory_trace`."""
    if K == 0:
        if u > s[0]:
            s[1] = u
            return 1
        return 0
    rev = (u < s[K]) if (K & 1) else (u > s[K])
    if rev:
        if K >= cap:  # overflow: forget the innermost loop, the top pair continues
            s[K - 1] = s[K]
            K -= 1
        else:
            K += 1
    s[K] = u
    while K >= 2:
        if K & 1:
            if K >= 3 and u >= s[K - 2]:
                K -= 2
                s[K] = u
            else:
                break
        else:
            if u <= s[K - 2]:
                K -= 2
                s[K] = u
            else:
                break
    return K


@njit(cache=True)
def fwd_update(u, s, P, ist, fst, G, u_min, u_max, inv_du, L, cap):
    """Apply input ``u`` [V] to the memory and return the output [nm] (eq. 8)."""
    if u < u_min:
        u = u_min
        ist[1] += 1
    elif u > u_max:
        u = u_max
        ist[1] += 1
    K0 = ist[0]
    K = _memory_update(u, s, K0, cap)
    if K == K0 + 1 and K0 >= 1:
        # a reversal finished pair K0 and nothing was wiped: store its prefix sum
        # (s[K0-1], s[K0] are untouched by the push)
        if K0 & 1:
            P[K0] = P[K0 - 1] + everett(G, u_min, inv_du, L, s[K0], s[K0 - 1])
        else:
            P[K0] = P[K0 - 1] - everett(G, u_min, inv_du, L, s[K0 - 1], s[K0])
    ist[0] = K
    if K == 0:
        y = P[0]
    elif K & 1:
        y = P[K - 1] + everett(G, u_min, inv_du, L, s[K], s[K - 1])
    else:
        y = P[K - 1] - everett(G, u_min, inv_du, L, s[K - 1], s[K])
    fst[0] = y
    return y


@njit(cache=True)
def forward_block(u, s, P, ist, fst, G, u_min, u_max, inv_du, L, cap):
    """Run :func:`fwd_update` over a block; returns y [nm]."""
    n = u.shape[0]
    y = np.empty(n)
    for k in range(n):
        y[k] = fwd_update(u[k], s, P, ist, fst, G, u_min, u_max, inv_du, L, cap)
    return y


@njit(cache=True)
def _solve_up(G, v, u_min, inv_du, du, L, beta0, lo, hi, t):
    """Smallest α in [lo, hi] with E(α, β0) = t, walking α-cells upward (eqs. 9–11).

    Inside cell (i, j) E is linear in α (eq. 10), E = A + B·fa, so the candidate is one
    division (eq. 11); it is the answer when it falls inside the cell, otherwise the walk
    moves on to the next cell (E is nondecreasing in α for nonnegative cell masses)."""
    z = (beta0 - u_min) * inv_du
    j = int(z)
    if j > L - 1:
        j = L - 1
    fb = z - j
    i = int((lo - u_min) * inv_du)
    if i > L - 1:
        i = L - 1
    while True:
        a_top = v[i + 1]
        last = a_top >= hi or i >= L - 1
        if last:
            a_top = hi
        a_lo = v[i]
        if a_lo < lo:
            a_lo = lo
        A = G[i, j] * (1.0 - fb) + G[i, j + 1] * fb
        B = (G[i + 1, j] - G[i, j]) * (1.0 - fb) + (G[i + 1, j + 1] - G[i, j + 1]) * fb
        if B > 0.0:
            a = v[i] + (t - A) / B * du  # eq. 11
            if a <= a_top or last:
                if a < a_lo:
                    a = a_lo
                if a > a_top:
                    a = a_top
                return a
        elif t <= A or last:
            return a_lo
        i += 1


@njit(cache=True)
def _solve_down(G, v, u_min, inv_du, du, L, alpha0, lo, hi, t):
    """Largest β in [lo, hi] with E(α0, β) = t, walking β-cells downward (eqs. 9–11).

    The mirror image of :func:`_solve_up` (β for α, downward for upward): kept as its own
    loop because a shared one would need a direction branch in every cell of the walk."""
    x = (alpha0 - u_min) * inv_du
    i = int(x)
    if i > L - 1:
        i = L - 1
    fa = x - i
    j = int((hi - u_min) * inv_du)
    if j > L - 1:
        j = L - 1
    while True:
        b_bot = v[j]
        last = b_bot <= lo or j <= 0
        if last:
            b_bot = lo
        b_hi = v[j + 1]
        if b_hi > hi:
            b_hi = hi
        A = G[i, j] * (1.0 - fa) + G[i + 1, j] * fa
        B = (G[i, j + 1] - G[i, j]) * (1.0 - fa) + (G[i + 1, j + 1] - G[i + 1, j]) * fa
        if B < 0.0:
            b = v[j] + (t - A) / B * du
            if b >= b_bot or last:
                if b > b_hi:
                    b = b_hi
                if b < b_bot:
                    b = b_bot
                return b
        elif t <= A or last:
            return b_hi
        j -= 1


@njit(cache=True)
def _tol(G, P, u_min, u_max, inv_du, L):
    """Rounding tolerance [nm] below which an unreachable target is not counted as clamped."""
    return 1e-9 * (abs(everett(G, u_min, inv_du, L, u_max, u_min)) + abs(P[0])) + 1e-12


@njit(cache=True)
def inv_solve(y, s, P, ist, fst, G, v, u_min, u_max, inv_du, du, L, cap):
    """Input u [V] that makes the output y [nm] from the present memory (no update)."""
    K = ist[0]
    ycur = fst[0]
    ucur = s[K]
    if y == ycur:
        return ucur
    up = y > ycur
    if K == 0 and not up:  # already at u_min: nothing lower to reach
        if y < P[0] - _tol(G, P, u_min, u_max, inv_du, L):
            ist[1] += 1
        return u_min
    # overflow: a reversal would merge the innermost loop first; do it now (the forward
    # update will see a continuation of the merged top pair)
    if K >= cap and ((up and (K & 1) == 0) or ((not up) and (K & 1) == 1)):
        _merge(s, ist)
        K = ist[0]
        if K & 1:
            ycur = P[K - 1] + everett(G, u_min, inv_du, L, s[K], s[K - 1])
        else:
            ycur = P[K - 1] - everett(G, u_min, inv_du, L, s[K - 1], s[K])
        fst[0] = ycur
        if (y > ycur) != up or y == ycur:
            # the merge alone overshot: smallest possible step in the wanted direction
            if up:
                return min(np.nextafter(ucur, np.inf), u_max)
            return max(np.nextafter(ucur, -np.inf), u_min)
    if up:
        if K & 1:
            kb = K - 1
            base = P[K - 1]
        else:
            kb = K
            base = ycur
        lo = ucur
        while kb >= 2 and y > P[kb - 1]:
            lo = s[kb - 1]
            kb -= 2
            base = P[kb]
        if kb == 0:
            hi = u_max
            ymax = P[0] + everett(G, u_min, inv_du, L, u_max, u_min)
            if y >= ymax:
                if y > ymax + _tol(G, P, u_min, u_max, inv_du, L):
                    ist[1] += 1
                return u_max
        else:
            hi = s[kb - 1]
        return _solve_up(G, v, u_min, inv_du, du, L, s[kb], lo, hi, y - base)
    else:
        if K & 1:
            kt = K
            base = ycur
        else:
            kt = K - 1
            base = P[K - 1]
        hi = ucur
        while kt >= 3 and y < P[kt - 1]:
            hi = s[kt - 1]
            kt -= 2
            base = P[kt]
        if kt == 1 and y <= P[0]:
            if y < P[0] - _tol(G, P, u_min, u_max, inv_du, L):
                ist[1] += 1
            return u_min
        lo = s[kt - 1]
        return _solve_down(G, v, u_min, inv_du, du, L, s[kt], lo, hi, base - y)


@njit(cache=True)
def inv_step(y, s, P, ist, fst, G, v, u_min, u_max, inv_du, du, L, cap):
    """One target y [nm] → u [V]: solve, then apply u to the memory (one compiled call)."""
    u = inv_solve(y, s, P, ist, fst, G, v, u_min, u_max, inv_du, du, L, cap)
    fwd_update(u, s, P, ist, fst, G, u_min, u_max, inv_du, L, cap)
    return u


@njit(cache=True)
def inverse_block(y, s, P, ist, fst, G, v, u_min, u_max, inv_du, du, L, cap):
    """Exact inverse over a block: u[k] such that the forward model gives y[k]."""
    n = y.shape[0]
    u = np.empty(n)
    for k in range(n):  # the body of inv_step, written out (numba did not inline the call: ~30 % slower)
        uk = inv_solve(y[k], s, P, ist, fst, G, v, u_min, u_max, inv_du, du, L, cap)
        fwd_update(uk, s, P, ist, fst, G, u_min, u_max, inv_du, L, cap)
        u[k] = uk
    return u


@njit(cache=True)
def memory_trace(u, rows, u_min, u_max, cap, out_lo, out_hi, out_sign, out_n):
    """Record the memory pairs at sample indices ``rows`` (sorted) for identification.

    For row r, pairs ``out_lo[r, :n], out_hi[r, :n]`` with sign ±1 make the output
    ``y0 + Σ sign·E(hi, lo)``. The memory logic is that of :func:`fwd_update`.
    """
    s = np.empty(cap + 1)
    s[0] = u_min
    K = 0
    r = 0
    nrows = rows.shape[0]
    for k in range(u.shape[0]):
        x = u[k]
        if x < u_min:
            x = u_min
        elif x > u_max:
            x = u_max
        K = _memory_update(x, s, K, cap)
        while r < nrows and rows[r] == k:
            for q in range(1, K + 1):
                if q & 1:
                    out_hi[r, q - 1] = s[q]
                    out_lo[r, q - 1] = s[q - 1]
                    out_sign[r, q - 1] = 1.0
                else:
                    out_hi[r, q - 1] = s[q - 1]
                    out_lo[r, q - 1] = s[q]
                    out_sign[r, q - 1] = -1.0
            out_n[r] = K
            r += 1
