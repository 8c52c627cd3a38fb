"""Simulated Thorlabs MDT693B / MDT694B, from the unit's command set as the vendor's manual
and MDT69x client libraries use it.

Wire format: commands end at CR or LF (the pairs CR LF and LF CR are one line end); an
empty line is answered ``CMD_NOT_DEFINED>`` (client libraries probe the port with it);
replies end with the prompt ``>``. Voltage read-backs (``XVOLTAGE?``, ``XYZVOLTAGE?``) are
the *measured* output, bracketed at 0.1 V resolution (``[ 24.8]``), not the setpoint;
``XMIN?``/``XMAX?`` answer bare numbers; ``VLIMIT?`` (the front-panel switch) ``[150]``;
``ID?`` ``key: value`` lines; ``ECHO?`` ``Echo On``/``Echo Off``. Values outside the
limits are clamped; echo is ON at power-up. ``XMAX?`` reports 150.50 while ``VLIMIT?``
reports 150, so the usable range is 0-150 V. ``SYSMIN=``/``SYSMAX=`` set every channel.

MDT693A compatibility mode (``cm=1``, ``cm?``): prompt ``*``; short commands ``XV<V>``,
``YV``, ``ZV``, ``AV`` (all), ``XR?``/``XR`` (read), ``XH<V>``/``XL<V>`` and ``XH?``/``XL?``
(limits), ``%`` (VLIMIT), ``E<0|1>`` (echo), ``I`` (ID); the long commands still work. An
undefined command is answered by the prompt alone in that mode (as client libraries
expect), ``CMD_NOT_DEFINED>`` otherwise.

Display intensity, master scan (``MSENABLE``, ``MSVOLTAGE``: added to every channel), the
rotary knob, the friendly name and the command list (``?``): :mod:`.mdt_panel`.
"""
from __future__ import annotations

import re
from collections.abc import Callable

from .base import SimDevice, Sink
from .mdt_panel import FrontPanel

_NUM = r"\s*([+-]?(?:\d+(?:\.\d*)?|\.\d+))\s*"
_SET = re.compile(rb"([XYZ])VOLTAGE=" + _NUM.encode())
_SET3 = re.compile(rb"XYZVOLTAGE=\[?" + _NUM.encode() + b"," + _NUM.encode() + b"," + _NUM.encode() + rb"\]?")
_ALL = re.compile(rb"ALLVOLTAGE=" + _NUM.encode())
_LIM = re.compile(rb"([XYZ]|SYS)(MIN|MAX)=" + _NUM.encode())
_ECHO = re.compile(rb"ECHO=([01])")
_CM = re.compile(rb"CM=([01])")
_SHORT_SET = re.compile(rb"([XYZA])V" + _NUM.encode())
_SHORT_LIM = re.compile(rb"([XYZ])([HL])" + _NUM.encode())


class SimMDT693B(SimDevice):
    """``SimMDT693B(sink=None, now=None, channels=3, echo=True, prompt=b">", vlimit_V=150.0,
    max_V=150.5, readback_step_V=0.1, readback_offset_V=0.0)``.

    ``channels=1`` behaves as an MDT694B (Y and Z commands are not defined).
    ``readback_step_V``/``readback_offset_V``: what the output measurement reports
    (0 = the exact output). ``inject_error()`` answers the next command as undefined.
    """

    protocol = "mdt693b"

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None, channels: int = 3,
                 echo: bool = True, prompt: bytes = b">", vlimit_V: float = 150.0,
                 max_V: float = 150.5, readback_step_V: float = 0.1, readback_offset_V: float = 0.0) -> None:
        self.axes = ("x", "y", "z")[:channels]
        super().__init__(sink, now=now)
        self.channels = channels
        self.echo = echo
        self.prompt = prompt
        self._normal_prompt = prompt
        self.compat = False
        self.vlimit_V = vlimit_V
        self.readback_step_V = readback_step_V
        self.readback_offset_V = readback_offset_V
        self._default_max = max_V
        self.min_V = {a: 0.0 for a in self.axes}
        self.max_V = {a: max_V for a in self.axes}
        #: the channel voltages as set (the output adds the master scan voltage) [V]
        self.set_V = {a: 0.0 for a in self.axes}
        self.panel = FrontPanel()

    def restore(self) -> None:
        self.min_V = {a: 0.0 for a in self.axes}
        self.max_V = {a: self._default_max for a in self.axes}

    def measured_V(self, axis: str) -> float:
        """The output as the unit measures and reports it [V]."""
        v = self.outputs[axis] + self.readback_offset_V
        if self.readback_step_V > 0:
            v = round(v / self.readback_step_V) * self.readback_step_V
        return v

    def _clamp(self, axis: str, v: float) -> float:
        self._requested(v, axis)
        return self._limit(axis, v)

    def _limit(self, axis: str, v: float) -> float:
        return min(max(v, self.min_V[axis]), min(self.max_V[axis], self.vlimit_V))

    def _set_channels(self, volts: dict[str, float]) -> None:
        """Channel voltages as set (already clamped) → the outputs: each plus the master
        scan voltage, held inside the channel's limits."""
        self.set_V.update(volts)
        offset = self.panel.master_offset_V()
        self._apply({a: self._limit(a, v + offset) if offset else v for a, v in volts.items()})

    def _master_changed(self) -> None:
        self._set_channels(dict(self.set_V))

    def reply(self, line: bytes) -> bytes:
        return (line + b"\r" if self.echo else b"") + self.command(line)

    def empty_line(self) -> bytes:
        return self._undefined()

    def overflow(self) -> bytes:
        return self._undefined()

    def _undefined(self) -> bytes:
        return self.prompt if self.compat else b"CMD_NOT_DEFINED" + self.prompt

    def _ok(self, body: bytes = b"") -> bytes:
        return (body + b"\r" if body else b"") + self.prompt

    def _readback(self, axes: list[str]) -> bytes:
        return self._ok(b"[" + b",".join(f"{self.measured_V(a):5.1f}".encode() for a in axes) + b"]")

    def command(self, line: bytes) -> bytes:
        """One command line (without terminator) → its complete reply."""
        self.commands += 1
        if self._take_injected() is not None:
            return self._undefined()
        cmd = line.strip().upper()
        for handler in (self._voltages, self._limits, self._system, self._compat_command, self._panel):
            out = handler(cmd)
            if out is not None:
                return out
        named = self.panel.set_name(line)
        return self._ok() if named else self._undefined()

    def _axis(self, letter: bytes) -> str | None:
        a = {b"X": "x", b"Y": "y", b"Z": "z"}.get(letter)
        return a if a in self.axes else None

    def _voltages(self, cmd: bytes) -> bytes | None:
        if m := _SET.fullmatch(cmd):
            a = self._axis(m.group(1))
            if a is None:
                return self._undefined()
            self._set_channels({a: self._clamp(a, float(m.group(2)))})
            return self._ok()
        if len(cmd) == 9 and cmd[1:] == b"VOLTAGE?" and (a := self._axis(cmd[:1])):
            return self._readback([a])
        if self.channels == 3 and (m := _SET3.fullmatch(cmd)):
            self._set_channels({a: self._clamp(a, float(m.group(k + 1))) for k, a in enumerate(self.axes)})
            return self._ok()
        if self.channels == 3 and cmd == b"XYZVOLTAGE?":
            return self._readback(list(self.axes))
        if m := _ALL.fullmatch(cmd):
            v = float(m.group(1))
            self._set_channels({a: self._clamp(a, v) for a in self.axes})
            return self._ok()
        return None

    def _limits(self, cmd: bytes) -> bytes | None:
        if m := _LIM.fullmatch(cmd):
            which, kind, v = m.group(1), m.group(2), float(m.group(3))
            axes = self.axes if which == b"SYS" else [self._axis(which)] if self._axis(which) else None
            return self._set_limit(axes, kind == b"MIN", v)
        if len(cmd) == 5 and cmd[1:] in (b"MIN?", b"MAX?") and (a := self._axis(cmd[:1])):
            return self._ok(f"{(self.min_V if cmd[1:] == b'MIN?' else self.max_V)[a]:.2f}".encode())
        if cmd in (b"SYSMIN?", b"SYSMAX?"):
            vals = self.min_V.values() if cmd == b"SYSMIN?" else self.max_V.values()
            return self._ok(f"{min(vals) if cmd == b'SYSMIN?' else max(vals):.2f}".encode())
        return None

    def _set_limit(self, axes, is_min: bool, v: float) -> bytes:
        if axes is None or not 0.0 <= v <= self._default_max:
            return self._undefined()
        for a in axes:
            (self.min_V if is_min else self.max_V)[a] = v
        return self._ok()

    def _system(self, cmd: bytes) -> bytes | None:
        if cmd == b"VLIMIT?":
            return self._ok(f"[{self.vlimit_V:.0f}]".encode())
        if m := _ECHO.fullmatch(cmd):
            self.echo = m.group(1) == b"1"
            return self._ok()
        if cmd == b"ECHO?":
            return self._ok(b"Echo On" if self.echo else b"Echo Off")
        if m := _CM.fullmatch(cmd):
            reply = self._ok()  # answered in the mode the command arrived in
            self.compat = m.group(1) == b"1"
            self.prompt = b"*" if self.compat else self._normal_prompt
            return reply
        if cmd == b"CM?":
            return self._ok(b"Compatibility Mode On" if self.compat else b"Compatibility Mode Off")
        if cmd in (b"ID?", b"I"):
            model = "MDT693B" if self.channels == 3 else "MDT694B"
            lines = [f"Model {model}", "Firmware Version: 1.09", f"Voltage Range: {self.vlimit_V:.0f}V",
                     "Serial Number: SIM00001", f"Name: {self.panel.name}"]
            return b"\r\n\r" + "\r".join(lines).encode() + b"\r\n" + self.prompt
        if cmd == b"SERIAL?":
            return b"SIM00001\r\n" + self.prompt
        if cmd == b"RESTORE":
            self.restore()
            return self._ok()
        return None

    def _panel(self, cmd: bytes) -> bytes | None:
        """Display, master scan, rotary knob, command list (:mod:`.mdt_panel`)."""
        body = self.panel.query(cmd)
        if body is not None:
            return self._ok(body)
        if cmd == b"FRIENDLY?":
            return self._ok(self.panel.name.encode())
        was = self.panel.master_offset_V()
        done = self.panel.set_int(cmd)
        if done is None and (v := self.panel.master_voltage(cmd)) is not None:
            self._requested(v, "master")
            self.panel.master_V, done = min(max(v, 0.0), self.vlimit_V), True
        if done is None:
            return None
        if self.panel.master_offset_V() != was:
            self._master_changed()
        return self._ok() if done else self._undefined()

    def _compat_command(self, cmd: bytes) -> bytes | None:
        """MDT693A short commands (compatibility mode only)."""
        if not self.compat:
            return None
        if m := _SHORT_SET.fullmatch(cmd):
            v = float(m.group(2))
            one = self._axis(m.group(1))
            if m.group(1) != b"A" and one is None:
                return self._undefined()
            axes = list(self.axes) if one is None else [one]
            self._set_channels({a: self._clamp(a, v) for a in axes})
            return self._ok()
        if len(cmd) in (2, 3) and cmd[1:2] == b"R" and cmd[2:] in (b"", b"?") and (a := self._axis(cmd[:1])):
            return self._readback([a])
        if m := _SHORT_LIM.fullmatch(cmd):
            a = self._axis(m.group(1))
            return self._set_limit([a] if a else None, m.group(2) == b"L", float(m.group(3)))
        if len(cmd) == 3 and cmd[1:2] in (b"H", b"L") and cmd[2:] == b"?" and (a := self._axis(cmd[:1])):
            return self._ok(f"{(self.max_V if cmd[1:2] == b'H' else self.min_V)[a]:.2f}".encode())
        if cmd == b"%":
            return self._ok(f"[{self.vlimit_V:.0f}]".encode())
        if cmd in (b"E0", b"E1"):
            self.echo = cmd == b"E1"
            return self._ok()
        return None


def SimMDT694B(sink: Sink | None = None, **options) -> SimMDT693B:  # noqa: N802 - device name
    """The single-channel MDT694B."""
    return SimMDT693B(sink, channels=1, **options)
