"""Simulated piezosystem jena NV200/D NET (open-loop voltage subset plus what the vendor's
client library reads at connect), from the NV200 command set as the vendor's
documentation and library describe it.

Wire format: commands end at CR, LF or CRLF; a read ``cmd`` is answered ``cmd,value\\r\\n``
+ XON, an error ``error,<n>\\r\\n`` + XON; a successful write sends nothing. A bare line end
is answered with the device type ``NV200/D_NET`` and CR LF (no XON), as the vendor's
library expects when it identifies the unit.

Parameters: ``set``, ``meas``, ``avmin``/``avmax`` [V], ``posmin``/``posmax`` (travel in
µm), ``stat`` (bit 0 actuator present, bits 1-2 sensor type, bit 3 closed loop), ``cl``,
``modsrc`` (1 at power-up: the setpoint follows the analog input until ``modsrc,0``),
``sr`` (slew rate in %/ms, 2000 = off), ``temp``, ``desc``, ``acserno``, ``acmeasure``,
``unitol``/``unitcl``, the data recorder (``recsrc``, ``recast``, ``recstr``, ``reclen``,
``recrun``, ``recoutf``, ``recout``; :mod:`.nv200_recorder`: with a sensor the position is the
sink's position sensor where the sink has one, e.g. the simulated scanner), and the arbitrary
waveform generator (``gbarb``, ``goarb``, ``gsarb``, ``gearb``, ``gcarb``, ``gtarb``,
``grun``; :mod:`.nv200_wave`), which drives the output while ``modsrc`` is 3: a buffer
value p [%] is the voltage ``avmin + p/100 (avmax - avmin)`` in open loop. It plays on the
unit's 50 us clock; every command and :meth:`SimNV200.poll` apply the samples due by then.

``meas`` is the piezo voltage without a sensor (``sensor="none"``) and the position in
µm with one (linear over the voltage range); ``set`` outside ``avmin..avmax`` gives
``error,4`` and changes nothing.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numpy as np

from .base import SimDevice, Sink
from .nv200_recorder import NV200Recorder
from .nv200_wave import BUFFER_SIZE, RANGES as WAVE_RANGES, WaveBuffer

XON = b"\x11"
DEVICE_TYPE = b"NV200/D_NET"
SENSOR_BITS = {"none": 0, "strain gauge": 1, "capacitive": 2, "LVDT": 3}
_READ_ONLY = {"meas", "avmin", "avmax", "stat", "temp", "desc", "acserno", "acmeasure", "posmin", "posmax",
              "unitol", "unitcl"}
_INT = {"cl", "modsrc", "stat", "grun", "goarb", "gsarb", "gearb", "gcarb", "gtarb", "acmeasure", "recast", "recstr", "reclen", "recrun"}
_RANGES = {"cl": (0, 1), "modsrc": (0, 3), "recast": (0, 2), "recstr": (1, 65535), "reclen": (0, 6144),
           "recrun": (0, 1), "sr": (0.0000008, 2000.0)}


class SimNV200(SimDevice):
    """``SimNV200(sink=None, now=None, avmin_V=-20.0, avmax_V=130.0, sensor="none",
    posmax_um=100.0)``; axis ``x``. ``inject_error(code)`` answers the next command with
    ``error,<code>`` (default 4)."""

    protocol = "nv200"
    axes = ("x",)

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None,
                 avmin_V: float = -20.0, avmax_V: float = 130.0, sensor: str = "none",
                 posmax_um: float = 100.0) -> None:
        super().__init__(sink, now=now)
        self.wave = WaveBuffer(self._wave_apply)
        if sensor not in SENSOR_BITS:
            raise ValueError(f"sensor must be one of {', '.join(SENSOR_BITS)}")
        self.sensor = sensor
        self.params: dict[str, float] = {"set": 0.0, "cl": 0, "modsrc": 1, "sr": 2000.0,
                                         "avmin": avmin_V, "avmax": avmax_V, "posmin": 0.0,
                                         "posmax": posmax_um if sensor != "none" else avmax_V,
                                         "temp": 31.5, "recast": 0, "recstr": 1, "reclen": 6144, "recrun": 0}
        self.text = {"desc": "TRITOR100SG" if sensor != "none" else "PSH15", "acserno": "SIM00001",
                     "unitol": "V", "unitcl": "um" if sensor != "none" else "V"}
        self.recorder = NV200Recorder(self._sensor_capture, self._position_of, sensor != "none")
        #: every write of a setting the unit stores in the actuator's memory: (name, value)
        self.stored_writes: list[tuple[str, int]] = []

    # -- the unit's quantities --
    def position_um(self) -> float:
        lo, hi = self.params["avmin"], self.params["avmax"]
        frac = (self.outputs["x"] - lo) / (hi - lo) if hi > lo else 0.0
        return self.params["posmin"] + frac * (self.params["posmax"] - self.params["posmin"])

    def status_word(self) -> int:
        return 1 | (SENSOR_BITS[self.sensor] << 1) | (8 if self.params["cl"] else 0)

    def _source_value(self, src: int) -> float:
        return {0: self.position_um() if self.sensor != "none" else self.outputs["x"],
                1: self.params["set"], 2: self.outputs["x"]}.get(src, 0.0)

    def _position_of(self, volts: float) -> float:
        lo, hi = self.params["avmin"], self.params["avmax"]
        frac = (volts - lo) / (hi - lo) if hi > lo else 0.0
        return self.params["posmin"] + frac * (self.params["posmax"] - self.params["posmin"])

    def _sensor_capture(self, t0_s: float, period_s: float, n: int):
        capture = getattr(self.sink, "capture_sensor", None)
        return capture(t0_s, period_s, n) if capture is not None else None

    def _sense_now(self) -> float:
        """Play the waveform, then bring the sink's simulation (its sensor) and the recorder up
        to now (the recorder must not fill samples due by now before the wave has played them)."""
        now = self.now()
        self._play_due(now)
        advance = getattr(self.sink, "advance", None)
        if advance is not None and getattr(self.sink, "capture_sensor", None) is not None:
            advance(now)
        self.recorder.sync(now)
        return now

    def _apply(self, changes) -> None:
        now = self.now()
        super()._apply(changes)
        self.recorder.output_changed(now, self.outputs["x"], self.params["set"])

    # -- wire --
    def _reply(self, name: str, value: str | float) -> bytes:
        if isinstance(value, str):
            text = value
        else:
            text = f"{int(value)}" if name in _INT else f"{value:.3f}"
        return f"{name},{text}\r\n".encode() + XON

    @staticmethod
    def _error(code: int) -> bytes:
        return f"error,{code}\r\n".encode() + XON

    def overflow(self) -> bytes:
        return self._error(1)

    def empty_line(self) -> bytes:
        return DEVICE_TYPE + b"\r\n"

    def poll(self) -> None:
        """Play the waveform samples that fell due by now and bring the load up to now (the
        servers call this when idle; the simulator's clock thread calls :meth:`play_due`)."""
        with self.lock:
            now = self.now()
            self._play_due(now)
            self.advance_load(now)

    def _play_due(self, now_s: float) -> None:
        """The waveform samples due by ``now_s`` as one block: the outputs for all of them at
        once, the recorder told in one call, the sink handed the changes in one
        ``sink.play(t_s, rows_V)`` where it has one (else one ``apply`` per change) — one
        call per sample costs more than the 50 µs tick on a loaded host."""
        t, percent = self.wave.take_due(now_s)
        if not len(t) or self.params["modsrc"] != 3:
            return
        lo, hi = self.params["avmin"], self.params["avmax"]
        v = lo + percent / 100.0 * (hi - lo)
        self._requested(float(v.min()), "x")
        self._requested(float(v.max()), "x")
        v = np.clip(v, lo, hi)
        changed = v != np.concatenate([[self.outputs["x"]], v[:-1]])
        if not changed.any():
            return
        t, v = t[changed], v[changed]
        self.outputs["x"] = float(v[-1])
        self.recorder.outputs_changed(t, v, v)
        play, held = getattr(self.sink, "play", None), getattr(self.sink, "held_voltage_V", None)
        if play is not None and held is not None:       # the load's other axes keep their voltage
            rows = np.repeat(np.asarray(held(), dtype=np.float64).reshape(1, 3), len(v), axis=0)
            rows[:, 0] = v
            play(t, rows)
        elif self.sink is not None:
            for tk, vk in zip(t.tolist(), v.tolist()):
                self.sink.apply({**self.outputs, "x": vk}, tk)

    def _wave_apply(self, percent: float, t_s: float) -> None:
        if self.params["modsrc"] != 3:
            return
        lo, hi = self.params["avmin"], self.params["avmax"]
        v = lo + percent / 100.0 * (hi - lo)
        self._requested(v, "x")
        v = min(max(v, lo), hi)
        if self.outputs["x"] != v:
            self.outputs["x"] = v
            self.recorder.output_changed(t_s, v, v)
            if self.sink is not None:
                self.sink.apply(dict(self.outputs), t_s)

    def _waveform(self, name: str, args: list[str]) -> bytes:
        try:
            nums = [float(a) for a in args]
        except ValueError:
            return self._error(1)
        if any(v != v or abs(v) == float("inf") for v in nums):
            return self._error(1)
        if name == "gbarb":
            if not nums or nums[0] != int(nums[0]) or not 0 <= nums[0] < BUFFER_SIZE or len(nums) > 2:
                return self._error(4 if nums else 3)
            i = int(nums[0])
            if len(nums) == 1:
                return f"gbarb,{i},{self.wave.values[i]:.3f}\r\n".encode() + XON
            if not 0.0 <= nums[1] <= 100.0:
                return self._error(4)
            self.wave.values[i] = nums[1]
            return b""
        if not nums:
            return self._reply(name, self.wave.params[name])
        if len(nums) > 1 or nums[0] != int(nums[0]):
            return self._error(5 if len(nums) > 1 else 4)
        was_running = self.wave.params["grun"]
        if not self.wave.set(name, int(nums[0]), self.now()):
            return self._error(4)
        if name == "grun" and nums[0] == 1 and not was_running and self.params["recast"] == 2:
            # recast 2: the recorder starts with the generator, on the tick of its sample 0
            self.recorder.start(self.wave.t0_s, int(self.params["recstr"]), int(self.params["reclen"]))
        return b""

    def command(self, line: bytes) -> bytes:
        self.poll()
        self.commands += 1
        injected = self._take_injected()
        if injected is not None:
            return self._error(4 if injected is True else int(cast(int, injected)))  # tests inject a code
        try:
            fields = [f.strip() for f in line.decode("ascii").strip().split(",")]
        except UnicodeDecodeError:
            return self._error(1)
        name, args = fields[0].lower(), fields[1:]
        if name in ("recsrc", "recout", "recoutf"):
            return self._recorder(name, args)
        if name == "gbarb" or name in WAVE_RANGES:
            return self._waveform(name, args)
        if name not in self.params and name not in self.text and name not in _READ_ONLY:
            return self._error(2)
        if not args:
            return self._read(name)
        if name in _READ_ONLY or name in self.text:
            return self._error(6)
        if len(args) > 1:
            return self._error(5)
        return self._write(name, args[0])

    def _read(self, name: str) -> bytes:
        if name == "meas":
            return self._reply(name, self._source_value(0))
        if name == "recrun":
            self._sense_now()
            return self._reply(name, int(self.recorder.running))
        if name == "stat":
            return self._reply(name, self.status_word())
        if name == "acmeasure":
            return self._reply(name, SENSOR_BITS[self.sensor])
        if name in self.text:
            return self._reply(name, self.text[name])
        return self._reply(name, self.params[name])

    def _write(self, name: str, arg: str) -> bytes:
        if not arg:
            return self._error(3)
        try:
            v = float(arg)
        except ValueError:
            return self._error(1)
        if v != v or abs(v) == float("inf"):
            return self._error(1)
        if name == "set":
            self._requested(v, "x")
            if not self.params["avmin"] <= v <= self.params["avmax"]:
                return self._error(4)
            self.params["set"] = v
            if self.recorder.state == "armed" and self.params["recast"] == 1:
                self.recorder.start(self.now(), int(self.params["recstr"]), int(self.params["reclen"]))
            if self.params["modsrc"] == 0:
                self._apply({"x": v})
            return b""
        lo, hi = _RANGES.get(name, (-float("inf"), float("inf")))
        if (name in _INT and v != int(v)) or not lo <= v <= hi:
            return self._error(4)
        self.params[name] = int(v) if name in _INT else v
        if name in ("cl", "modsrc"):
            self.stored_writes.append((name, int(v)))
        if name == "recrun":
            self._recrun(int(v))
        return b""

    def _recrun(self, v: int) -> None:
        """``recrun,1`` arms the recorder (``recast`` 0: it starts on the next tick),
        ``recrun,0`` stops it."""
        now = self._sense_now()
        if v == 0:
            self.recorder.stop()
        elif self.params["recast"] == 0:
            self.recorder.start(now, int(self.params["recstr"]), int(self.params["reclen"]))
        else:
            self.recorder.arm()

    def _recorder(self, name: str, args: list[str]) -> bytes:
        try:
            nums = [int(a) for a in args]
        except ValueError:
            return self._error(1)
        if not nums or nums[0] not in (0, 1):
            return self._error(3 if not nums else 4)
        ch = nums[0]
        rec = self.recorder
        if name == "recsrc":
            if len(nums) == 1:
                return f"recsrc,{ch},{rec.recsrc[ch]}\r\n".encode() + XON
            if len(nums) != 2 or not 0 <= nums[1] <= 7:
                return self._error(4)
            rec.recsrc[ch] = nums[1]
            return b""
        self._sense_now()
        data = rec.values(ch).tolist()
        if name == "recoutf":
            return (f"recoutf,{ch}," + ",".join(f"{v:.3f}" for v in data) + "\r\n").encode() + XON
        if len(nums) != 3:
            return self._error(3)
        idx, n = nums[1], nums[2]
        values = data[idx:idx + max(n, 1)]
        if not values:
            return self._error(4)
        return (f"recout,{ch},{idx}," + ",".join(f"{v:.3f}" for v in values) + "\r\n").encode() + XON
