"""Stable inversion of linear scanner dynamics: a regularised frequency-domain inverse,
as a causal FIR with preview (fixed latency) and as a non-causal offline filter.

For a discretised plant ``G(e^{jω})`` (delay and non-minimum-phase zeros included) the
inverse filter is the Tikhonov-regularised, band-limited ratio (Zou & Devasia 2004,
"preview-based optimal inversion", eq. 9 with a frequency weight; Croft, Shed & Devasia
2001, stable inversion)::

    H(ω) = F(ω) · conj(G(ω)) / (|G(ω)|² + λ²)

``F`` is a zero-phase low-pass (Butterworth magnitude of order 4 at ``bandwidth_Hz``) so
that the inverse does not amplify what the target does not contain, ``λ`` bounds the gain
near zeros on the unit circle. Its impulse response ``h[n]`` is two-sided: the part at
``n < 0`` is the preview (the plant's delay and its unstable-inverse part run backwards in
time). Truncated to ``−L ≤ n ≤ M`` and delayed by ``L`` samples it is a causal FIR whose
output lags the target by ``L`` samples — the latency a controller reports. Offline, the
whole two-sided filter is applied to the known trajectory (no latency).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .base import ModelError
from .lti import DiscreteLTI, FIROperator

log = logging.getLogger(__name__)

#: energy left outside the automatic tap window, relative to the whole filter
TAIL_ENERGY = 1e-10
#: Butterworth order of the band limit F
BAND_ORDER = 4


@dataclass(frozen=True)
class InverseTaps:
    """Two-sided inverse filter: ``taps[j]`` is ``h[j − preview]`` (``preview`` samples of
    look-ahead), Σ taps = 1 (unit DC gain)."""

    taps: np.ndarray
    preview: int
    bandwidth_Hz: float
    regularisation: float


def inverse_response(sys: DiscreteLTI, f_Hz: np.ndarray, bandwidth_Hz: float, regularisation: float) -> np.ndarray:
    """``H(f)`` of the module docstring at ``f_Hz``."""
    g = sys.frequency_response(f_Hz)
    band = 1.0 / np.sqrt(1.0 + (np.asarray(f_Hz) / bandwidth_Hz) ** (2 * BAND_ORDER))
    return band * np.conj(g) / (np.abs(g) ** 2 + regularisation**2)


def inverse_taps(sys: DiscreteLTI, bandwidth_Hz: float, regularisation: float = 1e-3,
                 preview: int | None = None, max_taps: int = 1 << 16) -> InverseTaps:
    """Impulse response of :func:`inverse_response`, truncated to a window holding all but
    :data:`TAIL_ENERGY` of its energy (or, with ``preview`` samples given, to that many
    samples of look-ahead), tapered at the ends and rescaled to unit DC gain."""
    fs = 1.0 / sys.dt_s
    if not (math.isfinite(bandwidth_Hz) and 0 < bandwidth_Hz):
        raise ModelError(f"bandwidth_Hz: {bandwidth_Hz!r}; need > 0 Hz")
    if not (math.isfinite(regularisation) and regularisation >= 0):
        raise ModelError(f"regularisation: {regularisation!r}; need ≥ 0")
    n_fft = 1 << 12
    while True:
        f = np.fft.rfftfreq(n_fft, sys.dt_s)
        h = np.fft.irfft(inverse_response(sys, f, bandwidth_Hz, regularisation), n_fft)
        h = np.roll(h, n_fft // 2)  # index n_fft//2 is n = 0
        e = np.cumsum(h**2)
        total = e[-1]
        edge = e[n_fft // 16] + (total - e[-n_fft // 16])
        if edge <= TAIL_ENERGY * total or n_fft >= 4 * max_taps:
            break
        n_fft *= 2
    c = n_fft // 2
    lo = int(np.searchsorted(e, 0.5 * TAIL_ENERGY * total))
    hi = int(np.searchsorted(e, (1 - 0.5 * TAIL_ENERGY) * total))
    L = c - lo if preview is None else int(preview)
    M = max(hi - c, 1)
    if L < 0 or L + M + 1 > max_taps:
        raise ModelError(f"preview: {L} samples; allowed 0 … {max_taps - M - 1} at dt {sys.dt_s:g} s")
    taps = h[c - L: c + M + 1].copy() if L <= c else np.concatenate([np.zeros(L - c), h[: c + M + 1]])
    taps *= _taper(taps.size, L)
    taps /= taps.sum()
    if preview is not None and c - lo > L:
        lost = float(np.sum(h[lo:c - L] ** 2) / total)
        log.info("preview of %d samples leaves out %.3g of the inverse's energy", L, lost)
    return InverseTaps(taps, L, float(min(bandwidth_Hz, fs / 2)), float(regularisation))


def _taper(n: int, centre: int) -> np.ndarray:
    """A window that is 1 around ``centre`` and falls to 0 at both ends over their outer
    eighth (cosine), so truncation does not leave a step."""
    w = np.ones(n)
    for side in (np.arange(centre), np.arange(n - 1, centre, -1)):
        m = max(1, side.size // 8)
        idx = side[:m]
        w[idx] = 0.5 - 0.5 * np.cos(np.pi * (np.arange(m) + 0.5) / m)
    return w


class PreviewInverse(FIROperator):
    """Causal preview inverse: reads the target ``latency_samples`` ahead, i.e. its output at
    sample k is the input that the plant needs at sample k − latency_samples. Input and
    output in the unit of the model (nm), at rest at ``initial`` (None: at the first target
    after each reset)."""

    def __init__(self, taps: InverseTaps, initial: float | None = 0.0, use_numba: bool = True) -> None:
        super().__init__(taps.taps, initial, use_numba)
        self.latency_samples = int(taps.preview)
        self.bandwidth_Hz = taps.bandwidth_Hz
        self.regularisation = taps.regularisation


def apply_offline(taps: InverseTaps, y: np.ndarray) -> np.ndarray:
    """The non-causal inverse over a whole trajectory ``y`` (at rest before and after:
    the ends are held). Same length as ``y``, no latency."""
    from scipy.signal import oaconvolve

    L = taps.preview
    M = taps.taps.size - 1 - L
    ypad = np.concatenate([np.full(M, y[0]), y, np.full(L, y[-1])])
    return oaconvolve(ypad, taps.taps, mode="valid")
