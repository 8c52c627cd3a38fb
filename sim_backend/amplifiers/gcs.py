"""Simulated PI GCS controller (open-loop subset of an E-727), byte-exact to docs/PROTOCOLS.md.

Axes ``1 2 3`` drive outputs x, y, z; voltage channels ``1 2 3`` belong to the same axes.
At power-up the servo is ON (so ``SVA`` gives error 303 until ``SVO <axis> 0``). An
``SVA`` with any bad argument applies nothing and latches the error. The first error
latched stays until ``ERR?`` reads and clears it. Commands are case-insensitive; lines end
at LF (a CR before it is ignored).
"""
from __future__ import annotations

from collections.abc import Callable

from .base import SimDevice, Sink

_AXIS = {"1": "x", "2": "y", "3": "z"}


def _num(tok: str) -> float | None:
    try:
        v = float(tok)
    except ValueError:
        return None
    return v if v == v and abs(v) != float("inf") else None


class SimGCS(SimDevice):
    """``SimGCS(sink=None, now=None, vmin_V=0.0, vmax_V=120.0)``. ``inject_error(code)``
    latches ``code`` (default 302) on the next command."""

    protocol = "gcs"

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None,
                 vmin_V: float = 0.0, vmax_V: float = 120.0) -> None:
        super().__init__(sink, now=now)
        self.servo = {k: True for k in _AXIS}
        self.vmi = {k: vmin_V for k in _AXIS}
        self.vma = {k: vmax_V for k in _AXIS}
        self.error = 0

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

    def command(self, line: bytes) -> bytes:
        self.commands += 1
        injected = self._take_injected()
        if injected is not None:
            self._latch(302 if injected is True else int(injected))  # type: ignore[arg-type]
        try:
            tokens = line.decode("ascii").split()
        except UnicodeDecodeError:
            return self._latch(1)
        cmd, args = tokens[0].upper(), tokens[1:]
        if cmd == "ERR?":
            code, self.error = self.error, 0
            return f"{code}\n".encode()
        if cmd == "*IDN?":
            return b"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, E-727 (simulated by afmctl), 0, 1.0\n"
        if cmd == "SAI?":
            return b" \n".join(k.encode() for k in _AXIS) + b"\n"
        if cmd in ("SVO", "SVA", "VMA", "VMI"):
            return self._set(cmd, args)
        if cmd in ("SVO?", "SVA?", "VOL?", "VMA?", "VMI?"):
            keys = args or list(_AXIS)
            if any(k not in _AXIS for k in keys):
                return self._latch(15)
            table = {"SVO?": {k: int(v) for k, v in self.servo.items()},
                     "SVA?": {k: f"{self.outputs[a]:.4f}" for k, a in _AXIS.items()},
                     "VOL?": {k: f"{self.outputs[a]:.4f}" for k, a in _AXIS.items()},
                     "VMA?": {k: f"{v:.4f}" for k, v in self.vma.items()},
                     "VMI?": {k: f"{v:.4f}" for k, v in self.vmi.items()}}[cmd]
            return self._items([(k, str(table[k])) for k in keys])
        return self._latch(2)

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
