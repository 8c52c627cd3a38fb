"""In-process simulation wiring for ``afmctl run`` with ``[simulation] enabled = true``.

A simulated amplifier of the configured driver (MDT693B/694B, GCS, NV200 on a pty; the
CAN amplifier on a python-can ``virtual`` channel) is served in this process with a
:class:`afmctl.sim_backend.scanner.Scanner` as its load, and the *real* driver is opened on it
through :func:`afmctl.control.hardware.open_driver` — the same code path as with hardware.
"""
from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AfmctlError
from afmctl.drivers.base import AmplifierInterface

log = logging.getLogger(__name__)

#: reply (and write) timeout [s] of the driver to a simulated amplifier in this process, of
#: every driver: the simulated device reads and answers from a thread of this process, which a
#: loaded host (or the loop's own thread) can keep from running for longer than a device on a
#: wire takes to answer (the drivers' 0.5 s default, kept for real devices: the CAN amplifier
#: went silent at a 2 kHz loop, the GCS and NV200 links' writes timed out between plays of
#: afmctl learn at load 7 on two cores). A configured ``amplifier.options.timeout_s`` wins.
SIMULATED_LINK_TIMEOUT_S = 2.0


def load_scanner_config(path: Path | None):
    """A ScannerConfig from a JSON file, or the default scanner."""
    from afmctl.sim_backend.scanner import ScannerConfig, default_scanner_config
    if path is None:
        return default_scanner_config()
    from afmctl.compensators.base import ModelError
    from afmctl.compensators.textfiles import read_json_file
    try:
        data = read_json_file(path, "scanner file")
    except ModelError as err:
        raise AfmctlError(f"simulation.scanner: {err}") from None
    from pydantic import ValidationError
    try:
        return ScannerConfig.model_validate(data)
    except ValidationError as err:
        from ..config import format_validation_error
        raise AfmctlError(format_validation_error(err, str(path), ScannerConfig)) from None


class ScannerTap:
    """The simulated scanner as a simulated amplifier's sink, keeping what reached it on the
    host's clock: every output the amplifier applies as it takes a setpoint (``apply``), with
    the ``time.perf_counter()`` [s] of that moment and the voltages [V] held from then on.
    Everything else (device-timed ``play``, ``advance``, the sensor) goes to the scanner.
    ``scanner``: the :class:`afmctl.sim_backend.scanner.Scanner`.

    Timed output changes are simulated in blocks (:meth:`Scanner.play
    <afmctl.sim_backend.scanner.Scanner.play>`, the same as one ``apply`` each): up to
    :data:`BATCH` of them, over at most :data:`SPAN_S`, wait, and any other use of the
    scanner simulates them first, so nothing ever sees the scanner behind what it was
    given. One ``apply`` costs ~150 µs of simulation, more than the 100 µs between the
    setpoints of a 10 kHz loop, which left the simulated amplifier's thread seconds behind
    the host (its STATUS reply to the end of a run then came after the driver's timeout); a
    block costs ~4 µs a setpoint."""

    #: most timed output changes held back before they are simulated in one block
    BATCH = 64
    #: longest span [s] of scanner time held back (a block of it runs with the GIL held)
    SPAN_S = 0.01

    def __init__(self, scanner: Any) -> None:
        self.scanner = scanner
        self._lock = threading.RLock()
        self._t: list[float] = []
        self._v: list[np.ndarray] = []
        self._pending_t: list[float] = []
        self._pending_V: list[np.ndarray] = []

    def apply(self, volts: Any, t_s: float | None = None) -> None:
        with self._lock:
            if t_s is None:            # "from now on": the scanner's own clock, at once
                self._simulate_pending()
                self.scanner.apply(volts)
                row = self.scanner.held_voltage_V()
            else:
                base = self._pending_V[-1] if self._pending_V else self.scanner.held_voltage_V()
                row = self.scanner.voltages_with(volts, base)
                self._pending_t.append(float(t_s))
                self._pending_V.append(row)
                if len(self._pending_t) >= self.BATCH or t_s - self._pending_t[0] >= self.SPAN_S:
                    self._simulate_pending()
            self._t.append(time.perf_counter())
            self._v.append(row)

    def _simulate_pending(self) -> None:
        if self._pending_t:
            t, rows = self._pending_t, self._pending_V
            self._pending_t, self._pending_V = [], []
            self.scanner.play(t, rows)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        if callable(getattr(type(self.scanner), name, None)):     # a method: what waited is simulated when called
            method = getattr(self.scanner, name)

            def current(*args: Any, **kwargs: Any) -> Any:
                with self._lock:
                    self._simulate_pending()
                    return method(*args, **kwargs)
            return current
        with self._lock:                                         # a value (a property, the config)
            self._simulate_pending()
            return getattr(self.scanner, name)

    def applied(self) -> tuple[np.ndarray, np.ndarray]:
        """``(t_perf_s (M,), u_V (M, 3))``: when each output change reached the scanner and
        the voltages held from then on."""
        with self._lock:
            return np.asarray(self._t, dtype=float), np.asarray(self._v, dtype=float).reshape(-1, 3)


#: setpoints looked ahead for the one an output change carries
MATCH_AHEAD = 64
#: most setpoints whose arrival :func:`arrival_delays_s` matches (the first of the run)
MAX_MATCHED = 200_000


def arrival_delays_s(tap: ScannerTap, deadlines_s: np.ndarray, u_V: np.ndarray, tol_V: float = 0.01) -> np.ndarray:
    """How late [s] each setpoint reached the simulated scanner after its tick's deadline
    (``deadlines_s`` on ``time.perf_counter``; ``u_V`` (N, 3) every voltage sent, from the
    first): each output change the scanner took (``tap``, in order) is matched with the
    setpoint nearest its voltages among the next :data:`MATCH_AHEAD` not yet matched, when
    within ``tol_V`` [V] (the link's resolution; a setpoint that changed nothing at that
    resolution has no change to match). NaN where a
    setpoint was not matched; at most :data:`MAX_MATCHED` setpoints, NaN after."""
    t_ev, u_ev = tap.applied()
    u = np.asarray(u_V, dtype=float)
    out = np.full(len(u), np.nan)
    k, n = 0, min(len(u), MAX_MATCHED)
    for m in range(len(t_ev)):
        if k >= n:
            break
        dist = np.max(np.abs(u[k:k + MATCH_AHEAD] - u_ev[m]), axis=1)
        best = int(np.argmin(dist))
        if dist[best] <= tol_V:
            out[k + best] = t_ev[m] - deadlines_s[k + best]
            k += best + 1
    return out


@contextlib.contextmanager
def simulated_amplifier(config) -> Iterator[tuple[Any, ScannerTap]]:
    """Serve a simulated amplifier + scanner in this process; yields ``(amplifier,
    scanner)`` with the real driver connected to it (the scanner as a :class:`ScannerTap`:
    what reached it, when). Everything is closed on exit."""
    from afmctl.sim_backend import testing
    from afmctl.sim_backend.scanner import Scanner
    scanner = ScannerTap(Scanner(load_scanner_config(config.simulation.scanner)))
    driver = config.amplifier.driver
    with contextlib.ExitStack() as stack:
        if driver == "can":
            channel = config.amplifier.port or "virtual:afmctl-sim"
            name = channel.split(":", 1)[1] if channel.startswith("virtual:") else channel
            stack.enter_context(testing.serve_can(name, sink=scanner, **config.simulation.device))
            port = f"virtual:{name}"
        else:
            try:
                server = stack.enter_context(testing.serve_pty(driver, sink=scanner, baud=config.simulation.baud,
                                                               **config.simulation.device))
            except (TypeError, ValueError) as err:
                raise AfmctlError(f"simulation.device: {err} (simulated {driver})") from None
            port = server.port
        from ..control.hardware import open_driver
        # the simulated amplifier answers from a thread of this process (SIMULATED_LINK_TIMEOUT_S);
        # a serial driver paces its writes to the simulated link's rate, as to a real port's
        default: dict[str, Any] = {"timeout_s": SIMULATED_LINK_TIMEOUT_S}
        if driver != "can":
            default["baudrate"] = config.simulation.baud
        config = config.model_copy(update={"amplifier": config.amplifier.model_copy(
            update={"options": {**default, **config.amplifier.options}})})
        amp = open_driver(config, port)
        stack.callback(amp.close)
        yield amp, scanner


def resting(config, scanner: Any) -> Any:
    """``scanner.rest`` (:meth:`afmctl.sim_backend.scanner.Scanner.rest`) when a run of
    ``config`` ends where a fresh simulated scanner rests — ``safety.on_finish = "safe"``
    with each axis's safe value at its lowest voltage — so that resting it between plays
    makes no jump; else None (the plays then go on from where the last one left off, with
    a log line saying so)."""
    low = scanner.rest_voltage_V()
    safe = np.array([config.safety.safe_value(a) for a in "xyz"])
    if config.safety.on_finish == "safe" and np.allclose(safe, low, atol=1e-6):
        return scanner.rest
    log.info("simulated scanner: the output does not end at its rest voltages %s V (safety.on_finish %r, safe %s V); "
             "each play starts where the last one left off", low.tolist(), config.safety.on_finish, safe.tolist())
    return None


def configured_amplifier(stack: contextlib.ExitStack, config) -> Any:
    """The configured amplifier, opened and closed with ``stack``: a simulated one served in
    this process with ``[simulation] enabled = true`` (:func:`simulated_amplifier`), else the
    driver on ``amplifier.port``."""
    if config.simulation.enabled:
        amp, _scanner = stack.enter_context(simulated_amplifier(config))
        return amp
    from ..control.hardware import open_driver
    amp = open_driver(config, config.amplifier.port)
    stack.callback(amp.close)
    return amp


def identify_pi_models(folder: str | Path, axes: str = "xy", dt_s: float = 1e-3, n: int = 400,
                       n_operators: int = 10, scanner_config=None) -> dict[str, Path]:
    """PI models identified from a simulated scanner (default: the default scanner) on a
    sweep of nested triangles 0–150 V, ``n`` samples per leg at ``dt_s`` [s]; saved as
    ``folder/<axis>_pi.json``. Returns ``{axis: path}`` — for examples, benchmarks and
    tests that need a compensator of the simulated scanner without a calibration run."""
    from afmctl.compensators.models import save_model
    from afmctl.compensators.pi import PIModel
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    legs = [(0, 150), (150, 0), (0, 110), (110, 20), (20, 150), (150, 0)]
    tri = np.concatenate([np.linspace(a, b, n) for a, b in legs])
    u = np.column_stack([tri if a in axes else np.zeros_like(tri) for a in "xyz"])
    y = Scanner(scanner_config or default_scanner_config()).run(u, dt_s)
    t = np.arange(len(tri)) * dt_s
    paths = {}
    for a in axes:
        k = "xyz".index(a)
        paths[a] = Path(folder) / f"{a}_pi.json"
        save_model(PIModel.identify(t, u[:, k], y[:, k], n_operators=n_operators), paths[a])
    return paths


def tracking_error(config, setpoints: np.ndarray, seq_range: tuple[int, int] | None = None) -> dict[str, Any]:
    """Replay the voltages sent (``setpoints["u_V"]``) through a fresh simulated scanner of
    the same configuration and compare the true tip position with the target [nm].

    Each voltage is held for one loop period, simulated at the scanner's own time step
    (so the ringing of its resonance after each step is in the result), and the position
    is compared at the end of the period — what a sensor sampled at the loop rate reads.
    Returns max and RMS absolute error per axis over ``seq_range`` (default: all)."""
    if len(setpoints) == 0:
        return {}
    err = replay_positions_nm(config, setpoints) - setpoints["target_nm"]
    if seq_range is not None:
        sel = (setpoints["seq"] >= seq_range[0]) & (setpoints["seq"] < seq_range[1])
        err = err[sel]
    if len(err) == 0:
        return {}
    axes = list(config.scanner.axes)
    idx = ["xyz".index(a) for a in axes]
    return {"axes": axes, "max_abs_nm": [float(np.abs(err[:, i]).max()) for i in idx],
            "rms_nm": [float(np.sqrt(np.mean(err[:, i] ** 2))) for i in idx]}


def replay_positions_nm(config, setpoints: np.ndarray, delay_ticks: int = 0) -> np.ndarray:
    """The true tip position [nm] (N, 3) at the end of each loop period when the voltages
    sent (``setpoints["u_V"]``) are replayed through a fresh simulated scanner of the
    configuration, each held for one loop period (see :func:`tracking_error`), reaching it
    ``delay_ticks`` periods late (the output path's delay the loop advanced them by)."""
    return replay_voltages_nm(setpoints["u_V"], config.dt_s, config.simulation.scanner, delay_ticks=delay_ticks)


def replay_voltages_nm(u_V: np.ndarray, dt_s: float, scanner_file: Path | None = None,
                       delay_ticks: int = 0) -> np.ndarray:
    """The true tip position [nm] (N, 3) at the end of each period ``dt_s`` [s] when each
    row of ``u_V`` [V] (N, 3) is held for one period on a fresh simulated scanner (the
    ``scanner_file`` JSON, else the default scanner), simulated at the scanner's own time
    step so that the ringing of its resonance after each step is in the result.
    ``delay_ticks``: each row reaches the scanner that many periods late (the output path's
    delay the loop advanced the setpoints by, :mod:`afmctl.control.path_delay`)."""
    from afmctl.sim_backend.scanner import Scanner
    scanner = Scanner(load_scanner_config(scanner_file))
    fine = scanner.config.dt_s
    sub = max(1, round(dt_s / fine))
    if not math.isclose(sub * fine, dt_s, rel_tol=1e-9):
        fine = dt_s / sub                 # the period is not a multiple of the scanner's step
    u = np.asarray(u_V, dtype=np.float64)
    if delay_ticks > 0 and len(u):
        u = np.vstack([np.repeat(u[:1], delay_ticks, axis=0), u])[:len(u)]
    u = np.repeat(u, sub, axis=0)
    return scanner.run(u, fine)[sub - 1::sub]


class SendClock:
    """A monotonic clock [s] that remembers the last time it returned (:attr:`stamp`).

    Give it to :class:`afmctl.control.safety.SafetyLayer` (``clock=``) and ``stamp`` to
    :class:`RecordingAmplifier` (``clock=``): the amplifier then knows exactly when the
    safety layer sent each value. ``base``: the underlying clock (default
    ``time.perf_counter``; tests pass a fake one)."""

    def __init__(self, base=time.perf_counter) -> None:
        self._base = base
        self.last = math.nan

    def __call__(self) -> float:
        self.last = self._base()
        return self.last

    def stamp(self) -> float:
        return self.last


class RecordingAmplifier(AmplifierInterface):
    """An in-memory :class:`afmctl.drivers.base.AmplifierInterface` that records and checks every value it
    receives — a dry-run target and the test double of the safety properties.

    ``limits_V``: ``{axis: (min_V, max_V)}`` it reports as its limits. ``check_limits_V`` /
    ``check_step_V``: the bounds every received value is checked against (violations are
    counted in :attr:`violations`, never raised, so that a test sees them all).
    ``check_slew_V_per_s`` with ``clock``: also check every change against the slew limit
    in volts per second of *time between sends*, ``|Δu| ≤ slew · Δt``, with ``Δt`` from
    ``clock()`` (pass ``SendClock.stamp`` of the clock the safety layer uses, so that the
    check sees exactly when each value was sent).
    ``readback``: optional callable returning what :meth:`get_voltages` reports (to fuzz
    device replies). ``fail_after``: raise a connection error on the n-th set_voltages call
    (and every call until :meth:`reconnect`).
    """

    name = "recording"

    def __init__(self, axes: tuple[str, ...] = ("x", "y", "z"), limits_V: dict[str, tuple[float, float]] | None = None,
                 *, check_limits_V: dict[str, tuple[float, float]] | None = None, check_step_V: float | None = None,
                 readback=None, initial_V: dict[str, float] | None = None,
                 check_slew_V_per_s: float | None = None, clock=None) -> None:
        import threading

        from afmctl.drivers.base import ConnectionState, VoltageLimits
        self._axes = tuple(axes)
        lim = limits_V or {a: (0.0, 150.0) for a in self._axes}
        self._limits = {a: VoltageLimits(*lim[a]) for a in self._axes}
        self.check_limits_V = check_limits_V or lim
        self.check_step_V = check_step_V
        self.check_slew_V_per_s = check_slew_V_per_s
        self.clock = clock
        self._t_prev = -math.inf
        self.readback = readback
        self.outputs: dict[str, float] = dict(initial_V or {a: 0.0 for a in self._axes})
        self.received: list[dict[str, float]] = []
        self.violations: list[str] = []
        self.fail = False
        self.fail_after: int | None = None
        self.reconnects = 0
        self._state = ConnectionState.CONNECTED
        self._lock = threading.Lock()

    @property
    def axes(self) -> tuple[str, ...]:
        return self._axes

    @property
    def limits(self):
        return self._limits

    @property
    def state(self):
        return self._state

    def set_voltages(self, volts) -> None:
        from afmctl.drivers.base import ConnectionState
        from afmctl.drivers.errors import AmplifierConnectionError
        if self.fail_after is not None and len(self.received) >= self.fail_after:
            self.fail, self.fail_after = True, None
        if self.fail:
            self._state = ConnectionState.FAULT
            raise AmplifierConnectionError("recording amplifier: link lost (simulated)")
        with self._lock:
            t = self.clock() if self.clock is not None else math.nan
            for a, v in volts.items():
                v = float(v)
                lo, hi = self.check_limits_V[a]
                if not (lo <= v <= hi):
                    self.violations.append(f"axis {a}: {v!r} V outside [{lo}, {hi}]")
                if self.check_step_V is not None and abs(v - self.outputs[a]) > self.check_step_V * (1 + 1e-9) + 1e-12:
                    self.violations.append(f"axis {a}: step {self.outputs[a]!r} -> {v!r} V "
                                           f"exceeds {self.check_step_V} V")
                if self.check_slew_V_per_s is not None and math.isfinite(t):
                    allowed = self.check_slew_V_per_s * max(t - self._t_prev, 0.0)
                    if abs(v - self.outputs[a]) > allowed * (1 + 1e-9) + 1e-12:
                        self.violations.append(f"axis {a}: {self.outputs[a]!r} -> {v!r} V in "
                                               f"{t - self._t_prev:.3g} s exceeds {self.check_slew_V_per_s} V/s")
            self._t_prev = t
            self.check_limits(volts)
            self.outputs.update({a: float(v) for a, v in volts.items()})
            self.received.append(dict(volts))

    def get_voltages(self) -> dict[str, float]:
        if self.fail:
            from afmctl.drivers.errors import AmplifierConnectionError
            raise AmplifierConnectionError("recording amplifier: link lost (simulated)")
        if self.readback is not None:
            return self.readback(dict(self.outputs))
        return dict(self.outputs)

    def info(self) -> dict[str, object]:
        return {"name": self.name, "axes": list(self._axes)}

    def reconnect(self) -> None:
        from afmctl.drivers.base import ConnectionState
        from afmctl.drivers.errors import AmplifierConnectionError
        if self.fail:
            raise AmplifierConnectionError("recording amplifier: still unreachable")
        self.reconnects += 1
        self._state = ConnectionState.CONNECTED

    def close(self) -> None:
        from afmctl.drivers.base import ConnectionState
        self._state = ConnectionState.CLOSED

    def as_array(self) -> np.ndarray:
        """Received values as (N, n_axes) [V]."""
        return np.array([[r.get(a, np.nan) for a in self._axes] for r in self.received]).reshape(-1, len(self._axes))
