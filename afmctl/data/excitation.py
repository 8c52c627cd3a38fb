"""Excitation signals a user plays to identify a scanner (``afmctl excite``).

Each generator returns the command voltage ``u_V`` sampled at ``rate_Hz`` and starting at
``u_min_V`` (a scanner at rest at its lowest voltage):

* :func:`static` — the major loop, then first-order reversal curves: descending branches
  from several turning points below ``u_max_V`` and ascending ones from several above
  ``u_min_V``. Without reversal curves the inside of the Preisach plane cannot be identified
  (Mayergoyz, *Mathematical Models of Hysteresis*, §1.3: the Everett function is the set of
  first-order reversal curves).
* :func:`creep` — a staircase up and down with dwells: creep shows only while the input
  rests.
* :func:`dynamics` — a small-signal random-phase periodic multisine around mid-range, all
  frequency bins of its period from ``f_min_Hz`` to ``f_max_Hz`` (flat up to the geometric
  mean of the two, falling as 1/f above it, so that the rate of change stays moderate),
  repeated so Welch's method can average; its amplitude keeps the rate of change within
  half of ``slew_V_per_s``.
* :func:`fast` — large triangles (10–90 % of the range) at rising rates, 2 Hz up to
  100 Hz (or what the sample rate and the slew limit allow), then large steps between 30 and
  70 % of the range (a jump, or a ramp at ``slew_V_per_s``). A small-signal multisine sees
  the amplifier and the scanner's dynamics only in series (``G_amp·G_mech`` times the
  hysteresis's local slope); large fast triangles tell a lag *before* the hysteresis (it
  rounds the voltage the loop turns on) from one *after* it (it rounds the loop's output),
  and show how the loops change with the scan rate (fast creep, rate-dependent hysteresis);
  the steps drive the amplifier into its slew (current) limit, which no small signal
  reaches (#36).
* :func:`concatenate` — segments joined by holds of ``gap_s`` (settling), each joined to the
  next by a ramp at the sweep speed.

Ramps run at ``sweep_V_per_s`` (a full-range sweep per second by default): slow enough
that the scanner's dynamics do not distort the static curves.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import AfmctlError


@dataclass(frozen=True)
class ExcitationSpec:
    """Common settings; all voltages in V, times in s, rates in Hz."""

    u_min_V: float
    u_max_V: float
    rate_Hz: float
    sweep_V_per_s: float | None = None
    slew_V_per_s: float | None = None
    dwell_s: float = 2.0
    gap_s: float = 1.0
    amplitude_frac: float = 0.02
    f_min_Hz: float = 5.0
    f_max_Hz: float | None = None
    periods: int = 8
    seed: int = 0

    @property
    def span_V(self) -> float:
        return self.u_max_V - self.u_min_V

    @property
    def sweep(self) -> float:
        """Ramp speed [V/s]: ``sweep_V_per_s`` or the span per second, within the slew limit."""
        v = self.sweep_V_per_s if self.sweep_V_per_s is not None else self.span_V
        return min(v, 0.5 * self.slew_V_per_s) if self.slew_V_per_s else v


def check_spec(spec: ExcitationSpec) -> None:
    """One :class:`AfmctlError` line naming the option and the allowed range."""
    if not (math.isfinite(spec.u_min_V) and math.isfinite(spec.u_max_V) and spec.u_max_V > spec.u_min_V):
        raise AfmctlError(f"--u-min-V/--u-max-V: {spec.u_min_V} … {spec.u_max_V}; need finite LO < HI (V)")
    if not (math.isfinite(spec.rate_Hz) and 1.0 <= spec.rate_Hz <= 10e6):
        raise AfmctlError(f"--rate-Hz: {spec.rate_Hz}; allowed 1 … 1e7 Hz")
    for name, v in (("--sweep-V-per-s", spec.sweep_V_per_s), ("--slew-V-per-s", spec.slew_V_per_s)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise AfmctlError(f"{name}: {v}; need a finite rate > 0 V/s")
    if not (math.isfinite(spec.dwell_s) and 0 < spec.dwell_s <= 3600):
        raise AfmctlError(f"--dwell-s: {spec.dwell_s}; allowed > 0 … 3600 s")
    if not (math.isfinite(spec.gap_s) and 0 <= spec.gap_s <= 3600):
        raise AfmctlError(f"--gap-s: {spec.gap_s}; allowed 0 … 3600 s")
    if not (math.isfinite(spec.amplitude_frac) and 0 < spec.amplitude_frac <= 0.5):
        raise AfmctlError(f"--amplitude-pct: {100 * spec.amplitude_frac:g}; allowed > 0 … 50 % of the range")
    f_hi = spec.f_max_Hz if spec.f_max_Hz is not None else 0.4 * spec.rate_Hz
    if not (math.isfinite(spec.f_min_Hz) and 0 < spec.f_min_Hz < f_hi <= 0.5 * spec.rate_Hz):
        raise AfmctlError(f"--f-min-Hz/--f-max-Hz: {spec.f_min_Hz:g} … {f_hi:g} Hz; need 0 < f_min < f_max ≤ "
                          f"half the rate ({0.5 * spec.rate_Hz:g} Hz)")
    if not 1 <= spec.periods <= 1000:
        raise AfmctlError(f"--periods: {spec.periods}; allowed 1 … 1000")


def ramp(u0: float, u1: float, spec: ExcitationSpec) -> np.ndarray:
    """From ``u0`` (excluded) to ``u1`` (included) at the sweep speed."""
    n = max(1, int(math.ceil(abs(u1 - u0) / spec.sweep * spec.rate_Hz)))
    return u0 + (u1 - u0) * np.arange(1, n + 1) / n


def hold(u: float, duration_s: float, spec: ExcitationSpec) -> np.ndarray:
    return np.full(int(round(duration_s * spec.rate_Hz)), float(u))


def through(points: list[float], spec: ExcitationSpec, dwell_s: float = 0.0) -> np.ndarray:
    """Ramps through ``points`` (the first is the start, excluded), dwelling at each."""
    parts = []
    for a, b in zip(points[:-1], points[1:]):
        parts.append(ramp(a, b, spec))
        if dwell_s:
            parts.append(hold(b, dwell_s, spec))
    return np.concatenate(parts) if parts else np.zeros(0)


def static(spec: ExcitationSpec, n_reversals: int = 12) -> np.ndarray:
    """Major loop, then descending and ascending first-order reversal curves."""
    lo, hi = spec.u_min_V, spec.u_max_V
    pts = [lo, hi, lo]
    for k in range(1, n_reversals + 1):  # descending FORCs from turning points α_k
        pts += [lo + spec.span_V * k / (n_reversals + 1), lo]
    pts += [hi]
    for k in range(n_reversals, 0, -1):  # ascending FORCs from turning points β_k = α_{k−1}
        # (on the same levels as the descending ones: measured better in the speed ladder
        # than levels half-way between them, 0.68 vs 1.03 % at 1 line/s)
        pts += [lo + spec.span_V * (k - 1) / (n_reversals + 1), hi]
    pts += [lo]
    return np.concatenate([[lo], through(pts, spec)])


def creep(spec: ExcitationSpec, n_levels: int = 4) -> np.ndarray:
    """Staircase lo → hi → lo in ``n_levels`` steps each way, dwelling ``dwell_s`` at each."""
    lo = spec.u_min_V
    up = [lo + spec.span_V * k / n_levels for k in range(n_levels + 1)]
    pts = up + up[-2::-1]
    fast = ExcitationSpec(**{**spec.__dict__, "sweep_V_per_s": spec.sweep * 10})
    return np.concatenate([[lo], through(pts, fast, spec.dwell_s)])


def multisine(spec: ExcitationSpec) -> np.ndarray:
    """Random-phase multisine, zero mean, peak ``amplitude_frac``·span, slew-limited,
    ``periods`` periods plus one leading period (transient)."""
    fs = spec.rate_Hz
    f_hi = spec.f_max_Hz if spec.f_max_Hz is not None else 0.4 * fs
    n = 1 << max(8, int(math.ceil(math.log2(fs / spec.f_min_Hz))))
    k = np.arange(1, n // 2)
    f = k * fs / n
    lines = k[(f >= spec.f_min_Hz) & (f <= f_hi)]
    if lines.size < 8:
        raise AfmctlError(f"--f-min-Hz/--f-max-Hz: only {lines.size} frequency lines; widen the band")
    rng = np.random.default_rng(spec.seed)
    spec_c = np.zeros(n // 2 + 1, dtype=complex)
    f_corner = math.sqrt(spec.f_min_Hz * f_hi)  # amplitude ∝ 1/f above: bounded slew, rich low band
    spec_c[lines] = np.exp(2j * math.pi * rng.random(lines.size)) / np.maximum(1.0, f[lines - 1] / f_corner)
    x = np.fft.irfft(spec_c, n)
    x *= spec.amplitude_frac * spec.span_V / np.max(np.abs(x))
    if spec.slew_V_per_s:
        rate = np.max(np.abs(np.diff(np.concatenate([x, x[:1]])))) * fs
        if rate > 0.5 * spec.slew_V_per_s:
            x *= 0.5 * spec.slew_V_per_s / rate
    return np.tile(x, spec.periods + 1)


def dynamics(spec: ExcitationSpec) -> np.ndarray:
    """Ramp to mid-range, settle ``gap_s``, then the multisine around mid-range."""
    mid = 0.5 * (spec.u_min_V + spec.u_max_V)
    lo = spec.u_min_V
    return np.concatenate([[lo], ramp(lo, mid, spec), hold(mid, spec.gap_s, spec), mid + multisine(spec),
                           hold(mid, spec.gap_s, spec), ramp(mid, lo, spec)])


#: :func:`fast`: triangle rates [Hz] (those the sample rate and slew limit allow), and at
#: least this many cycles and seconds at each
FAST_RATES_HZ: tuple[float, ...] = (2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
FAST_CYCLES, FAST_MIN_S = 3, 0.4
#: :func:`fast`: step levels (fractions of the range), steps each way, and the hold at each [s]
STEP_LEVELS, STEP_COUNT, STEP_HOLD_S = (0.3, 0.7), 4, 0.02


def fast(spec: ExcitationSpec) -> np.ndarray:
    """Triangles between 10 and 90 % of the range at :data:`FAST_RATES_HZ` (each rate at least
    :data:`FAST_CYCLES` cycles and :data:`FAST_MIN_S`), up to the rate with 100 samples per
    cycle and the one whose ramps stay within half of ``slew_V_per_s``; then
    :data:`STEP_COUNT` steps up and down between :data:`STEP_LEVELS` of the range, held
    :data:`STEP_HOLD_S` each (module docstring). Starts at ``u_min_V``."""
    lo, hi = spec.u_min_V + 0.1 * spec.span_V, spec.u_min_V + 0.9 * spec.span_V
    top = spec.rate_Hz / 100.0
    if spec.slew_V_per_s:
        top = min(top, 0.5 * spec.slew_V_per_s / (2.0 * (hi - lo)))
    parts = [np.array([spec.u_min_V]), ramp(spec.u_min_V, lo, spec)]
    for f in (f for f in FAST_RATES_HZ if f <= top):
        n = int(round(max(FAST_CYCLES / f, FAST_MIN_S) * f)) * int(round(spec.rate_Hz / f))
        ph = (np.arange(1, n + 1) / spec.rate_Hz * f) % 1.0
        parts.append(lo + (hi - lo) * (1.0 - np.abs(2.0 * ph - 1.0)))
    a, b = (spec.u_min_V + x * spec.span_V for x in STEP_LEVELS)
    parts.append(ramp(lo, a, spec))
    hold_n = max(1, int(round(STEP_HOLD_S * spec.rate_Hz)))
    edge = ExcitationSpec(**{**spec.__dict__, "sweep_V_per_s": spec.slew_V_per_s or math.inf})
    for level, prev in [(b, a), (a, b)] * STEP_COUNT:
        parts += [np.full(hold_n, prev), ramp(prev, level, edge)]
    parts += [np.full(hold_n, a), ramp(a, spec.u_min_V, spec)]
    return np.concatenate(parts)


def concatenate(parts: list[np.ndarray], spec: ExcitationSpec) -> np.ndarray:
    """Segments joined by holds of ``gap_s`` (and ramps where their ends differ)."""
    out = [parts[0]]
    for p in parts[1:]:
        out.append(hold(out[-1][-1], spec.gap_s, spec))
        if p[0] != out[-1][-1]:
            out.append(ramp(out[-1][-1], p[0], spec))
        out.append(p)
    return np.concatenate(out)


KINDS = ("static", "creep", "dynamics", "fast", "all")


def excitation(kind: str, spec: ExcitationSpec) -> np.ndarray:
    """The voltage sequence of ``kind`` (one of :data:`KINDS`), within [u_min_V, u_max_V]."""
    check_spec(spec)
    makers = {"static": static, "creep": creep, "dynamics": dynamics, "fast": fast}
    if kind == "all":
        u = concatenate([makers[k](spec) for k in ("static", "creep", "dynamics", "fast")], spec)
    elif kind in makers:
        u = makers[kind](spec)
    else:
        raise AfmctlError(f"--kind: {kind!r}; allowed: {', '.join(KINDS)}")
    return np.clip(u, spec.u_min_V, spec.u_max_V)
