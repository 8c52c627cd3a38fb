"""Test plants that are NOT the models under test.

:class:`RelayPreisachPlant` — a vectorised classical Preisach model built from relays
(hysterons) on a regular grid of switching voltages, with a configurable weight density
(uniform, a Gaussian mixture with asymmetric loops by default, or any callable), an
optional reversible linear part, measurement noise and a seed. Its loops are asymmetric,
which no PI operator can represent exactly — a fair test of PI compensation.

:class:`CreepingPlant` — any plant followed by linear creep (bank of first-order lags),
for extended-PI tests.

Units: input u [V] (default range 0–150 V), output y [nm]. Plants are stateful:
``run(u)`` continues from where the last call ended; ``reset()`` starts afresh.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from numba import njit

from afmctl.compensators.creep import LinearCreep


@njit(cache=True)
def _relay_run(u, alpha, beta, mu, state, out):  # pragma: no cover - compiled
    """Relays switch on at u ≥ alpha, off at u ≤ beta; out = Σ mu·state (recomputed exactly
    from the on-set each sample would cost O(relays); we update incrementally and re-sum
    every 4096 samples to keep rounding bounded)."""
    total = 0.0
    for j in range(mu.shape[0]):
        if state[j]:
            total += mu[j]
    for k in range(u.shape[0]):
        v = u[k]
        for j in range(mu.shape[0]):
            if state[j]:
                if v <= beta[j]:
                    state[j] = 0
                    total -= mu[j]
            elif v >= alpha[j]:
                state[j] = 1
                total += mu[j]
        if k % 4096 == 4095:
            total = 0.0
            for j in range(mu.shape[0]):
                if state[j]:
                    total += mu[j]
        out[k] = total

#: default asymmetric mixture: (weight, alpha centre V, beta centre V, sigma_alpha V, sigma_beta V, correlation).
#: With the defaults below the major loop is ~25 % of the span wide and its falling branch
#: deviates from the 180°-turned rising branch (what any PI loop satisfies) by ~11 %.
DEFAULT_MIXTURE: tuple[tuple[float, float, float, float, float, float], ...] = (
    (1.0, 80.0, 40.0, 50.0, 40.0, 0.6),
    (0.4, 40.0, 5.0, 20.0, 8.0, 0.0),
)


@dataclass
class RelayPreisachPlant:
    """Relay Preisach plant ``y = y0 + linear_nm_per_V·u + Σ μ(α,β)·γ_αβ(u)`` [nm].

    Relays ``γ_αβ ∈ {0, 1}`` switch on when ``u ≥ α`` and off when ``u ≤ β`` (``α > β``),
    with ``α, β`` on a grid of ``grid`` levels over ``[u_min_V, u_max_V]`` (relay grid
    resolution). ``density`` is ``"mixture"`` (Gaussian mixture ``mixture``, default
    asymmetric), ``"uniform"``, or a callable ``f(alpha, beta) -> weights``. The relay
    weights are scaled so that the hysteretic part spans ``hysteresis_nm`` over a full
    0→max sweep. All relays start off (a demagnetised-at-u_min scanner). ``noise_nm``
    adds Gaussian measurement noise (``seed``).
    """

    u_min_V: float = 0.0
    u_max_V: float = 150.0
    grid: int = 100
    density: str | Callable[[np.ndarray, np.ndarray], np.ndarray] = "mixture"
    mixture: Sequence[tuple[float, float, float, float, float, float]] = DEFAULT_MIXTURE
    hysteresis_nm: float = 7000.0
    linear_nm_per_V: float = 50.0
    offset_nm: float = 0.0
    noise_nm: float = 0.0
    seed: int = 0
    alpha: np.ndarray = field(init=False, repr=False)
    beta: np.ndarray = field(init=False, repr=False)
    mu: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.grid < 2:
            raise ValueError("grid: at least 2 levels")
        if not self.u_max_V > self.u_min_V:
            raise ValueError("u_max_V must be > u_min_V")
        lv = np.linspace(self.u_min_V, self.u_max_V, self.grid + 1)
        self.levels = 0.5 * (lv[:-1] + lv[1:])   # cell centres: relays switch strictly inside the range
        ia, ib = np.tril_indices(self.grid, k=-1)  # alpha index > beta index
        self._ia, self._ib = ia, ib
        self.alpha, self.beta = self.levels[ia], self.levels[ib]
        mu = self._density(self.alpha, self.beta)
        mu = np.clip(np.asarray(mu, dtype=float), 0.0, None)
        if mu.sum() <= 0:
            raise ValueError("density: all relay weights are zero")
        self.mu = mu * (self.hysteresis_nm / mu.sum())
        self.rng = np.random.default_rng(self.seed)
        self.reset()

    def _density(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if callable(self.density):
            return self.density(a, b)
        if self.density == "uniform":
            return np.ones_like(a)
        if self.density == "mixture":
            out = np.zeros_like(a)
            for wt, ca, cb, sa, sb, rho in self.mixture:
                za, zb = (a - ca) / sa, (b - cb) / sb
                q = (za * za - 2 * rho * za * zb + zb * zb) / (1 - rho * rho)
                out += wt * np.exp(-0.5 * q)
            return out
        raise ValueError(f"density: {self.density!r}; use 'mixture', 'uniform' or a callable")

    def reset(self) -> None:
        self.state = np.zeros(self.alpha.size, dtype=np.uint8)
        self.rng = np.random.default_rng(self.seed)

    def run(self, u_V: np.ndarray) -> np.ndarray:
        """Plant output y [nm] for input u [V] (state carried between calls)."""
        u = np.ascontiguousarray(u_V, dtype=float)
        y = np.empty(u.size)
        _relay_run(u, self.alpha, self.beta, self.mu, self.state, y)
        y += self.offset_nm + self.linear_nm_per_V * u
        if self.noise_nm > 0:
            y = y + self.rng.normal(0.0, self.noise_nm, u.size)
        return y

    def output_range_nm(self) -> tuple[float, float]:
        """Output at u_min (all relays off) and at u_max after a full rise (all on)."""
        lo = self.offset_nm + self.linear_nm_per_V * self.u_min_V
        return lo, self.offset_nm + self.linear_nm_per_V * self.u_max_V + float(self.mu.sum())


@dataclass
class CreepingPlant:
    """``plant`` followed by linear creep: ``y = creep(plant(u))`` [nm] at ``dt_s``.

    Creep fractions ``weights`` (Σ < 1) with time constants ``time_constants_s``; the lag
    states start at the plant output for ``u_initial_V`` held.
    """

    plant: RelayPreisachPlant
    dt_s: float = 1e-3
    time_constants_s: Sequence[float] = (0.05, 0.5, 3.0)
    weights: Sequence[float] = (0.02, 0.03, 0.03)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.plant.reset()
        y0 = float(self.plant.run(np.array([self.plant.u_min_V]))[0])
        self.plant.reset()
        self.creep = LinearCreep(self.time_constants_s, self.weights, self.dt_s, initial=y0)

    def run(self, u_V: np.ndarray) -> np.ndarray:
        return self.creep.block(self.plant.run(u_V))


# ------------------------------------------------------------ simulated scanners -------

def stiff_hysteresis():
    """The "stiff" unseen plant's loop (benchmarks/unseen_plants.py) as the simulator's
    Gaussian Preisach density: 70 nm/V reversible, two asymmetric components."""
    from afmctl.sim_backend.config import GaussianPreisachConfig, PreisachComponent
    return GaussianPreisachConfig(linear_nm_per_V=70.0, components=[
        PreisachComponent(mass_nm=2500, alpha_V=70, beta_V=40, sigma_alpha_V=20, sigma_beta_V=20, rho=0.5),
        PreisachComponent(mass_nm=1200, alpha_V=120, beta_V=100, sigma_alpha_V=15, sigma_beta_V=15, rho=0.6)])


def play_x(cfg, u_V: np.ndarray, dt_s: float) -> np.ndarray:
    """x position [nm] of a fresh simulated scanner ``cfg`` driven by ``u_V`` [V] on x
    (y and z at 0 V), one row per sample of ``dt_s`` [s]."""
    from afmctl.sim_backend.scanner import Scanner
    U = np.zeros((np.asarray(u_V).size, 3))
    U[:, 0] = u_V
    return Scanner(cfg).run(U, dt_s)[:, 0]


# ------------------------------------------------------------------- signals ----------

def triangle(t_s: np.ndarray, freq_Hz: float, lo: float, hi: float) -> np.ndarray:
    """Symmetric triangle between ``lo`` and ``hi`` starting at ``lo``."""
    ph = (np.asarray(t_s) * freq_Hz) % 1.0
    return lo + (hi - lo) * (1.0 - np.abs(2.0 * ph - 1.0))


def decaying_triangle(dt_s: float, cycles: int, lo_V: float, hi_V: float, samples_per_cycle: int = 1000,
                      final_fraction: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Triangle from ``lo_V`` whose peak decays linearly from ``hi_V`` towards ``lo_V``
    (to ``final_fraction`` of the span): identification excitation with nested minor
    loops. Returns ``(t_s, u_V)``."""
    n = cycles * samples_per_cycle
    t = np.arange(n) * dt_s
    ph = (np.arange(n) / samples_per_cycle) % 1.0
    tri = 1.0 - np.abs(2.0 * ph - 1.0)
    env = 1.0 - (1.0 - final_fraction) * (np.arange(n) // samples_per_cycle) / max(cycles - 1, 1)
    return t, lo_V + (hi_V - lo_V) * env * tri


def staircase(dt_s: float, levels: Sequence[float], dwell_s: float, ramp_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Hold each of ``levels`` for ``dwell_s`` (optional linear ramps of ``ramp_s`` between
    them). Returns ``(t_s, signal)``."""
    nd = max(1, int(round(dwell_s / dt_s)))
    nr = int(round(ramp_s / dt_s))
    parts = [np.full(nd, float(levels[0]))]
    for a, b in zip(levels[:-1], levels[1:]):
        if nr > 0:
            parts.append(np.linspace(a, b, nr + 1)[1:])
        parts.append(np.full(nd, float(b)))
    x = np.concatenate(parts)
    return np.arange(x.size) * dt_s, x


def user_style_record(slew_V_per_s: float, fs: float = 50_000.0, u_max: float = 150.0) -> np.ndarray:
    """What a lab records without afmctl's excitation [V] at ``fs`` [Hz], its waveforms
    pieced together (the command jumps where one starts at another voltage): a rest, nested
    triangles at 1 Hz (from 0 V to 100, 80, … 20 % of the range, then centred ones of 100, 60
    and 30 %), 20 triangles at 10 Hz over 80 % of the range, 40 at 40 Hz over 50 %, and a
    logarithmic 1 Hz → 2 kHz chirp of ±10 V around mid-range whose amplitude falls where it
    would exceed 80 % of the amplifier's slew limit [V/s]."""
    def tri(f: float, lo: float, amp: float, cycles: int) -> np.ndarray:
        t = np.arange(int(round(cycles / f * fs))) / fs
        return lo + amp * (1.0 - np.abs(2.0 * ((t * f) % 1.0) - 1.0))

    parts = [np.zeros(int(0.2 * fs))] + [tri(1.0, 0.0, a * u_max, 1) for a in (1.0, 0.8, 0.6, 0.4, 0.2)]
    for a in (1.0, 0.6, 0.3):
        lo = 0.5 * (1.0 - a) * u_max
        parts += [np.linspace(0.0, lo, int(0.05 * fs)), tri(1.0, lo, a * u_max, 1), np.linspace(lo, 0.0, int(0.05 * fs))]
    parts += [tri(10.0, 0.1 * u_max, 0.8 * u_max, 20), tri(40.0, 0.25 * u_max, 0.5 * u_max, 40)]
    T, mid = 8.0, 0.5 * u_max
    t = np.arange(int(T * fs)) / fs
    k = np.log(2000.0) / T
    amp = np.minimum(10.0, 0.8 * slew_V_per_s / (2 * np.pi * np.exp(k * t)))
    parts += [np.linspace(0.0, mid, int(0.5 * fs)), mid + amp * np.sin(2 * np.pi * (np.exp(k * t) - 1.0) / k),
              np.linspace(mid, 0.0, int(0.5 * fs))]
    return np.concatenate(parts)


def pi_with_a_mode_record() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``afmctl excite --kind all`` (0–100 V at 5 kHz, short) through a four-play PI loop and
    one 400 Hz mode: t [s], u [V], y [nm]; a record whose ``auto`` selects a ``+dynamics``
    chain in a few seconds."""
    from afmctl.compensators.chain import ChainModel
    from afmctl.compensators.dynamics import LinearDynamicsModel
    from afmctl.compensators.pi import PIModel
    from afmctl.data.excitation import ExcitationSpec, excitation

    spec = ExcitationSpec(u_min_V=0.0, u_max_V=100.0, rate_Hz=5000.0, dwell_s=0.3, gap_s=0.1, periods=2,
                          f_min_Hz=20.0, sweep_V_per_s=400.0)
    u = excitation("all", spec)
    t = np.arange(u.size) / spec.rate_Hz
    plant = ChainModel(hysteresis=PIModel(thresholds=[0.0, 20.0, 40.0, 60.0], weights=[60.0, 15.0, 10.0, 5.0],
                                          initial_state=[0.0] * 4),
                       dynamics=LinearDynamicsModel.from_modes([(400.0, 0.05)]))
    return t, u, plant.forward(1.0 / spec.rate_Hz).block(u)
