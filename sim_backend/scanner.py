"""The simulated 3-axis piezo scanner (the plant that stands in for hardware).

Chain per axis (x, y lateral; z vertical)::

    command u [V] → amplifier (limits, DAC quantisation, slew, bandwidth)
                  → hysteresis (asymmetric Gaussian-mixture Preisach by default, or any
                    compensators model's forward())
                  → creep (log-spaced lag bank) → structural mode (2nd order, exact zoh)
    then x/y/z cross-coupling (3×3 matrix) and thermal drift [nm] → true tip position.

Two ways to drive it:

* offline / tests: :meth:`Scanner.run` simulates a whole block of voltages (N, 3) with a
  given sample period, much faster than real time;
* streaming / hardware-in-the-loop: simulated amplifiers call :meth:`Scanner.apply` whenever
  their output changes (the value is held) and :meth:`Scanner.advance` moves simulated time
  to ``t_s`` (driven by a clock), in steps of ``config.dt_s``.

Both carry the same state, bit for bit (a run in blocks of any size, or sample by sample
through apply/advance, gives identical positions). Deterministic for a given
``config.seed`` (noise only enters the sensor reading :meth:`Scanner.read_sensor_nm` and
image heights). The plant kernels release the GIL and :meth:`Scanner.advance` simulates a
long gap in chunks of :attr:`Scanner.ADVANCE_CHUNK` samples, so an in-process scanner
driven from an amplifier thread leaves other threads (a real-time loop) running.
"""
from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from afmctl.compensators.base import ModelError
from afmctl.compensators.temperature import T_MAX_C, T_MIN_C
from . import _plant_kernels as K
from .config import (
    AXES,
    AmplifierConfig,
    AxisConfig,
    CreepConfig,
    DriftConfig,
    DynamicsConfig,
    ExternalModelConfig,
    GaussianPreisachConfig,
    NoiseConfig,
    PreisachComponent,
    ScannerConfig,
    SensorConfig,
    default_scanner_config,
    linear_scanner_config,
)
from .plant import AxisPlant
from .sensor import SAMPLE_TOL, PositionSensor, SensorCapture

log = logging.getLogger(__name__)


def whole_samples(span_s: float, dt_s: float) -> int:
    """The whole samples of ``dt_s`` [s] in ``span_s`` [s], a span short of a whole
    number by less than :data:`SAMPLE_TOL` of a sample counting as that number."""
    return int(math.floor(span_s / dt_s + SAMPLE_TOL))


__all__ = [
    "AXES",
    "AmplifierConfig",
    "AxisConfig",
    "CreepConfig",
    "DriftConfig",
    "DynamicsConfig",
    "ExternalModelConfig",
    "GaussianPreisachConfig",
    "NoiseConfig",
    "PreisachComponent",
    "Scanner",
    "ScannerConfig",
    "SensorConfig",
    "SensorCapture",
    "default_scanner_config",
    "linear_scanner_config",
]


class _Drift:
    """Thermal drift [nm] for the three axes from ambient temperature (and voltages)."""

    def __init__(self, cfg: DriftConfig, T0_C: float) -> None:
        self.cfg = cfg
        self.T0_C = T0_C
        self._params: Any = None   # DriftParams (imported only for kind params)
        self._warned_dt = False
        if cfg.kind == "params":
            from afmctl.compensators.drift import DriftParams
            if cfg.params is not None:
                self._params = DriftParams.from_dict(cfg.params, where="drift.params")
            else:
                self._params = DriftParams.named(cfg.named)
        self.reset(T0_C)

    def reset(self, T0_C: float) -> None:
        self.T0_C = T0_C
        self.T_state = np.array([T0_C])
        self._predictor: Any = None   # a DriftPredictor, built for one sample period
        self._predictor_dt: float | None = None
        self._predictor_used = False
        self.last_nm = np.zeros(3)

    def prepare(self, dt_s: float) -> None:
        """Build the drift predictor for the sample period ``dt_s`` now (it is otherwise
        built by the first :meth:`block`); no effect for the other kinds."""
        if self.cfg.kind == "params" and (self._predictor is None or self._predictor_dt != dt_s):
            self._predictor = self._params.predictor(dt_s)
            self._predictor.reset(self.T0_C)
            self._predictor_dt = dt_s
            self._predictor_used = False

    def block(self, T_C: np.ndarray, u_V: np.ndarray, dt_s: float) -> np.ndarray:
        n = T_C.shape[0]
        if self.cfg.kind == "none" or n == 0:
            return np.zeros((n, 3))
        if self.cfg.kind == "expansion":
            out = np.empty((n, 3))
            a = math.exp(-dt_s / self.cfg.thermal_tau_s)
            coef = np.asarray(self.cfg.expansion_nm_per_K, dtype=np.float64)
            K.expansion_drift_nb(np.ascontiguousarray(T_C), out, coef, a, self.T_state, self.T0_C)
        else:
            if self._predictor is None or self._predictor_dt != dt_s:
                if self._predictor is not None and self._predictor_used and not self._warned_dt:
                    self._warned_dt = True
                    log.warning("drift predictor rebuilt for a new sample period %.3g s; its state restarts "
                                "(keep one sample period per scanner for continuous drift)", dt_s)
                self._predictor = None
                self.prepare(dt_s)
            self._predictor_used = True
            out = np.asarray(self._predictor.block(np.ascontiguousarray(T_C), np.ascontiguousarray(u_V)), dtype=np.float64)
        self.last_nm = out[-1].copy()
        return out


class Scanner:
    """A simulated 3-axis piezo scanner; see the module docstring.

    Thread-safe for the streaming calls (:meth:`apply`, :meth:`advance`,
    :meth:`position_nm`): simulated amplifiers may call from their own threads.
    """

    def __init__(self, config: ScannerConfig | None = None, *, fast: bool = True) -> None:
        self.config = config if config is not None else default_scanner_config()
        self.fast = fast
        self.axes = {a: AxisPlant(self.config.axis(a), fast=fast) for a in AXES}
        self.coupling = np.asarray(self.config.coupling, dtype=np.float64)
        self._lock = threading.RLock()
        self.reset()
        # Load the compiled kernels (numba cache) and build the drift predictor now, not in
        # the first apply() on an amplifier thread, where the load holds the GIL for tens
        # of ms and stalls a real-time loop running beside it; then start from scratch.
        self.run(np.zeros((1, 3)))
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the initial state: t = 0, every axis at its lowest voltage in negative
        saturation, ambient temperature ``config.ambient_T_C``, drift zero, noise re-seeded."""
        with self._lock:
            self._clock = (0.0, float(self.config.dt_s), 0)
            self._T_C = float(self.config.ambient_T_C)
            self._drift = _Drift(self.config.drift, self._T_C)
            self.rest()
            self.rng = np.random.default_rng(self.config.seed)
            self.sensor = PositionSensor([self.config.axis(a).sensor for a in AXES], self.config.seed)
            self._captures: list[SensorCapture] = []
            #: output changes handed to :meth:`play` for a time more than a sample before the
            #: simulated time (a wave point the amplifier handed over too late: not simulated)
            self.late_changes = 0

    def rest(self) -> None:
        """The piezo as a fresh scanner has it, while time goes on: every axis back at its
        lowest voltage in negative saturation with its creep and vibration settled, and the
        thermal drift back to zero at the present ambient temperature. The clock, the
        noise's generator and the sensor go on (an amplifier's clock keeps running; the
        next readings are new noise). What ``afmctl learn`` on an in-process simulator does
        before each play, so that every play starts as ``afmctl run`` does on a fresh one."""
        with self._lock:
            for ax in self.axes.values():
                ax.reset()
            self._held_V = self.rest_voltage_V()
            self._drift.reset(self._T_C)
            self._drift.prepare(self.config.dt_s)
            self._pos = self._compose(np.array([[self.axes[a].y_nm for a in AXES]]), np.zeros((1, 3)))[0]

    def rest_voltage_V(self) -> np.ndarray:
        """Where :meth:`rest` leaves the command voltage [x, y, z] V: each axis's lowest."""
        return np.array([self.axes[a].u_min_V for a in AXES], dtype=float)

    def _compose(self, disp: np.ndarray, drift: np.ndarray) -> np.ndarray:
        """Coupling then drift, row by row in a fixed order of operations (not ``disp @ C.T``,
        whose BLAS rounding depends on the number of rows), so that a run in blocks of any
        size — and the streaming path — gives bit-identical positions."""
        c = self.coupling
        out = np.empty_like(disp)
        for i in range(3):
            out[:, i] = disp[:, 0] * c[i, 0] + disp[:, 1] * c[i, 1] + disp[:, 2] * c[i, 2] + drift[:, i]
        return out

    def set_ambient_temperature(self, T_C: float) -> None:
        """Ambient temperature [°C] held from now on (drives the thermal drift)."""
        T = float(T_C)
        if not math.isfinite(T) or not T_MIN_C <= T <= T_MAX_C:
            raise ModelError(f"T_C: {T!r} out of range; allowed {T_MIN_C:g}…{T_MAX_C:g} °C")
        with self._lock:
            self._T_C = T

    @property
    def ambient_T_C(self) -> float:
        return self._T_C

    def position_nm(self) -> np.ndarray:
        """True tip position [x, y, z] nm at :attr:`time_s` (no noise)."""
        with self._lock:
            return self._pos.copy()

    def snapshot(self) -> tuple[float, np.ndarray]:
        """``(time_s, position_nm)`` read together: the simulated time [s] and the true tip
        position [x, y, z] nm at that time (no other thread can advance in between)."""
        with self._lock:
            return self.time_s, self._pos.copy()

    @property
    def time_s(self) -> float:
        """The simulated time [s]: an exact count of samples since the last change of the
        sample period (``start + count·dt``), so that it lands on the times a device's clock
        computes (``t0 + k·period``) however many blocks it was simulated in; a running sum
        of ``n·dt`` drifts by rounding and would apply a change a sample early."""
        start, dt, count = self._clock
        return start + count * dt

    def _tick(self, n: int, dt: float) -> None:
        """The clock advanced by ``n`` samples of ``dt`` [s]."""
        start, clock_dt, count = self._clock
        if dt != clock_dt:
            start, clock_dt, count = start + count * clock_dt, dt, 0
        self._clock = (start, clock_dt, count + n)

    def read_sensor_nm(self) -> np.ndarray:
        """A position-sensor reading: true position plus Gaussian noise
        (``config.noise.position_std_nm``)."""
        with self._lock:
            return self._pos + self.rng.normal(0.0, self.config.noise.position_std_nm, 3) if self.config.noise.position_std_nm > 0 else self._pos.copy()

    def capture_sensor(self, t0_s: float, period_s: float, n: int) -> SensorCapture:
        """Ask for ``n`` position-sensor readings [x, y, z] nm at ``t0_s + k·period_s`` [s]
        (a data recorder armed now): filled as simulated time passes them (each the reading
        of the last sample ending at or before that time; a time already past gets the
        present reading). See :mod:`afmctl.sim_backend.sensor` and ``AxisConfig.sensor``."""
        cap = SensorCapture(t0_s, period_s, n)
        with self._lock:
            self._captures = [c for c in self._captures if not c.done]
            if not self._captures:          # the sensor wakes settled at the present position
                self.sensor.reset(self._pos)
            self._captures.append(cap)
            cap.hold(self.time_s, self.sensor.last_nm, self.config.dt_s, self._piezo_now())
        return cap

    def _piezo_now(self) -> np.ndarray:
        """The piezo voltage [x, y, z] V now (after the amplifier stage)."""
        return np.array([self.axes[a].u_piezo_V for a in AXES])

    def _sense(self, pos: np.ndarray, dt: float, volts: np.ndarray, volts_before: np.ndarray) -> None:
        """Run the position sensor over a simulated block and hand its readings (and the
        block's piezo voltages ``volts`` [V], ``volts_before`` those held at its start) to
        the waiting captures (only while one waits)."""
        before = self.sensor.last_nm.copy()
        readings = self.sensor.block(pos, dt)
        for cap in self._captures:
            cap.fill(self.time_s, dt, readings, before, volts, volts_before)
        self._captures = [c for c in self._captures if not c.done]

    def piezo_voltage_V(self) -> np.ndarray:
        """Voltage at each piezo [x, y, z] V (after the amplifier model)."""
        with self._lock:
            return self._piezo_now()

    def held_voltage_V(self) -> np.ndarray:
        """The command voltage currently held [x, y, z] V."""
        with self._lock:
            return self._held_V.copy()

    def drift_nm(self) -> np.ndarray:
        """The thermal drift part of the last position [x, y, z] nm."""
        with self._lock:
            return self._drift.last_nm.copy()

    def nominal_gain_nm_per_V(self) -> np.ndarray:
        """Range / voltage span per axis [nm/V] — the linear calibration an uncompensated
        AFM uses to turn positions into voltages."""
        return np.array([self.axes[a].static_gain_nm_per_V() for a in AXES])

    def voltage_limits_V(self) -> np.ndarray:
        """(3, 2) array of [u_min_V, u_max_V] per axis."""
        return np.array([[self.axes[a].u_min_V, self.axes[a].u_max_V] for a in AXES])

    # ------------------------------------------------------------------ block simulation
    def run(self, u_V: np.ndarray, dt_s: float | None = None, T_C: np.ndarray | None = None,
            return_voltage: bool = False):
        """Simulate command voltages ``u_V`` (N, 3) [V], each held for ``dt_s`` seconds
        (default ``config.dt_s``), from the current state; returns the true tip positions
        (N, 3) [nm] at the end of each sample. ``T_C`` (N,) is the ambient temperature per
        sample (default: the held one). Advances :attr:`time_s` by N·dt_s and leaves the
        last voltage held. With ``return_voltage`` also returns the piezo voltages (N, 3)."""
        dt = float(self.config.dt_s if dt_s is None else dt_s)
        if not (math.isfinite(dt) and dt > 0):
            raise ModelError(f"dt_s: {dt_s!r} must be a positive finite number of seconds")
        u = np.asarray(u_V, dtype=np.float64)
        if u.ndim != 2 or u.shape[1] != 3:
            raise ModelError(f"u_V: expected shape (N, 3) [x, y, z volts], got {u.shape}")
        if not np.all(np.isfinite(u)):
            bad = int(np.flatnonzero(~np.isfinite(u).all(axis=1))[0])
            raise ModelError(f"u_V: non-finite voltage in row {bad}; all values must be finite")
        n = u.shape[0]
        with self._lock:
            if T_C is None:
                T = np.full(n, self._T_C)
            else:
                T = np.asarray(T_C, dtype=np.float64).reshape(-1)
                if T.shape[0] != n or not np.all(np.isfinite(T)):
                    raise ModelError(f"T_C: expected {n} finite temperatures [°C], got shape {T.shape}")
            disp = np.empty((n, 3))
            volts = np.empty((n, 3))
            volts_before = self._piezo_now() if self._captures else None
            for i, a in enumerate(AXES):
                y, v = self.axes[a].run(np.ascontiguousarray(u[:, i]), dt, return_voltage=True)
                disp[:, i] = y
                volts[:, i] = v
            drift = self._drift.block(T, volts, dt)
            pos = self._compose(disp, drift)
            if n and volts_before is not None:
                self._sense(pos, dt, volts, volts_before)
            if n:
                self._pos = pos[-1].copy()
                self._held_V = u[-1].copy()
                if T_C is not None:
                    self._T_C = float(T[-1])
            self._tick(n, dt)
        return (pos, volts) if return_voltage else pos

    # ------------------------------------------------------------------ streaming
    def apply(self, volts: Mapping[str, float], t_s: float | None = None) -> None:
        """Sink for simulated amplifiers: from time ``t_s`` on (default: now) hold the given
        voltages, e.g. ``{"x": 10.0, "y": 0.5}``; axes not named keep their value. If
        ``t_s`` is later than :attr:`time_s` the scanner first advances to ``t_s`` with the
        old voltages."""
        with self._lock:
            if t_s is not None:
                self.advance(t_s)
            self._held_V = self.voltages_with(volts, self._held_V)

    @staticmethod
    def voltages_with(volts: Mapping[str, float], held_V: np.ndarray) -> np.ndarray:
        """The row (x, y, z) [V] held after ``apply(volts)`` from ``held_V`` [V]: the named
        axes replaced, the others kept; a new array. Raises ModelError naming an unknown
        axis or a value that is not a finite number of volts."""
        held = np.array(held_V, dtype=np.float64).reshape(3)
        for key, value in volts.items():
            k = str(key).lower()
            if k not in AXES:
                raise ModelError(f"volts: unknown axis {key!r}; allowed x, y, z")
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise ModelError(f"volts.{k}: {value!r} is not a number of volts") from None
            if not math.isfinite(v):
                raise ModelError(f"volts.{k}: {value!r} is not a finite voltage")
            held[AXES.index(k)] = v
        return held

    def play(self, t_s: Sequence[float], rows_V: Sequence[Sequence[float]]) -> None:
        """Sink for amplifiers that play on their own clock: the same as
        ``apply({"x": r[0], "y": r[1], "z": r[2]}, t)`` for each time ``t`` [s] and row ``r``
        [V] in order, simulated in one block (a buffered stream at 10 kHz hands over ~10
        samples per millisecond; one :meth:`run` per sample would cost more than the period).
        The held voltage of each stretch of whole ``config.dt_s`` samples is the one the
        sequence of ``apply`` calls would hold there."""
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        rows = np.asarray(rows_V, dtype=np.float64).reshape(-1, 3)
        if t.shape[0] != rows.shape[0]:
            raise ModelError(f"play: {t.shape[0]} times for {rows.shape[0]} rows of volts")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(rows))):
            raise ModelError("play: times [s] and volts must be finite")
        if not len(rows):
            return
        with self._lock:
            dt = self.config.dt_s
            counts = []
            t0, done = self.time_s, 0                   # the clock counts samples, not sums of n·dt
            self.late_changes += int(np.count_nonzero(t < t0 - dt))
            for t_k in t.tolist():                      # whole samples before each change, as advance()
                n = max(whole_samples(t_k - (t0 + done * dt), dt), 0)
                counts.append(n)
                done += n
            before = np.vstack([self._held_V[None, :], rows[:-1]])    # held until each change
            u = np.repeat(before, counts, axis=0)
            for k in range(0, len(u), self.ADVANCE_CHUNK):
                self.run(u[k:k + self.ADVANCE_CHUNK], dt)
            self._held_V = rows[-1].copy()

    #: most samples simulated in one block by :meth:`advance`; a long idle gap is simulated
    #: in chunks of this size so that no single stretch of Python-level work (e.g. the
    #: drift predictor, which holds the GIL) stalls other threads for long. Chunking does
    #: not change the result (block simulation carries its state exactly).
    ADVANCE_CHUNK = 2048

    def advance(self, t_s: float) -> None:
        """Simulate up to time ``t_s`` [s] with the held voltages, in whole samples of
        ``config.dt_s`` (a remainder shorter than one sample waits for the next call).
        Earlier times are ignored. ``t_s`` must be finite."""
        t = float(t_s)
        if not math.isfinite(t):
            raise ModelError(f"t_s: {t_s!r} is not a finite time in seconds")
        with self._lock:
            dt = self.config.dt_s
            n = whole_samples(t - self.time_s, dt)
            while n > 0:
                k = min(n, self.ADVANCE_CHUNK)
                self.run(np.broadcast_to(self._held_V, (k, 3)), dt)
                n -= k

    def image(self, sample: Any, **kwargs: Any):
        """Raster-image ``sample``; see :func:`afmctl.sim_backend.imaging.raster_image`."""
        from .imaging import raster_image

        return raster_image(self, sample, **kwargs)
