"""Extended Prandtl–Ishlinskii model: PI hysteresis plus inflexion creep (HC operator).

Source: *Unified hysteresis and creep compensation in AFM tip positioning with an
extended PI model* — inflexion creep eqs. 1–2, HC operator eq. 3, output eq. 4,
least squares eq. 5, inverse eqs. 6–11.

Inflexion creep (eqs. 1–2, with the sign of the exponent the extraction lost)::

    C(u_d, τ) = (1 − exp(−λ·τ)) · M(u_d),     M(u_d) = a · b^{u_d}      [nm]

``u_d`` [V] is the voltage at which the input came to rest, ``τ`` [s] the time since.

**Our reading of eq. 3** (the paper is loose here; this is the rule the code, its inverse
and the tests follow):

* *Direction.* The creep has the sign ``s`` of the last non-zero input increment before
  the dwell (+ after rising, − after falling), whatever the sign of ``u`` itself. The
  paper's "> 0"/"< 0" conditions are read as conditions on the direction of motion.
  ``M(u) = a·b^u`` is used for any ``u`` (also negative); ``a ≥ 0``, ``0.5 < b ≤ 2``.
* *Dwell start.* A creep episode starts at the first sample with ``u(t) = u(t−T)``
  (exact equality) after a motion, with ``τ = 0`` at that sample (so ``C = 0`` there),
  and ``τ`` grows by ``dt_s`` per sample.
* *During the episode* the input may stay put or move *against* the creep (what a
  compensator does) by at most ``band(u_d) = 1.01·M(u_d)/min_k S_k`` volts, where
  ``S_k`` are the partial sums of the forward weights (the smallest slope of the loop);
  the creep term keeps growing.
* *End.* A move in the creep direction ends the episode and the creep term vanishes
  (eq. 3, third case). A move against it beyond the band ends it too; there the creep
  reached so far is frozen and fades out linearly while the input moves on by one more
  band width (so after any real step it has vanished, as in eq. 3). A frozen remainder
  (if the input stops inside that fade zone) is dropped at the next move in its own
  direction that is not a compensating move. The fade keeps the output continuous in
  the input, which is what makes the operator exactly invertible.
* *Magnitude.* Eq. 3 splits the creep over the plays as ``C_ri = i/(n+1)·C``; only the
  weighted sum ``Σ w_i·C_ri`` is observable, and we normalise the shares so that it
  equals ``C`` — ``a`` is then directly the measured creep magnitude of Figs. 5–6.

So the forward output is ``y = offset + Σ w_i·x_i(u) + creep term`` [nm]. As a
function of the current input the output is non-decreasing with jumps only *against*
the direction of motion (a vanishing creep term), so every target is reachable: the
inverse evaluates the same state machine on the voltage it emits, uses the closed-form
PI inverse (eqs. 8–11) where the creep term is locally constant and a bisection to the
last bit inside a fade zone. During a target dwell it lowers (raises) the voltage exactly
as much as the modelled creep would raise (lower) the tip.
"""
from __future__ import annotations

import logging
import math
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, FiniteFloat

from . import _pi_kernels as K
from .base import ModelError, StreamingOperator
from .input_checks import block_samples, finite_sample, number_option, sample_period
from .pi import (PIFamilyModel, PIOperator, fit_pi_weights,
                             prepare_pi_identification)

log = logging.getLogger(__name__)

BAND_MARGIN = 1.01


class CreepEpisodes:
    """The dwell/creep state machine of the HC operator (see the module docstring).

    Shared by :class:`EPIForward` and :class:`EPIInverse` so both follow one rule. Per
    sample: :meth:`advance` once, then :meth:`term` for any candidate input (no state
    change), then :meth:`commit` with the input actually applied.
    Units: voltages in V, creep in nm, ``dt_s`` in s.
    """

    def __init__(self, a_nm: float, b: float, lambda_per_s: float, dt_s: float,
                 min_slope_nm_per_V: float, u_initial_V: float) -> None:
        self.a = float(a_nm)
        self.b = float(b)
        self._log_b = math.log(self.b)
        self.lam = float(lambda_per_s)
        self.dt = float(dt_s)
        self.min_slope = float(min_slope_nm_per_V)
        self.u_initial = float(u_initial_V)
        self.reset()

    def reset(self) -> None:
        self.u_prev = self.u_initial
        self.last_dir = 0
        self.active = False
        self.s = 0
        self.u_d = 0.0
        self.m_d = 0.0
        self.band = 0.0
        self.k = 0
        self.sc = 0.0
        # fading frozen creep: F₊ ≥ 0 fades out while u falls from fp_anchor by fp_width;
        # F₋ ≤ 0 fades out while u rises from fm_anchor by fm_width
        self.fp = 0.0
        self.fp_anchor = 0.0
        self.fp_width = 0.0
        self.fm = 0.0
        self.fm_anchor = 0.0
        self.fm_width = 0.0

    def packed(self) -> tuple[np.ndarray, np.ndarray]:
        """``(cs, prm)`` arrays of the compiled twin (:mod:`afmctl.compensators._pi_kernels`),
        in the reset state."""
        cs = np.zeros(K.CS_SIZE)
        cs[0] = self.u_initial
        prm = np.array([self.a, self._log_b, self.lam, self.dt, self.min_slope, BAND_MARGIN])
        return cs, prm

    def magnitude(self, u_V: float) -> float:
        """``M(u) = a·b^u`` [nm] (eq. 2); capped at 1e300 instead of overflowing."""
        e = u_V * self._log_b
        return self.a * math.exp(e if e < 690.0 else 690.0)

    def advance(self) -> None:
        """Start a new sample: advance the episode clock, update ``s·C(u_d, τ)``."""
        if self.active:
            self.k += 1
            self.sc = self.s * (1.0 - math.exp(-self.lam * (self.k * self.dt))) * self.m_d
        else:
            self.sc = 0.0

    # Plain-Python twin of ``_pi_kernels._fade``: this class is the reference the compiled
    # creep path is tested against bit for bit, so the copy stays (same operations, same order).
    @staticmethod
    def _fade(dist: float, width: float) -> float:
        if dist <= 0.0:
            return 1.0
        if width <= 0.0:
            return 0.0
        g = 1.0 - dist / width
        return g if g > 0.0 else 0.0

    def in_band(self, d: int, u: float) -> bool:
        """Is a move in direction ``d`` to ``u`` a compensating move inside the band of
        the active episode (against its creep, at most ``band`` volts from ``u_d``)?"""
        if not self.active or d == 0:
            return False
        if d > 0:
            return self.s < 0 and u - self.u_d <= self.band
        return self.s > 0 and self.u_d - u <= self.band

    def term(self, u: float) -> float:
        """Creep part of the output [nm] if the input at this sample is ``u``."""
        up = self.u_prev
        d = 1 if u > up else (-1 if u < up else 0)
        comp = self.in_band(d, u)
        tp = 0.0
        if self.fp != 0.0 and (d <= 0 or comp):
            tp = self.fp * self._fade(self.fp_anchor - u, self.fp_width)
        tm = 0.0
        if self.fm != 0.0 and (d >= 0 or comp):
            tm = self.fm * self._fade(u - self.fm_anchor, self.fm_width)
        te = 0.0
        if self.active:
            if d == 0 or comp:
                te = self.sc
            elif d != self.s:   # left the band against the creep: fades out over one more band
                te = self.sc * self._fade(self.s * (self.u_d - u) - self.band, self.band)
        return (tp + tm) + te

    def commit(self, u: float) -> None:
        """Update the state after the input ``u`` was applied at this sample."""
        up = self.u_prev
        d = 1 if u > up else (-1 if u < up else 0)
        if d == 0:
            if not self.active and self.last_dir != 0:
                self.active = True
                self.s = self.last_dir
                self.u_d = u
                self.m_d = self.magnitude(u)
                self.band = BAND_MARGIN * self.m_d / self.min_slope
                self.k = 0
        elif self.in_band(d, u):
            self.last_dir = d          # compensating move: the episode goes on
        else:
            if d > 0:
                self.fp = 0.0          # a rise releases frozen positive creep
                if self.fm != 0.0 and self._fade(u - self.fm_anchor, self.fm_width) == 0.0:
                    self.fm = 0.0
            else:
                self.fm = 0.0
                if self.fp != 0.0 and self._fade(self.fp_anchor - u, self.fp_width) == 0.0:
                    self.fp = 0.0
            if self.active:
                if d != self.s:        # exit against the creep: freeze, fade out with motion
                    if self.s > 0:
                        self.fp, self.fp_anchor, self.fp_width = self.sc, self.u_d - self.band, self.band
                        if self._fade(self.fp_anchor - u, self.fp_width) == 0.0:
                            self.fp = 0.0
                    else:
                        self.fm, self.fm_anchor, self.fm_width = self.sc, self.u_d + self.band, self.band
                        if self._fade(u - self.fm_anchor, self.fm_width) == 0.0:
                            self.fm = 0.0
                self.active = False
            self.last_dir = d
        self.u_prev = u


class EPIForward(StreamingOperator):
    """HC operator sum (eqs. 3–4): u [V] → y [nm] at sample period ``dt_s``.

    ``use_numba=True`` (default) runs the compiled twin of the state machine;
    ``use_numba=False`` the plain-Python reference (bit-identical, tested).
    """

    def __init__(self, pi: PIOperator, episodes: CreepEpisodes, use_numba: bool = True) -> None:
        self.pi = pi
        self.episodes = episodes
        self.use_numba = use_numba
        self._cs0, self._prm = episodes.packed()
        self._cs = self._cs0.copy()

    def reset(self) -> None:
        self.pi.reset()
        self.episodes.reset()
        self._cs[:] = self._cs0

    def step(self, x: float) -> float:
        u = finite_sample("input", x)
        if self.use_numba:
            return K.epi_forward_step(u, self.pi._P, self.pi.out_offset, self._cs, self._prm)
        h = self.pi.step(u)
        ep = self.episodes
        ep.advance()
        T = ep.term(u)
        ep.commit(u)
        return h + T

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("input", x)
        out = np.empty_like(x)
        if self.use_numba:
            K.epi_forward_block(x, self.pi._P, self.pi.out_offset, self._cs, self._prm, out)
            return out
        step = self.step
        for i, v in enumerate(x.tolist()):
            out[i] = step(v)
        return out


class EPIInverse(StreamingOperator):
    """Exact inverse of :class:`EPIForward`: y [nm] → u [V] (see the module docstring).

    Closed form (PI inverse, eqs. 8–11) wherever the creep term is constant around the
    solution; where it fades with the input (just after leaving a dwell against the
    creep) the monotone forward map is solved by bisection to the last bit.
    """

    def __init__(self, pi_inverse: PIOperator, pi_forward: PIOperator, episodes: CreepEpisodes,
                 use_numba: bool = True) -> None:
        self.pi_inv = pi_inverse
        self.pi_fwd = pi_forward
        self.episodes = episodes
        self.use_numba = use_numba
        self._cs0, self._prm = episodes.packed()
        self._cs = self._cs0.copy()

    def reset(self) -> None:
        self.pi_inv.reset()
        self.pi_fwd.reset()
        self.episodes.reset()
        self._cs[:] = self._cs0

    def _solve(self, y: float, c0: float) -> float:
        ep = self.episodes
        up = ep.u_prev
        rising = c0 > up
        u = c0
        for _ in range(8):                      # piecewise-constant creep: fixed point
            T = ep.term(u)
            u_new = self.pi_inv.peek(y - T)
            if u_new == u:
                return u
            if (u_new > up) != rising:
                break
            u = u_new
        # Bisection on the forward map, which is non-decreasing in u with jumps only
        # against the motion. Brackets grow geometrically from u_prev, so the solution
        # found is the one nearest to the previous voltage.
        fwd = self.pi_fwd

        def Y(v: float) -> float:
            return fwd.peek(v) + ep.term(v)

        sgn = 1.0 if rising else -1.0
        step = max(0.25 * abs(c0 - up), 1e-9 * (1.0 + abs(up)))
        near = up
        for _ in range(K.BRACKET_DOUBLINGS + 1):
            far = up + sgn * step
            if (Y(far) >= y) if rising else (Y(far) <= y):
                break
            near = far
            step *= 2.0
        else:
            return up          # no finite bracket (overflowing creep law): hold the voltage
        lo, hi = (near, far) if rising else (far, near)
        while True:
            mid = 0.5 * (lo + hi)
            if not (lo < mid < hi):
                return hi if rising else lo
            if rising:
                if Y(mid) >= y:
                    hi = mid
                else:
                    lo = mid
            elif Y(mid) <= y:
                lo = mid
            else:
                hi = mid

    def step(self, x: float) -> float:
        y = finite_sample("input", x)
        if self.use_numba:
            return K.epi_inverse_step(y, self.pi_inv._P, self.pi_inv.in_offset, self.pi_fwd._P,
                                      self.pi_fwd.out_offset, self._cs, self._prm)
        ep = self.episodes
        ep.advance()
        up = ep.u_prev
        T0 = ep.term(up)
        c0 = self.pi_inv.peek(y - T0)
        u = c0 if c0 == up else self._solve(y, c0)
        # advance both PI banks (kernel calls without the input check of step(): the creep
        # term may be ±inf for an overflowing creep law, exactly as in the compiled twin)
        pi, pf = self.pi_inv, self.pi_fwd
        K.pi_step_packed(y - ep.term(u), pi._P, pi.in_offset, pi.out_offset)
        K.pi_step_packed(u, pf._P, pf.in_offset, pf.out_offset)
        ep.commit(u)
        return u

    def block(self, x: np.ndarray) -> np.ndarray:
        x = block_samples("input", x)
        out = np.empty_like(x)
        if self.use_numba:
            K.epi_inverse_block(x, self.pi_inv._P, self.pi_inv.in_offset, self.pi_fwd._P,
                                self.pi_fwd.out_offset, self._cs, self._prm, out)
            return out
        step = self.step
        for i, v in enumerate(x.tolist()):
            out[i] = step(v)
        return out


class EPIModel(PIFamilyModel):
    """Extended PI model file (``kind = "epi"``): the PI fields plus the creep law
    ``M(u) = creep_a_nm · creep_b^u``, rate ``creep_lambda_per_s``. Time-dependent: the
    operators need the sample period ``dt_s``."""

    kind: Literal["epi"] = "epi"
    time_dependent: ClassVar[bool] = True
    creep_a_nm: FiniteFloat = Field(ge=0, le=1e6, description="creep magnitude factor a in M(u) = a·b^u [nm], ≤ 1 mm")
    creep_b: FiniteFloat = Field(gt=0.5, le=2.0, description="creep magnitude base b per volt (M(u) = a·b^u), 0.5 < b ≤ 2")
    creep_lambda_per_s: FiniteFloat = Field(gt=0, description="creep rate λ in C = (1 − e^{−λt})·M [1/s]")

    def _episodes(self, dt_s: float | None) -> CreepEpisodes:
        dt = sample_period(dt_s, "extended PI model")
        r, w, x0 = self.forward_parameters()
        return CreepEpisodes(self.creep_a_nm, self.creep_b, self.creep_lambda_per_s, dt,
                             float(np.min(np.cumsum(w))), float(x0[0]))

    def forward(self, dt_s: float | None = None, use_numba: bool = True) -> EPIForward:
        """Operator u [V] → y [nm] at sample period ``dt_s`` [s]."""
        r, w, x0 = self.forward_parameters()
        return EPIForward(PIOperator(r, w, x0, out_offset=self.offset_nm, validate=False), self._episodes(dt_s),
                          use_numba=use_numba)

    def inverse(self, dt_s: float | None = None, use_numba: bool = True) -> EPIInverse:
        """Feedforward compensator y [nm] → u [V] at sample period ``dt_s`` [s]."""
        r, w, x0 = self.inverse_parameters()
        rf, wf, xf = self.forward_parameters()
        return EPIInverse(PIOperator(r, w, x0, in_offset=self.offset_nm, validate=False),
                          PIOperator(rf, wf, xf, out_offset=self.offset_nm, validate=False), self._episodes(dt_s),
                          use_numba=use_numba)

    def summary(self) -> str:
        lines = ["model            : extended Prandtl–Ishlinskii with inflexion creep (kind epi)"]
        lines += self._pi_summary_lines()
        lines.append(f"creep            : C(u,t) = (1 - exp(-{self.creep_lambda_per_s:.6g}/s * t)) * "
                     f"{self.creep_a_nm:.6g} nm * {self.creep_b:.8g}^u")
        tau = 1.0 / self.creep_lambda_per_s
        lines.append(f"creep time const : {tau:.6g} s")
        return "\n".join(lines)

    @classmethod
    def identify(cls, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, n_operators: int | None = None,
                 **options: Any) -> "EPIModel":
        """Fit an extended PI model to data that contains dwells.

        1. Dwells (runs of equal input samples, at least ``min_dwell_samples``, default 10,
           after a motion) give the creep: per dwell ``y(τ) − y(0) = s·M_j·(1 − e^{−λτ})``
           with one λ for all dwells (1-D search over log λ, ``M_j`` by linear least
           squares), then ``log M_j = log a + u_j·log b`` (eqs. 1–2, Figs. 5–6).
        2. The PI part (eq. 5, invertibility constraints as for ``pi``) is fitted to the
           data minus the creep the HC state machine predicts for this input. (Fitting
           the creep scale jointly with the weights was tried and tracked dwells worse.)

        Options: ``thresholds``, ``min_slope_fraction``, ``max_rows`` (as for ``pi``),
        ``min_dwell_samples``, ``dwell_tol_V`` (default 0: a dwell is exact repetition).
        The time column must be uniformly sampled.
        """
        min_dwell = number_option("min_dwell_samples", options.pop("min_dwell_samples", 10), lo=3, integer=True)
        tol = number_option("dwell_tol_V", options.pop("dwell_tol_V", 0.0), lo=0.0)
        u, y, r, x0 = prepare_pi_identification(t_s, u_V, y_nm, n_operators, options)
        t = np.asarray(t_s, dtype=np.float64).ravel()
        dt = _uniform_dt(t)
        a, b, lam = fit_inflexion_creep(u, y, dt, min_dwell_samples=min_dwell, dwell_tol_V=tol)
        fit_opts = {k: options.pop(k) for k in ("min_slope_fraction", "max_rows") if k in options}
        if options:
            raise ModelError(f"options: unknown option(s) {', '.join(sorted(options))}; allowed: thresholds, "
                             "min_slope_fraction, max_rows, min_dwell_samples, dwell_tol_V")
        # pass 1: plain PI for the smallest slope (sets the creep band); then the PI part
        # on the data minus the creep the HC state machine predicts for this input.
        # The band depends on the smallest slope, so repeat until it settles.
        w, off = fit_pi_weights(u, y, r, x0, **fit_opts)
        for _ in range(4):
            min_slope = float(np.min(np.cumsum(w)))
            creep = creep_term(u, a, b, lam, dt, min_slope, float(x0[0]))
            w, off = fit_pi_weights(u, y - creep, r, x0, **fit_opts)
            if abs(float(np.min(np.cumsum(w))) - min_slope) <= 1e-12 * abs(min_slope):
                break
        return cls(thresholds=r.tolist(), weights=w.tolist(), initial_state=x0.tolist(), offset_nm=off,
                   creep_a_nm=a, creep_b=b, creep_lambda_per_s=lam)


def _uniform_dt(t: np.ndarray) -> float:
    d = np.diff(t)
    dt = float(np.median(d))
    if dt <= 0 or np.max(np.abs(d - dt)) > 1e-3 * dt:
        raise ModelError("t_s: the extended PI model needs uniformly sampled data "
                         f"(median period {dt:g} s, steps from {d.min():g} to {d.max():g} s)")
    return dt


def creep_term(u_V: np.ndarray, a_nm: float, b: float, lambda_per_s: float, dt_s: float,
               min_slope_nm_per_V: float, u_initial_V: float, use_numba: bool = True) -> np.ndarray:
    """The creep part ``y − PI(u)`` [nm] of the extended PI forward output for input ``u``."""
    ep = CreepEpisodes(a_nm, b, lambda_per_s, dt_s, min_slope_nm_per_V, u_initial_V)
    u = np.ascontiguousarray(u_V, dtype=np.float64)
    out = np.empty(u.size)
    if use_numba:
        cs, prm = ep.packed()
        K.epi_creep_block(u, cs, prm, out)
        return out
    for i, v in enumerate(u.tolist()):
        ep.advance()
        out[i] = ep.term(v)
        ep.commit(v)
    return out


def find_dwells(u_V: np.ndarray, min_dwell_samples: int = 10, dwell_tol_V: float = 0.0
                ) -> list[tuple[int, int, int]]:
    """Dwells of the input: ``(k0, k1, s)`` with ``u[k0..k1]`` held (``|Δu| ≤ tol``),
    ``k0`` the first repeated sample (τ = 0), ``s`` the sign of the motion before it."""
    u = np.asarray(u_V, dtype=float)
    held = np.abs(np.diff(u)) <= dwell_tol_V          # held[k-1]: u[k] ≈ u[k-1]
    out = []
    k = 1
    n = u.size
    last_dir = 0
    while k < n:
        if held[k - 1]:
            k0 = k
            while k < n and held[k - 1]:
                k += 1
            k1 = k - 1
            if last_dir != 0 and k1 - k0 + 1 >= min_dwell_samples:
                out.append((k0, k1, last_dir))
        else:
            last_dir = 1 if u[k] > u[k - 1] else -1
            k += 1
    return out


def fit_inflexion_creep(u_V: np.ndarray, y_nm: np.ndarray, dt_s: float, *, min_dwell_samples: int = 10,
                        dwell_tol_V: float = 0.0) -> tuple[float, float, float]:
    """Creep parameters ``(a [nm], b, λ [1/s])`` from the dwells in ``(u, y)`` (eqs. 1–2)."""
    from scipy.optimize import minimize_scalar

    if min_dwell_samples < 3:
        raise ModelError(f"min_dwell_samples: {min_dwell_samples} must be ≥ 3")
    if dwell_tol_V < 0:
        raise ModelError(f"dwell_tol_V: {dwell_tol_V} must be ≥ 0")
    dwells = find_dwells(u_V, min_dwell_samples, dwell_tol_V)
    if not dwells:
        raise ModelError(f"data: no dwells found (input held for ≥ {min_dwell_samples} samples after a move); "
                         "the extended PI model needs a staircase or holds at the turning points")
    segs = []
    for k0, k1, s in dwells:
        tau = (np.arange(k1 - k0 + 1)) * dt_s
        dy = y_nm[k0:k1 + 1] - y_nm[k0]
        segs.append((tau, dy, s, float(u_V[k0])))
    t_longest = max(seg[0][-1] for seg in segs)

    def amplitudes(lam: float) -> tuple[float, list[float]]:
        sse = 0.0
        amps = []
        for tau, dy, _, _ in segs:
            g = 1.0 - np.exp(-lam * tau)
            gg = float(g @ g)
            A = float(g @ dy) / gg if gg > 0 else 0.0
            sse += float(np.sum((dy - A * g) ** 2))
            amps.append(A)
        return sse, amps

    lo, hi = math.log(0.05 / t_longest), math.log(0.5 / dt_s)
    grid = np.linspace(lo, hi, 61)
    sse = [amplitudes(math.exp(g))[0] for g in grid]
    j = int(np.argmin(sse))
    a_lo, a_hi = grid[max(j - 1, 0)], grid[min(j + 1, len(grid) - 1)]
    res = minimize_scalar(lambda g: amplitudes(math.exp(g))[0], bounds=(a_lo, a_hi), method="bounded",
                          options={"xatol": 1e-11, "maxiter": 200})
    lam = math.exp(float(res.x))
    _, amps = amplitudes(lam)
    M = np.array([A * s for A, (_, _, s, _) in zip(amps, segs)])
    ud = np.array([seg[3] for seg in segs])
    ok = M > 0
    if not np.any(ok):
        raise ModelError("data: no dwell shows creep in the direction of the preceding move; "
                         "the extended PI model cannot describe this creep")
    M, ud = M[ok], ud[ok]
    if M.size >= 2 and np.ptp(ud) > 0:
        coef = np.polyfit(ud, np.log(M), 1)
        a, b = math.exp(coef[1]), math.exp(coef[0])
    else:
        a, b = float(np.exp(np.mean(np.log(M)))), 1.0
    if not 0.5 < b <= 2.0:
        raise ModelError(f"data: the dwell creep magnitudes give b = {b:.6g} in M(u) = a·b^u, outside the "
                         "allowed 0.5 < b ≤ 2; the creep does not follow the extended PI law")
    log.info("inflexion creep: %d dwells, lambda %.4g 1/s, a %.4g nm, b %.6g", len(segs), lam, a, b)
    return a, b, lam
