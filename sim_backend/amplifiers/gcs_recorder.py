"""The data recorder of the simulated GCS controller (E-727), sans-I/O.

GCS 2 data recorder commands as PIPython's ``datarectools.Datarecorder`` issues them (facts
from PIPython's ``GCSBaseCommands`` / ``gcs2datarectools`` and PI's GCS manuals):

* ``DRC <table> <source> <option>`` — what a record table records: option 0 nothing,
  1 commanded position of axis <source> [µm], 2 actual position of axis <source> [µm],
  3 position error (1 − 2) [µm], 7 piezo voltage of output channel <source> [V]
  (PIPython's ``PIEZO_VOLTAGE_7``: the voltage the amplifier stage puts on the piezo),
  14 open-loop control value of axis <source> [V] (``OPENLOOP_INPUT_14``: the voltage
  commanded in open loop, ``SVA`` or the wave generator); ``DRC?`` answers
  ``<table>=<source> <option>``.
* ``DRT <table> <trigger> <value>`` — when recording (re)starts (table 0 = every table):
  0 default (``WGO`` starting a generator, ``WGR``), 1 any command that changes the position
  (``MOV``, ``SVA``, ``WGO``, ``WGR``), 2 the next command (then back to 0), 4 at once;
  ``DRT?`` answers ``<table>=<trigger> <value>``.
* ``RTR <n>`` / ``RTR?`` — a record point every n servo cycles; ``TNR?`` the record tables;
  ``SPA 1 0x16000300 <n>`` (Data Recorder Chan Number, 1 to 8) shares the 262,144 points
  among n tables (PI's E-727 manual: the points are allocated in equal shares to the tables
  ``TNR?`` counts, and the number of tables may be chosen; *unconfirmed*: the command level
  a real E-727 asks for it, and whether it keeps the tables' sources, which are reset here);
  ``DRL?`` the points recorded since the last trigger; ``WGR`` restarts recording at the
  next servo tick (it is *unconfirmed* whether a real E-727 waits for the next wave cycle).
* ``DRR? [<offset> <n> [<table> ...]]`` — the GCS array: header lines ``# key = value``
  (``TYPE = 1``, ``SEPARATOR = 32``, ``DIM``, ``SAMPLE_TIME``, ``NDATA``, ``NAME<i>``),
  ``# END_HEADER``, then one line per point with one column per table. As every multi-line
  GCS answer, each line but the last ends with a space before the LF.

Timing: a trigger at time t starts the table at the first servo tick t0 >= t (a ``WGO`` on
the tick the generators start: record point 0 is taken in the servo cycle that outputs wave
point 0). Point k is taken at t0 + k·RTR·servo_cycle: an open-loop control value or
commanded position is the value in force then (wave point k at RTR = wave rate), an actual
position the scanner's position sensor at that instant (:meth:`Scanner.capture_sensor`) —
the response to the points before it — and a piezo voltage the scanner's amplifier stage
output at that instant (after its bandwidth and slew; the capture's ``v_V``). Without a sensor in the sink the actual position is the device's linear
model of the output (as ``POS?``) and the piezo voltage the command. A table records until it holds ``max_points`` points.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

#: record tables (``TNR?``) at power-on and at most (parameter 0x16000300), total points over
#: all of them (parameter 0x16000200 on E-7xx)
N_TABLES = 8
TOTAL_POINTS = 262_144
DATA_REC_MAX_POINTS_PARAM = 0x16000200
DATA_REC_CHAN_NUMBER_PARAM = 0x16000300
OPTIONS = {0: "Nothing", 1: "Commanded Position of axis", 2: "Actual Position of axis",
           3: "Position Error of axis", 7: "Voltage of output chan", 14: "Open loop control of axis"}
#: the options read from the scanner (its position sensor, its amplifier stage)
CAPTURED = (2, 3, 7)
TRIGGERS = (0, 1, 2, 4)


class RecorderError(Exception):
    """A recorder command the controller refuses; ``code`` is the GCS error it latches."""

    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


@dataclass
class Table:
    source: str
    option: int
    trigger: int = 0
    trigger_value: str = "0"
    t0_s: float | None = None        # start of the present recording (None: never triggered)
    capture: Any = None              # the scanner's SensorCapture for actual positions
    volts: Any = None                # output voltage [V] of the source channel at each point
    filled: int = 0                  # points of ``volts`` taken so far


class DataRecorder:
    """``DataRecorder(servo_cycle_s, sensor, model_um, channels)``: ``sensor(t0_s, period_s,
    n)`` returns a capture of the sink's position sensor or None; ``model_um(channel, volts)``
    the device's linear position of an output voltage; ``channels`` the axis/channel ids."""

    def __init__(self, servo_cycle_s: float, sensor: Callable[[float, float, int], Any],
                 model_um: Callable[[str, float], float], channels: tuple[str, ...]) -> None:
        self.servo_cycle_s = float(servo_cycle_s)
        self.sensor = sensor
        self.model_um = model_um
        self.channels = channels
        self.rate = 1
        #: the output voltage [V] per channel in force now
        self._held = {c: 0.0 for c in channels}
        #: the tables whose recording still takes points
        self._filling: list[Table] = []
        self.tables: dict[int, Table] = {}
        self.max_points = 0
        self.set_tables(N_TABLES)

    def set_tables(self, n: int) -> None:
        """Share the points among ``n`` record tables (1 to :data:`N_TABLES`; parameter
        0x16000300): every table back to its power-on source and option, nothing recording."""
        if not 1 <= n <= N_TABLES:
            raise RecorderError(17)
        for tab in self.tables.values():
            if tab.capture is not None:
                tab.capture.cancel()
        c = self.channels
        self.max_points = TOTAL_POINTS // n
        self.tables = {t: Table(c[(t - 1) % len(c)], 2 if t <= len(c) else 7 if t <= 2 * len(c) else 0)
                       for t in range(1, n + 1)}
        self._filling = []

    # -- what the controller tells it --
    def output_changed(self, t_s: float, volts: dict[str, float]) -> None:
        """The outputs [V] per channel from ``t_s`` on (points due before ``t_s`` get the
        old outputs)."""
        self._fill(t_s, strict=True)
        self._held.update(volts)

    def outputs_changed(self, t_s: np.ndarray, volts: Mapping[str, np.ndarray]) -> None:
        """:meth:`output_changed` for a block of changes at once: from ``t_s[i]`` (non-
        decreasing) on the outputs per channel are ``volts[channel][i]`` — the same points
        filled with the same values as one call per change, without a call per change."""
        t = np.asarray(t_s, dtype=np.float64)
        if not len(t):
            return
        period = self.rate * self.servo_cycle_s
        for tab in self._filling:
            if tab.filled >= self.max_points or tab.t0_s is None:
                continue
            # change i holds from point first[i] on (points due strictly before it keep the old)
            first = np.ceil((t - tab.t0_s) / period - 1e-9)
            upto = int(min(first[-1], self.max_points))
            if upto > tab.filled:
                k = np.arange(tab.filled, upto)
                i = np.searchsorted(first, k, side="right") - 1
                col = np.asarray(volts[tab.source], dtype=np.float64)
                tab.volts[tab.filled:upto] = np.where(i >= 0, col[np.maximum(i, 0)], self._held[tab.source])
                tab.filled = upto
        self._filling = [t for t in self._filling if t.filled < self.max_points]
        self._held.update({c: float(v[-1]) for c, v in volts.items()})

    def sync(self, now_s: float) -> None:
        """Points due by ``now_s`` take the outputs in force."""
        self._fill(now_s, strict=False)

    def _fill(self, t_s: float, strict: bool) -> None:
        if not self._filling:           # nothing records: the common case, kept cheap
            return
        period = self.rate * self.servo_cycle_s
        for tab in self._filling:
            if tab.filled >= self.max_points or tab.t0_s is None:
                continue
            x = (t_s - tab.t0_s) / period
            last = math.ceil(x - 1e-9) - 1 if strict else math.floor(x + 1e-9)
            upto = min(last + 1, self.max_points)
            if upto > tab.filled:
                tab.volts[tab.filled:upto] = self._held[tab.source]
                tab.filled = upto
        self._filling = [t for t in self._filling if t.filled < self.max_points]

    def event(self, kind: str, now_s: float) -> None:
        """A command that may trigger: ``"wgo"`` (a generator starts: ``now_s`` is its tick),
        ``"wgr"``, ``"move"`` (MOV/SVA), ``"command"`` (any other command)."""
        fire = {"wgo": (0, 1, 2), "wgr": (0, 1, 2), "move": (1, 2), "command": (2,)}[kind]
        started = [t for t in self.tables.values() if t.trigger in fire and t.option]
        for tab in started:
            if tab.trigger == 2:
                tab.trigger = 0
        self._start(started, now_s)

    def _start(self, tables: list[Table], now_s: float) -> None:
        if not tables:
            return
        self.sync(now_s)
        t0 = math.ceil(now_s / self.servo_cycle_s - 1e-9) * self.servo_cycle_s
        period = self.rate * self.servo_cycle_s
        capture = None
        if any(t.option in CAPTURED for t in tables):
            capture = self.sensor(t0, period, self.max_points)
        for tab in tables:
            if tab.capture is not None:
                tab.capture.cancel()
            tab.t0_s, tab.capture = t0, capture if tab.option in CAPTURED else None
            tab.volts, tab.filled = np.zeros(self.max_points), 0
        self._filling = [t for t in self.tables.values() if t.t0_s is not None and t.filled < self.max_points]

    # -- host commands --
    def drc(self, args: list[str]) -> None:
        if not args or len(args) % 3:
            raise RecorderError(1)
        new = {}
        for tab, src, opt in zip(args[::3], args[1::3], args[2::3]):
            t, o = int_token(tab), int_token(opt)
            if t not in self.tables or o not in OPTIONS or (o and src not in self.channels):
                raise RecorderError(17)
            new[t] = (src, o)
        for t, (src, o) in new.items():
            self.tables[t].source, self.tables[t].option = src, o

    def drt(self, args: list[str]) -> None:
        if not args or len(args) % 3:
            raise RecorderError(1)
        for tab, trig, value in zip(args[::3], args[1::3], args[2::3]):
            t, s = int_token(tab), int_token(trig)
            if (t != 0 and t not in self.tables) or s not in TRIGGERS:
                raise RecorderError(17)
            for k in (self.tables if t == 0 else [t]):
                self.tables[k].trigger, self.tables[k].trigger_value = s, value

    def rtr(self, args: list[str]) -> None:
        if len(args) != 1:
            raise RecorderError(1)
        n = int_token(args[0])
        if not 1 <= n <= 2**31 - 1:
            raise RecorderError(17)
        self.rate = n

    def start_immediate(self, now_s: float) -> None:
        """DRT ... 4: the tables set to trigger "immediately" start now."""
        self._start([t for t in self.tables.values() if t.trigger == 4 and t.option], now_s)

    def ids(self, args: list[str]) -> list[int]:
        ids = [int_token(a) for a in args] or list(self.tables)
        if any(t not in self.tables for t in ids):
            raise RecorderError(17)
        return ids

    def recorded(self, t: int, now_s: float) -> int:
        """Points table ``t`` holds by ``now_s`` (``DRL?``)."""
        self.sync(now_s)
        tab = self.tables[t]
        if tab.t0_s is None or not tab.option:
            return 0
        return min(tab.filled, tab.capture.count) if tab.capture is not None else tab.filled

    def values(self, t: int, first: int, n: int) -> np.ndarray:
        """Points ``first`` .. ``first + n - 1`` (0-based, all recorded) of table ``t`` in
        its unit."""
        tab = self.tables[t]
        volts = tab.volts[first:first + n]
        if tab.option == 7 and tab.capture is not None:
            return tab.capture.v_V[first:first + n, self.channels.index(tab.source)].copy()
        if tab.option in (7, 14):
            return volts.copy()
        if tab.option == 2 and tab.capture is not None:     # the position sensor: no model needed
            return tab.capture.y_nm[first:first + n, self.channels.index(tab.source)] / 1000.0
        commanded = np.array([self.model_um(tab.source, float(v)) for v in volts])
        if tab.option == 1:
            return commanded
        if tab.capture is not None:
            axis = self.channels.index(tab.source)
            actual = tab.capture.y_nm[first:first + n, axis] / 1000.0
        else:
            actual = commanded
        return actual if tab.option == 2 else commanded - actual

    def name(self, t: int) -> str:
        tab = self.tables[t]
        return f"{OPTIONS[tab.option]} {tab.source}"


def int_token(tok: str) -> int:
    """A GCS integer argument (``17``, ``17.0``); error 1 (parameter syntax) otherwise."""
    try:
        v = float(tok)
    except ValueError:
        raise RecorderError(1) from None
    if not math.isfinite(v) or v != int(v):
        raise RecorderError(1)
    return int(v)
