"""The typed :class:`Amplifier` interface every backend implements.

Layering (as in pyLabLib / PIPython / caproto): a *transport* moves bytes or frames, a
*codec* (pure, no I/O) turns typed messages into bytes and back, and the *driver* here
speaks typed commands. A driver takes an open transport; it never builds one — see
:func:`drivers.registry.open_amplifier` for selection by name and URL.

Voltages are in volts. Axes are named ``"x"``, ``"y"``, ``"z"`` (a single-channel unit has
only ``"x"``).
"""
from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass

from drivers.errors import LimitError


class ConnectionState(enum.Enum):
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
        """Command output voltages [V] on some axes. Values outside :attr:`limits` raise
        :class:`~drivers.errors.LimitError` before any byte is sent."""

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
