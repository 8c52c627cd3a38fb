"""Bouc–Wen identification loop: the forward simulation with its parameter sensitivities.

:func:`bw_sens_py` is the plain-Python reference; :func:`bw_sens_nb` is the same source
compiled with ``numba.njit(cache=True, nogil=True)`` (tests/test_bouc_wen.py: equal to
1e-12 relative). It integrates the hysteretic state ``h`` [nm] exactly as the forward
operator does (:func:`afmctl.compensators.bouc_wen.bw_forward_block`: the same RK4
sub-steps, the same operations in the same order, so the same ``h`` bit for bit) and
alongside it the tangent of every RK4 sub-step: ``dh/dA``, ``dh/dβ``, ``dh/dγ``, ``dh/dn``
and, for the rate-dependent model (:mod:`afmctl.compensators.rate_bouc_wen`: ``A`` of sample
``k`` is ``A·(1 + c·q_k)``, ``q_k`` its capped input rate [V/s]), ``dh/dc``: the derivative of
the computed ``h`` with the sub-step count held fixed. Without rates (``q`` empty) every
sample's ``A`` is ``A`` itself, bit for bit.
One such pass replaces the 5–6 extra simulations of a finite-difference Jacobian in the
least-squares fit (a 637,585-row record: ~62 ms per simulation).
"""
from __future__ import annotations

import math

import numba


def substeps_py(du, du_sub, max_sub):
    """``(sgn, m, dx)``: direction, count and length [V] of the RK4 sub-steps of an input move
    ``du`` [V] (``du != 0``): ``m = ceil(|du|/du_sub)`` equal sub-steps; a move longer than
    ``max_sub`` sub-steps integrates only its last ``max_sub`` (10⁵ stiffness lengths: h has
    converged to its branch long before, and RK4 stays inside its stability region)."""
    sgn = 1.0 if du > 0.0 else -1.0
    ratio = abs(du) / du_sub
    if ratio > max_sub:
        return sgn, max_sub, sgn * du_sub
    m = int(math.ceil(ratio))
    if m < 1:
        m = 1
    return sgn, m, du / m


def stage_py(hs, ta, tb, tg, tn, tc, sgn, A, ga, qa, beta, gamma, n, want_n):
    """One RK4 stage at ``h = hs`` with sensitivities ``(ta, tb, tg, tn, tc)`` = dh/d(A₀, β, γ, n, c):
    returns ``dh/du`` = A − (β·sgn·sgn(h) + γ)·|h|^n (the operations of the forward kernel's
    ``_rhs`` in its order; ``A`` = A₀·ga the sample's amplitude, ``qa`` = ∂A/∂c) and its total
    derivatives along the five sensitivities."""
    ah = abs(hs)
    p = ah ** n
    s = 1.0 if hs > 0.0 else (-1.0 if hs < 0.0 else 0.0)
    c = beta * sgn * s + gamma
    fh = -c * n * (p / ah) * s if ah > 0.0 else 0.0  # ∂f/∂h (0 on the kink h = 0)
    fn = -c * p * math.log(ah) if (want_n and ah > 0.0) else 0.0  # ∂f/∂n
    return A - c * p, fh * ta + ga, fh * tb - sgn * s * p, fh * tg - p, fh * tn + fn, fh * tc + qa


def _make_sens(substeps, stage):
    """The simulation loop calling ``substeps`` and ``stage`` (plain Python, or their numba twins)."""

    def bw_sens(u, q, c, h0, u0, A, beta, gamma, n, du_sub, max_sub, rows, want_n, h_out, s_out):
        h = h0
        u_prev = u0
        sa = 0.0
        sb = 0.0
        sg = 0.0
        sn = 0.0
        sc = 0.0
        j = 0
        n_rows = rows.shape[0]
        rated = q.shape[0] > 0
        for k in range(u.shape[0]):
            x = u[k]
            du = x - u_prev
            if du != 0.0:
                ga = 1.0
                qa = 0.0
                if rated:
                    ga = 1.0 + c * q[k]
                    qa = A * q[k]
                Ak = A * ga
                sgn, m, dx = substeps(du, du_sub, max_sub)
                for _ in range(m):
                    k1, ka1, kb1, kg1, kn1, kc1 = stage(h, sa, sb, sg, sn, sc, sgn, Ak, ga, qa, beta, gamma, n, want_n)
                    half = 0.5 * dx
                    k2, ka2, kb2, kg2, kn2, kc2 = stage(h + half * k1, sa + half * ka1, sb + half * kb1,
                                                        sg + half * kg1, sn + half * kn1, sc + half * kc1, sgn,
                                                        Ak, ga, qa, beta, gamma, n, want_n)
                    k3, ka3, kb3, kg3, kn3, kc3 = stage(h + half * k2, sa + half * ka2, sb + half * kb2,
                                                        sg + half * kg2, sn + half * kn2, sc + half * kc2, sgn,
                                                        Ak, ga, qa, beta, gamma, n, want_n)
                    k4, ka4, kb4, kg4, kn4, kc4 = stage(h + dx * k3, sa + dx * ka3, sb + dx * kb3, sg + dx * kg3,
                                                        sn + dx * kn3, sc + dx * kc3, sgn, Ak, ga, qa, beta, gamma,
                                                        n, want_n)
                    w = dx / 6.0
                    h = h + w * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
                    sa = sa + w * (ka1 + 2.0 * ka2 + 2.0 * ka3 + ka4)
                    sb = sb + w * (kb1 + 2.0 * kb2 + 2.0 * kb3 + kb4)
                    sg = sg + w * (kg1 + 2.0 * kg2 + 2.0 * kg3 + kg4)
                    sn = sn + w * (kn1 + 2.0 * kn2 + 2.0 * kn3 + kn4)
                    sc = sc + w * (kc1 + 2.0 * kc2 + 2.0 * kc3 + kc4)
            u_prev = x
            if j < n_rows and rows[j] == k:
                h_out[j] = h
                s_out[j, 0] = sa
                s_out[j, 1] = sb
                s_out[j, 2] = sg
                s_out[j, 3] = sn
                if rated:
                    s_out[j, 4] = sc
                j += 1

    return bw_sens


#: plain-Python reference: drive ``h`` from ``(h0 [nm], u0 [V])`` over ``u`` [V] (dh/du = A_k −
#: (β·sgn(Δu)·sgn(h) + γ)·|h|^n, RK4 on ``ceil(|Δu|/du_sub)`` sub-steps, at most ``max_sub``; A_k =
#: A·(1 + c·q[k]), or A when ``q`` is empty); at each sample index ``rows[j]`` (increasing) write
#: ``h`` into ``h_out[j]`` and dh/d(A, β, γ, n) into ``s_out[j, 0:4]`` (dh/dn only if ``want_n``,
#: else 0), and dh/dc into ``s_out[j, 4]`` when ``q`` is not empty
bw_sens_py = _make_sens(substeps_py, stage_py)
#: the sub-step rule, compiled (also the forward operator's, :func:`afmctl.compensators.bouc_wen._advance`)
substeps_nb = numba.njit(cache=True, nogil=True)(substeps_py)
#: :data:`bw_sens_py`, compiled
bw_sens_nb = numba.njit(cache=True, nogil=True)(_make_sens(substeps_nb, numba.njit(cache=True, nogil=True)(stage_py)))
