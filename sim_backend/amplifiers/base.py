"""What every simulated amplifier shares: the sink it drives, its clock, and fault
injection hooks used by tests."""
from __future__ import annotations

import math

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol


class Sink(Protocol):
    """Anything that takes the amplifier's output: ``apply(volts, t_s)`` with
    ``volts`` a mapping axis -> V, ``t_s`` the clock time [s]. A
    :class:`afmctl.sim_backend.scanner.Scanner` is one."""

    def apply(self, volts: Mapping[str, float], t_s: float | None = None) -> None: ...


class RecordingSink:
    """A sink that remembers every output change (thread-safe).

    ``history`` is a list of ``(t_s, {axis: V})``; keep ``max_history`` small for long
    runs (older entries are dropped); ``count`` counts every call.
    """

    def __init__(self, max_history: int = 100_000) -> None:
        self.max_history = max_history
        self.history: list[tuple[float, dict[str, float]]] = []
        self.count = 0
        self.last: dict[str, float] = {}
        self._lock = threading.Lock()

    def apply(self, volts: Mapping[str, float], t_s: float | None = None) -> None:
        with self._lock:
            self.count += 1
            self.last.update(volts)
            self.history.append((float(t_s) if t_s is not None else float("nan"), dict(volts)))
            if len(self.history) > self.max_history:
                del self.history[: len(self.history) - self.max_history]


class CsvRecorder:
    """A sink that writes every output change to a CSV file and forwards it to ``inner``.

    Columns ``t_s,x_V,y_V,z_V``: the time the amplifier applied the change [s] and the
    voltages [V] then held on every axis (axes never set read 0). One row per
    :meth:`apply`, in the order the amplifier applied them, so a test can check that every
    setpoint arrived in order. Rows are buffered; :meth:`flush` writes them out (``afmctl sim``
    does every ``RECORD_FLUSH_S``), :meth:`close` too.
    """

    AXES = ("x", "y", "z")

    def __init__(self, path: str, inner: "Sink | None" = None) -> None:
        self.inner = inner
        self._held = {a: 0.0 for a in self.AXES}
        self._lock = threading.Lock()
        self._file = open(path, "w", encoding="utf-8", buffering=1 << 16)  # noqa: SIM115
        self._file.write("t_s,x_V,y_V,z_V\n")
        self.count = 0

    def apply(self, volts: Mapping[str, float], t_s: float | None = None) -> None:
        with self._lock:
            self._held.update({a: float(v) for a, v in volts.items() if a in self._held})
            if not self._file.closed:
                t = float(t_s) if t_s is not None else float("nan")
                self._file.write(f"{t!r},{self._held['x']!r},{self._held['y']!r},{self._held['z']!r}\n")
                self.count += 1
        if self.inner is not None:
            self.inner.apply(volts, t_s)

    def play(self, t_s: Sequence[float], rows_V: Sequence[Sequence[float]]) -> None:
        """Clock-timed rows x, y, z [V] (a wave generator's or stream's block): one CSV row
        each, then the whole block to the inner sink (its ``play`` if it has one)."""
        with self._lock:
            if not self._file.closed:
                for t, row in zip(t_s, rows_V):
                    self._held.update(zip("xyz", (float(v) for v in row)))
                    self._file.write(f"{float(t)!r},{self._held['x']!r},{self._held['y']!r},{self._held['z']!r}\n")
                    self.count += 1
        inner = self.inner
        if inner is not None and hasattr(inner, "play"):
            inner.play(t_s, rows_V)
        elif inner is not None:
            for t, row in zip(t_s, rows_V):
                inner.apply(dict(zip("xyz", row)), t)

    def __getattr__(self, name: str):
        # the rest of the sink's interface (advance, position_nm, ...) is the inner sink's
        inner = self.__dict__.get("inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)

    def flush(self) -> None:
        """Write the buffered rows to the file (a reader sees every row applied so far)."""
        with self._lock:
            if not self._file.closed:
                self._file.flush()

    def close(self) -> None:
        with self._lock:
            if not self._file.closed:
                self._file.close()


def elapsed_clock() -> Callable[[], float]:
    """A clock that reads 0 s now and counts wall-clock seconds from here (the default
    ``now`` of every simulated amplifier, so a Scanner sink starts at its t = 0)."""
    t0 = time.monotonic()
    return lambda: time.monotonic() - t0


class SimDevice:
    """Base of the sans-I/O simulated serial amplifiers: ``feed(bytes) -> reply bytes``.

    :attr:`lock` (re-entrant) is held by :meth:`feed` and by a device clock's ``poll``: the
    server's thread and the simulator's clock thread (:class:`afmctl.simulation.service.SimService`)
    may both play a wave generator's due points, never at the same time."""

    protocol = ""
    #: axis names driven by the device
    axes: tuple[str, ...] = ("x", "y", "z")

    def __init__(self, sink: Sink | None = None, *, now: Callable[[], float] | None = None) -> None:
        self.sink = sink
        self.now = now or elapsed_clock()
        self.outputs: dict[str, float] = {a: 0.0 for a in self.axes}
        #: smallest and largest voltage ever *requested* by a host (before clamping) [V]
        self.requested_min_V = float("inf")
        self.requested_max_V = float("-inf")
        #: per axis: (smallest, largest) voltage ever requested by a host [V]
        self.requested_V: dict[str, tuple[float, float]] = {}
        self.commands = 0
        self._inject: object | None = None
        self._rx = bytearray()
        self._pair_end: int | None = None
        #: held while a command or a poll changes the device (:class:`SimDevice`)
        self.lock = threading.RLock()

    #: the load is advanced on polls in steps of at least this [s] (a step costs a fixed
    #: overhead: many small ones would cost more than the simulation itself)
    LOAD_STEP_S = 0.05

    def advance_load(self, now_s: float) -> None:
        """Bring a load that simulates on its own time (the simulated scanner: ``advance``)
        up to ``now_s`` [s] with the outputs held, once it lags by :data:`LOAD_STEP_S`.
        Called on the servers' idle polls, so the load keeps pace with the device's clock: a
        reply never waits for seconds of idle simulation to catch up (a loaded host takes
        longer than a client's reply timeout)."""
        advance = getattr(self.sink, "advance", None)
        if advance is not None and now_s - getattr(self, "_load_t", -math.inf) >= self.LOAD_STEP_S:
            self._load_t = now_s
            advance(now_s)

    def play_due(self, now_s: float | None = None) -> None:
        """Hand the load what the device's own clock (a wave generator) played by now (or
        ``now_s`` [s]), under :attr:`lock`, without advancing the load otherwise (the
        simulator's clock thread calls this when :meth:`next_due_s` says the server has not)."""
        with self.lock:
            self._play_due(self.now() if now_s is None else now_s)

    def next_due_s(self) -> float | None:
        """When the device's own clock plays its next point [s]; None when it plays nothing
        (read without the lock: a tick late at worst)."""
        wave = getattr(self, "wave", None)
        return None if wave is None else wave.next_due_s()

    def _play_due(self, now_s: float) -> None:
        """The points a device clock played by ``now_s`` [s] (none without a wave generator)."""

    def inject_error(self, code: object = None) -> None:
        """Make the next command fail with a device error (protocol-specific ``code``)."""
        self._inject = code if code is not None else True

    def _take_injected(self) -> object | None:
        code, self._inject = self._inject, None
        return code

    def _requested(self, v: float, axis: str) -> None:
        self.requested_min_V = min(self.requested_min_V, v)
        self.requested_max_V = max(self.requested_max_V, v)
        lo, hi = self.requested_V.get(axis, (v, v))
        self.requested_V[axis] = (min(lo, v), max(hi, v))

    def _apply(self, changes: Mapping[str, float]) -> None:
        changed = {a: v for a, v in changes.items() if self.outputs.get(a) != v}
        self.outputs.update(changes)
        if changed and self.sink is not None:
            self.sink.apply(dict(self.outputs), self.now())

    def line_break(self) -> None:
        """The link dropped: a partial command line in the input buffer is discarded."""
        self._rx.clear()
        self._pair_end = None

    #: bytes that end a command line (any of them)
    line_ends: bytes = b"\r\n"
    #: a partial line longer than this is dropped and answered by :meth:`overflow`
    max_line: int = 256

    def feed(self, data: bytes) -> bytes:
        """Bytes from the host in, reply bytes out (may be empty): every complete line
        (a trailing CR stripped) goes to :meth:`reply`, an empty one to
        :meth:`empty_line`. Where both CR and LF end a line, the pairs CR LF and LF CR
        are one line end (also when split across two reads)."""
        with self.lock:
            return self._feed_lines(data)

    def _feed_lines(self, data: bytes) -> bytes:
        """:meth:`feed` with :attr:`lock` held."""
        self._rx += data
        out = bytearray()
        while True:
            if self._rx and self._pair_end is not None:
                if self._rx[0] == self._pair_end:
                    del self._rx[0]  # second half of a CR LF / LF CR pair
                self._pair_end = None
            ends = [k for k in (self._rx.find(bytes((e,))) for e in self.line_ends) if k >= 0]
            if not ends:
                if len(self._rx) > self.max_line:  # no real device buffers a line this long
                    self._rx.clear()
                    out += self.overflow()
                return bytes(out)
            i = min(ends)
            end = self._rx[i]
            if len(self.line_ends) > 1 and end in b"\r\n":
                self._pair_end = (b"\n" if end == 13 else b"\r")[0]
            line = bytes(self._rx[:i]).rstrip(b"\r")
            del self._rx[: i + 1]
            out += self.reply(line) if line.strip() else self.empty_line()

    def empty_line(self) -> bytes:
        """Reply to an empty command line (default: none)."""
        return b""

    def reply(self, line: bytes) -> bytes:
        """The bytes sent back for one command line (default: :meth:`command`)."""
        return self.command(line)

    def command(self, line: bytes) -> bytes:
        """One command line (without terminator) → its reply."""
        raise NotImplementedError

    def overflow(self) -> bytes:
        """Reply to an over-long line without terminator."""
        return b""
