"""Simulated PI GCS 2 controller (an E-727 in its open-loop subset), from the GCS command
set as PI's manuals and PIPython use it.

Axes ``1 2 3`` drive outputs x, y, z; voltage channels ``1 2 3`` belong to the same axes.
At power-up the servo is ON (so ``SVA`` gives error 303 until ``SVO <axis> 0``). An
``SVA`` with any bad argument applies nothing and latches the error. The first error
latched stays until ``ERR?`` reads and clears it. Commands are case-insensitive; lines end
at LF (a CR before it is ignored). ``*IDN?`` names the model ``E-727`` (the serial-number
field says it is simulated), ``CSV?`` answers 2 (GCS 2), ``HLP?`` lists the commands.

Position: ``POS?`` is the position the sensor reads, here linear over the voltage range
onto the travel ``TMN?``..``TMX?`` [µm]. ``MOV`` needs the servo on (error 5 otherwise,
7 outside the travel); with the servo on it sets the target and the simulator puts the
output voltage where that position lies (an ideal servo).

Wave generator (see :mod:`.gcs_wave`): generator g drives axis g; with the servo off a
table value is the output voltage [V], with it on a target position [µm]. Values are
clamped to VMI..VMA (and recorded as requested). It plays on the controller's servo clock
(``servo_cycle_s``, parameter 0x0E000200 via ``SPA?``): every command and every
:meth:`SimGCS.poll` first applies the points that fell due, with their own times.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import cast

import numpy as np

from .base import SimDevice, Sink
from .gcs_recorder import (DATA_REC_CHAN_NUMBER_PARAM, DATA_REC_MAX_POINTS_PARAM, TOTAL_POINTS,
                           DataRecorder, RecorderError, int_token)
from .gcs_wave import SERVO_CYCLE_S, SERVO_UPDATE_TIME_PARAM, WaveError, WaveGenerator

_AXIS = {"1": "x", "2": "y", "3": "z"}
IDN = b"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, E-727, SIM-afmctl, 01.00.00.00\n"
_HELP = ("*IDN?", "CSV?", "ERR?", "HLP?", "SAI?", "SVO", "SVO?", "SVA", "SVA?", "VOL?", "VMA", "VMA?",
         "VMI", "VMI?", "POS?", "MOV", "MOV?", "ONT?", "TMN?", "TMX?", "SPA", "SPA?", "HPA?", "WAV", "WAV?", "WSL",
         "WSL?", "WGC", "WGC?", "WTR", "WTR?", "WGO", "WGO?", "WMS?", "TWC", "WOS", "WOS?", "#9",
         "DRC", "DRC?", "DRT", "DRT?", "RTR", "RTR?", "TNR?", "DRL?", "DRR?", "WGR")
#: single-byte GCS commands (no LF): #9 asks which wave generators run
_RUNNING_BYTE = 0x09


def _num(tok: str) -> float | None:
    try:
        v = float(tok)
    except ValueError:
        return None
    return v if v == v and abs(v) != float("inf") else None


class SimGCS(SimDevice):
    """``SimGCS(sink=None, now=None, vmin_V=0.0, vmax_V=120.0, servo_cycle_s=50e-6)``.
    ``inject_error(code)`` latches ``code`` (default 302) on the next command."""

    protocol = "gcs"
    #: the host may choose the data recorder's tables (``SPA 1 0x16000300 n``); False: a
    #: firmware that protects the parameter (error 60)
    record_tables_settable = True

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None,
                 vmin_V: float = 0.0, vmax_V: float = 120.0, servo_cycle_s: float = SERVO_CYCLE_S) -> None:
        super().__init__(sink, now=now)
        self.wave = WaveGenerator(self._wave_apply, generators=len(_AXIS), servo_cycle_s=servo_cycle_s)
        self.servo = {k: True for k in _AXIS}
        self.vmi = {k: vmin_V for k in _AXIS}
        self.vma = {k: vmax_V for k in _AXIS}
        self.error = 0
        self.travel_um = (0.0, 100.0)
        self.target = {k: 0.0 for k in _AXIS}
        #: per generator the output offset added to every wave value (``WOS``; 0 at power-on)
        self.wave_offset_V = {int(k): 0.0 for k in _AXIS}
        #: the data recorder (:mod:`.gcs_recorder`): reads the sink's position sensor if it has one
        self.recorder = DataRecorder(servo_cycle_s, self._sensor_capture, self._model_um, tuple(_AXIS))

    def _latch(self, code: int) -> bytes:
        if self.error == 0:
            self.error = code
        return b""

    @staticmethod
    def _items(items: list[tuple[str, str]]) -> bytes:
        return b" \n".join(f"{k}={v}".encode() for k, v in items) + b"\n"

    line_ends = b"\n"  # LF ends a command (a CR before it is stripped)
    max_line = 1024

    def overflow(self) -> bytes:
        self._latch(304)  # "received command is too long", read with ERR?
        return b""

    def feed(self, data: bytes) -> bytes:
        """Lines as :meth:`SimDevice.feed`; the byte 0x09 (``#9``) between lines is a
        command on its own, answered at once with the running generators as hex."""
        with self.lock:
            out = bytearray()
            while (i := data.find(bytes((_RUNNING_BYTE,)))) >= 0:
                out += super().feed(data[:i])
                self.poll()
                out += f"{self.wave.running_mask():X}\n".encode()
                data = data[i + 1:]
            return bytes(out + super().feed(data))

    def poll(self, now_s: float | None = None) -> None:
        """Play the wave points that fell due by now (or ``now_s``; the servers call this when
        idle; the simulator's clock thread calls :meth:`play_due`), then bring the load up to
        now. The points go as one block: the outputs computed for all of them at once, the
        recorder told in one call, the sink handed the changes in one ``sink.play(t_s, rows_V)``
        where it has one (the simulated scanner simulates a block in one call) else one
        ``apply`` per change. A call per point costs more than the 50 µs servo cycle on a
        loaded host, and a simulator that falls behind its own clock never answers again."""
        with self.lock:
            now = self.now() if now_s is None else now_s
            self._play_due(now)
            self.advance_load(now)

    def _play_due(self, now_s: float) -> None:
        """The wave points due by ``now_s`` as one block (:meth:`poll`)."""
        t, gid, val = self.wave.take_due(now_s)
        if not len(t):
            return
        rows = self._wave_rows(gid, val)
        prev = np.vstack([[self.outputs[a] for a in "xyz"], rows[:-1]])
        changed = np.any(rows != prev, axis=1)
        if not changed.any():
            return
        t, rows = t[changed], rows[changed]
        for i, a in enumerate("xyz"):
            self.outputs[a] = float(rows[-1, i])
        self.recorder.outputs_changed(t, {k: rows[:, "xyz".index(a)] for k, a in _AXIS.items()})
        play: Callable[..., None] | None = getattr(self.sink, "play", None)
        if play is not None:
            play(t, rows)
        elif self.sink is not None:
            for tk, row in zip(t.tolist(), rows.tolist()):
                self.sink.apply(dict(zip("xyz", row)), tk)

    def _wave_rows(self, gid: np.ndarray, value: np.ndarray) -> np.ndarray:
        """The outputs [x, y, z] V after each wave point (generator ``gid``, table value
        ``value``), as :meth:`_wave_apply` sets them one by one."""
        rows = np.empty((len(gid), 3))
        idx = np.arange(len(gid))
        for key, axis in _AXIS.items():
            mine = gid == int(key)
            col = "xyz".index(axis)
            if not mine.any():
                rows[:, col] = self.outputs[axis]
                continue
            volts = self._wave_volts(int(key), value[mine])
            at = np.maximum.accumulate(np.where(mine, idx, -1))
            full = np.empty(len(gid))
            full[mine] = volts
            rows[:, col] = np.where(at >= 0, full[np.maximum(at, 0)], self.outputs[axis])
        return rows

    def _wave_volts(self, gen: int, value: np.ndarray) -> np.ndarray:
        """Generator ``gen``'s table values as output voltages [V]: plus its ``WOS`` offset,
        a position [µm] mapped onto the voltage range with the servo on, clipped to
        VMI..VMA (the requested extremes noted)."""
        key = str(gen)
        value = value + self.wave_offset_V[gen]     # generator output = WOS offset + wave value
        if self.servo[key]:  # a position [µm] → the voltage that puts the ideal servo there
            t0, t1 = self.travel_um
            value = self.vmi[key] + (value - t0) / (t1 - t0) * (self.vma[key] - self.vmi[key])
        axis = _AXIS[key]
        self._requested(float(value.min()), axis)
        self._requested(float(value.max()), axis)
        return np.clip(value, self.vmi[key], self.vma[key])

    def _wave_apply(self, gen: int, value: float, t_s: float) -> None:
        """One wave point (a generator stopped by ``WGO 0`` plays what fell due one by one)."""
        v = float(self._wave_volts(gen, np.array([value]))[0])
        axis = _AXIS[str(gen)]
        if self.outputs[axis] != v:
            self.outputs[axis] = v
            self.recorder.output_changed(t_s, self._channel_volts())
            if self.sink is not None:
                self.sink.apply(dict(self.outputs), t_s)

    def _channel_volts(self) -> dict[str, float]:
        return {k: self.outputs[a] for k, a in _AXIS.items()}

    def _apply(self, changes) -> None:
        """Host-set outputs (SVA, MOV): the recorder sees them from now on, and they may
        trigger it (``DRT`` 1)."""
        now = self.now()
        self.recorder.event("move", now)
        super()._apply(changes)
        self.recorder.output_changed(now, self._channel_volts())

    def _sensor_capture(self, t0_s: float, period_s: float, n: int):
        """A capture of the sink's position sensor, or None when the sink has none."""
        capture = getattr(self.sink, "capture_sensor", None)
        return capture(t0_s, period_s, n) if capture is not None else None

    def _model_um(self, key: str, volts: float) -> float:
        """The linear position [µm] of an output voltage (over VMI..VMA onto the travel)."""
        lo, hi = self.vmi[key], self.vma[key]
        frac = (volts - lo) / (hi - lo) if hi > lo else 0.0
        return self.travel_um[0] + frac * (self.travel_um[1] - self.travel_um[0])

    def _sense_now(self) -> float:
        """Play the wave and bring the sink's simulation (and so its sensor) up to now;
        returns now [s]. The wave first: the recorder fills the points due by now with the
        output in force, which must include every wave point due by then (a loaded host
        reaches this later than the command's poll)."""
        now = self.now()
        self.poll(now)
        advance = getattr(self.sink, "advance", None)
        if advance is not None and getattr(self.sink, "capture_sensor", None) is not None:
            advance(now)
        return now

    def _recorder_command(self, cmd: str, args: list[str]) -> bytes | None:
        """The data recorder commands (:mod:`.gcs_recorder`); None when ``cmd`` is not one."""
        r = self.recorder
        try:
            if cmd in ("DRC", "DRT", "RTR"):
                {"DRC": r.drc, "DRT": r.drt, "RTR": r.rtr}[cmd](args)
                if cmd == "DRT":
                    r.start_immediate(self.now())
                return b""
            if cmd == "WGR":
                r.event("wgr", self.now())
                return b""
            if cmd in ("RTR?", "TNR?"):
                return f"{r.rate if cmd == 'RTR?' else len(r.tables)}\n".encode()
            if cmd in ("DRC?", "DRT?", "DRL?"):
                ids = r.ids(args)
                if cmd == "DRL?":
                    now = self._sense_now()
                    return self._items([(str(t), str(r.recorded(t, now))) for t in ids])
                field = {"DRC?": lambda t: f"{t.source} {t.option}", "DRT?": lambda t: f"{t.trigger} {t.trigger_value}"}
                return self._items([(str(t), field[cmd](r.tables[t])) for t in ids])
            if cmd == "DRR?":
                return self._drr(args)
        except RecorderError as err:
            return self._latch(err.code)
        return None

    def _drr(self, args: list[str]) -> bytes:
        """``DRR? [offset n [tables]]``: the GCS array (header, then one line per point)."""
        r = self.recorder
        now = self._sense_now()
        if args and len(args) < 2:
            raise RecorderError(1)
        tables = r.ids(args[2:]) if len(args) > 2 else [t for t, tab in r.tables.items() if tab.option]
        first = int(_num(args[0]) or 0) - 1 if args else 0
        have = min((r.recorded(t, now) for t in tables), default=0)
        want = int(_num(args[1]) or 0) if args else have
        if first < 0 or want < 1 or (args and _num(args[1]) is None):
            raise RecorderError(17)
        n = max(0, min(want, have - first))
        head = ["# REM E-727", "# VERSION = 1", "# TYPE = 1", "# SEPARATOR = 32", f"# DIM = {len(tables)}",
                f"# SAMPLE_TIME = {r.rate * r.servo_cycle_s:.9g}", f"# NDATA = {n}"]
        head += [f"# NAME{i} = {r.name(t)}" for i, t in enumerate(tables)]
        head.append("# END_HEADER")
        fmt = " ".join(["%.6f"] * len(tables))
        data = np.column_stack([r.values(t, first, n) for t in tables]) if tables else np.zeros((n, 0))
        rows = [fmt % tuple(row) for row in data.tolist()]
        return (" \n".join(head + rows) + "\n").encode()

    def _wave_command(self, cmd: str, args: list[str]) -> bytes | None:
        """The wave generator commands; None when ``cmd`` is not one."""
        try:
            if cmd == "WAV":
                self.wave.wav(args)
                return b""
            if cmd in ("WSL", "WGC", "WGO"):
                self._cmd_now = self.now()  # one WGO starts all its generators on one tick
                for gen, val in self._int_pairs(args, 2):
                    {"WSL": self.wave.wsl, "WGC": self.wave.wgc}.get(cmd, self._wgo)(gen, val[0])
                return b""
            if cmd == "WTR":
                for gen, (rate, interp) in self._int_pairs(args, 3):
                    self.wave.wtr(gen, rate, interp)
                return b""
            if cmd == "TWC":  # no trigger points are simulated (TWS is not): nothing to clear
                return b""
            if cmd == "WOS":
                return self._wos(args)
            return self._wave_query(cmd, args)
        except WaveError as err:
            return self._latch(err.code)

    def _wos(self, args: list[str]) -> bytes:
        """``WOS <gen> <offset V> ...``: the generator's output offset."""
        if not args or len(args) % 2 or any(not a.isdigit() for a in args[::2]):
            raise WaveError(1)
        for g, v in zip(args[::2], args[1::2]):
            value = _num(v)
            if int(g) not in self.wave_offset_V or value is None:
                raise WaveError(17)
            self.wave_offset_V[int(g)] = float(value)
        return b""

    def _wgo(self, gen: int, mode: int) -> None:
        self.wave.wgo(gen, mode, self._cmd_now)
        if mode:
            self.recorder.event("wgo", self._cmd_now)  # once: the generators start on one tick

    @staticmethod
    def _int_pairs(args: list[str], width: int) -> list[tuple[int, list[int]]]:
        if not args or len(args) % width:
            raise WaveError(1)
        nums = [_num(a) for a in args]
        if any(v is None or v != int(v) for v in nums):
            raise WaveError(1)
        ints = [int(v) for v in nums]  # type: ignore[arg-type]
        return [(ints[i], ints[i + 1:i + width]) for i in range(0, len(ints), width)]

    def _wave_query(self, cmd: str, args: list[str]) -> bytes | None:
        w = self.wave
        if cmd not in ("WSL?", "WGC?", "WGO?", "WTR?", "WAV?", "WMS?", "WOS?"):
            return None
        ids = [int(a) for a in args if a.isdigit()]
        if cmd == "WOS?":
            gens = ids or list(self.wave_offset_V)
            if len(ids) != len(args) or any(g not in self.wave_offset_V for g in gens):
                raise WaveError(17)
            return self._items([(str(g), f"{self.wave_offset_V[g]:.4f}") for g in gens])
        if len(ids) != len(args):
            raise WaveError(1)
        gens = ids or list(w.gens)
        if cmd in ("WSL?", "WGC?", "WGO?", "WTR?"):
            if any(g not in w.gens for g in gens):
                raise WaveError(17)
            field = {"WSL?": lambda g: str(g.table), "WGC?": lambda g: str(g.cycles),
                     "WGO?": lambda g: str(g.mode), "WTR?": lambda g: f"{g.rate} {g.interpolation}"}[cmd]
            return self._items([(str(k), field(w.gens[k])) for k in gens])
        if cmd in ("WAV?", "WMS?"):
            tables = ids[::2] if cmd == "WAV?" and ids else (ids or list(w.tables))
            if any(t not in w.tables for t in tables) or (cmd == "WAV?" and any(p != 1 for p in ids[1::2])):
                raise WaveError(17)
            if cmd == "WAV?":
                return self._items([(f"{t} 1", str(len(w.tables[t]))) for t in tables])
            return self._items([(str(t), str(w.max_points)) for t in tables])
        return None

    def _spa_query(self, args: list[str]) -> bytes:
        """``SPA? 1 0x0E000200`` → the servo update time [s]; other parameters: error 56."""
        if len(args) != 2:
            return self._latch(1)
        try:
            param = int(args[1], 0)
        except ValueError:
            return self._latch(1)
        known = {SERVO_UPDATE_TIME_PARAM: f"{self.wave.servo_cycle_s:.9g}",
                 DATA_REC_MAX_POINTS_PARAM: str(TOTAL_POINTS),
                 DATA_REC_CHAN_NUMBER_PARAM: str(len(self.recorder.tables))}
        if args[0] not in _AXIS or param not in known:
            # PI: unknown parameter (54), answered with an empty line (unconfirmed: what a real
            # E-727 sends then; PIPython's getparam() reads the error and carries on)
            self._latch(54)
            return b"\n"
        return self._items([(f"{args[0]} {args[1]}", known[param])])

    def _spa(self, args: list[str]) -> bytes:
        """``SPA 1 0x16000300 <n>``: the data recorder's tables (1 to 8,
        :meth:`DataRecorder.set_tables`); the other parameters simulated here are not the
        host's to change (error 60, protected: command level too low), nor is this one when
        :attr:`record_tables_settable` is False (a firmware that protects it)."""
        if len(args) % 3 or not args:
            return self._latch(1)
        try:
            triples = [(item, int(param, 0), value) for item, param, value in zip(args[::3], args[1::3], args[2::3])]
        except ValueError:
            return self._latch(1)
        if any(item not in _AXIS or param != DATA_REC_CHAN_NUMBER_PARAM for item, param, _ in triples) or \
                not self.record_tables_settable:
            return self._latch(60)
        try:
            for _item, _param, value in triples:
                self.recorder.set_tables(int_token(value))
        except RecorderError as err:
            return self._latch(err.code)
        return b""

    def command(self, line: bytes) -> bytes:
        self.poll()
        self.commands += 1
        injected = self._take_injected()
        if injected is not None:
            self._latch(302 if injected is True else int(cast(int, injected)))  # tests inject a code
        try:
            tokens = line.decode("ascii").split()
        except UnicodeDecodeError:
            return self._latch(1)
        cmd, args = tokens[0].upper(), tokens[1:]
        if cmd == "SPA?":
            return self._spa_query(args)
        if cmd == "SPA":
            return self._spa(args)
        if cmd == "HPA?":  # the parameters this simulator knows: id= level max-item type group text
            return (b"0x0E000200=\t0\t1\tFLOAT\tservo\tservo update time [s] \n"
                    b"0x16000200=\t0\t1\tINT\tdata recorder\tdata recorder max points \n"
                    b"0x16000300=\t0\t1\tINT\tdata recorder\tdata recorder chan number\n")
        if cmd not in ("DRT", "DRT?", "ERR?"):
            self.recorder.event("command", self.now())  # DRT 2: "next command" triggers
        wave = self._wave_command(cmd, args)
        if wave is not None:
            return wave
        rec = self._recorder_command(cmd, args)
        if rec is not None:
            return rec
        if cmd == "ERR?":
            code, self.error = self.error, 0
            return f"{code}\n".encode()
        if cmd == "*IDN?":
            return IDN
        if cmd == "CSV?":
            return b"2\n"
        if cmd == "HLP?":
            # framed by a title and an end line, as a controller's help (PIPython strips both)
            lines = ["The following commands are available:", *_HELP, "end of help"]
            return b" \n".join(c.encode() for c in lines) + b"\n"
        if cmd == "MOV":
            return self._move(args)
        if cmd == "SAI?":
            return b" \n".join(k.encode() for k in _AXIS) + b"\n"
        if cmd in ("SVO", "SVA", "VMA", "VMI"):
            return self._set(cmd, args)
        if cmd in ("SVO?", "SVA?", "VOL?", "VMA?", "VMI?", "POS?", "MOV?", "ONT?", "TMN?", "TMX?"):
            keys = args or list(_AXIS)
            if any(k not in _AXIS for k in keys):
                return self._latch(15)
            tables: dict[str, Mapping[str, object]] = {"SVO?": {k: int(v) for k, v in self.servo.items()},
                     "SVA?": {k: f"{self.outputs[a]:.4f}" for k, a in _AXIS.items()},
                     "VOL?": {k: f"{self.outputs[a]:.4f}" for k, a in _AXIS.items()},
                     "VMA?": {k: f"{v:.4f}" for k, v in self.vma.items()},
                     "VMI?": {k: f"{v:.4f}" for k, v in self.vmi.items()},
                     "POS?": {k: f"{self.position_um(k):.4f}" for k in _AXIS},
                     "MOV?": {k: f"{v:.4f}" for k, v in self.target.items()},
                     "ONT?": {k: 1 for k in _AXIS},
                     "TMN?": {k: f"{self.travel_um[0]:.4f}" for k in _AXIS},
                     "TMX?": {k: f"{self.travel_um[1]:.4f}" for k in _AXIS}}
            table = tables[cmd]
            return self._items([(k, str(table[k])) for k in keys])
        return self._latch(2)

    def position_um(self, key: str) -> float:
        """Sensor position of axis ``key`` [µm]: linear over VMI..VMA onto the travel."""
        lo, hi = self.vmi[key], self.vma[key]
        frac = (self.outputs[_AXIS[key]] - lo) / (hi - lo) if hi > lo else 0.0
        return self.travel_um[0] + frac * (self.travel_um[1] - self.travel_um[0])

    def _move(self, args: list[str]) -> bytes:
        if not args or len(args) % 2:
            return self._latch(1)
        moves = {}
        for key, tok in zip(args[::2], args[1::2]):
            v = _num(tok)
            if key not in _AXIS:
                return self._latch(15)
            if v is None:
                return self._latch(1)
            if not self.servo[key]:
                return self._latch(5)   # PI: move not allowed with servo off
            if not self.travel_um[0] <= v <= self.travel_um[1]:
                return self._latch(7)   # PI: position out of limits
            moves[key] = v
        t0, t1 = self.travel_um
        for key, v in moves.items():
            self.target[key] = v
        self._apply({_AXIS[k]: self.vmi[k] + (v - t0) / (t1 - t0) * (self.vma[k] - self.vmi[k])
                     for k, v in moves.items()})
        return b""

    def _set(self, cmd: str, args: list[str]) -> bytes:
        if not args or len(args) % 2:
            return self._latch(1)
        pairs = list(zip(args[::2], args[1::2]))
        values = []
        for key, tok in pairs:
            if key not in _AXIS:
                return self._latch(15)
            v = _num(tok)
            if v is None:
                return self._latch(1)
            values.append((key, v))
        if cmd == "SVO":
            if any(v not in (0.0, 1.0) for _, v in values):
                return self._latch(17)
            for key, v in values:
                self.servo[key] = bool(v)
            return b""
        if cmd in ("VMA", "VMI"):
            for key, v in values:
                (self.vma if cmd == "VMA" else self.vmi)[key] = v
            return b""
        for key, v in values:  # SVA: all or nothing
            self._requested(v, _AXIS[key])
            if self.servo[key]:
                return self._latch(303)
            if not self.vmi[key] <= v <= self.vma[key]:
                return self._latch(302)
        self._apply({_AXIS[key]: v for key, v in values})
        return b""
