"""Frequency-domain tools of the learning step (:mod:`afmctl.compensators.learning`).

Every signal of one iteration lives on one FFT grid (:class:`Grid`): a periodic table
(played cyclically, as a wave generator does) on its own length — then the bins are exactly
its harmonics — and any other record zero-padded to at least twice its length, so that a
two-sided (non-causal) filter does not wrap around.

* :func:`smoothed_ratio` — a frequency response from two spectra, ``Σ A·B* / Σ |B|²`` over
  a window of neighbouring bins (the H1 estimator of Welch's method applied along
  frequency, Pintelon & Schoukens, *System Identification*, 2nd ed., §2.6), weighted by
  the excitation so that the harmonics that carry the signal dominate; bins the input does
  not excite are marked unreliable.
* :func:`zero_phase_q` — the Q-filter: a real (zero-phase) Butterworth magnitude.
* :func:`interpolate_unreliable` — fills unreliable bins from the reliable ones
  (log-magnitude and unwrapped phase, linear in frequency).
* :func:`estimate_lag_samples` — the lag of a recording behind a reference, from the peak
  of their cross-correlation (differenced signals, parabolic sub-sample peak).

Spectra are of *differenced* signals (``Δx[n] = x[n] − x[n−1]``): a record that starts and
ends at rest then has a difference that is zero at both ends, so circular and linear
convolution agree and a DC offset (a hysteresis loop's) drops out; the ratio of two
differenced spectra is the ratio of the signals' spectra.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

#: a bin is reliable when its windowed excitation is at least this fraction of the peak
RELIABLE_FRACTION = 1e-5
#: a measured bin's window holds at least this many times the noise's power (the noise's
#: amplitude a quarter of the measured one's at most)
MIN_SNR = 16.0
#: half-width of the smoothing window, a fraction of the frequency
REL_WIDTH = 0.03


@dataclass(frozen=True)
class Grid:
    """The FFT grid of one iteration: ``n`` samples at ``dt_s`` [s] padded to ``n_fft``."""

    n: int
    dt_s: float
    n_fft: int
    periodic: bool

    @classmethod
    def for_record(cls, n: int, dt_s: float, periodic: bool) -> "Grid":
        """The grid for ``n`` samples: the record's own length when ``periodic``, else a
        fast FFT length of at least ``2 n``."""
        return cls(n, dt_s, n if periodic else sfft.next_fast_len(2 * n, real=True), periodic)

    @property
    def f_Hz(self) -> np.ndarray:
        """Frequencies of the rfft bins [Hz]."""
        return np.fft.rfftfreq(self.n_fft, self.dt_s)

    def spectrum(self, x: np.ndarray) -> np.ndarray:
        """rfft of ``x`` (zero-padded to ``n_fft``)."""
        return sfft.rfft(np.asarray(x, dtype=float), self.n_fft)

    def diff_spectrum(self, x: np.ndarray) -> np.ndarray:
        """rfft of the differenced signal (circular difference for a periodic table)."""
        x = np.asarray(x, dtype=float)
        d = x - np.roll(x, 1) if self.periodic else np.diff(x, prepend=x[0])
        return self.spectrum(d)

    def diff_noise(self, noise_psd_nm2: np.ndarray, plays: int = 1) -> np.ndarray:
        """The expected ``|N(f)|²`` of :meth:`diff_spectrum` of the noise of ``plays``
        recordings (summed), each of ``n`` samples with the power ``noise_psd_nm2`` per
        sample at each bin's frequency."""
        w = 2.0 * np.sin(np.pi * self.f_Hz * self.dt_s)
        return plays * self.n * np.asarray(noise_psd_nm2, dtype=float) * w * w

    def apply(self, response: np.ndarray, x: np.ndarray, smooth_ends: bool = False) -> np.ndarray:
        """``x`` filtered by the frequency response ``response`` (one value per bin): the
        first ``n`` samples of the inverse FFT of ``response · X``. ``smooth_ends``: a
        record that is not periodic continues into its padding along raised cosines, from
        its last value down to 0 and from 0 up to its first (:meth:`padded`), instead of
        jumping to 0: a jump holds every frequency, and a filter that amplifies high ones
        (a scanner's inverse) would answer it with a spike at the record's ends."""
        xx = self.padded(x) if smooth_ends and not self.periodic else np.asarray(x, dtype=float)
        return sfft.irfft(response * self.spectrum(xx), self.n_fft)[: self.n]

    def padded(self, x: np.ndarray) -> np.ndarray:
        """``x`` on the whole grid (``n_fft`` samples): the record, then half the padding
        falling from its last value to 0 and half rising from 0 to its first value (the
        padding wraps around to the record's start), each along a raised cosine."""
        x = np.asarray(x, dtype=float)
        out = np.zeros(self.n_fft)
        out[: self.n] = x
        k = (self.n_fft - self.n) // 2
        if k > 0 and x.size:
            fall = 0.5 + 0.5 * np.cos(np.pi * np.arange(1, k + 1) / (k + 1))
            out[self.n: self.n + k] = x[-1] * fall
            out[self.n_fft - k:] = x[0] * fall[::-1]
        return out


def smoothed_ratio(num: np.ndarray, den: np.ndarray, f_Hz: np.ndarray, rel_width: float = REL_WIDTH,
                   min_bins: int = 2, threshold: float = RELIABLE_FRACTION,
                   noise_power: np.ndarray | None = None, min_snr: float = MIN_SNR) -> tuple[np.ndarray, np.ndarray]:
    """``(ratio, reliable)``: ``Σ num·den* / Σ |den|²`` over the bins within
    ``max(min_bins, rel_width · k)`` of bin ``k`` (wider at high frequency, like a
    fractional-octave smoother), and whether the window's ``Σ |den|²`` is at least
    ``threshold`` (default :data:`RELIABLE_FRACTION`) of its largest value and, with
    ``noise_power`` (the noise's expected ``|N(f)|²`` in ``num``, per bin), the window's
    ``Σ |num|²`` at least ``min_snr`` (default :data:`MIN_SNR`) times the noise's: a
    measurement, not noise.
    Unreliable bins hold 0."""
    k = np.arange(f_Hz.size)
    half = np.maximum(min_bins, np.floor(rel_width * k)).astype(int)
    lo = np.clip(k - half, 0, f_Hz.size)
    hi = np.clip(k + half + 1, 0, f_Hz.size)
    cross = np.concatenate([[0.0], np.cumsum(num * np.conj(den))])
    power = np.concatenate([[0.0], np.cumsum(np.abs(den) ** 2)])
    p = power[hi] - power[lo]
    reliable = p >= threshold * float(np.max(p)) if p.size and np.max(p) > 0 else np.zeros(p.size, bool)
    if noise_power is not None:
        out = np.concatenate([[0.0], np.cumsum(np.abs(num) ** 2)])
        noise = np.concatenate([[0.0], np.cumsum(noise_power)])
        reliable &= (out[hi] - out[lo]) >= min_snr * (noise[hi] - noise[lo])
    ratio = np.zeros(f_Hz.size, dtype=complex)
    ratio[reliable] = (cross[hi] - cross[lo])[reliable] / p[reliable]
    return ratio, reliable


def interpolate_unreliable(values: np.ndarray, reliable: np.ndarray, fill: complex | None = None) -> np.ndarray:
    """``values`` with the unreliable bins filled by linear interpolation of the reliable
    ones' log-magnitude and unwrapped phase; beyond the last reliable bin the last value is
    held (or ``fill`` where given). No reliable bin: all ``fill`` (or 1)."""
    out = np.array(values, dtype=complex)
    idx = np.flatnonzero(reliable & (np.abs(out) > 0))
    if idx.size == 0:
        out[:] = 1.0 if fill is None else fill
        return out
    k = np.arange(out.size)
    mag = np.interp(k, idx, np.log(np.abs(out[idx])))
    ph = np.interp(k, idx, np.unwrap(np.angle(out[idx])))
    filled = np.exp(mag + 1j * ph)
    if fill is not None:
        filled[k > idx[-1]] = fill
        filled[k < idx[0]] = fill
    out[~reliable] = filled[~reliable]
    return out


def zero_phase_q(f_Hz: np.ndarray, cutoff_Hz: float, order: int = 4) -> np.ndarray:
    """The Q-filter's magnitude ``1/√(1 + (f/f_c)^{2·order})``, real (zero phase): it
    bounds the learning to where the learning filter is trusted (Bristow, Tharayil &
    Alleyne, IEEE Control Systems Mag. 26(3), 2006, §"Q-filter")."""
    if not math.isfinite(cutoff_Hz):
        return np.ones_like(f_Hz)
    return 1.0 / np.sqrt(1.0 + (np.asarray(f_Hz) / max(cutoff_Hz, 1e-12)) ** (2 * order))


def estimate_lag_samples(reference: np.ndarray, recording: np.ndarray, max_lag: int) -> float:
    """How many samples ``recording`` lags ``reference`` (negative: leads), within
    ``±max_lag``: the peak of the circular cross-correlation of the differenced signals,
    refined by a parabola through the peak and its neighbours. 0 when either is constant."""
    a = np.diff(np.asarray(reference, dtype=float))
    b = np.diff(np.asarray(recording, dtype=float))
    if a.size < 3 or not np.any(a) or not np.any(b):
        return 0.0
    n = sfft.next_fast_len(2 * a.size, real=True)
    xc = sfft.irfft(np.conj(sfft.rfft(a, n)) * sfft.rfft(b, n), n)
    m = int(max(1, min(max_lag, a.size - 2)))
    lags = np.concatenate([np.arange(0, m + 1), np.arange(-m, 0)])
    vals = np.concatenate([xc[: m + 1], xc[-m:]])
    j = int(np.argmax(vals))
    lag = float(lags[j])
    left, right = xc[(lags[j] - 1) % n], xc[(lags[j] + 1) % n]
    denom = left - 2 * vals[j] + right
    if denom < 0:
        lag += 0.5 * (left - right) / denom
    return lag
