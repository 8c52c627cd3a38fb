"""Continuous LTI systems with a pure delay: zero-order-hold discretisation and streaming.

A system is given by its zeros and poles in rad/s and a delay ``τ`` in s, with the gain
chosen for unit DC gain::

    G(s) = k · Π(s − z_i) / Π(s − p_i) · e^{−sτ},   G(0) = 1

Discretised at sample period ``T`` with a zero-order hold (the input is held between
samples, as a DAC does) and the delay split as ``τ = (d + f)·T`` (d whole samples,
0 ≤ f < 1), the state update is exact for a held input (Franklin, Powell & Workman,
*Digital Control of Dynamic Systems*, §4.3.3, fractional delay)::

    x_{k+1} = Φ·x_k + Γ1·u_{k−d} + Γ0·u_{k−d−1},   y_k = C·x_k + D·u(t_k − τ)
    Φ = e^{AT},  Γ1 = ∫_0^{T−fT} e^{Aσ}dσ·B,  Γ0 = e^{A(T−fT)}·∫_0^{fT} e^{Aσ}dσ·B

A record whose output sample ``k`` is read a fraction ``λ`` (0 < λ ≤ 1) of the period
*after* the command ``u_k`` is applied — at the end of each hold interval for ``λ = 1``, as
the simulated scanner reports its positions — leads that convention by ``λ·T``. Such a
``lead`` (in samples: it is a convention of the sampling, so it scales with ``T``) reads the
state inside the interval, which keeps the operator causal (no delay with it)::

    y_k = C·x(t_k + λT) + D·u_k = C·e^{AλT}·x_k + (C·∫_0^{λT} e^{Aσ}dσ·B + D)·u_k

The state space is built in time scaled by the poles' mean magnitude so that a kHz mode
does not give polynomial coefficients spanning 12 decades.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm
from scipy.signal import zpk2ss

from . import _lti_kernels as K
from .base import ModelError, StreamingOperator
from .input_checks import block_samples, finite_sample


def unit_dc_gain(zeros: np.ndarray, poles: np.ndarray) -> float:
    """The gain ``k`` that makes ``k·Π(−z)/Π(−p) = 1`` (real for conjugate-symmetric sets)."""
    num = np.prod(-np.asarray(poles, dtype=complex)) if len(poles) else 1.0
    den = np.prod(-np.asarray(zeros, dtype=complex)) if len(zeros) else 1.0
    return float(np.real(num / den))


def frequency_response(zeros: np.ndarray, poles: np.ndarray, delay_s: float, f_Hz: np.ndarray) -> np.ndarray:
    """Continuous ``G(j2πf)`` (complex, unit DC gain) at the frequencies ``f_Hz``."""
    s = 2j * math.pi * np.asarray(f_Hz, dtype=float)
    k = unit_dc_gain(zeros, poles)
    g = np.full(s.shape, k, dtype=complex)
    for z in zeros:
        g *= s - z
    for p in poles:
        g /= s - p
    return g * np.exp(-s * delay_s)


@dataclass(frozen=True)
class DiscreteLTI:
    """Zero-order-hold discretisation of a unit-DC-gain system (see the module docstring).

    ``D0`` multiplies ``u_{k−d}`` and ``D1`` ``u_{k−d−1}`` in the output (only one is non-zero)."""

    dt_s: float
    Ad: np.ndarray
    B1: np.ndarray
    B2: np.ndarray
    C: np.ndarray
    D0: float
    D1: float
    delay_samples: int

    def frequency_response(self, f_Hz: np.ndarray) -> np.ndarray:
        """Discrete-time response ``G(e^{jωT})`` at ``f_Hz`` (what the operator does to a
        sampled sine of that frequency)."""
        w = 2 * math.pi * np.asarray(f_Hz, dtype=float) * self.dt_s
        zinv = np.exp(-1j * w)
        n = self.Ad.shape[0]
        g = self.D0 + self.D1 * zinv
        if n:
            eye = np.eye(n)
            M = np.exp(1j * w)[:, None, None] * eye[None] - self.Ad[None]
            rhs = self.B1[None, :] + self.B2[None, :] * zinv[:, None]
            xs = np.linalg.solve(M, rhs[..., None])[..., 0]
            g = g + xs @ self.C
        return g * zinv ** self.delay_samples


def discretise(zeros: np.ndarray, poles: np.ndarray, delay_s: float, dt_s: float,
               lead_samples: float = 0.0) -> DiscreteLTI:
    """Exact zero-order-hold discretisation at ``dt_s`` [s] with the fractional delay, or
    with the output read ``lead_samples`` (0…1) of a period after each command (module
    docstring; a lead and a delay exclude each other)."""
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ModelError(f"dt_s: {dt_s!r}; the dynamics model needs a sample period > 0 s")
    if not (0.0 <= lead_samples <= 1.0) or (lead_samples > 0 and delay_s > 0):
        raise ModelError(f"lead_samples: {lead_samples!r}; allowed 0…1 sample, and only without a delay")
    zeros = np.asarray(zeros, dtype=complex)
    poles = np.asarray(poles, dtype=complex)
    n = poles.size
    d_total = delay_s / dt_s
    d = int(math.floor(d_total + 1e-9))
    frac = max(0.0, d_total - d)
    if frac < 1e-9:
        frac = 0.0
    if n == 0:
        D = 1.0
        return DiscreteLTI(dt_s, np.zeros((0, 0)), np.zeros(0), np.zeros(0), np.zeros(0),
                           D if frac == 0 else 0.0, 0.0 if frac == 0 else D, d)
    w0 = float(np.exp(np.mean(np.log(np.abs(poles)))))
    k = unit_dc_gain(zeros, poles) * w0 ** (zeros.size - n)
    A, B, C, D = zpk2ss(zeros / w0, poles / w0, k)
    A = np.real(A) * w0
    B = np.real(B[:, 0]) * w0
    C = np.real(C[0])
    D = float(np.real(D[0, 0]))
    Ad, G_a = _zoh(A, B, dt_s - frac * dt_s)
    _, G_b = _zoh(A, B, frac * dt_s)
    Phi = expm(A * dt_s)
    B1, B2 = G_a, Ad @ G_b
    D0, D1 = (D, 0.0) if frac == 0 else (0.0, D)
    if lead_samples > 0:                 # read the state λT into the interval (docstring)
        E_l, G_l = _zoh(A, B, lead_samples * dt_s)
        D0 = D + float(C @ G_l)
        C = C @ E_l
    return DiscreteLTI(dt_s, np.ascontiguousarray(Phi), np.ascontiguousarray(B1), np.ascontiguousarray(B2),
                       np.ascontiguousarray(C), D0, D1, d)


def _zoh(A: np.ndarray, B: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """(e^{Ah}, ∫_0^h e^{Aσ}dσ·B) by one matrix exponential of the augmented matrix."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A
    M[:n, n] = B
    E = expm(M * h)
    return E[:n, :n], E[:n, n]


class LTIOperator(StreamingOperator):
    """Streaming forward operator of a :class:`DiscreteLTI`: ``y = initial + G(u − initial)``.

    Starts at rest with input and output equal to ``initial`` (the unit of the input;
    the dynamics model uses nm). ``use_numba=False`` runs the plain-Python reference."""

    def __init__(self, sys: DiscreteLTI, initial: float = 0.0, use_numba: bool = True) -> None:
        self.sys = sys
        self.initial = finite_sample("initial", initial)
        self.use_numba = use_numba
        self.x = np.zeros(sys.Ad.shape[0])
        self.buf = np.zeros(sys.delay_samples + 2)
        self.pos = np.zeros(1, dtype=np.int64)
        self._one = np.empty(1)

    def reset(self) -> None:
        self.x[:] = 0.0
        self.buf[:] = 0.0
        self.pos[0] = 0

    def block(self, x: np.ndarray) -> np.ndarray:
        u = block_samples("input", x) - self.initial
        out = np.empty_like(u)
        s = self.sys
        kern = K.lti_block_nb if self.use_numba else K.lti_block_py
        kern(u, out, s.Ad, s.B1, s.B2, s.C, s.D0, s.D1, self.x, self.buf, self.pos)
        return out + self.initial

    def step(self, x: float) -> float:
        self._one[0] = finite_sample("input", x)
        return float(self.block(self._one)[0])


class FIROperator(StreamingOperator):
    """Streaming FIR filter ``y_k = Σ_j h_j·u_{k−j}`` whose past inputs start at ``initial``
    (a signal at rest); ``initial=None``: at rest at the first input after each
    :meth:`reset`. ``use_numba=False`` runs the plain-Python reference."""

    def __init__(self, taps: np.ndarray, initial: float | None = 0.0, use_numba: bool = True) -> None:
        self.h = np.ascontiguousarray(taps, dtype=np.float64)
        if self.h.ndim != 1 or self.h.size == 0:
            raise ModelError("taps: need a non-empty 1-D array")
        self.initial = None if initial is None else finite_sample("initial", initial)
        self.use_numba = use_numba
        self.buf = np.zeros(self.h.size)
        self.pos = np.zeros(1, dtype=np.int64)
        self._one = np.empty(1)
        self._rest = self.initial
        self.reset()

    def reset(self) -> None:
        self.buf[:] = 0.0
        self.pos[0] = 0
        self._rest = self.initial

    def block(self, x: np.ndarray) -> np.ndarray:
        u = block_samples("input", x)
        if self._rest is None:
            if u.size == 0:
                return u.copy()
            self._rest = float(u[0])
        u = u - self._rest
        out = np.empty_like(u)
        kern = K.fir_block_nb if self.use_numba else K.fir_block_py
        kern(u, out, self.h, self.buf, self.pos)
        return out + self._rest

    def step(self, x: float) -> float:
        self._one[0] = finite_sample("input", x)
        return float(self.block(self._one)[0])
