"""Simulated piezosystem jena NV200 (open-loop voltage subset), byte-exact to docs/PROTOCOLS.md.

Choices where the protocol notes are unconfirmed: a successful write sends no reply; a
read ``cmd`` is answered ``cmd,value\\r\\n`` + XON; errors ``error,<n>\\r\\n`` + XON. Lines
end at CR, LF or CRLF. At power-up ``modsrc`` is 1 (analog input), so ``set`` changes the
output only after ``modsrc,0``. ``set`` outside ``avmin..avmax`` gives ``error,4`` and
changes nothing. Output voltages are reported by ``meas`` (open loop).
"""
from __future__ import annotations

from collections.abc import Callable

from .base import SimDevice, Sink

XON = b"\x11"
_READ_ONLY = {"meas", "avmin", "avmax", "stat"}
_PARAMS = {"set", "meas", "avmin", "avmax", "stat", "cl", "modsrc", "sr"}


class SimNV200(SimDevice):
    """``SimNV200(sink=None, now=None, avmin_V=-20.0, avmax_V=130.0)``; axis ``x``.
    ``inject_error(code)`` answers the next command with ``error,<code>`` (default 4)."""

    protocol = "nv200"
    axes = ("x",)

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None,
                 avmin_V: float = -20.0, avmax_V: float = 130.0) -> None:
        super().__init__(sink, now=now)
        self.params: dict[str, float] = {"set": 0.0, "cl": 0, "modsrc": 1, "sr": 100.0,
                                         "avmin": avmin_V, "avmax": avmax_V}

    def _reply(self, name: str, value: float) -> bytes:
        text = f"{int(value)}" if name in ("cl", "modsrc", "stat") else f"{value:.3f}"
        return f"{name},{text}\r\n".encode() + XON

    @staticmethod
    def _error(code: int) -> bytes:
        return f"error,{code}\r\n".encode() + XON

    def status_word(self) -> int:
        return 1 | (8 if self.params["cl"] else 0)

    def overflow(self) -> bytes:
        return self._error(1)

    def command(self, line: bytes) -> bytes:
        self.commands += 1
        injected = self._take_injected()
        if injected is not None:
            return self._error(4 if injected is True else int(injected))  # type: ignore[arg-type]
        try:
            fields = line.decode("ascii").strip().split(",")
        except UnicodeDecodeError:
            return self._error(1)
        name, args = fields[0].strip().lower(), fields[1:]
        if name not in _PARAMS:
            return self._error(2)
        if not args:
            if name == "meas":
                return self._reply(name, self.outputs["x"])
            if name == "stat":
                return self._reply(name, self.status_word())
            return self._reply(name, self.params[name])
        if name in _READ_ONLY:
            return self._error(6)
        if len(args) > 1:
            return self._error(5)
        if not args[0].strip():
            return self._error(3)
        try:
            v = float(args[0])
        except ValueError:
            return self._error(1)
        if v != v or abs(v) == float("inf"):
            return self._error(1)
        if name == "set":
            self._requested(v, "x")
            if not self.params["avmin"] <= v <= self.params["avmax"]:
                return self._error(4)
            self.params["set"] = v
            if self.params["modsrc"] == 0:
                self._apply({"x": v})
            return b""
        if name in ("cl", "modsrc"):
            if v != int(v) or not 0 <= v <= (1 if name == "cl" else 3):
                return self._error(4)
            self.params[name] = int(v)
            return b""
        if name == "sr":
            if not 0 < v <= 100:
                return self._error(4)
        self.params[name] = v
        return b""
