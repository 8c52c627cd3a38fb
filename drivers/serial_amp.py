"""Common machinery of the serial amplifier drivers: limits, connection state, error
mapping, pipelined writes and reconnect with backoff.

A driver takes an open-able :class:`~afmctl.drivers.transport.SerialTransport`; it never builds
one (see :func:`afmctl.drivers.registry.open_amplifier`).

Life cycle: the constructor connects (handshake, device limits, read-back of the actual
output). A lost port puts the driver in ``DISCONNECTED``, a silent device (timeout) or a
garbled reply in ``FAULT``; both refuse further commands until :meth:`reconnect`, which reopens the port
with exponential backoff, reads back what the amplifier outputs *now* and sends no
setpoint (so the output never jumps). :meth:`close` is idempotent.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from abc import abstractmethod
from collections.abc import Mapping

from .base import Amplifier, ConnectionState, VoltageLimits
from .errors import AmplifierConnectionError, AmplifierError, AmplifierTimeout, LimitError, ProtocolError
from .transport import SerialTransport

log = logging.getLogger(__name__)

HostLimits = Mapping[str, "VoltageLimits | tuple[float, float]"] | tuple[float, float] | VoltageLimits | None


def normalize_host_limits(host_limits: HostLimits, axes: tuple[str, ...]) -> dict[str, VoltageLimits]:
    """Host limits as given by a user: one ``(min_V, max_V)`` for all axes, or a mapping
    axis -> ``(min_V, max_V)`` in which the key ``"*"`` stands for every axis not named."""
    if host_limits is None:
        return {}
    if isinstance(host_limits, VoltageLimits) or (isinstance(host_limits, tuple) and len(host_limits) == 2
                                                   and not isinstance(host_limits[0], tuple)):
        items = {a: host_limits for a in axes}
    else:
        items = dict(host_limits)  # type: ignore[arg-type]
        if "*" in items:
            common = items.pop("*")
            items = {**{a: common for a in axes}, **items}
    out = {}
    for axis, lim in items.items():
        if not isinstance(lim, VoltageLimits):
            lo, hi = lim  # type: ignore[misc]
            lim = VoltageLimits(float(lo), float(hi))
        if not (math.isfinite(lim.min_V) and math.isfinite(lim.max_V) and lim.min_V <= lim.max_V):
            raise LimitError(f"host limits for axis {axis}: [{lim.min_V}, {lim.max_V}] V is not a valid range")
        out[axis] = lim
    return out


def intersect_limits(device: Mapping[str, VoltageLimits], host: Mapping[str, VoltageLimits]) -> dict[str, VoltageLimits]:
    out = {}
    for axis, d in device.items():
        h = host.get(axis)
        lo, hi = (d.min_V, d.max_V) if h is None else (max(d.min_V, h.min_V), min(d.max_V, h.max_V))
        if lo > hi:
            raise LimitError(f"axis {axis}: host limits [{h.min_V:g}, {h.max_V:g}] V do not overlap the "
                             f"device range [{d.min_V:g}, {d.max_V:g}] V")
        out[axis] = VoltageLimits(lo, hi)
    unknown = set(host) - set(device)
    if unknown:
        raise LimitError(f"host limits name unknown axis {sorted(unknown)}; axes: {', '.join(device)}")
    return out


def _volts(axis: object, value: object) -> float:
    """``value`` as a float [V], or LimitError: text, bytes and booleans are not voltages
    (``"5"`` or ``True`` is a caller's bug, not a request), and a number too large for a
    float is out of every range."""
    if isinstance(value, (str, bytes, bytearray, bool, _numpy_bool_types())):
        raise LimitError(f"axis {axis}: {value!r} is not a voltage (expected a number of volts)")
    try:
        return float(value)  # type: ignore[arg-type]
    except OverflowError:
        raise LimitError(f"axis {axis}: {value!r} V is outside every voltage range") from None
    except (TypeError, ValueError) as err:
        raise LimitError(f"axis {axis}: voltage is not a number: {err}") from None


def _numpy_bool_types() -> tuple[type, ...]:
    """numpy's bool type if numpy is already imported (drivers do not import it)."""
    import sys
    np = sys.modules.get("numpy")
    return (np.bool_,) if np is not None else ()


class LimitedAmplifier(Amplifier):
    """What every backend (serial and CAN) shares: host-side limit checks, the visible
    state, the lock that serialises callers, and reconnect with backoff. A backend
    implements :meth:`_open_and_handshake`; ``transport`` has ``close()`` and ``url``."""

    def __init__(self, transport: object, *, host_limits: HostLimits = None, max_step_V: float | None = None,
                 reconnect_timeout_s: float = 5.0, backoff_s: tuple[float, float] = (0.05, 1.0)) -> None:
        self.transport = transport
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.backoff_s = backoff_s
        self._state = ConnectionState.DISCONNECTED
        self._lock = threading.RLock()
        self.reconnects = 0
        self._host_limits_arg = host_limits
        self._limits: dict[str, VoltageLimits] = {}
        self._device_limits: dict[str, VoltageLimits] = {}
        self._last: dict[str, float] = {}
        if max_step_V is not None and not (max_step_V > 0 and math.isfinite(max_step_V)):
            raise LimitError(f"max_step_V must be a positive number of volts, got {max_step_V!r}")
        self.max_step_V = max_step_V

    @property
    def limits(self) -> Mapping[str, VoltageLimits]:
        return dict(self._limits)

    @property
    def device_limits(self) -> Mapping[str, VoltageLimits]:
        return dict(self._device_limits)

    @property
    def last_output(self) -> dict[str, float]:
        """Last voltages commanded or read back [V] (the output the driver believes in)."""
        return dict(self._last)

    def _set_device_limits(self, device: Mapping[str, VoltageLimits]) -> None:
        self._device_limits = dict(device)
        self._limits = intersect_limits(device, normalize_host_limits(self._host_limits_arg, tuple(device)))

    def validate(self, volts: Mapping[str, float]) -> dict[str, float]:
        """Limit check of a request (finite, inside limits, within ``max_step_V`` of the
        last output); returns the request as ``{axis: float}`` in axis order."""
        if not isinstance(volts, Mapping):
            raise LimitError(f"voltages must be a mapping axis -> V, e.g. {{'x': 10.0}}; got {type(volts).__name__}")
        if not volts:
            raise LimitError("no axis given; axes: " + ", ".join(self.axes))
        values = {a: _volts(a, v) for a, v in volts.items()}
        self.check_limits(values)
        if self.max_step_V is not None:
            for a, v in values.items():
                prev = self._last.get(a)
                if prev is not None and abs(v - prev) > self.max_step_V:
                    raise LimitError(f"axis {a}: step {prev:g} V -> {v:g} V exceeds max_step_V={self.max_step_V:g} V")
        return {a: values[a] for a in self.axes if a in values}

    @property
    def state(self) -> ConnectionState:
        return self._state

    @abstractmethod
    def _open_and_handshake(self) -> None:
        """Open the transport if needed, read the device limits and the actual output."""

    def reconnect(self) -> None:
        """Close and re-open the link until the handshake succeeds, waiting ``backoff_s``
        (first, largest delay [s]) doubling between attempts, for at most
        ``reconnect_timeout_s``. Sends no setpoint: :attr:`last_output` is what the
        amplifier outputs now, so the output never jumps."""
        with self._lock:
            if self._state is ConnectionState.CLOSED:
                raise AmplifierConnectionError(f"{self.name} is closed; open a new one")
            self._state = ConnectionState.RECONNECTING
            deadline = time.monotonic() + self.reconnect_timeout_s
            delay, max_delay = self.backoff_s
            last_err: AmplifierError | None = None
            while True:
                self.transport.close()
                try:
                    self._open_and_handshake()
                except AmplifierError as err:
                    last_err = err
                    log.info("%s: reconnect to %s failed (%s); retrying in %.2f s", self.name,
                             self.transport.url, err, delay)
                else:
                    self._state = ConnectionState.CONNECTED
                    self.reconnects += 1
                    log.info("%s: reconnected to %s; output is %s", self.name, self.transport.url, self._last)
                    return
                if time.monotonic() + delay > deadline:
                    self.transport.close()
                    self._state = ConnectionState.DISCONNECTED
                    raise AmplifierConnectionError(
                        f"{self.name}: could not reconnect to {self.transport.url} within "
                        f"{self.reconnect_timeout_s:g} s (last error: {last_err})")
                time.sleep(delay)
                delay = min(delay * 2, max_delay)


class SerialAmplifier(LimitedAmplifier):
    """Base of the serial drivers. Subclasses implement the protocol hooks."""

    #: default baud rate of the protocol
    default_baudrate = 115200

    def __init__(self, transport: SerialTransport, *, host_limits: HostLimits = None,
                 max_step_V: float | None = None, reconnect_timeout_s: float = 5.0,
                 backoff_s: tuple[float, float] = (0.05, 1.0), connect: bool = True) -> None:
        super().__init__(transport, host_limits=host_limits, max_step_V=max_step_V,
                         reconnect_timeout_s=reconnect_timeout_s, backoff_s=backoff_s)
        self._identity: dict[str, object] = {}
        if connect:
            self.connect()

    # -- protocol hooks --
    @abstractmethod
    def _handshake(self) -> tuple[dict[str, VoltageLimits], dict[str, object]]:
        """Configure the device for host control; return (device limits, identity)."""

    @abstractmethod
    def _read_voltages(self) -> dict[str, float]:
        """Query the applied output voltages (pipeline already synced)."""

    @abstractmethod
    def _write_setpoint(self, values: dict[str, float]) -> None:
        """Encode (inside :attr:`limits`) and write one setpoint without waiting for a reply."""

    @abstractmethod
    def _sync(self) -> None:
        """Wait for every outstanding reply; raise the device's errors."""

    def _reset_pipeline(self) -> None:
        """Forget outstanding replies (after reopen)."""

    # -- state --
    def _io(self, fn, *args):
        """Run ``fn`` and map link failures onto the visible state."""
        # A failure while connected is news worth a warning; during connect/reconnect the
        # caller gets the exception itself (the CLI prints it as its one error line).
        level = logging.WARNING if self._state is ConnectionState.CONNECTED else logging.DEBUG
        try:
            return fn(*args)
        except AmplifierConnectionError:
            if self._state is not ConnectionState.CLOSED:
                self._state = ConnectionState.DISCONNECTED
                log.log(level, "%s: link lost on %s", self.name, self.transport.url)
            raise
        except AmplifierTimeout:
            if self._state is not ConnectionState.CLOSED:
                self._state = ConnectionState.FAULT
                log.log(level, "%s: device on %s went silent", self.name, self.transport.url)
            raise
        except ProtocolError as err:
            # A reply that does not parse (no device error code) means the reply stream is
            # out of step: refuse further commands until reconnect() resynchronises.
            if err.code is None and self._state is ConnectionState.CONNECTED:
                self._state = ConnectionState.FAULT
                log.warning("%s: garbled reply on %s: %s", self.name, self.transport.url, err)
            raise

    def _guard(self) -> None:
        if self._state is ConnectionState.CLOSED:
            raise AmplifierConnectionError(f"{self.name} on {self.transport.url} is closed")
        if self._state is not ConnectionState.CONNECTED:
            raise AmplifierConnectionError(
                f"{self.name} on {self.transport.url} is {self._state.value}; call reconnect()")

    # -- life --
    def connect(self) -> None:
        with self._lock:
            self._io(self._open_and_handshake)
            self._state = ConnectionState.CONNECTED

    def _open_and_handshake(self) -> None:
        if not self.transport.is_open:
            self.transport.open()
        self._reset_pipeline()
        device, identity = self._handshake()
        self._set_device_limits(device)
        self._identity = identity
        self._last = self._read_voltages()

    def close(self) -> None:
        with self._lock:
            if self._state is ConnectionState.CLOSED:
                return
            if self._state is ConnectionState.CONNECTED:
                try:
                    self._sync()
                except AmplifierError as err:
                    log.warning("%s: on close: %s", self.name, err)
            self.transport.close()
            self._state = ConnectionState.CLOSED

    # -- commands --
    def set_voltages(self, volts: Mapping[str, float]) -> None:
        with self._lock:  # validate under the lock: max_step_V is relative to the last output
            values = self.validate(volts)
            self._guard()
            self._io(self._write_setpoint, values)
            self._last.update(values)

    def get_voltages(self) -> dict[str, float]:
        with self._lock:
            self._guard()
            self._io(self._sync)
            values = self._io(self._read_voltages)
            self._last.update(values)
            return values

    def flush(self) -> None:
        with self._lock:
            self._guard()
            self._io(self._sync)

    def check_errors(self) -> None:
        self.flush()

    def info(self) -> dict[str, object]:
        return {
            "driver": self.name,
            "port": self.transport.url,
            "baudrate": self.transport.baudrate,
            "state": self._state.value,
            "axes": list(self.axes),
            "device_limits_V": {a: [lim.min_V, lim.max_V] for a, lim in self._device_limits.items()},
            "limits_V": {a: [lim.min_V, lim.max_V] for a, lim in self._limits.items()},
            **self._identity,
        }
