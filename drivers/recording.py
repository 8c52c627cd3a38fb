"""What a device's data recorder hands back, in one shape for every backend (and for a
motion measured by an external sensor, read from a file by ``afmctl.data.motion_files``).

Alignment with the device-timed wave output (the record trigger is the wave start):
``t_s[k] = k * period_s`` counts from the device tick at which wave table point 0 is
output. ``u_V[axis][k]`` is the output voltage in force at that tick (with the recorder
and the wave at the same rate: table point k); ``y_nm[axis][k]`` is the position sensor
read at that tick, i.e. the response to the points output before it (a causal offset of
at least one device tick, plus the sensor's own delay and bandwidth).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

#: what a recorder can record per axis: the measured position [nm], the output voltage [V]
#: (the command the device outputs), the piezo voltage [V] (what reaches the piezo after
#: the amplifier stage's bandwidth and slew: the NV200's piezo-voltage source, PI's record
#: option 7, the CAN amplifier's monitor), where the device has it
SIGNALS = ("y_nm", "u_V", "v_V")


@dataclass(frozen=True)
class RecorderSetup:
    """An armed recording: ``points`` per signal and axis, one every ``divider`` ticks of
    the device's recorder clock ``clock_s`` [s] (``period_s = divider * clock_s``)."""

    axes: tuple[str, ...]
    signals: tuple[str, ...]
    points: int
    divider: int
    clock_s: float
    #: backend-specific bookkeeping (record tables, channels, ...)
    extra: Mapping[str, object] = field(default_factory=dict)

    @property
    def period_s(self) -> float:
        return self.divider * self.clock_s


@dataclass(frozen=True)
class Recording:
    """A recorded motion: ``t_s`` (N,) [s] from the record trigger (the wave start),
    per axis ``y_nm`` (N,) measured position [nm], ``u_V`` (N,) output voltage [V] and
    ``v_V`` (N,) piezo voltage [V] (each only for the signals recorded), ``period_s`` [s],
    and where it came from
    (``source``: e.g. ``"gcs DRR?"``, ``"nv200 recoutf"``, ``"can REC_DATA"``, ``"can REC_DATA_FD"``,
    ``"file motion.csv"``)."""

    t_s: np.ndarray
    y_nm: Mapping[str, np.ndarray]
    u_V: Mapping[str, np.ndarray]
    period_s: float
    source: str
    v_V: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.t_s)
        for name, group in (("y_nm", self.y_nm), ("u_V", self.u_V), ("v_V", self.v_V)):
            for axis, arr in group.items():
                if len(arr) != n:
                    raise ValueError(f"recording {self.source}: {name}[{axis}] has {len(arr)} points, t_s has {n}")

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys([*self.y_nm, *self.u_V, *self.v_V]))

    def __len__(self) -> int:
        return len(self.t_s)


def check_axes_signals(axes: Sequence[str], signals: Sequence[str],
                       known_axes: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The axes and signals of a recorder request as tuples; ValueError names the allowed ones."""
    ax = tuple(axes)
    if not ax or any(a not in known_axes for a in ax) or len(set(ax)) != len(ax):
        raise ValueError(f"recorder axes {list(ax)}: give one or more of {', '.join(known_axes)} (each once)")
    sig = tuple(signals)
    if not sig or any(s not in SIGNALS for s in sig) or len(set(sig)) != len(sig):
        raise ValueError(f"recorder signals {list(sig)}: give one or more of {', '.join(SIGNALS)}")
    return ax, sig


def check_points(points: int, divider: int, *, capacity: int, name: str) -> None:
    """ValueError naming the range when ``points`` or ``divider`` is outside it."""
    if not (isinstance(points, int) and 1 <= points <= capacity):
        raise ValueError(f"recorder points {points!r}: {name} records 1..{capacity} points per signal")
    if not (isinstance(divider, int) and 1 <= divider <= 2**31 - 1):
        raise ValueError(f"recorder divider {divider!r}: a whole number of clock ticks >= 1")


def joined_recording(parts: Sequence[Recording]) -> Recording:
    """Consecutive parts of one recording (read while it was taken:
    :meth:`~afmctl.drivers.base.Amplifier.read_recorded`) as one, its ``t_s`` from the first
    part's first point."""
    if not parts:
        raise ValueError("joined_recording: no parts")
    first = parts[0]

    def cat(name: str) -> dict[str, np.ndarray]:
        return {a: np.concatenate([np.asarray(getattr(p, name)[a], dtype=np.float64) for p in parts])
                for a in getattr(first, name)}

    n = sum(len(p) for p in parts)
    return Recording(float(first.t_s[0]) + time_axis(n, first.period_s) if n else time_axis(0, first.period_s),
                     cat("y_nm"), cat("u_V"), first.period_s, first.source, cat("v_V"))


def time_axis(n: int, period_s: float) -> np.ndarray:
    """``k * period_s`` for k < n [s]."""
    return np.arange(n, dtype=np.float64) * float(period_s)


class RecordingMismatch(ValueError):
    """A recording that does not match the table that was played (length, trigger, values):
    not to be learned from."""


def align_to_table(rec: Recording, tables_V: Mapping[str, Sequence[float]], *, cycle: int = 0,
                   tol_V: float = 0.005) -> Recording:
    """The part of ``rec`` that recorded cycle ``cycle`` (0-based) of the wave ``tables_V``
    (per axis [V], played at the recording's rate: one recorded point per table point),
    checked: the recording holds the whole cycle, and for every axis whose output voltage was
    recorded it equals the table within ``tol_V`` (the device's output resolution). The
    result's ``t_s`` counts from that cycle's first point; ``y_nm[k]`` is the sensor at the
    tick of table point k (the response to the points before it, see the module notes).

    Raises :class:`RecordingMismatch` (a ``ValueError``) naming what differs: too few points,
    or the voltage off the table — then with the shift (in points, within ±half a table)
    that would match it, when one does: a trigger offset."""
    lengths = {len(np.asarray(t)) for t in tables_V.values()}
    if len(lengths) != 1 or 0 in lengths:
        raise RecordingMismatch("tables_V: give one non-empty table per axis, all of one length")
    n = lengths.pop()
    first, last = cycle * n, (cycle + 1) * n
    if cycle < 0 or len(rec) < last:
        raise RecordingMismatch(f"recording {rec.source}: {len(rec)} points, cycle {cycle} of a {n}-point table "
                                f"needs {last}")
    for axis, table in tables_V.items():
        if axis not in rec.u_V:
            continue
        want = np.asarray(table, dtype=np.float64)
        got = np.asarray(rec.u_V[axis][first:last], dtype=np.float64)
        err = np.abs(got - want)
        if err.max() > tol_V:
            k = int(np.argmax(err))
            raise RecordingMismatch(f"recording {rec.source}: axis {axis}: the recorded output differs from the "
                                    f"table by {err.max():.4g} V at point {k} (tolerance {tol_V:g} V)"
                                    + _shift_hint(rec.u_V[axis], want, first, tol_V) + "; not learned from")
    sl = slice(first, last)
    return Recording(time_axis(n, rec.period_s), {a: v[sl].copy() for a, v in rec.y_nm.items()},
                     {a: v[sl].copy() for a, v in rec.u_V.items()}, rec.period_s, rec.source,
                     {a: v[sl].copy() for a, v in rec.v_V.items()})


def _shift_hint(u_V: np.ndarray, table: np.ndarray, first: int, tol_V: float) -> str:
    """", it matches N points later/earlier (trigger offset)" when a shift makes it match."""
    n = len(table)
    u = np.asarray(u_V, dtype=np.float64)
    for shift in sorted(range(-(n // 2), n // 2 + 1), key=abs):
        lo, hi = first + shift, first + shift + n
        if shift and 0 <= lo and hi <= len(u) and np.abs(u[lo:hi] - table).max() <= tol_V:
            return f"; it matches {abs(shift)} point(s) {'later' if shift > 0 else 'earlier'} (a trigger offset)"
    return ""
