"""Physik Instrumente GCS controllers, open-loop subset (``SVO``, ``SVA``, ``VOL?``,
``VMI``/``VMA``, ``ERR?``) over serial.

Streaming: ``SVA`` has no reply, so setpoints are written back to back; every
``check_every`` setpoints the driver appends ``ERR?`` to the same write and reads that
reply when it has arrived (at most one check outstanding) — an error latched by the
device is raised as :class:`~afmctl.drivers.errors.ProtocolError` with its GCS code.
Connect resynchronises on the reply to ``*IDN?`` (no fixed quiet window), so replies that
arrive 100 ms late are fine.
"""
from __future__ import annotations

from . import codec_gcs as codec
from .base import VoltageLimits
from .errors import ProtocolError
from .serial_amp import SerialAmplifier
from .transport import SerialTransport

_AXES = ("x", "y", "z")


class GCSAmplifier(SerialAmplifier):
    """``GCSAmplifier(transport, n_axes=3, check_every=50, host_limits=None, ...)``.
    Axes x, y, z map onto the first ``n_axes`` GCS axis identifiers reported by ``SAI?``
    (and the voltage channels 1..n)."""

    name = "gcs"

    def __init__(self, transport: SerialTransport, *, n_axes: int = 3, check_every: int = 50, **options) -> None:
        if not 1 <= n_axes <= 3:
            raise ValueError("n_axes must be 1..3")
        self._axes = _AXES[:n_axes]
        self.check_every = max(1, int(check_every))
        self._ids: dict[str, str] = {}
        self._check_outstanding = False
        self._since_check = 0
        super().__init__(transport, **options)

    @property
    def axes(self) -> tuple[str, ...]:
        return self._axes

    def _reset_pipeline(self) -> None:
        self._check_outstanding = False
        self._since_check = 0

    def _query(self, command: str) -> bytes:
        self.transport.write(codec.encode(command))
        return self.transport.read_frame(codec.split_reply)

    def _check(self) -> None:
        codec.check_error_reply(self._query("ERR?"))

    def _handshake(self):
        # resynchronise on *IDN? (its reply holds commas, no other reply here does), then
        # read and clear an error latched before we came
        idn = self.transport.resync(codec.TERMINATOR, codec.encode("*IDN?"), codec.split_reply,
                                    lambda frame: b"," in frame).decode("ascii", "replace").strip()
        codec.parse_error_code(self._query("ERR?"))
        ids = codec.parse_axes(self._query("SAI?"))
        if len(ids) < len(self._axes):
            raise ProtocolError(f"controller has {len(ids)} axes, {len(self._axes)} needed", data=",".join(ids).encode())
        self._ids = dict(zip(self._axes, ids))
        id_list = " ".join(self._ids.values())
        self.transport.write(codec.encode("SVO " + " ".join(f"{i} 0" for i in self._ids.values())))
        self._check()
        chans = [str(k + 1) for k in range(len(self._axes))]
        vmi = codec.parse_items(self._query("VMI? " + " ".join(chans)), chans)
        vma = codec.parse_items(self._query("VMA? " + " ".join(chans)), chans)
        limits = {}
        for a, ch in zip(self._axes, chans):
            if not vmi[ch] <= vma[ch]:
                raise ProtocolError(f"device limits of axis {a} are empty: [{vmi[ch]}, {vma[ch]}] V")
            limits[a] = VoltageLimits(vmi[ch], vma[ch])
        return limits, {"identity": idn, "gcs_axes": id_list}

    def _read_voltages(self) -> dict[str, float]:
        chans = [str(k + 1) for k in range(len(self._axes))]
        items = codec.parse_items(self._query("VOL? " + " ".join(chans)), chans)
        return {a: items[ch] for a, ch in zip(self._axes, chans)}

    def _drain(self) -> None:
        for reply in self.transport.take_frames(codec.split_reply):
            if not self._check_outstanding:
                raise ProtocolError("unsolicited reply from GCS controller", data=reply)
            self._check_outstanding = False
            codec.check_error_reply(reply)

    def _write_setpoint(self, values: dict[str, float]) -> None:
        by_id = {self._ids[a]: v for a, v in values.items()}
        lows = {self._ids[a]: self._limits[a].min_V for a in values}
        highs = {self._ids[a]: self._limits[a].max_V for a in values}
        data = codec.encode_sva(by_id, lows, highs)
        self._drain()
        self._since_check += 1
        if self._since_check >= self.check_every and not self._check_outstanding:
            data += codec.encode("ERR?")
            self._check_outstanding = True
            self._since_check = 0
        self.transport.write(data)

    def _sync(self) -> None:
        if self._check_outstanding:
            reply = self.transport.read_frame(codec.split_reply)
            self._check_outstanding = False
            codec.check_error_reply(reply)
        self._check()
        self._since_check = 0
