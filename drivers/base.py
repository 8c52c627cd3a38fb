"""The typed :class:`Amplifier` interface every backend implements.

Layering (as in pyLabLib / PIPython / caproto): a *transport* moves bytes or frames, a
*codec* (pure, no I/O) turns typed messages into bytes and back, and the *driver* here
speaks typed commands. A driver takes an open transport; it never builds one — see
:func:`afmctl.drivers.registry.open_amplifier` for selection by name and URL.

Voltages are in volts. Axes are named ``"x"``, ``"y"``, ``"z"`` (a single-channel unit has
only ``"x"``).

Streaming semantics: :meth:`Amplifier.set_voltages` checks the limits, writes the setpoint
and returns without waiting for the device where the protocol allows it (pipelining); an
error the device reports for an earlier setpoint is raised by a later call, and
:meth:`Amplifier.flush` waits until everything written has been applied and checked.
After a lost link (``DISCONNECTED``) or a silent device (``FAULT``) every command raises
:class:`~afmctl.drivers.errors.AmplifierConnectionError` until :meth:`Amplifier.reconnect`.
Implementations: :mod:`afmctl.drivers.mdt`, :mod:`afmctl.drivers.gcs`, :mod:`afmctl.drivers.nv200`,
:mod:`afmctl.drivers.can_amp`; see docs/DRIVERS.md.
"""
from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass

from .errors import LimitError


class ConnectionState(enum.Enum):
    """Visible link state: CONNECTED (commands accepted), DISCONNECTED (port lost),
    FAULT (device silent or bus error), RECONNECTING (inside reconnect()), CLOSED."""

    DISCONNECTED = "disconnected"
    CONNECTED = "connected"
    RECONNECTING = "reconnecting"
    FAULT = "fault"
    CLOSED = "closed"


@dataclass(frozen=True)
class VoltageLimits:
    """Closed interval [min_V, max_V] for one axis."""

    min_V: float
    max_V: float

    def check(self, axis: str, value_V: float) -> None:
        """Raise :class:`LimitError` naming the axis and range if ``value_V`` is outside."""
        if not (self.min_V <= value_V <= self.max_V):  # also rejects NaN
            raise LimitError(
                f"axis {axis}: {value_V!r} V is outside the allowed range "
                f"[{self.min_V:g}, {self.max_V:g}] V")


class Amplifier(ABC):
    """A piezo amplifier with one or more voltage channels."""

    #: driver name as used in configuration (``"mdt693b"``, ``"gcs"``, ``"nv200"``, ``"can"``)
    name: str = ""

    @property
    @abstractmethod
    def axes(self) -> tuple[str, ...]:
        """Axis names this unit drives."""

    @property
    @abstractmethod
    def limits(self) -> Mapping[str, VoltageLimits]:
        """Effective limits per axis: the intersection of device and host limits."""

    @property
    @abstractmethod
    def state(self) -> ConnectionState:
        """Visible connection state."""

    @abstractmethod
    def set_voltages(self, volts: Mapping[str, float]) -> None:
        """Command output voltages [V] on some axes (the others keep their value). Values
        outside :attr:`limits` (or NaN/inf) raise :class:`~afmctl.drivers.errors.LimitError` before
        any byte is sent. May return before the device applied it (see module notes)."""

    @abstractmethod
    def get_voltages(self) -> dict[str, float]:
        """Read back the applied output voltages [V] from the device."""

    @abstractmethod
    def info(self) -> dict[str, object]:
        """Identity and limits as read from the device."""

    def enable(self) -> None:
        """Enable the outputs (no-op where the device has no such command)."""

    def disable(self) -> None:
        """Disable the outputs (no-op where the device has no such command)."""

    def check_errors(self) -> None:
        """Query the device's error state and raise if it reports one."""

    def flush(self) -> None:
        """Wait until every pipelined setpoint has been written and checked."""

    @abstractmethod
    def reconnect(self) -> None:
        """Re-open the link with backoff and read back the actual output (never jumps)."""

    @abstractmethod
    def close(self) -> None:
        """Close the link. Idempotent."""

    def check_limits(self, volts: Mapping[str, float]) -> None:
        """Raise :class:`LimitError` if any value is outside :attr:`limits` or the axis is
        unknown."""
        lim = self.limits
        for axis, v in volts.items():
            if axis not in lim:
                raise LimitError(f"axis {axis!r} is not driven by {self.name or type(self).__name__}; "
                                 f"allowed axes: {', '.join(self.axes)}")
            lim[axis].check(axis, float(v))

    def __enter__(self) -> "Amplifier":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
