"""The excitation of ``afmctl calibrate`` cut into pieces a device's recorder holds, and the
recorded pieces joined again (pure numpy; nothing here talks to a device).

A data recorder holds a finite number of points (the E-727 262,144 over all its record
tables, the NV200 6144 per channel — and its waveform buffer 1024 —, the CAN amplifier
what ``REC_STATUS`` says), so a long excitation is played and recorded as pieces, one wave
table each, one after another. Between two pieces the device *holds the last voltage* while
the next table is uploaded: the scanner's hysteresis state does not change during a hold
(it depends on the voltage's extremes, not on time), its creep goes on, its dynamics settle.

:func:`cut_points` chooses where to cut so that such a hold does least harm: inside a hold
the excitation already has (the gaps between its parts, the creep dwells) first, at a
turning point of the voltage next, anywhere on a ramp last; never inside a period of the
multisine (its periods must stay whole for the frequency response) — each piece as long as
the device allows. A piece shorter than :func:`shortest_piece` (one multisine period) cannot
be cut at all: :func:`plan_pieces` refuses such a device before anything moves.

:func:`join` puts the recorded pieces back on one time axis *with the holds between them*:
each hold's length is measured on the host clock (the start of a piece less the end of the
one before, rounded to whole samples), its voltage is the held one, its position is not
recorded (linearly interpolated from the end of one piece to the start of the next; the
rows are marked in ``measured``, the CSV's column ``measured``, and every fit and score of
``afmctl identify`` leaves them out). The joined record so carries the history the scanner
really saw — the creep of every hold is in the voltages that follow — and the hysteresis
memory is whole (the pieces are contiguous in voltage). What joining costs against one
continuous recording is measured by ``benchmarks/calibrate_join.py`` (docs/BENCHMARKS.md).

Units: V, nm, s; indices are samples at the loop period.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..data.excitation import ExcitationSpec, concatenate, creep, dynamics, multisine, static
from ..errors import AfmctlError

#: cut priorities (higher is better)
CUT_IN_HOLD, CUT_AT_TURN, CUT_ON_RAMP, NO_CUT = 3, 2, 1, 0
#: a piece is at least this share of the longest one (a cut is not searched before it)
MIN_SHARE = 0.5


@dataclass
class Excitation:
    """The voltages of ``afmctl excite --kind all`` (``u_V`` (N,) [V] at ``rate_Hz``) with,
    per sample, how good a cut after it is (``priority``) and the multisine's period
    [samples] (``period``)."""

    u_V: np.ndarray
    priority: np.ndarray
    period: int
    rate_Hz: float

    @property
    def duration_s(self) -> float:
        return len(self.u_V) / self.rate_Hz


def excitation_all(spec: ExcitationSpec) -> Excitation:
    """:func:`afmctl.data.excitation.excitation` of kind ``all`` for ``spec``, with its cut
    priorities: the multisine's inside is :data:`NO_CUT` but at its period boundaries."""
    from ..data.excitation import check_spec, fast
    check_spec(spec)
    parts = [static(spec), creep(spec), dynamics(spec), fast(spec)]
    u = np.clip(concatenate(parts, spec), spec.u_min_V, spec.u_max_V)
    prio = ramp_priorities(u)
    period = len(multisine(ExcitationSpec(**{**spec.__dict__, "periods": 0})))
    # where the multisine lies: the dynamics part ends where the first three parts joined
    # end; inside it, after the lead-in (one sample, the ramp to mid-range, the hold), then
    # (periods + 1) periods
    dyn = parts[2]
    lead = len(dyn) - (spec.periods + 1) * period - len(_tail(spec))
    start = len(concatenate(parts[:3], spec)) - len(dyn) + lead
    stop = start + (spec.periods + 1) * period
    prio[start:stop - 1] = NO_CUT
    prio[start + period - 1:stop:period] = CUT_AT_TURN        # after each whole period
    return Excitation(u, prio, period, spec.rate_Hz)


def _tail(spec: ExcitationSpec) -> np.ndarray:
    """What :func:`afmctl.data.excitation.dynamics` puts after the multisine."""
    from ..data.excitation import hold, ramp
    mid = 0.5 * (spec.u_min_V + spec.u_max_V)
    return np.concatenate([hold(mid, spec.gap_s, spec), ramp(mid, spec.u_min_V, spec)])


def ramp_priorities(u_V: np.ndarray) -> np.ndarray:
    """Per sample how good a cut *after* it is: in a hold (the voltage equal before and
    after), at a turning point (the slope changes sign), else on a ramp."""
    u = np.asarray(u_V, dtype=np.float64)
    prio = np.full(len(u), CUT_ON_RAMP, dtype=np.int8)
    if len(u) < 3:
        return prio
    d = np.diff(u)
    before, after = d[:-1], d[1:]              # the steps into and out of samples 1..N-2
    hold = (before == 0.0) & (after == 0.0)
    turn = (np.sign(before) * np.sign(after) < 0) | ((before == 0.0) != (after == 0.0))
    prio[1:-1][turn] = CUT_AT_TURN
    prio[1:-1][hold] = CUT_IN_HOLD
    prio[-1] = CUT_IN_HOLD
    return prio


def shortest_piece(exc: Excitation) -> int:
    """The fewest rows a piece may have [samples]: one multisine period (a piece can end
    after a whole period at the earliest)."""
    return int(exc.period)


def cut_points(priority: np.ndarray, max_rows: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` covering ``0 .. len(priority)``, each at most ``max_rows``
    long, each cut after the best sample (highest priority, then the latest) among the last
    :data:`MIN_SHARE` of the rows a piece may have. Raises ValueError when a stretch of
    :data:`NO_CUT` is longer than ``max_rows``."""
    n = len(priority)
    out: list[tuple[int, int]] = []
    start = 0
    lo_share = max(1, int(math.ceil(MIN_SHARE * max_rows)))
    while start < n:
        if n - start <= max_rows:
            out.append((start, n))
            break
        window = priority[start + lo_share - 1:start + max_rows]
        best = int(window.max())
        if best == NO_CUT:              # search the whole allowed length for a place
            window = priority[start:start + max_rows]
            best = int(window.max())
            if best == NO_CUT:
                raise ValueError(f"no place to cut within {max_rows} samples from sample {start}")
            k = start + int(np.flatnonzero(window == best)[-1])
        else:
            k = start + lo_share - 1 + int(np.flatnonzero(window == best)[-1])
        out.append((start, k + 1))
        start = k + 1
    return out


@dataclass
class PiecePlan:
    """One axis's excitation cut into pieces: ``bounds`` [(start, stop)] into ``exc.u_V``."""

    axis: str
    exc: Excitation
    bounds: list[tuple[int, int]]

    def table(self, k: int) -> np.ndarray:
        a, b = self.bounds[k]
        return self.exc.u_V[a:b]


def plan_pieces(exc: Excitation, axis: str, capacity: int, device: str) -> PiecePlan:
    """The pieces of ``exc`` for a device whose table and recorder hold ``capacity`` rows;
    one :class:`AfmctlError` line when even the shortest piece does not fit."""
    need = shortest_piece(exc)
    if capacity < need:
        raise AfmctlError(
            f"afmctl calibrate: the {device} holds {capacity} points per table and recording "
            f"({capacity / exc.rate_Hz:.3g} s at {exc.rate_Hz:g} Hz); the shortest piece of the excitation is one "
            f"multisine period, {need} points ({need / exc.rate_Hz:.3g} s): lower loop.rate_Hz or raise "
            f"--f-min-Hz; nothing was moved")
    return PiecePlan(axis, exc, cut_points(exc.priority, capacity))


@dataclass
class PieceRecord:
    """One recorded piece: the rows ``start .. start + len`` of the excitation; ``u_V`` the
    table played, ``y_nm`` the measured position, ``v_V`` the piezo voltage (or None);
    ``t_start_s`` host time just before the device was told to start it [s]."""

    start: int
    u_V: np.ndarray
    y_nm: np.ndarray
    v_V: np.ndarray | None
    t_start_s: float


@dataclass
class Joined:
    """The recorded pieces on one time axis (module docstring): ``t_s``, ``u_V``, ``y_nm``,
    ``v_V`` (or None), ``measured`` (False on the rows of the holds between pieces) and the
    holds inserted ``holds`` [(row, samples)]."""

    t_s: np.ndarray
    u_V: np.ndarray
    y_nm: np.ndarray
    v_V: np.ndarray | None
    measured: np.ndarray
    holds: list[tuple[int, int]] = field(default_factory=list)

    @property
    def held_share(self) -> float:
        """The share of the rows that are holds between pieces (their positions
        interpolated, not measured), 0..1."""
        return float(1.0 - np.count_nonzero(self.measured) / len(self.measured)) if len(self.measured) else 0.0

    def columns(self) -> dict[str, np.ndarray]:
        """The CSV columns ``t,u,y[,v][,measured]`` (s, V, nm, V, 0/1): ``measured`` when
        holds were inserted, 0 on their rows (``afmctl identify`` leaves them out of the fit)."""
        cols = {"t": self.t_s, "u": self.u_V, "y": self.y_nm}
        if self.v_V is not None:
            cols["v"] = self.v_V
        if not self.measured.all():
            cols["measured"] = self.measured.astype(np.float64)
        return cols


def gap_samples(prev: PieceRecord, nxt: PieceRecord, dt_s: float) -> int:
    """The hold between two pieces [samples]: the start of ``nxt`` less the end of ``prev``
    on the host clock, in whole samples (never negative)."""
    ended = prev.t_start_s + len(prev.u_V) * dt_s
    return max(0, int(round((nxt.t_start_s - ended) / dt_s)))


def join(pieces: list[PieceRecord], dt_s: float, with_holds: bool = True) -> Joined:
    """The pieces as one record (module docstring); ``with_holds=False`` puts them end to
    end (the holds left out: what joining without the history would give)."""
    if not pieces:
        raise AfmctlError("afmctl calibrate: nothing was recorded")
    u, y, v, m, holds = [], [], [], [], []
    with_v = all(p.v_V is not None for p in pieces)
    rows = 0
    for k, p in enumerate(pieces):
        if k and with_holds:
            g = gap_samples(pieces[k - 1], p, dt_s)
            if g:
                u.append(np.full(g, pieces[k - 1].u_V[-1]))
                y.append(np.linspace(pieces[k - 1].y_nm[-1], p.y_nm[0], g + 2)[1:-1])
                if with_v:
                    v.append(np.full(g, pieces[k - 1].v_V[-1]))   # type: ignore[index]
                m.append(np.zeros(g, dtype=bool))
                holds.append((rows, g))
                rows += g
        u.append(p.u_V)
        y.append(p.y_nm)
        if with_v and p.v_V is not None:
            v.append(p.v_V)
        m.append(np.ones(len(p.u_V), dtype=bool))
        rows += len(p.u_V)
    uu = np.concatenate(u)
    return Joined(np.arange(len(uu)) * dt_s, uu, np.concatenate(y), np.concatenate(v) if with_v else None,
                  np.concatenate(m), holds)


def follow_table(played_V: np.ndarray, table_V: np.ndarray, tol_V: float) -> int:
    """How many recorded samples a streamed table took: ``played_V`` (the output the
    recorder saw at each tick [V]) must be ``table_V`` in order with *holds* inserted (a
    stream FIFO that ran empty holds the last output: the scanner saw those holds, so they
    belong to the recording). Returns the count of recorded samples through the table's last
    row; ValueError when the output left the table or the recording ends before it."""
    played = np.asarray(played_V, dtype=np.float64)
    table = np.asarray(table_V, dtype=np.float64)
    i = 0                                   # the next table row to be output
    for j, v in enumerate(played.tolist()):
        if i < len(table) and abs(v - table[i]) <= tol_V:
            i += 1
            if i == len(table):
                return j + 1
        elif i == 0 or abs(v - table[i - 1]) > tol_V:
            raise ValueError(f"the output left the table at recorded sample {j} ({v:.4g} V; the table's row {i} "
                             f"is {table[min(i, len(table) - 1)]:.4g} V)")
    raise ValueError(f"the recording ended after row {i} of {len(table)}: the stream held the output for "
                     f"{len(played) - i} ticks (the host did not keep the FIFO filled)")
