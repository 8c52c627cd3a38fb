"""Simulated Thorlabs MDT693B / MDT694B, byte-exact to docs/PROTOCOLS.md.

Choices where the protocol notes are unconfirmed: commands end at CR or LF (CRLF works;
empty lines are ignored); every query reply is bracketed and followed by ``\\r`` and the
prompt (``[ 24.80]\\r>``); ``XYZVOLTAGE=`` accepts the values with or without brackets;
values outside the limits are clamped; echo is ON at power-up (drivers send ``ECHO=0``);
``XMAX?`` reports 150.50 while ``VLIMIT?`` (the front-panel switch) reports 150, so the
usable range is 0-150 V. ``SYSMIN=``/``SYSMAX=`` set the limits of every channel.
"""
from __future__ import annotations

import re
from collections.abc import Callable

from .base import SimDevice, Sink

_NUM = r"\s*([+-]?(?:\d+(?:\.\d*)?|\.\d+))\s*"
_SET = re.compile(rb"([XYZ])VOLTAGE=" + _NUM.encode())
_SET3 = re.compile(rb"XYZVOLTAGE=\[?" + _NUM.encode() + b"," + _NUM.encode() + b"," + _NUM.encode() + rb"\]?")
_ALL = re.compile(rb"ALLVOLTAGE=" + _NUM.encode())
_LIM = re.compile(rb"([XYZ]|SYS)(MIN|MAX)=" + _NUM.encode())
_ECHO = re.compile(rb"ECHO=([01])")


class SimMDT693B(SimDevice):
    """``SimMDT693B(sink=None, now=None, channels=3, echo=True, prompt=b">", vlimit_V=150.0)``.

    ``channels=1`` behaves as an MDT694B (Y and Z commands are not defined).
    ``inject_error()`` answers the next command with ``CMD_NOT_DEFINED>``.
    """

    protocol = "mdt693b"

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None, channels: int = 3,
                 echo: bool = True, prompt: bytes = b">", vlimit_V: float = 150.0,
                 max_V: float = 150.5) -> None:
        self.axes = ("x", "y", "z")[:channels]
        super().__init__(sink, now=now)
        self.channels = channels
        self.echo = echo
        self.prompt = prompt
        self.vlimit_V = vlimit_V
        self._default_max = max_V
        self.min_V = {a: 0.0 for a in self.axes}
        self.max_V = {a: max_V for a in self.axes}

    def restore(self) -> None:
        self.min_V = {a: 0.0 for a in self.axes}
        self.max_V = {a: self._default_max for a in self.axes}

    def _clamp(self, axis: str, v: float) -> float:
        self._requested(v, axis)
        lo = self.min_V[axis]
        hi = min(self.max_V[axis], self.vlimit_V)
        return min(max(v, lo), hi)

    def reply(self, line: bytes) -> bytes:
        return (line + b"\r" if self.echo else b"") + self.command(line)

    def overflow(self) -> bytes:
        return b"CMD_NOT_DEFINED" + self.prompt

    def _ok(self, body: bytes = b"") -> bytes:
        return (body + b"\r" if body else b"") + self.prompt

    @staticmethod
    def _fmt(values: list[float]) -> bytes:
        return b"[" + b",".join(f"{v:6.2f}".encode() for v in values) + b"]"

    def command(self, line: bytes) -> bytes:
        """One command line (without terminator) → its complete reply."""
        self.commands += 1
        if self._take_injected() is not None:
            return b"CMD_NOT_DEFINED" + self.prompt
        cmd = line.strip().upper()
        ax = {b"X": "x", b"Y": "y", b"Z": "z"}
        if m := _SET.fullmatch(cmd):
            a = ax[m.group(1)]
            if a not in self.axes:
                return b"CMD_NOT_DEFINED" + self.prompt
            self._apply({a: self._clamp(a, float(m.group(2)))})
            return self._ok()
        if len(cmd) == 9 and cmd[1:] == b"VOLTAGE?" and cmd[:1] in ax and ax[cmd[:1]] in self.axes:
            return self._ok(self._fmt([self.outputs[ax[cmd[:1]]]]))
        if self.channels == 3 and (m := _SET3.fullmatch(cmd)):
            self._apply({a: self._clamp(a, float(m.group(k + 1))) for k, a in enumerate(self.axes)})
            return self._ok()
        if self.channels == 3 and cmd == b"XYZVOLTAGE?":
            return self._ok(self._fmt([self.outputs[a] for a in self.axes]))
        if m := _ALL.fullmatch(cmd):
            v = float(m.group(1))
            self._apply({a: self._clamp(a, v) for a in self.axes})
            return self._ok()
        if m := _LIM.fullmatch(cmd):
            which, kind, v = m.group(1), m.group(2), float(m.group(3))
            axes = self.axes if which == b"SYS" else [ax[which]] if ax[which] in self.axes else None
            if axes is None or not 0.0 <= v <= self._default_max:
                return b"CMD_NOT_DEFINED" + self.prompt
            for a in axes:
                (self.min_V if kind == b"MIN" else self.max_V)[a] = v
            return self._ok()
        if len(cmd) == 5 and cmd[1:] in (b"MIN?", b"MAX?") and cmd[:1] in ax and ax[cmd[:1]] in self.axes:
            a = ax[cmd[:1]]
            return self._ok(self._fmt([(self.min_V if cmd[1:] == b"MIN?" else self.max_V)[a]]))
        if cmd in (b"SYSMIN?", b"SYSMAX?"):
            vals = self.min_V.values() if cmd == b"SYSMIN?" else self.max_V.values()
            return self._ok(self._fmt([min(vals) if cmd == b"SYSMIN?" else max(vals)]))
        if cmd == b"VLIMIT?":
            return self._ok(f"[{self.vlimit_V:4.0f}]".encode())
        if m := _ECHO.fullmatch(cmd):
            self.echo = m.group(1) == b"1"
            return self._ok()
        if cmd == b"ECHO?":
            return self._ok(b"[%d]" % int(self.echo))
        if cmd == b"ID?":
            model = b"MDT693B" if self.channels == 3 else b"MDT694B"
            return (b"Model " + model + b"\rSimulated by afmctl sim_backend\rFirmware Version 1.09\r\r"
                    + self.prompt)
        if cmd == b"SERIAL?":
            return self._ok(b"[SIM00001]")
        if cmd == b"RESTORE":
            self.restore()
            return self._ok()
        return b"CMD_NOT_DEFINED" + self.prompt


def SimMDT694B(sink: Sink | None = None, **options) -> SimMDT693B:  # noqa: N802 - device name
    """The single-channel MDT694B."""
    return SimMDT693B(sink, channels=1, **options)
