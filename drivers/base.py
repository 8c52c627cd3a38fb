"""The amplifier template every backend (serial and CAN) is built on.

python-can's ``BusABC`` lesson: the *public* methods are concrete and hold the safety
checks — limits and ``max_step_V`` (before any byte is sent), the lock that serialises
callers, the visible connection state and the mapping of link failures onto it — while a
backend only fills in protected hooks (``_open_link``, ``_handshake``, ``_read_voltages``,
``_write_setpoint``, ``_sync``, ...). No backend re-implements :meth:`Amplifier.set_voltages`.
The data recorder follows the same pattern: :meth:`Amplifier.configure_recorder`, :meth:`~Amplifier.read_recording`
(a :class:`~afmctl.drivers.recording.Recording`) are concrete; a backend with a recorder sets
``has_recorder`` and fills ``_recorder_clock_s``, ``_recorder_capacity``,
``_configure_recorder``, ``_recorded_points``, ``_read_recording``; one without raises
:class:`~afmctl.drivers.errors.RecorderUnavailable`.

Layering (as in pyLabLib / PIPython / caproto): a *transport* moves bytes or frames, a
*codec* (pure, no I/O) turns typed messages into bytes and back, and the *driver* speaks
typed commands. A driver takes an open-able transport; :meth:`Amplifier.open` builds one
from a URL (see :func:`afmctl.drivers.registry.open_amplifier`).

Voltages are in volts. Axes are named ``"x"``, ``"y"``, ``"z"`` (a single-channel unit has
only ``"x"``).

Streaming semantics: :meth:`Amplifier.set_voltages` checks the limits, writes the setpoint
and returns without waiting for the device where the protocol allows it (pipelining); an
error the device reports for an earlier setpoint is raised by a later call, and
:meth:`Amplifier.flush` waits until everything written has been applied and checked.
After a lost link (``DISCONNECTED``) or a silent device (``FAULT``) every command raises
:class:`~afmctl.drivers.errors.AmplifierConnectionError` until :meth:`Amplifier.reconnect`,
which reopens with backoff, reads back what the amplifier outputs *now* and sends no
setpoint (the output never jumps). Implementations: :mod:`afmctl.drivers.mdt`,
:mod:`afmctl.drivers.gcs`, :mod:`afmctl.drivers.nv200`, :mod:`afmctl.drivers.can_amp`;
see docs/DRIVERS.md.
"""
from __future__ import annotations

import enum
import logging
import math
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from .errors import (AmplifierConnectionError, AmplifierError, AmplifierTimeout, LimitError, ProtocolError,
                     RecorderUnavailable, RecordingCancelled)
from .recording import Recording, RecorderSetup, check_axes_signals, check_points

log = logging.getLogger(__name__)
_T = TypeVar("_T")


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
        items = dict(host_limits)
        if "*" in items:
            common = items.pop("*")
            items = {**{a: common for a in axes}, **items}
    out = {}
    for axis, lim in items.items():
        if not isinstance(lim, VoltageLimits):
            lo, hi = lim
            lim = VoltageLimits(float(lo), float(hi))
        if not (math.isfinite(lim.min_V) and math.isfinite(lim.max_V) and lim.min_V <= lim.max_V):
            raise LimitError(f"host limits for axis {axis}: [{lim.min_V}, {lim.max_V}] V is not a valid range")
        out[axis] = lim
    return out


def intersect_limits(device: Mapping[str, VoltageLimits], host: Mapping[str, VoltageLimits]) -> dict[str, VoltageLimits]:
    """Per axis the intersection of the device's and the host's range; LimitError when
    they do not overlap or the host names an axis the device does not have."""
    out = {}
    for axis, d in device.items():
        h = host.get(axis)
        lo, hi = (d.min_V, d.max_V) if h is None else (max(d.min_V, h.min_V), min(d.max_V, h.max_V))
        if h is not None and lo > hi:
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
    np = sys.modules.get("numpy")  # drivers do not import numpy; reject its bool if loaded
    bools = (np.bool_,) if np is not None else ()
    if isinstance(value, (str, bytes, bytearray, bool, *bools)):
        raise LimitError(f"axis {axis}: {value!r} is not a voltage (expected a number of volts)")
    try:
        return float(value)  # type: ignore[arg-type]
    except OverflowError:
        raise LimitError(f"axis {axis}: {value!r} V is outside every voltage range") from None
    except (TypeError, ValueError) as err:
        raise LimitError(f"axis {axis}: voltage is not a number: {err}") from None


class AmplifierInterface(ABC):
    """What the controller and the safety layer use of an amplifier. Every hardware
    backend implements it through the :class:`Amplifier` template; in-memory test doubles
    (``afmctl.simulation.link.RecordingAmplifier``) implement it directly."""

    name: str = ""

    @property
    @abstractmethod
    def axes(self) -> tuple[str, ...]:
        """Axis names this unit drives."""

    @property
    @abstractmethod
    def limits(self) -> Mapping[str, VoltageLimits]:
        """Effective limits per axis [V]."""

    @property
    @abstractmethod
    def state(self) -> ConnectionState:
        """Visible connection state."""

    @abstractmethod
    def set_voltages(self, volts: Mapping[str, float]) -> None:
        """Command output voltages [V] on some axes."""

    @abstractmethod
    def get_voltages(self) -> dict[str, float]:
        """Read back the output voltages [V]."""

    @abstractmethod
    def info(self) -> dict[str, object]:
        """Identity and limits."""

    @abstractmethod
    def reconnect(self) -> None:
        """Re-open the link (never jumps the output)."""

    @abstractmethod
    def close(self) -> None:
        """Close the link. Idempotent."""

    def enable(self) -> None:
        """Enable the outputs (no-op where the device has no such command)."""

    def disable(self) -> None:
        """Disable the outputs (no-op where the device has no such command)."""

    def flush(self) -> None:
        """Wait until every pipelined setpoint has been written and checked."""

    def check_errors(self) -> None:
        """Query the device's error state and raise if it reports one."""

    def check_limits(self, volts: Mapping[str, float]) -> None:
        """Raise :class:`LimitError` if any value is outside :attr:`limits` or the axis is unknown."""
        lim = self.limits
        for axis, v in volts.items():
            if axis not in lim:
                raise LimitError(f"axis {axis!r} is not driven by {self.name or type(self).__name__}; "
                                 f"allowed axes: {', '.join(self.axes)}")
            lim[axis].check(axis, float(v))

    def __enter__(self) -> "AmplifierInterface":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Amplifier(AmplifierInterface):
    """A piezo amplifier with one or more voltage channels (the template; see module notes).

    ``Amplifier(transport, host_limits=None, max_step_V=None, reconnect_timeout_s=5.0,
    backoff_s=(0.05, 1.0), connect=True)``: the constructor connects (handshake, device
    limits, read-back of the actual output). ``transport`` has ``url`` and ``close()``.
    """

    #: driver name as used in configuration (``"mdt693b"``, ``"gcs"``, ``"nv200"``, ``"can"``)
    name: str = ""
    #: wait for pipelined replies before closing (False where that needs a round trip
    #: the device may never answer, e.g. CAN)
    sync_on_close: bool = True
    #: resolution of the output the device reports [V] (0: it reports the setpoint
    #: exactly). A read-back is a measured value: the step check from it allows half this.
    readback_resolution_V: float = 0.0

    def __init__(self, transport: Any, *, host_limits: HostLimits = None, max_step_V: float | None = None,
                 reconnect_timeout_s: float = 5.0, backoff_s: tuple[float, float] = (0.05, 1.0),
                 connect: bool = True) -> None:
        if max_step_V is not None and not (max_step_V > 0 and math.isfinite(max_step_V)):
            raise LimitError(f"max_step_V must be a positive number of volts, got {max_step_V!r}")
        self.transport = transport
        self.max_step_V = max_step_V
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.backoff_s = backoff_s
        self.reconnects = 0
        self._state = ConnectionState.DISCONNECTED
        self._lock = threading.RLock()
        self._host_limits_arg = host_limits
        self._limits: dict[str, VoltageLimits] = {}
        self._device_limits: dict[str, VoltageLimits] = {}
        self._last: dict[str, float] = {}
        #: axes whose :attr:`last_output` is a read-back (known to ± resolution / 2)
        self._measured: set[str] = set()
        self._identity: dict[str, object] = {}
        if connect:
            self.connect()

    # ---- construction from a URL (the registry calls this) ----
    @classmethod
    @abstractmethod
    def open(cls, port: str, *, baudrate: int | None = None, timeout_s: float = 0.5,
             write_timeout_s: float | None = None, **options: Any) -> "Amplifier":
        """Build the transport for ``port``, connect and return the driver."""

    # ---- hooks a backend implements ----
    @property
    @abstractmethod
    def axes(self) -> tuple[str, ...]:
        """Axis names this unit drives."""

    @abstractmethod
    def _open_link(self) -> None:
        """Open the transport if it is closed and forget any outstanding reply."""

    @abstractmethod
    def _handshake(self) -> tuple[dict[str, VoltageLimits], dict[str, object]]:
        """Bring the device under host control; return (device limits [V], identity)."""

    @abstractmethod
    def _read_voltages(self) -> dict[str, float]:
        """Query the applied output voltages [V] (the pipeline is already synced)."""

    @abstractmethod
    def _write_setpoint(self, values: dict[str, float]) -> dict[str, float] | None:
        """Encode (inside :attr:`limits`) and send one validated setpoint without waiting
        for its reply. Return the full output it commands if that differs from
        ``values`` (e.g. a frame that carries every axis)."""

    @abstractmethod
    def _sync(self) -> None:
        """Wait for every outstanding reply; raise the device's errors."""

    def _raise_pending(self) -> None:
        """Raise an error the device reported asynchronously (default: none)."""

    def _set_enabled(self, enabled: bool) -> None:
        """Switch the outputs on or off (default: the device has no such command)."""

    def _info_extra(self) -> dict[str, object]:
        """Backend-specific entries of :meth:`info`."""
        return {}

    def _on_close(self) -> None:
        """Last words to a connected device before the link closes (default: none)."""

    # ---- recorder hooks (a backend with a data recorder sets has_recorder and fills these) ----
    #: the device has a data recorder this driver drives (see :meth:`configure_recorder`)
    has_recorder: bool = False
    #: the device reads back points already recorded while it still records (:meth:`read_recorded`)
    reads_while_recording: bool = False
    #: a recording longer than the recorder's capacity goes into a ring that keeps the last
    #: capacity's points: each is read back (:meth:`read_recorded`) before that many more
    #: are taken (:meth:`recorder_max_points` says how long a recording may be)
    records_ring: bool = False
    #: the recording armed last (:meth:`configure_recorder`), None before or after it is dropped
    _recorder_setup: RecorderSetup | None = None

    def _recorder_clock_s(self) -> float:
        """The recorder's base sample period [s] (one tick of the device clock)."""
        raise NotImplementedError

    def _recorder_capacity(self, axes: tuple[str, ...], signals: tuple[str, ...]) -> int:
        """The most points per signal the recorder holds for these axes and signals."""
        raise NotImplementedError

    def _recorder_max_points(self, axes: tuple[str, ...], signals: tuple[str, ...]) -> int:
        """The most points per signal one recording may have: what the recorder holds, or on
        a device that :attr:`records_ring`, the most its arm command takes."""
        return self._recorder_capacity(axes, signals)

    def _configure_recorder(self, setup: RecorderSetup) -> RecorderSetup:
        """Arm the recorder to start with the next wave start; returns the setup with the
        backend's bookkeeping in ``extra``."""
        raise NotImplementedError

    def _read_points(self, setup: RecorderSetup, first: int, n: int) -> Recording:
        """Points ``first`` .. ``first + n - 1`` (0-based, all recorded) of the armed
        recording, also while it goes on (a backend that sets ``reads_while_recording``)."""
        raise NotImplementedError

    def _recorded_points(self, setup: RecorderSetup) -> int:
        """Points recorded so far (per signal, the least over them)."""
        raise NotImplementedError

    def _read_recording(self, setup: RecorderSetup, cancel: Callable[[], bool]) -> Recording:
        """Read the whole recording back (every point is there); a backend that reads in
        chunks raises :class:`RecordingCancelled` between two when ``cancel()`` is true."""
        raise NotImplementedError

    def _record_tables(self) -> int | None:
        """Record tables sharing the recorder's memory now; None: each signal has its own."""
        return None

    def _set_record_tables(self, n: int) -> int | None:
        """Share the recorder's memory among ``n`` tables if the device lets the host;
        returns the count in force (None: each signal has its own memory)."""
        return None

    def _no_recorder(self) -> RecorderUnavailable:
        return RecorderUnavailable(
            f"{self.name or type(self).__name__} has no data recorder: measure the motion with an external "
            "sensor and give it as a file (t,y or t,x,y,z in nm; docs/DRIVERS.md, 'Recording the motion')")

    # ---- limits ----
    @property
    def limits(self) -> Mapping[str, VoltageLimits]:
        """Effective limits per axis: the intersection of device and host limits."""
        return dict(self._limits)

    @property
    def device_limits(self) -> Mapping[str, VoltageLimits]:
        return dict(self._device_limits)

    @property
    def last_output(self) -> dict[str, float]:
        """Last voltages commanded or read back [V] (the output the driver believes in)."""
        return dict(self._last)

    @property
    def state(self) -> ConnectionState:
        """Visible connection state."""
        return self._state

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
                tol = self.readback_resolution_V / 2 if a in self._measured else 0.0
                if prev is not None and abs(v - prev) > self.max_step_V + tol:
                    raise LimitError(f"axis {a}: step {prev:g} V -> {v:g} V exceeds max_step_V={self.max_step_V:g} V")
        return {a: values[a] for a in self.axes if a in values}

    # ---- state ----
    def _io(self, fn: Callable[..., _T], *args: Any) -> _T:
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
        self._raise_pending()

    def _open_and_handshake(self) -> None:
        self._open_link()
        device, identity = self._handshake()
        self._device_limits = dict(device)
        self._limits = intersect_limits(device, normalize_host_limits(self._host_limits_arg, tuple(device)))
        self._identity = identity
        self._last = self._read_voltages()
        self._measured = set(self._last)

    # ---- life ----
    def connect(self) -> None:
        """Open the link, handshake, read the limits and the actual output."""
        with self._lock:
            try:
                self._io(self._open_and_handshake)
            except AmplifierError:
                self.transport.close()
                raise
            self._state = ConnectionState.CONNECTED

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

    def close(self) -> None:
        """Close the link (after the pipelined replies where :attr:`sync_on_close`). Idempotent."""
        with self._lock:
            if self._state is ConnectionState.CLOSED:
                return
            if self._state is ConnectionState.CONNECTED and self.sync_on_close:
                try:
                    self._sync()
                except AmplifierError as err:
                    log.warning("%s: on close: %s", self.name, err)
            if self._state is ConnectionState.CONNECTED:
                self._on_close()
            self.transport.close()
            self._state = ConnectionState.CLOSED

    # ---- commands ----
    def set_voltages(self, volts: Mapping[str, float]) -> None:
        """Command output voltages [V] on some axes (the others keep their value). Values
        outside :attr:`limits`, NaN/inf, or a step over ``max_step_V`` raise
        :class:`~afmctl.drivers.errors.LimitError` before any byte is sent. May return
        before the device applied it (see module notes)."""
        with self._lock:  # validate under the lock: max_step_V is relative to the last output
            values = self.validate(volts)
            self._guard()
            full = self._io(self._write_setpoint, values)
            self._last.update(full if full is not None else values)
            self._measured.difference_update(values)

    def get_voltages(self) -> dict[str, float]:
        """Read back the output voltages [V] as the device reports them (a measured value
        on some units: see each driver's ``readback_resolution_V``)."""
        with self._lock:
            self._guard()
            self._io(self._sync)
            values = self._io(self._read_voltages)
            self._last.update(values)
            self._measured.update(values)
            return values

    def flush(self) -> None:
        """Wait until every pipelined setpoint has been written and checked."""
        with self._lock:
            self._guard()
            self._io(self._sync)

    def check_errors(self) -> None:
        """Query the device's error state and raise if it reports one."""
        self.flush()

    def enable(self) -> None:
        """Enable the outputs (no-op where the device has no such command)."""
        with self._lock:
            self._guard()
            self._io(self._set_enabled, True)

    def disable(self) -> None:
        """Disable the outputs (no-op where the device has no such command)."""
        with self._lock:
            self._guard()
            self._io(self._set_enabled, False)

    # ---- data recorder (the same on every backend that has one) ----
    def recorder_clock_s(self) -> float:
        """The recorder's base sample period [s]; a recording's period is a whole multiple."""
        if not self.has_recorder:
            raise self._no_recorder()
        with self._lock:
            self._guard()
            return self._io(self._recorder_clock_s)

    def recorder_capacity(self, axes: Sequence[str] | None = None,
                          signals: Sequence[str] = ("y_nm", "u_V")) -> int:
        """The most points per signal one recording of these axes and signals holds."""
        return self._recorder_points(self._recorder_capacity, axes, signals)

    def recorder_max_points(self, axes: Sequence[str] | None = None,
                            signals: Sequence[str] = ("y_nm", "u_V")) -> int:
        """The most points per signal one recording of these axes and signals may have: its
        :meth:`recorder_capacity`, or more on a device that :attr:`records_ring` (read back
        while it records)."""
        return self._recorder_points(self._recorder_max_points, axes, signals)

    def _recorder_points(self, hook: Callable[[tuple[str, ...], tuple[str, ...]], int],
                         axes: Sequence[str] | None, signals: Sequence[str]) -> int:
        """``hook(axes, signals)`` asked of the device (default axes: all of them)."""
        if not self.has_recorder:
            raise self._no_recorder()
        ax = tuple(axes) if axes is not None else self.axes
        with self._lock:
            self._guard()
            return self._io(hook, ax, tuple(signals))

    def record_tables(self) -> int | None:
        """How many record tables share the recorder's memory now, on a device whose memory
        is shared (the E-727: 262,144 points in equal shares, ``TNR?``); None on one whose
        signals each have memory of their own (the NV200, the CAN amplifier)."""
        if not self.has_recorder:
            raise self._no_recorder()
        with self._lock:
            self._guard()
            return self._io(self._record_tables)

    def set_record_tables(self, n: int) -> int | None:
        """Share the recorder's memory among ``n`` tables (fewer tables, more points each:
        :meth:`recorder_capacity` grows) where the device lets the host choose; a device that
        refuses keeps its tables (logged). Returns the count in force afterwards; None where
        each signal has memory of its own. Drops any recording armed before."""
        if not self.has_recorder:
            raise self._no_recorder()
        if int(n) < 1:
            raise LimitError(f"record tables: {n}; allowed: 1 or more")
        with self._lock:
            self._guard()
            self._recorder_setup = None
            return self._io(self._set_record_tables, int(n))

    def configure_recorder(self, axes: Sequence[str] | None = None, *, points: int, divider: int = 1,
                           signals: Sequence[str] = ("y_nm", "u_V")) -> RecorderSetup:
        """Arm the device's data recorder: from the next wave start (``start_wave``; on CAN
        the stream's first played sample) it records ``points`` points of each of
        ``signals`` (``"y_nm"`` measured position, ``"u_V"`` output voltage) on ``axes``
        (default: all), one every ``divider`` ticks of :meth:`recorder_clock_s`. With the
        wave at the same rate, point k is taken at the tick of wave point k. Raises
        :class:`RecorderUnavailable` on a device without one, :class:`LimitError` for a
        request outside what the recorder holds (naming the range)."""
        if not self.has_recorder:
            raise self._no_recorder()
        with self._lock:
            self._guard()
            try:
                ax, sig = check_axes_signals(axes if axes is not None else self.axes, signals, self.axes)
                check_points(points, divider, capacity=self._io(self._recorder_max_points, ax, sig), name=self.name)
            except ValueError as err:
                raise LimitError(str(err)) from None
            setup = RecorderSetup(ax, sig, points, divider, self._io(self._recorder_clock_s))
            self._recorder_setup = self._io(self._configure_recorder, setup)
            return self._recorder_setup

    def recorded_points(self) -> int:
        """Points of the armed recording taken so far (0 before the trigger)."""
        setup = self._armed_setup()
        with self._lock:
            self._guard()
            return self._io(self._recorded_points, setup)

    def read_recording(self, timeout_s: float = 10.0, poll_s: float = 0.02,
                       cancel: Callable[[], bool] | None = None) -> Recording:
        """Wait (at most ``timeout_s`` [s]) until the armed recording holds every point,
        then read it back as a :class:`~afmctl.drivers.recording.Recording` (t_s from the
        wave start; y_nm, u_V per axis). A recording that does not fill in time raises
        :class:`~afmctl.drivers.errors.AmplifierTimeout` saying how far it got. ``cancel``:
        asked while waiting and between the read-back's chunks; true gives up with
        :class:`~afmctl.drivers.errors.RecordingCancelled` (a long read-back over a slow
        link, seconds to minutes, never holds up a stop)."""
        setup = self._armed_setup()
        stop = cancel if cancel is not None else (lambda: False)
        deadline = time.monotonic() + timeout_s
        while True:
            if stop():
                raise RecordingCancelled(f"{self.name}: the read-back of the recording was cancelled")
            n = self.recorded_points()
            if n >= setup.points:
                break
            if time.monotonic() > deadline:
                raise AmplifierTimeout(f"{self.name}: the recording holds {n} of {setup.points} points after "
                                       f"{timeout_s:g} s (was the wave started after configure_recorder()?)")
            time.sleep(poll_s)
        with self._lock:
            self._guard()
            rec = self._io(self._read_recording, setup, stop)
        if len(rec) != setup.points:
            raise ProtocolError(f"{self.name}: the recording read back has {len(rec)} points, {setup.points} were armed")
        return rec

    def read_recorded(self, first: int, n: int) -> Recording:
        """Points ``first`` .. ``first + n - 1`` (0-based) of the armed recording, already
        recorded (:meth:`recorded_points`) — on a device that :attr:`reads_while_recording`
        also while the recording goes on, so that a long recording is read back while it is
        taken; its ``t_s`` from the wave start as in :meth:`read_recording`. Parts join with
        :func:`~afmctl.drivers.recording.joined_recording`."""
        setup = self._armed_setup()
        if not self.reads_while_recording:
            raise AmplifierError(f"{self.name}: the recorder is read back once it is full (read_recording)")
        if not (0 <= first and 1 <= n and first + n <= setup.points):
            raise AmplifierError(f"{self.name}: points {first}..{first + n - 1} lie outside the armed "
                                 f"{setup.points}")
        with self._lock:
            self._guard()
            rec = self._io(self._read_points, setup, first, n)
        if len(rec) != n:
            raise ProtocolError(f"{self.name}: {len(rec)} points came back, {n} were asked")
        return rec

    def _armed_setup(self) -> RecorderSetup:
        if not self.has_recorder:
            raise self._no_recorder()
        setup = getattr(self, "_recorder_setup", None)
        if setup is None:
            raise AmplifierError(f"{self.name}: no recording armed; call configure_recorder() first")
        return setup

    def info(self) -> dict[str, object]:
        """Identity and limits as read from the device."""
        return {
            "driver": self.name,
            "port": self.transport.url,
            "state": self._state.value,
            "axes": list(self.axes),
            "device_limits_V": {a: [lim.min_V, lim.max_V] for a, lim in self._device_limits.items()},
            "limits_V": {a: [lim.min_V, lim.max_V] for a, lim in self._limits.items()},
            "readback_resolution_V": self.readback_resolution_V,
            **self._info_extra(),
            **self._identity,
        }
