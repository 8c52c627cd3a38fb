"""The wave generator of the simulated GCS controller, sans-I/O (no thread, no port).

GCS 2 wave generator commands as PIPython issues them (facts from its ``GCSBaseCommands``
and PI's GCS manuals): wave tables are written with ``WAV`` (segments ``PNT`` and ``LIN``,
``X`` starts a new table, ``&`` appends a segment, ``+`` adds onto the table point by
point), ``WSL`` connects a generator to a table, ``WGC`` sets its cycles (0 = endless),
``WTR`` its table rate (a point lasts ``rate`` servo cycles) and interpolation type,
``WGO`` starts (mode bit 0: now) or stops (0) it, ``TWC`` clears the generator trigger
points, the single byte ``#9`` (0x09) answers a hex mask of the running generators.

Playback: generator g started (at the first servo tick t0 at or after the ``WGO``) plays table point k of the whole run
(cycles laid end to end) at exactly ``t0 + k * rate * servo_cycle_s``; :meth:`run_until` is
called with the controller's clock and applies every overdue point with its own computed
time, so the timing is that of the controller's servo clock, not of the caller.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

#: the controller's servo cycle [s] unless given: the E-727's servo update time per its user
#: manual (E727T0005), read by hosts as parameter 0x0E000200 (SERVO_UPDATE_TIME)
SERVO_CYCLE_S = 50e-6
#: points one wave table holds (``WMS?``)
MAX_POINTS = 262_144
SERVO_UPDATE_TIME_PARAM = 0x0E000200


class WaveError(Exception):
    """A wave command the controller refuses; ``code`` is the GCS error it latches."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


@dataclass
class Generator:
    table: int
    cycles: int = 1          # 0 = until stopped
    rate: int = 1            # servo cycles per table point
    interpolation: int = 0
    mode: int = 0            # last WGO mode; 0 once stopped or finished
    t0_s: float = 0.0
    k: int = 0               # next point of the run
    played: int = 0
    points: list[float] = field(default_factory=list)  # table as it was when started
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))  # the same as an array


def lin_segment(seg_len: int, amplitude: float, offset: float, n: int, first: int, speed: int) -> list[float]:
    """A ``LIN`` segment: ``seg_len`` points, ``offset`` before point ``first`` (0-based, as in
    the E-727 manual's ``WAV 2 & LIN 3000 -40 50 3000 0 650`` example), a
    rise by ``amplitude`` over ``n`` points, then ``offset + amplitude``. ``speed`` points at
    each end of the rise accelerate and decelerate at constant rate (velocity trapezoid)."""
    if not (0 <= first and n >= 1 and first + n <= seg_len and 0 <= 2 * speed <= n):
        raise WaveError(17)
    out = [offset] * first
    span = max(n - 1, 1)
    s = float(speed)
    for i in range(n):
        x = float(i)
        if s == 0:
            frac = x / span
        else:  # distance under a velocity that ramps 0→v over s, holds, ramps v→0 over s
            v = 1.0 / (span - s)
            if x < s:
                frac = v * x * x / (2 * s)
            elif x <= span - s:
                frac = v * (x - s / 2)
            else:
                frac = 1.0 - v * (span - x) ** 2 / (2 * s)
        out.append(offset + amplitude * frac)
    out += [offset + amplitude] * (seg_len - len(out))
    return out


class WaveGenerator:
    """``WaveGenerator(apply, generators=3, servo_cycle_s=SERVO_CYCLE_S)``; generator g
    (1-based) drives output index g-1: ``apply(g, value_V, t_s)``."""

    def __init__(self, apply: Callable[[int, float, float], None], generators: int = 3,
                 servo_cycle_s: float = SERVO_CYCLE_S, max_points: int = MAX_POINTS) -> None:
        self.apply = apply
        self.servo_cycle_s = float(servo_cycle_s)
        self.max_points = int(max_points)
        self.tables: dict[int, list[float]] = {t: [] for t in range(1, generators + 1)}
        self.gens: dict[int, Generator] = {g: Generator(table=g) for g in range(1, generators + 1)}

    # -- host commands --
    def wav(self, args: list[str]) -> None:
        """``WAV <table> <X|&|+> <PNT|LIN> ...``"""
        if len(args) < 3:
            raise WaveError(1)
        table, mode, kind = _int(args[0]), args[1], args[2].upper()
        if table not in self.tables or mode not in ("X", "&", "+"):
            raise WaveError(17 if table not in self.tables else 1)
        if any(g.mode and g.table == table for g in self.gens.values()):
            raise WaveError(17)  # a running generator's table cannot change
        nums = [_float(a) for a in args[3:]]
        if kind == "PNT":
            seg = self._pnt(table, mode, nums)
        elif kind == "LIN" and len(nums) == 6:
            seg_len, amp, off, n, first, speed = nums
            seg = lin_segment(_whole(seg_len), amp, off, _whole(n), _whole(first), _whole(speed))
        else:
            raise WaveError(1)
        self._store(table, mode, seg)

    def _pnt(self, table: int, mode: str, nums: list[float]) -> list[float]:
        if len(nums) < 3:
            raise WaveError(1)
        first, n, points = _whole(nums[0]), _whole(nums[1]), nums[2:]
        if n != len(points):
            raise WaveError(1)
        # the segment's first point: 1, or (appending, as PIPython's writewavepoints does) the
        # index the segment gets in the table
        if first != 1 and not (mode == "&" and first == len(self.tables[table]) + 1):
            raise WaveError(17)
        return points

    def _store(self, table: int, mode: str, seg: list[float]) -> None:
        old = self.tables[table]
        if mode == "&":                  # appended in place (a long table comes in many lines)
            if len(old) + len(seg) > self.max_points:
                raise WaveError(17)
            old.extend(seg)
            return
        if mode == "X":
            new = list(seg)
        elif mode == "&":
            new = old + seg
        else:
            new = [(old[i] if i < len(old) else 0.0) + (seg[i] if i < len(seg) else 0.0)
                   for i in range(max(len(old), len(seg)))]
        if len(new) > self.max_points:
            raise WaveError(17)
        self.tables[table] = new

    def wsl(self, gen: int, table: int) -> None:
        g = self._gen(gen)
        if table not in self.tables or g.mode:
            raise WaveError(17)
        g.table = table

    def wgc(self, gen: int, cycles: int) -> None:
        if cycles < 0:
            raise WaveError(17)
        self._gen(gen).cycles = cycles

    def wtr(self, gen: int, rate: int, interpolation: int) -> None:
        g = self._gen(gen)
        if rate < 1 or interpolation not in (0, 1) or g.mode:
            raise WaveError(17)
        g.rate, g.interpolation = rate, interpolation

    def wgo(self, gen: int, mode: int, now_s: float) -> None:
        g = self._gen(gen)
        if mode == 0:
            self.run_until(now_s)
            g.mode = 0
            return
        if mode != 1:
            raise WaveError(17)  # only "start immediately" (bit 0) is simulated
        if not self.tables[g.table]:
            raise WaveError(17)
        # the generator starts at the next tick of the servo clock (tick n at n * servo_cycle_s)
        t0 = math.ceil(now_s / self.servo_cycle_s - 1e-9) * self.servo_cycle_s
        g.mode, g.t0_s, g.k, g.points = mode, t0, 0, list(self.tables[g.table])
        g.values = np.asarray(g.points, dtype=np.float64)

    def _gen(self, gen: int) -> Generator:
        if gen not in self.gens:
            raise WaveError(17)
        return self.gens[gen]

    # -- clock --
    def point_time_s(self, g: Generator, k: int) -> float:
        """When point ``k`` of the run plays [s]: ``t0 + k * rate * servo_cycle``."""
        return g.t0_s + k * g.rate * self.servo_cycle_s

    def run_until(self, now_s: float) -> int:
        """Apply every point due at or before ``now_s``, in time order across generators
        (one ``apply`` per point); returns how many were applied."""
        t, gid, v = self.take_due(now_s)
        for tk, gk, vk in zip(t.tolist(), gid.tolist(), v.tolist()):
            self.apply(gk, vk, tk)
        return len(t)

    def take_due(self, now_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every point due at or before ``now_s`` as arrays in time order across generators
        (ties by generator): times [s], generator ids, table values; the generators move
        past them (what :meth:`run_until` applies one by one, without a call per point)."""
        ts, gids, vals = [], [], []
        for gid, g in self.gens.items():
            if not g.mode:
                continue
            k = np.arange(g.k, self._due_end(g, now_s))
            if len(k):
                ts.append(g.t0_s + k * g.rate * self.servo_cycle_s)
                gids.append(np.full(len(k), gid))
                vals.append(g.values[k % len(g.values)])
                g.k += len(k)
                g.played += len(k)
            if g.k >= (len(g.points) * g.cycles if g.cycles else math.inf):
                g.mode = 0
        if not ts:
            return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0)
        times, ids, values = np.concatenate(ts), np.concatenate(gids), np.concatenate(vals)
        order = np.lexsort((ids, times))
        return times[order], ids[order], values[order]

    def _due_end(self, g: Generator, now_s: float) -> int:
        """One past the last point of ``g``'s run due at or before ``now_s`` (exactly the
        points whose :meth:`point_time_s` is not after it)."""
        total = len(g.points) * g.cycles if g.cycles else math.inf
        step = g.rate * self.servo_cycle_s
        end = max(g.k, int(math.floor((now_s - g.t0_s) / step)) + 1) if now_s >= g.t0_s else g.k
        end = int(min(end, total))
        while end < total and self.point_time_s(g, end) <= now_s:
            end += 1
        while end > g.k and self.point_time_s(g, end - 1) > now_s:
            end -= 1
        return end

    def running_mask(self) -> int:
        return sum(1 << (gid - 1) for gid, g in self.gens.items() if g.mode)

    def next_due_s(self) -> float | None:
        """When the next point not yet played falls due [s] (None: no generator runs)."""
        due = [self.point_time_s(g, g.k) for g in self.gens.values() if g.mode]
        return min(due) if due else None


def _float(tok: str) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise WaveError(1) from None
    if not math.isfinite(v):
        raise WaveError(1)
    return v


def _int(tok: str) -> int:
    return _whole(_float(tok))


def _whole(v: float) -> int:
    if v != int(v):
        raise WaveError(1)
    return int(v)
