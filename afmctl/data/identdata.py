"""Measured identification data made fit for a model fit (``afmctl identify``, ``model validate``).

Real recordings are not the polite ``t,u,y`` of a simulator. This module, independent of the
model kind, checks and conditions them:

* :func:`check_units` — voltages within ±1000 V, displacement within ±1 mm; displacement that
  looks like µm (a gain below 0.5 nm/V) is refused with a hint (``--y-unit um``).
* :func:`remove_spikes` — isolated outliers of ``y`` (Hampel filter: a sample further than
  ``k`` robust standard deviations from its running median is replaced by that median).
* :func:`resample_uniform` — non-uniform time stamps → a uniform grid (median period, linear
  interpolation).
* :func:`measured_mask` — the optional column ``measured``: 0 on samples whose ``y`` was not
  measured (the holds between the pieces of ``afmctl calibrate``, interpolated); every fit
  and every held-out score leaves them out, while the models' memory runs through them.
* :func:`burn_in_index` — the first sample at which the input has passed both of its extremes;
  for rate-independent hysteresis with the wiping-out property the memory from then on no
  longer depends on the unknown state the recording started in.
* :func:`estimate_delay` — the input→output delay (whole samples) that minimises the residual of
  a fast Prandtl–Ishlinskii proxy fit.
* :func:`excitation_notes` — what the input cannot identify (Preisach interior without reversal
  curves, creep without holds, dynamics without several rates) and what to record instead.

Units: t [s], u [V], y [nm], delays [s].
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from afmctl.compensators.coverage import Coverage, turning_points

from ..errors import AfmctlError

log = logging.getLogger(__name__)

U_LIMIT_V = 1000.0        #: |u| allowed in data files [V] (no piezo amplifier drives more)
Y_LIMIT_NM = 1.0e6        #: |y| allowed in data files [nm] (1 mm)
MIN_GAIN_NM_PER_V = 0.5   #: below this gain a displacement column is taken to be in µm
MIN_MEASURED = 16         #: measured samples a record needs at the least (column ``measured``)
Y_UNITS = {"nm": 1.0, "um": 1000.0, "µm": 1000.0}


@dataclass
class Conditioned:
    """Identification data after :func:`condition`; ``fit_from`` is the burn-in index."""

    t_s: np.ndarray
    u_V: np.ndarray
    y_nm: np.ndarray
    fit_from: int = 0
    delay_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    #: the recorded piezo voltage [V] (the optional column ``v``), on the same samples; None without it
    v_V: np.ndarray | None = None
    #: True on the samples whose ``y`` was measured, False where it was not (the optional
    #: column ``measured``: 0 on the holds ``afmctl calibrate`` inserts between recorded pieces,
    #: their ``y`` interpolated); None when every sample was measured
    measured: np.ndarray | None = None

    @property
    def left_out(self) -> np.ndarray | None:
        """True on the samples not measured (left out of every fit and score), or None."""
        return None if self.measured is None else ~self.measured


def check_units(u_V: np.ndarray, y_nm: np.ndarray, where: str) -> None:
    """One-line :class:`AfmctlError` when ``u`` or ``y`` cannot be volts / nanometres."""
    umax = float(np.max(np.abs(u_V)))
    if umax > U_LIMIT_V:
        raise AfmctlError(f"{where}: column u: {umax:g} V is outside the allowed range "
                          f"−{U_LIMIT_V:g}…{U_LIMIT_V:g} V (is the column in mV?)")
    ymax = float(np.max(np.abs(y_nm)))
    if ymax > Y_LIMIT_NM:
        raise AfmctlError(f"{where}: column y: {ymax:g} nm is outside the allowed range "
                          f"−{Y_LIMIT_NM:g}…{Y_LIMIT_NM:g} nm (is the column in pm or m?)")
    du, dy = float(np.ptp(u_V)), float(np.ptp(y_nm))
    if du > 0 and 0 < dy / du < MIN_GAIN_NM_PER_V:
        raise AfmctlError(f"{where}: column y: a span of {dy:g} nm for {du:g} V ({dy / du:.3g} nm/V, allowed "
                          f"≥ {MIN_GAIN_NM_PER_V:g} nm/V) looks like µm; convert to nm or pass --y-unit um")


def remove_spikes(y_nm: np.ndarray, window: int = 7, k: float = 8.0) -> tuple[np.ndarray, int]:
    """Hampel filter: replace samples further than ``k`` robust σ from the running median
    (``window`` samples) by that median. Returns ``(y, count)``; σ is 1.4826 × the MAD of
    ``y − median`` over the whole record (so quantised, quiet data do not flag everything).
    A sample must also stand out by more than 4 local sample-to-sample steps, so the sharp
    turning points of a noise-free triangle response are not taken for spikes."""
    from scipy.ndimage import median_filter

    if y_nm.size < 3 * window:
        return y_nm.copy(), 0
    med = median_filter(y_nm, size=window, mode="nearest")
    dev = y_nm - med
    sigma = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
    if sigma <= 0:
        sigma = max(float(np.std(dev)), 1e-12)
    step = median_filter(np.abs(np.diff(y_nm, prepend=y_nm[0])), size=window, mode="nearest")
    bad = np.abs(dev) > np.maximum(k * sigma, 4.0 * step)
    out = y_nm.copy()
    out[bad] = med[bad]
    return out, int(np.count_nonzero(bad))


def resample_uniform(t_s: np.ndarray, *cols: np.ndarray, rel_tol: float = 1e-3
                     ) -> tuple[np.ndarray, list[np.ndarray], bool]:
    """Columns on a uniform grid (median period) by linear interpolation; ``changed`` is
    false (and the inputs are returned) when the samples are already uniform."""
    d = np.diff(t_s)
    dt = float(np.median(d))
    if d.size == 0 or np.max(np.abs(d - dt)) <= rel_tol * dt:
        return t_s, list(cols), False
    n = int(np.floor((t_s[-1] - t_s[0]) / dt + 1e-9)) + 1
    t = t_s[0] + dt * np.arange(n)
    return t, [np.interp(t, t_s, c) for c in cols], True


def burn_in_index(u_V: np.ndarray, tol_fraction: float = 0.002) -> int:
    """First sample at which the input has come within ``tol_fraction`` of its span to both its
    minimum and its maximum. A record that starts at its lowest voltage has passed one
    extreme at its first sample, but the state it starts in is still unknown: a scanner that
    rested there may sit on a virgin curve (every hysteron in the middle, not at negative
    saturation, which every model assumes at reset), and its first ascent differs from every
    later one. So the burn-in lasts until the input has reached its maximum too (#36: on a
    plant starting in a virgin state, the joint Preisach + creep fit explained the first
    ascent's 1.5 µm mismatch with slow creep, 8 % for 4.4 %, and left 39 nm RMS; burnt in,
    5.1 % and 1.2 nm)."""
    lo, hi = float(np.min(u_V)), float(np.max(u_V))
    tol = tol_fraction * (hi - lo)
    k_lo = int(np.argmax(u_V <= lo + tol))
    k_hi = int(np.argmax(u_V >= hi - tol))
    return max(k_lo, k_hi)


def delayed(t_s: np.ndarray, u_V: np.ndarray, delay_s: float) -> np.ndarray:
    """``u(t − delay_s)`` on the samples ``t_s`` (held at ``u[0]`` before the record)."""
    if delay_s <= 0:
        return u_V
    return np.interp(t_s - delay_s, t_s, u_V, left=float(u_V[0]))


def estimate_delay(u_V: np.ndarray, y_nm: np.ndarray, fit_from: int, max_samples: int = 200,
                   n_plays: int = 8, max_rows: int = 20000, skip: np.ndarray | None = None) -> tuple[int, float]:
    """Delay in whole samples (0…``max_samples``) minimising the RMS residual of an
    unconstrained PI fit of ``y[k]`` on the plays of ``u[k − d]``, over the samples ``skip``
    (a boolean mask) does not mark. Returns ``(d, gain)`` with ``gain`` the relative RMS
    improvement over d = 0."""
    from afmctl.compensators.pi import default_thresholds, play_matrix

    r = default_thresholds(u_V, n_plays)
    X = np.column_stack([play_matrix(u_V, r, np.full(r.size, float(u_V[0]))), np.ones(u_V.size)])
    start = fit_from + max_samples
    if u_V.size - start < 4 * n_plays:
        return 0, 0.0
    rows = np.arange(start, u_V.size)
    if skip is not None:
        rows = rows[~skip[start:]]
    if rows.size < 4 * n_plays:
        return 0, 0.0
    rows = rows[np.unique(np.linspace(0, rows.size - 1, min(max_rows, rows.size)).round().astype(np.int64))]
    rms = []
    for d in range(max_samples + 1):
        A, b = X[rows - d], y_nm[rows]
        p, *_ = np.linalg.lstsq(A, b, rcond=None)
        rms.append(float(np.sqrt(np.mean((A @ p - b) ** 2))))
    best = int(np.argmin(rms))
    return best, (rms[0] - rms[best]) / rms[0] if rms[0] > 0 else 0.0


def excitation_notes(t_s: np.ndarray, u_V: np.ndarray) -> list[str]:
    """What this input cannot identify, and what to record instead (``afmctl excite``;
    :class:`~afmctl.compensators.coverage.Coverage`)."""
    cov = Coverage.of(t_s, u_V)
    notes: list[str] = []
    if not cov.minor_loops:
        notes.append("the input reverses only near its extremes (no minor loops): the inside of the Preisach "
                     "plane is not identified (kind preisach takes its PI-like prior there, so minor loops are "
                     "predicted about as a PI model predicts them); record reversal curves: afmctl excite --kind static")
    if not cov.holds:
        notes.append("no hold after a voltage step: creep is not identified (kinds epi, creep, +creep; auto does not "
                     "try them); record holds of ≥ 1 s: afmctl excite --kind creep")
    elif not cov.long_holds:
        notes.append("no hold of ≥ 1 s after a voltage step: the slower creep lags are not identified; record holds: "
                     "afmctl excite --kind creep")
    if not cov.several_rates:
        notes.append("the input runs at one rate: rate dependence and resonance (+dynamics) are not identified; "
                     "record a chirp: afmctl excite --kind dynamics")
    elif not cov.large_fast:
        notes.append("no large fast part (triangles at 10 Hz and up over much of the range, or steps): an amplifier "
                     "lag before the hysteresis is not told from one after it and the amplifier's slew limit is not "
                     "seen; record afmctl excite --kind fast (and the piezo voltage as column v if the amplifier or "
                     "controller gives it)")
    return notes


def condition(t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, where: str, *,
              burn_in: str = "auto", delay: str = "auto", despike: bool = True,
              uniform: bool = False, dynamics_delay: bool = False, v_V: np.ndarray | None = None,
              measured: np.ndarray | None = None) -> Conditioned:
    """Units, spikes, uniform sampling, burn-in and delay of measured ``t,u,y`` (see the module
    docstring). ``burn_in``: ``auto``, ``none`` or seconds; ``delay``: ``auto`` or seconds;
    ``uniform``: resample non-uniform records (for time-dependent model kinds; interpolation
    cuts the corners of the input, so rate-independent kinds keep the samples as they are);
    ``dynamics_delay``: a dynamics stage may be fitted, which fits the delay itself
    (fractional, jointly with its poles): ``delay="auto"`` then leaves a record with fast
    parts undelayed (a whole-sample shift ahead of it would take an amplifier's lag for a
    delay, #24). ``v_V``: the recorded piezo voltage [V] (column ``v``), resampled with the
    rest; the sensor's delay is the output's, so it is shifted with the command.
    ``measured``: the column ``measured`` (1 where ``y`` was measured, 0 where it was not;
    :func:`measured_mask`); a resampled sample counts as measured when both its neighbours
    were."""
    check_units(u_V, y_nm, where)
    mask = measured_mask(measured, u_V.size, where)
    c = Conditioned(t_s, u_V, y_nm, v_V=v_V, measured=mask)
    if despike:
        c.y_nm, n = remove_spikes(y_nm)
        if n:
            c.notes.append(f"spikes: {n} sample(s) of y replaced by their running median")
    changed = False
    if uniform:
        extra = ([] if v_V is None else [v_V]) + ([] if mask is None else [mask.astype(np.float64)])
        c.t_s, cols, changed = resample_uniform(t_s, u_V, c.y_nm, *extra)
        c.u_V, c.y_nm = cols[0], cols[1]
        if v_V is not None:
            c.v_V = cols[2]
        if mask is not None:
            c.measured = cols[-1] >= 1.0 - 1e-9
    if changed:
        c.notes.append(f"sampling: non-uniform; resampled to {c.t_s.size} samples every "
                       f"{float(c.t_s[1] - c.t_s[0]):.4g} s")
    c.fit_from = _burn_in(c, burn_in, where)
    c.delay_s = _delay(c, delay, where, dynamics_delay)
    return c


def measured_mask(measured: np.ndarray | None, n: int, where: str) -> np.ndarray | None:
    """The column ``measured`` (``n`` values, each 0 or 1) as booleans; None when it is
    absent or all ones. One-line :class:`AfmctlError` for other values or when fewer than
    :data:`MIN_MEASURED` samples were measured."""
    if measured is None:
        return None
    m = np.asarray(measured, dtype=np.float64).reshape(-1)
    if m.size != n:
        raise AfmctlError(f"{where}: column measured: {m.size} values for {n} samples")
    if not np.all((m == 0.0) | (m == 1.0)):
        bad = int(np.flatnonzero((m != 0.0) & (m != 1.0))[0])
        raise AfmctlError(f"{where}: column measured: row {bad + 1} holds {m[bad]:g}; allowed 0 (not measured, "
                          "e.g. interpolated) or 1 (measured)")
    mask = m == 1.0
    if mask.all():
        return None
    if np.count_nonzero(mask) < MIN_MEASURED:
        raise AfmctlError(f"{where}: column measured: {np.count_nonzero(mask)} sample(s) measured; at least "
                          f"{MIN_MEASURED} are needed")
    return mask


def _burn_in(c: Conditioned, burn_in: str, where: str) -> int:
    if burn_in == "none":
        return 0
    if burn_in == "auto":
        k = burn_in_index(c.u_V)
        if k and _reaches_both(c.u_V[k + 1:], c.u_V):
            pass  # at least one full cycle follows the burn-in
        elif k:
            c.notes.append("burn-in: no full input cycle follows the point where the input has passed both "
                           "extremes; the record is taken to start relaxed at its first voltage")
            return 0
    else:
        s = _seconds("--burn-in", burn_in, float(c.t_s[-1] - c.t_s[0]))
        k = int(np.searchsorted(c.t_s - c.t_s[0], s))
    if k:
        c.notes.append(f"burn-in: the first {float(c.t_s[k] - c.t_s[0]):.4g} s ({k} samples, until the input "
                       "passed both extremes) only set the model's memory; fit and residuals start after it")
    return min(k, c.u_V.size - 1)


def _reaches_both(part: np.ndarray, whole: np.ndarray, tol_fraction: float = 0.002) -> bool:
    """Whether ``part`` comes within ``tol_fraction`` of the span to both extremes of ``whole``."""
    lo, hi = float(np.min(whole)), float(np.max(whole))
    tol = tol_fraction * (hi - lo)
    return bool(np.any(part <= lo + tol) and np.any(part >= hi - tol))


def _delay(c: Conditioned, delay: str, where: str, dynamics_delay: bool = False) -> float:
    dt = float(np.median(np.diff(c.t_s)))
    if delay != "auto":
        return _seconds("--delay", delay, 1.0)
    max_samples = min(200, (c.u_V.size - c.fit_from) // 20)
    skip = _near_fast_parts(c.t_s, c.u_V, max_samples)
    if skip is not None and dynamics_delay:
        c.notes.append("delay: the record has fast parts; a dynamics stage fits the delay there with its poles "
                       "(a chain without one has none; --delay S sets one)")
        return 0.0
    d, gain = estimate_delay(c.u_V, c.y_nm, c.fit_from, max_samples=max_samples, skip=skip)
    if d == 0 or gain < 0.05:  # creep also looks like a small lag; a sensor delay stands out
        return 0.0
    c.notes.append(f"delay: the output lags the input by {d} sample(s) = {d * dt:.4g} s "
                   f"(PI residual {100 * gain:.3g} % lower); stored as delay_s")
    return d * dt


def _near_fast_parts(t_s: np.ndarray, u_V: np.ndarray, margin: int) -> np.ndarray | None:
    """Samples in or up to ``margin`` samples after a part with fast content
    (:func:`~afmctl.compensators.dynamics_identify.dynamics_parts`), or None when there is none:
    there an amplifier's lag or a structural mode looks like a delay of many samples, which
    the dynamics stage fits itself (fractional, jointly with its poles; #24). A sensor's delay
    shows in the slow parts too."""
    from afmctl.compensators.dynamics_identify import dynamics_parts, is_uniform, parts_mask

    if not is_uniform(t_s):              # the dynamics stage needs uniform samples too
        return None
    parts = dynamics_parts(u_V, t_s)
    return parts_mask(u_V.size, parts, margin) if parts else None


def _seconds(flag: str, text: str, hi: float) -> float:
    try:
        v = float(text)
    except ValueError:
        raise AfmctlError(f"{flag}: {text!r} is not a number of seconds or 'auto'") from None
    if not (np.isfinite(v) and 0 <= v <= hi):
        raise AfmctlError(f"{flag}: {text} s is outside the allowed range 0…{hi:g} s")
    return v
