"""Thorlabs MDT693B (3 channels x, y, z) and MDT694B (1 channel x) over serial.

Streaming: every set command is answered by the prompt alone, so the driver writes
setpoints without waiting and counts the prompts as they come back, keeping at most
``max_in_flight`` commands unanswered (bounded latency, full link rate). A
``CMD_NOT_DEFINED`` reply to any pipelined command raises
:class:`~afmctl.drivers.errors.ProtocolError` at the next call.

Connect resynchronises on a known reply (``ID?`` names the model) instead of waiting for a
quiet line, so a link whose replies arrive 100 ms late (USB-serial latency timers,
serial-over-IP) connects, and a late ``CMD_NOT_DEFINED>`` for the bare line end is
skipped. The unit's read-back (``XVOLTAGE?``) is its *measured* output at 0.1 V
resolution (:attr:`MDT693B.readback_resolution_V`), not the setpoint echoed back.
"""
from __future__ import annotations

import collections

from . import codec_mdt as codec
from .base import VoltageLimits
from .errors import ProtocolError
from .serial_amp import SerialAmplifier
from .transport import SerialTransport


class MDT693B(SerialAmplifier):
    """Thorlabs MDT693B three-channel open-loop piezo controller.

    ``MDT693B(transport, host_limits=None, max_step_V=None, max_in_flight=32,
    reconnect_timeout_s=5.0)``; voltages in V, axes ``x, y, z``.
    """

    name = "mdt693b"
    _axes: tuple[str, ...] = ("x", "y", "z")
    #: resolution of the measured output the unit reports [V]
    readback_resolution_V = 0.1

    def __init__(self, transport: SerialTransport, *, max_in_flight: int = 32, **options) -> None:
        if max_in_flight < 1:
            raise ValueError("max_in_flight must be >= 1")
        self.max_in_flight = int(max_in_flight)
        self._pending: collections.deque[bytes] = collections.deque()
        self._prompts = codec.PROMPTS
        super().__init__(transport, **options)

    @property
    def axes(self) -> tuple[str, ...]:
        return self._axes

    def _split(self, buf: bytearray) -> int:
        return codec.split_reply(buf, self._prompts)

    def _reset_pipeline(self) -> None:
        self._pending.clear()
        self._prompts = codec.PROMPTS

    def _query(self, command: str) -> tuple[bytes, bytes]:
        cmd = codec.encode(command)
        self.transport.write(cmd)
        return cmd, self.transport.read_frame(self._split)

    def _handshake(self):
        probe = codec.encode("ECHO=0") + codec.encode("ID?")
        reply = self.transport.resync(codec.TERMINATOR, probe, self._split, codec.is_id_reply)
        self._prompts = reply[-1:]  # '>' (or '*' in compatibility mode) from now on
        ident = " | ".join(codec.parse_lines(codec.encode("ID?"), reply))
        cmd, reply = self._query("VLIMIT?")
        vlimit = codec.parse_value(cmd, reply)
        limits = {}
        for a in self._axes:
            lo = codec.parse_value(*self._query(f"{a.upper()}MIN?"))
            hi = codec.parse_value(*self._query(f"{a.upper()}MAX?"))
            hi = min(hi, vlimit)
            if not lo <= hi:
                raise ProtocolError(f"device limits of axis {a} are empty: [{lo}, {hi}] V")
            limits[a] = VoltageLimits(lo, hi)
        return limits, {"identity": ident, "vlimit_V": vlimit, "prompt": self._prompts.decode()}

    def _read_voltages(self) -> dict[str, float]:
        if len(self._axes) == 3:
            cmd, reply = self._query("XYZVOLTAGE?")
            return dict(zip(self._axes, codec.parse_values(cmd, reply, 3)))
        cmd, reply = self._query("XVOLTAGE?")
        return {"x": codec.parse_value(cmd, reply)}

    def _encode(self, values: dict[str, float]) -> list[bytes]:
        lim = self._limits
        if len(values) == 3 and len(self._axes) == 3:
            return [codec.encode_set_xyz([values[a] for a in self._axes],
                                         [lim[a].min_V for a in self._axes],
                                         [lim[a].max_V for a in self._axes])]
        return [codec.encode_set(a, v, lim[a].min_V, lim[a].max_V) for a, v in values.items()]

    def _handle(self, reply: bytes) -> None:
        cmd = self._pending.popleft()
        codec.parse_ack(cmd, reply)

    def _drain(self) -> None:
        for reply in self.transport.take_frames(self._split):
            if not self._pending:
                raise ProtocolError("unsolicited reply from MDT", data=reply)
            self._handle(reply)

    def _write_setpoint(self, values: dict[str, float]) -> None:
        commands = self._encode(values)  # raises LimitError before anything is written
        self._drain()
        while len(self._pending) + len(commands) > self.max_in_flight and self._pending:
            self._handle(self.transport.read_frame(self._split))
        self.transport.write(b"".join(commands))
        self._pending.extend(commands)

    def _sync(self) -> None:
        while self._pending:
            self._handle(self.transport.read_frame(self._split))
        self._drain()

    def raw(self, command: str) -> str:
        """Send one command line and return the reply body (for the bench; no limit check!
        Only queries ending in ``?`` are allowed)."""
        command = command.strip()
        # one printable line, no assignment: "XVOLTAGE=200\rID?" must not slip a set through
        if (not command.endswith("?") or "=" in command
                or any(not (" " <= ch <= "~") for ch in command)):
            raise ProtocolError(f"raw() only sends one query line (printable, ending in '?', no '='), "
                                f"got {command!r}")
        with self._lock:
            self._guard()
            self._io(self._sync)
            cmd, reply = self._io(self._query, command)
            return codec.reply_body(cmd, reply, self._prompts).decode("ascii", "replace")


class MDT694B(MDT693B):
    """Thorlabs MDT694B single-channel controller (axis ``x``)."""

    name = "mdt694b"
    _axes = ("x",)
