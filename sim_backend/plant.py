"""Per-axis plant of the simulated scanner: amplifier → hysteresis → creep → structural mode.

* :func:`everett_table` — Everett function of a Gaussian-mixture Preisach density on a grid.
* :class:`GaussianPreisachOperator` — the classical Preisach operator (image-based paper,
  eqs. 3, 7, 8) as a :class:`~afmctl.compensators.base.StreamingOperator` u [V] → y [nm].
* :class:`AxisPlant` — one axis, block simulation with carried state for any sample period.

Every stage has a plain-Python reference in :mod:`afmctl.sim_backend._plant_kernels`; the numba
twin is used when ``fast=True`` (the default).
"""
from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
from scipy.linalg import expm

from afmctl.compensators.base import StreamingOperator
from . import _plant_kernels as K
from .config import AxisConfig, CreepConfig, DynamicsConfig, ExternalModelConfig, GaussianPreisachConfig

log = logging.getLogger(__name__)

#: capacity of the Preisach memory (turning points); deeper nesting wipes the innermost loop
MEMORY_CAPACITY = 512
_NONE = np.zeros(0)


def preisach_weights(cfg: GaussianPreisachConfig) -> np.ndarray:
    """Relay weights [nm] of the discretised Preisach plane: ``W[i, j]`` is the mass of the
    cell α ∈ [v_i, v_{i+1}], β ∈ [v_j, v_{j+1}] (v = grid nodes), zero for j > i, half a
    cell on the diagonal. Relay (i, j) switches up at u ≥ v_{i+1} and down at u ≤ v_j."""
    n = cfg.n_grid
    v = np.linspace(cfg.u_min_V, cfg.u_max_V, n)
    c = 0.5 * (v[:-1] + v[1:])
    A, B = np.meshgrid(c, c, indexing="ij")  # A: α (rows), B: β (columns)
    tri = np.tril(np.ones((n - 1, n - 1)), 0)
    tri[np.diag_indices(n - 1)] = 0.5
    W = np.zeros((n - 1, n - 1))
    for comp in cfg.components:
        da = (A - comp.alpha_V) / comp.sigma_alpha_V
        db = (B - comp.beta_V) / comp.sigma_beta_V
        q = (da * da - 2 * comp.rho * da * db + db * db) / (1 - comp.rho**2)
        g = np.exp(-0.5 * q) * tri
        total = g.sum()
        if total > 0:
            W += comp.mass_nm * g / total
    return W


def everett_table(cfg: GaussianPreisachConfig) -> np.ndarray:
    """Everett function at the grid nodes: ``E[a, b]`` = mass of the relays with
    α ≤ v_a and β ≥ v_b (the relays switched off by falling from v_a to v_b), zero for
    a ≤ b. Shape (n_grid, n_grid), nm."""
    W = preisach_weights(cfg)
    n = cfg.n_grid
    # S[i, b] = Σ_{j ≥ b} W[i, j]
    S = np.cumsum(W[:, ::-1], axis=1)[:, ::-1]
    E = np.zeros((n, n))
    E[1:, : n - 1] = np.cumsum(S, axis=0)
    E[np.triu_indices(n, 0)] = 0.0
    return E


class GaussianPreisachOperator(StreamingOperator):
    """Classical Preisach hysteresis u [V] → y [nm] (image-based paper, eq. 3) with a
    Gaussian-mixture density; output y = linear_nm_per_V·(u − u_min_V) + P[u]. Starts in
    negative saturation (u = u_min_V, all relays down). Inputs are clipped to the plane."""

    def __init__(self, cfg: GaussianPreisachConfig, fast: bool = True) -> None:
        self.cfg = cfg
        self.E = everett_table(cfg)
        self.lo = float(cfg.u_min_V)
        self.hi = float(cfg.u_max_V)
        self.lin = float(cfg.linear_nm_per_V)
        self._kernel = K.preisach_nb if fast else K.preisach_py
        self.reset()

    def reset(self) -> None:
        # memory of :func:`afmctl.sim_backend._plant_kernels.preisach_py`: turning points s[0..K]
        # (s[0] = lo), prefix sums P, ist = [K]
        self.s = np.zeros(MEMORY_CAPACITY + 1)
        self.s[0] = self.lo
        self.P = np.zeros(MEMORY_CAPACITY + 1)
        self.ist = np.zeros(1, dtype=np.int64)

    def step(self, x: float) -> float:
        return float(self.block(np.array([x]))[0])

    def block(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        out = np.empty_like(x)
        self._kernel(x, out, self.E, self.lo, self.hi, self.lin, self.s, self.P, self.ist)
        return out

    @property
    def saturation_nm(self) -> float:
        """Output at u_max_V (all relays up)."""
        return self.lin * (self.hi - self.lo) + float(self.E[-1, 0])


def mode_matrices(dyn: DynamicsConfig, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of p'' = ω²(r − p) − (ω/Q)p' (unit DC gain):
    returns (Ad 2×2, Bd 2,) with [p, v]_{k+1} = Ad·[p, v]_k + Bd·r_k."""
    w = 2 * math.pi * dyn.resonance_Hz
    Ac = np.array([[0.0, 1.0], [-w * w, -w / dyn.quality_factor]])
    Bc = np.array([0.0, w * w])
    M = np.zeros((3, 3))
    M[:2, :2] = Ac
    M[:2, 2] = Bc
    Md = expm(M * dt_s)
    return np.ascontiguousarray(Md[:2, :2]), np.ascontiguousarray(Md[:2, 2])


def creep_coefficients(creep: CreepConfig, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(a_k, g_k): lag poles exp(−dt/τ_k) for log-spaced τ_k and equal gains summing to
    ``fraction`` (nonlinearities paper, eq. 21)."""
    tau = np.geomspace(creep.tau_min_s, creep.tau_max_s, creep.n_lags)
    return np.exp(-dt_s / tau), np.full(creep.n_lags, creep.fraction / creep.n_lags)


class AxisPlant:
    """One axis of the scanner: command voltage [V] → displacement [nm] (before coupling
    and drift). :meth:`run` simulates a block with any sample period and carries state."""

    def __init__(self, cfg: AxisConfig, fast: bool = True) -> None:
        self.cfg = cfg
        self.fast = fast
        amp = cfg.amplifier
        self.u_min_V = amp.u_min_V
        self.u_max_V = amp.u_max_V
        self.lsb_V = (amp.u_max_V - amp.u_min_V) / (2**amp.bits - 1) if amp.bits > 0 else 0.0
        hyst = cfg.hysteresis
        self._external = isinstance(hyst, ExternalModelConfig)
        #: the external model (a compensators model) or None
        self.model: Any = None
        #: the hysteresis operator: the Gaussian Preisach one, or the external model's forward
        #: (built for the first sample period used); Any: the two kinds differ (saturation_nm)
        self.hysteresis: Any = None
        if isinstance(hyst, ExternalModelConfig):
            from afmctl.compensators.models import model_from_dict

            self.model = model_from_dict(hyst.model, where="hysteresis.model")
            self._hyst_ops: dict[float, StreamingOperator] = {}
        else:
            self.hysteresis = GaussianPreisachOperator(hyst, fast=fast)
        #: per sample period (and ("extra", period)): the discretised coefficients
        self._cache: dict[Any, Any] = {}
        self.reset()

    # ------------------------------------------------------------------ helpers
    def _coeffs(self, dt_s: float) -> tuple:
        c = self._cache.get(dt_s)
        if c is None:
            amp = self.cfg.amplifier
            slew, bw = amp.effective_slew_V_per_s(), amp.effective_bandwidth_Hz()
            max_step = slew * dt_s if slew else math.inf
            a_lp = math.exp(-2 * math.pi * bw * dt_s) if bw else 0.0
            if self.cfg.creep is not None and self.cfg.creep.fraction > 0:
                a_c, g_c = creep_coefficients(self.cfg.creep, dt_s)
            else:
                a_c, g_c = np.zeros(0), np.zeros(0)
            if self.cfg.dynamics is not None:
                ad, bd = mode_matrices(self.cfg.dynamics, dt_s)
                use_dyn = True
            else:
                ad, bd, use_dyn = np.eye(2), np.zeros(2), False
            c = (max_step, a_lp, a_c, g_c, ad, bd, use_dyn)
            self._cache[dt_s] = c
        return c

    def _extra(self, dt_s: float) -> list[tuple[np.ndarray, np.ndarray]]:
        key = ("extra", dt_s)
        m = self._cache.get(key)
        if m is None:
            m = [mode_matrices(d, dt_s) for d in self.cfg.extra_modes]
            self._cache[key] = m
        return m

    def _hyst(self, dt_s: float) -> StreamingOperator:
        if not self._external:
            return self.hysteresis
        # one operator for the whole run; time-dependent models are built for the first dt
        if self.hysteresis is None:
            self.hysteresis = self.model.forward(dt_s)
        return self.hysteresis

    def reset(self) -> None:
        """Initial state: amplifier at u_min_V, hysteresis in negative saturation, creep
        and mode at rest at the corresponding displacement."""
        self.amp_state = np.array([self.u_min_V, self.u_min_V])
        if self._external:
            self.hysteresis = None  # built lazily for the first sample period used
            h0 = 0.0
        else:
            self.hysteresis.reset()
            h0 = float(self.hysteresis.block(np.array([self.u_min_V]))[0])
        n_l = self.cfg.creep.n_lags if self.cfg.creep is not None else 0
        self.creep_state = np.full(n_l, h0)
        self.mode_state = np.array([h0, 0.0])
        self.extra_states = [np.array([h0, 0.0]) for _ in self.cfg.extra_modes]
        self.u_piezo_V = self.u_min_V
        self.y_nm = h0
        #: the lagged voltage [V] the Preisach part of a rate-dependent hysteresis last saw
        self.rate_state = self.u_min_V

    # ------------------------------------------------------------------ simulation
    def run(self, u_V: np.ndarray, dt_s: float, return_voltage: bool = False):
        """Simulate the command voltages ``u_V`` (N,) held for ``dt_s`` each; returns the
        displacement (N,) nm, and the piezo voltage (N,) V after the amplifier if asked."""
        u = np.ascontiguousarray(u_V, dtype=np.float64)
        max_step, a_lp, a_c, g_c, ad, bd, use_dyn = self._coeffs(float(dt_s))
        v = np.empty_like(u)
        amp_k = K.amplifier_nb if self.fast else K.amplifier_py
        amp_k(u, v, self.amp_state, self.u_min_V, self.u_max_V, self.lsb_V, max_step, a_lp)
        h = self._hysteresis_of(v, float(dt_s))
        y = np.empty_like(u)
        post_k = K.creep_dynamics_nb if self.fast else K.creep_dynamics_py
        post_k(h, y, a_c, g_c, self.creep_state, ad, bd, self.mode_state, use_dyn)
        for (ad_k, bd_k), z in zip(self._extra(float(dt_s)), self.extra_states):
            # a further mode in series: the same kernel without creep lags
            y_in = y.copy()
            post_k(y_in, y, _NONE, _NONE, _NONE, ad_k, bd_k, z, True)
        if u.shape[0]:
            self.u_piezo_V = float(v[-1])
            self.y_nm = float(y[-1])
        return (y, v) if return_voltage else y

    def _hysteresis_of(self, v: np.ndarray, dt_s: float) -> np.ndarray:
        """The hysteresis stage for piezo voltages ``v`` [V]; with ``rate_lag_s`` > 0 the
        Preisach part sees ``v`` through an exact first-order lag (state carried) and the
        reversible part ``linear_nm_per_V`` follows ``v`` directly (rate-dependent
        hysteresis: the loop widens as the input gets faster)."""
        gauss = self.cfg.hysteresis if isinstance(self.cfg.hysteresis, GaussianPreisachConfig) else None
        tau = 0.0 if gauss is None else float(gauss.rate_lag_s)
        if tau <= 0.0 or v.size == 0:
            return self._hyst(dt_s).block(v)
        from scipy.signal import lfilter
        a = math.exp(-dt_s / tau)
        lagged, zf = lfilter([1.0 - a], [1.0, -a], v, zi=[a * self.rate_state])
        self.rate_state = float(zf[0]) / a
        assert gauss is not None  # tau > 0 only for the Gaussian Preisach hysteresis
        return self._hyst(dt_s).block(lagged) + gauss.linear_nm_per_V * (v - lagged)

    def static_gain_nm_per_V(self) -> float:
        """Mean sensitivity over the full range on the major ascending branch [nm/V]
        (what a user would calibrate from the data sheet: range / voltage span)."""
        if not self._external:
            return self.hysteresis.saturation_nm / (self.u_max_V - self.u_min_V)
        op = self.model.forward(1e-3)
        y = op.block(np.linspace(self.u_min_V, self.u_max_V, 301))
        return float((y[-1] - y[0]) / (self.u_max_V - self.u_min_V))

    def linear_response(self, f_Hz: np.ndarray, dt_s: float) -> np.ndarray:
        """Small-signal frequency response of the axis' linear stages as simulated at
        ``dt_s`` [s] (amplifier low-pass → creep → structural mode; slew and quantisation
        ignored), unit DC gain: multiply by the hysteresis' local slope [nm/V] for
        nm per V. Exact for :meth:`run` at that sample period (the discrete filters'
        own responses)."""
        _, a_lp, a_c, g_c, ad, bd, use_dyn = self._coeffs(float(dt_s))
        zinv = np.exp(-2j * math.pi * np.asarray(f_Hz, dtype=float) * dt_s)
        g = (1.0 - a_lp) / (1.0 - a_lp * zinv)
        creep = np.ones_like(g)
        for a, gk in zip(a_c, g_c):
            creep -= gk * (1.0 - (1.0 - a) / (1.0 - a * zinv))
        g = g * creep
        modes = ([(ad, bd)] if use_dyn else []) + self._extra(float(dt_s))
        for ad_k, bd_k in modes:
            # z_k = Ad·z_{k−1} + bd·r_k, output z_k[0]:  P = e1ᵀ (I − Ad z⁻¹)⁻¹ bd · R
            M = np.eye(2)[None] - ad_k[None] * zinv[:, None, None]
            g = g * np.linalg.solve(M, np.broadcast_to(bd_k, (zinv.size, 2))[..., None])[:, 0, 0]
        return g
