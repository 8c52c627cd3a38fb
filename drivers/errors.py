"""The short exception hierarchy of :mod:`afmctl.drivers`.

Every error may carry the device's own error ``code`` and ``text`` and the raw bytes that
caused it (``data``), so that a person at the bench sees what the amplifier said.
"""
from __future__ import annotations


class AmplifierError(Exception):
    """Base of every driver error."""

    def __init__(self, message: str, *, code: int | str | None = None, text: str | None = None,
                 data: bytes | None = None) -> None:
        parts = [message]
        if code is not None:
            parts.append(f"device code {code}")
        if text:
            parts.append(f"device text {text!r}")
        if data is not None:
            parts.append(f"bytes {data!r}")
        super().__init__("; ".join(parts))
        self.code = code
        self.text = text
        self.data = data


class AmplifierConnectionError(AmplifierError):
    """The link could not be opened or was lost (port vanished, bus down). Named so that
    it does not shadow the builtin ``ConnectionError``."""


class AmplifierTimeout(AmplifierError):
    """A read or write did not complete within its timeout (device silent)."""


class ProtocolError(AmplifierError):
    """The device replied with bytes that do not parse, or with an error code."""


class LimitError(AmplifierError):
    """A requested value is outside the configured or device limits; nothing was sent."""


class RecorderUnavailable(AmplifierError):
    """The device has no data recorder (or none for what was asked, e.g. a position on a
    unit without a sensor): measure the motion with an external sensor and give it as a
    file (``t,y`` nm or ``t,x,y,z`` nm CSV; docs/DRIVERS.md, "Recording the motion")."""


class RecordingCancelled(AmplifierError):
    """A read-back of the data recorder was given up at the caller's request (between two
    of its chunks: the link is left clean)."""


class RecordingOverwritten(ProtocolError):
    """Points of a recording longer than the recorder (a ring, ``records_ring``) were asked
    for after the recorder had taken its capacity's worth more: they are gone. Read a ring
    back while it records, in step with it."""
