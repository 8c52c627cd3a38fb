"""The real-time loop: trajectory → drift → inverse models → safety → amplifier.

:class:`Controller` runs one thread that ticks at a fixed rate (``loop.rate_Hz``, 1 kHz by
default) on absolute deadlines (``next += period``): it sleeps until shortly before the
deadline, then spins (``loop.spin_s``). Per tick it takes the next target sample
``r`` [nm], asks the drift predictor for ``d̂`` [nm] (ambient temperature, heat from the
voltages already sent), inverts the hysteresis/creep models on ``r − d̂`` and hands the
voltages to :class:`afmctl.control.safety.SafetyLayer`, the only path to the amplifier. A link that
buffers (serial) makes ``set_voltages`` block; the lateness that causes is measured.

Nothing on the loop thread writes files, logs or calls user code: each sent setpoint goes
into a preallocated ring buffer, and a dispatcher thread hands batches to the run log
(:mod:`afmctl.control.runlog`, whose own thread writes and flushes) and to sinks
(:meth:`Controller.add_sink`).

Sinks (e.g. the zenoh bridge) may define any of

* ``on_setpoints(batch)`` — numpy structured array, dtype
  :data:`afmctl.control.runlog.SETPOINT_DTYPE`: ``seq`` (uint64), ``t_s``, ``target_nm`` (3,),
  ``corrected_nm`` (3,), ``u_V`` (3,);
* ``on_drift(estimate)`` — dict ``{"seq", "t_s", "T_C", "drift_nm": [x, y, z], "std_nm"}``
  (the latest estimate of the batch; ``std_nm`` is the Kalman filter's 1-σ per axis [nm]
  with ``compensation.drift.kalman = true``, else None);
* ``on_status(status)`` — dict ``{"state", "event", "detail", "seq", "t_s", "stats"}`` on
  every state change and every ``status_interval_s``.

They are called from the dispatcher thread, never from the loop thread.

Drift measurements (:meth:`Controller.submit_drift_measurement`, any thread) wait in a
small deque; the loop thread fuses them into the Kalman filter before its next sample.

States (:class:`State`): ``idle`` (not started), ``running``, ``holding`` (the watchdog saw
the trajectory stall: output held or ramping to the safe value), ``fault`` (a driver error:
output held by the device, reconnecting; on success the output ramps from the read-back
voltage to the pending setpoint and the run resumes), ``stopped``. While ``running`` the
loop thread is in one of the modes of :class:`afmctl.control.machine.Mode` (``run``,
``settle``, ``finish``); :mod:`afmctl.control.machine` holds the loop thread's tick methods,
:mod:`afmctl.control.stats` the timing histograms.

Preview horizon: when the pipeline's inverse reads the target ``L`` samples ahead (a
chain with a dynamics stage, :mod:`afmctl.control.preview`), the loop feeds it the trajectory ``L``
samples ahead of the output; the output lags what the loop reads by the fixed
:attr:`Controller.latency_s` (in :meth:`Controller.stats` and every status), and the run
log records each output beside the target it aims at.

Timing statistics (:meth:`Controller.stats`): lateness = how long after its deadline a
tick started [s] (p50 and p99 from a histogram of every tick of the run — 0.5 µs bins
below 2 ms, 100 µs bins above — and the max); a deadline is *missed* when a tick starts more than half a period late. When the loop falls more than
``loop.resync_periods`` behind (e.g. a blocked link), it restarts its schedule
(``overruns``) instead of bursting.
"""
from __future__ import annotations

import collections
import gc
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.compensators.temperature import T_MAX_C, T_MIN_C

from . import stats as loop_stats
from ..errors import AfmctlError, error_line
from . import cpu_pinning
from .machine import (C_COR, C_D, C_S, C_SEQ, C_T, C_TGT, C_TICK, C_U, END_OF_TRAJECTORY, N_COLS,
                           RING_ROWS, LoopMachine, Mode, State)  # noqa: F401 - Mode re-exported
from .runlog import DRIFT_DTYPE, SETPOINT_DTYPE, RunLogWriter
from .learned_table import LearnedSource
from .safety import SafetyLayer
from ..inputs import trajectories
from ..inputs.trajectories import check_positions, resample

log = logging.getLogger(__name__)

_RING = RING_ROWS
#: largest run-time segment after resampling to the loop period [samples]
MAX_SEGMENT_SAMPLES = 1_000_000
#: drift measurements waiting for the loop thread (more are refused)
MAX_PENDING_DRIFT_MEASUREMENTS = 64
_END = END_OF_TRAJECTORY
# histogram helpers under their former names (see afmctl.control.stats)
_HBINS = loop_stats.N_BINS
_bin = loop_stats.bin_of
_percentiles = loop_stats.percentiles


def _as_block(arr: Any, where: str = "trajectory") -> np.ndarray:
    """Validate a block of positions (N, 3) [nm]; returns it as a float64 array."""
    a = np.ascontiguousarray(arr, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise AfmctlError(f"{where}: positions must have shape (N, 3) [nm], got {a.shape}")
    check_positions(a, lambda i: f"{where}: sample {i}")
    return a


def _flat(rows: np.ndarray) -> list[float]:
    """A block as one flat list x0, y0, z0, x1, ... (one GC-tracked object per block)."""
    return rows.ravel().tolist()


def helper_priority(loop_priority: int | None, cpus: frozenset[int] | None = None) -> None:
    """Make the calling thread SCHED_FIFO one step below a real-time loop thread (priority
    ``loop_priority``; None: leave it). Every thread of the loop's process that takes the
    interpreter lock now and then (feeder, dispatcher, run log, the zenoh pipe threads) runs
    so, because an ordinary thread preempted by other processes while holding the lock makes
    the loop wait for it (priority inversion). ``cpus``: pin the thread there too (the CPUs
    that are not the loop's, :mod:`afmctl.control.cpu_pinning`; None: leave)."""
    cpu_pinning.pin_this_thread(cpus)
    if loop_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(max(1, loop_priority - 1)))
        except (AttributeError, OSError):
            pass


def quiet_window_wait_s(now_s: float, deadline_s: float, period_s: float, spin_s: float) -> float:
    """How long [s] a helper thread waits from ``now_s`` to be inside the loop's quiet window.

    The loop ticks at ``deadline_s + k · period_s`` (perf_counter [s]), works for a while, then
    sleeps until ``spin_s`` before the next deadline and spins. The quiet window of each period
    starts a quarter period after the deadline (the tick's work done) and ends ``spin_s`` plus
    a quarter period before the next one; a helper that starts there hands the interpreter
    lock back before the loop needs it. 0 when ``now_s`` is inside a window, when the loop is
    not running (``deadline_s`` 0) or when the period leaves no window (fast loops)."""
    start = 0.25 * period_s
    end = 0.75 * period_s - spin_s
    if deadline_s <= 0.0 or end - start < 1e-4:
        return 0.0
    phase = (now_s - deadline_s) % period_s
    if start <= phase <= end:
        return 0.0
    return (start - phase) % period_s


class Controller:
    """Fixed-rate feedforward controller; see the module docstring.

    Parameters
    ----------
    config: :class:`afmctl.config.Config`.
    amplifier: an open :class:`afmctl.drivers.base.Amplifier`; the controller never closes it.
    pipeline: optional :class:`afmctl.control.pipeline.CompensationPipeline` (default: built from
        ``config``).
    """

    status_interval_s = 0.5
    dispatch_interval_s = 0.02
    #: test hook for ``amplifier.output = "stream"``: called once per producer wake-up on
    #: the loop thread (tests inject host stalls there); None in use
    stream_stall_hook: Any = None

    def __init__(self, config, amplifier, *, pipeline=None) -> None:
        self.config = config
        self.amplifier = amplifier
        self.dt_s = float(config.dt_s)
        if pipeline is None:
            from .pipeline import build_pipeline
            pipeline = build_pipeline(config)
        self.pipeline = pipeline
        axes = list(config.scanner.axes)
        if config.amplifier.output == "wave":
            from .wave_run import check_wave_config
            check_wave_config(config, amplifier)   # refuse at once, before anything runs
        if config.amplifier.output == "stream" and not hasattr(amplifier, "start_stream"):
            raise AfmctlError(f"amplifier.output = 'stream': the {config.amplifier.driver} driver has no "
                              "buffered stream; allowed with driver 'can'")
        self.safety = SafetyLayer(amplifier, axes, {a: config.limits(a) for a in axes},
                                  config.slew_V_per_s(), self.dt_s,
                                  {a: config.safety.safe_value(a) for a in axes})
        self._state = State.IDLE
        self._request: str | None = None
        self._sinks: list[Any] = []
        self._deque: collections.deque = collections.deque()
        self._queue_mode = False
        self._learned_source: LearnedSource | None = None
        self._queue_end_when_idle = False
        self._thread: threading.Thread | None = None
        self._feeder: threading.Thread | None = None
        self._rc_thread: threading.Thread | None = None
        self._rc_error: BaseException | None = None
        self._dispatcher: threading.Thread | None = None
        self._feed_stop = False
        self._feed_error: str | None = None
        self._events: collections.deque = collections.deque()
        self._drift_meas: collections.deque = collections.deque()
        self._ring = np.zeros((_RING, N_COLS))
        self._hist = loop_stats.new_histogram()
        self._whist = loop_stats.new_histogram()
        self._missed_log: collections.deque = collections.deque(maxlen=32)
        self._reset_stats()
        self._T_C = float(config.compensation.temperature.T_C)
        self._T_file: tuple[np.ndarray, np.ndarray] | None = None
        self.runlog: RunLogWriter | None = None
        self.runlog_path: Path | None = None
        #: why the run log failed (the run was stopped), or None
        self.runlog_error: str | None = None
        self._done = threading.Event()
        #: perf_counter time [s] of the deadline of the loop's latest tick (0: not running);
        #: written by the loop thread, read by the dispatcher to keep off the next deadline
        self._deadline_s = 0.0
        #: loop.cpu resolved: the loop thread's CPU and the other threads' CPUs
        self.cpu_plan = cpu_pinning.plan_for(config.loop)

    # ------------------------------------------------------------------ public API
    @property
    def latency_samples(self) -> int:
        """Preview horizon [samples]: the loop reads the trajectory this far ahead of its
        output (the pipeline's dynamics inverse needs it; 0 without one, and 0 with
        ``amplifier.output = "wave"``, whose table is computed from the whole trajectory)."""
        if self.config.amplifier.output == "wave":
            return 0
        return int(getattr(self.pipeline, "latency_samples", 0))

    @property
    def latency_s(self) -> float:
        """The output's fixed lag behind the trajectory it reads [s]: ``latency_samples``
        loop periods. A trajectory file is read ahead (its timeline is kept, the run takes
        this much longer); live setpoints (queue mode, zenoh) reach the output this late."""
        return self.latency_samples * self.dt_s

    @property
    def state(self) -> State:
        return self._state

    @property
    def trajectory_error(self) -> str | None:
        """Why the trajectory source failed during the last run (the run ended safely), or None."""
        return self._feed_error

    @property
    def running(self) -> bool:
        """True while the loop thread (or its dispatcher) is alive."""
        return any(t is not None and t.is_alive() for t in (self._thread, self._dispatcher))

    def add_sink(self, sink: Any) -> None:
        """Register an object with ``on_setpoints``/``on_drift``/``on_status`` (any subset)."""
        self._sinks.append(sink)

    def remove_sink(self, sink: Any) -> None:
        if sink in self._sinks:
            self._sinks.remove(sink)

    def set_temperature(self, t_s: float, T_C: float) -> None:
        """Ambient temperature reading [°C] at time ``t_s`` [s] for the drift predictor."""
        try:
            T = float(T_C)
        except (TypeError, ValueError):
            raise AfmctlError(f"temperature: T_C {T_C!r} is not a number") from None
        if not (math.isfinite(T) and T_MIN_C <= T <= T_MAX_C):
            raise AfmctlError(f"temperature: T_C {T!r} outside the allowed range {T_MIN_C:g}..{T_MAX_C:g} °C")
        self._T_C = T

    def submit_drift_measurement(self, measured_drift_nm: Any, std_nm: float, t_s: float | None = None) -> None:
        """Hand a drift measurement to the Kalman filter (``compensation.drift.kalman``).

        ``measured_drift_nm``: 3 values [nm] x, y, z (NaN = axis not measured), the drift
        at controller time ``t_s`` [s] (default: now); ``std_nm``: its 1-σ [nm]. Validated
        here (AfmctlError naming the field and range); the loop thread fuses it before its
        next sample (never blocks the loop). Accepted while the controller runs.
        """
        if getattr(self.pipeline, "kalman", None) is None:
            raise AfmctlError("drift-measurement: the Kalman filter is off "
                              "(set compensation.drift.enabled = true and compensation.drift.kalman = true)")
        try:
            z = np.asarray(measured_drift_nm, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            z = np.empty(0)
        if z.shape != (3,) or np.any(np.isinf(z)) or np.all(np.isnan(z)) or np.any(np.abs(z[np.isfinite(z)]) > 1e6):
            raise AfmctlError(f"drift-measurement: measured_drift_nm {measured_drift_nm!r:.80} must be 3 values "
                              "in -1e6..1e6 nm (NaN = axis not measured, at least one measured)")
        if isinstance(std_nm, (str, bytes, bool)):
            std = math.nan
        else:
            try:
                std = float(std_nm)
            except (TypeError, ValueError):
                std = math.nan
        if not (math.isfinite(std) and 1e-6 <= std <= 1e6):
            raise AfmctlError(f"drift-measurement: std_nm {std_nm!r:.40} outside the allowed range 1e-6..1e6 nm")
        t = math.nan
        if t_s is not None:
            if not isinstance(t_s, (str, bytes, bool)):
                try:
                    t = float(t_s)
                except (TypeError, ValueError):
                    pass
            if not (math.isfinite(t) and 0.0 <= t <= 1e7):
                raise AfmctlError(f"drift-measurement: t_s {t_s!r:.40} outside the allowed range 0..1e7 s "
                                  "(controller time since start)")
        if not self.running or self._state is State.STOPPED:
            raise AfmctlError(f"drift-measurement: controller is {self._state.value}; "
                              "measurements are accepted while it runs")
        if len(self._drift_meas) >= MAX_PENDING_DRIFT_MEASUREMENTS:
            raise AfmctlError(f"drift-measurement: {MAX_PENDING_DRIFT_MEASUREMENTS} measurements already "
                              "pending; the loop is not consuming them")
        self._drift_meas.append(((float(z[0]), float(z[1]), float(z[2])), std, t))

    def submit_segment(self, positions_nm: np.ndarray, dt_s: float) -> int:
        """Append a segment (N, 3) [nm] sampled every ``dt_s`` [s] (resampled to the loop
        period) to the run-time queue; returns the number of loop samples queued.

        Accepted when idle or when running in queue mode (``start(None)`` or
        ``trajectory.kind = "queue"``).
        """
        try:
            dt = float(dt_s)
        except (TypeError, ValueError):
            raise AfmctlError(f"segment: dt_s {dt_s!r} is not a number") from None
        if not (math.isfinite(dt) and 1e-6 <= dt <= 10.0):
            raise AfmctlError(f"segment: dt_s {dt_s!r} outside the allowed range 1e-6..10 s")
        if self.running and not self._queue_mode:
            raise AfmctlError("segment: the controller is running a finite trajectory; segments are "
                              "accepted in queue mode (trajectory.kind = 'queue')")
        src = _as_block(positions_nm, "segment")  # validate before resampling
        n_out = int(math.floor(max(len(src) - 1, 0) * dt / self.dt_s + 1e-9)) + 1
        if n_out > MAX_SEGMENT_SAMPLES:
            raise AfmctlError(f"segment: {len(src)} samples every {dt:g} s make {n_out} loop samples; "
                              f"at most {MAX_SEGMENT_SAMPLES} per segment (split it)")
        rows = _as_block(resample(np.asarray(positions_nm, dtype=np.float64), dt, self.dt_s), "segment")
        bs = self.config.loop.block_samples
        for k in range(0, len(rows), bs):
            self._deque.append(_flat(rows[k:k + bs]))
        return len(rows)

    def _learned_or(self, source: Any) -> Any:
        """A ``kind = "learned"`` spec as its :class:`LearnedSource` (the wave machine plays its
        table instead of planning one); any other source as it is."""
        if getattr(source, "kind", None) == "learned":
            source = LearnedSource.from_file(source.file)
        self._learned_source = source if isinstance(source, LearnedSource) else None
        if self._learned_source is not None and self.config.amplifier.output != "wave":
            raise AfmctlError("start: a learned table plays on the amplifier's clock: set amplifier.output = 'wave'")
        return source

    def start(self, source: Any = None, *, runlog_path: str | Path | None = None) -> None:
        """Start the loop thread.

        ``source``: None (run-time segments, queue mode), a trajectory spec of
        :mod:`afmctl.config` (built by :func:`afmctl.inputs.trajectories.build`), an array
        (N, 3) [nm] at the loop period, or an iterable of such blocks.
        """
        if self.running:
            raise AfmctlError(f"start: controller is {self._state.value}; stop it first")
        if self._rc_thread is not None:
            self._rc_thread.join(60.0)
            if self._rc_thread.is_alive():
                raise AfmctlError("start: the previous run's reconnect attempt is still in the driver")
        it: Iterator | None
        source = self._learned_or(source)
        self._queue_mode = False
        self._queue_end_when_idle = False
        if source is None:
            self._queue_mode = True
            it = None
        elif getattr(source, "kind", None) == "queue":
            self._queue_mode = True
            self._queue_end_when_idle = source.idle == "end"
            it = None
        elif hasattr(source, "blocks_at"):
            it = iter(source.blocks_at(self.dt_s, self.config.loop.block_samples))
        elif hasattr(source, "kind"):
            it = iter(trajectories.build(source, self.dt_s, self.config.loop.block_samples))
        elif isinstance(source, np.ndarray):
            it = iter(trajectories.blocks_of(source, self.config.loop.block_samples))
        elif isinstance(source, Iterable):
            it = iter(source)
        else:
            raise AfmctlError(f"start: unsupported trajectory source {type(source).__name__}")
        if self._queue_mode and self.config.amplifier.output == "wave":
            raise AfmctlError("start: amplifier.output = 'wave' plays a finite trajectory computed before the "
                              "run; run-time segments (queue mode) need output = 'setpoints' or 'stream'")
        if not self._queue_mode:
            self._deque.clear()
        self._drift_meas.clear()        # measurements of a previous run refer to its filter
        tsec = self.config.compensation.temperature
        if tsec.source == "file" and tsec.file is not None:
            from ..data.datafiles import read_csv
            data = read_csv(tsec.file, ("t", "T"))
            self._T_file = (np.asarray(data["t"], float), np.asarray(data["T"], float))
        # reset counters of a previous run
        self._request = None
        self.runlog_error = None
        self._feed_stop = False
        self._feed_error = None
        self._done.clear()
        self._reset_stats()
        self._warm_up()
        if self.config.loop.gc_freeze:
            gc.collect()
            gc.freeze()   # long-lived objects leave the collector's generations
        if self.config.runlog.enabled:
            self._open_runlog(runlog_path)
        self._set_state(State.RUNNING, "start")
        if it is not None:
            self._feeder = threading.Thread(target=self._feed, args=(it,), name="afmctl-feeder", daemon=True)
            self._feeder.start()
        self._thread = threading.Thread(target=self._loop_main, name="afmctl-loop", daemon=True)
        self._dispatcher = threading.Thread(target=self._dispatch_main, name="afmctl-dispatch", daemon=True)
        self._thread.start()
        self._dispatcher.start()

    def _open_runlog(self, runlog_path: str | Path | None) -> None:
        """Create this run's log (default name: runlog.dir/<scanner>-<time>[-k].afmlog)."""
        if runlog_path is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            base = Path(self.config.runlog.dir) / f"{self.config.scanner.name}-{stamp}"
            runlog_path = base.with_name(base.name + ".afmlog")
            k = 1
            while runlog_path.exists():
                runlog_path = base.with_name(f"{base.name}-{k}.afmlog")
                k += 1
        meta = {"scanner": self.config.scanner.name, "dt_s": self.dt_s, "rate_Hz": self.config.loop.rate_Hz,
                "axes": list(self.config.scanner.axes), "driver": self.config.amplifier.driver,
                "config": self.config.model_dump(mode="json")}
        prio = self.config.loop.realtime_priority
        self.runlog = RunLogWriter(runlog_path, meta, flush_interval_s=self.config.runlog.flush_interval_s,
                                   fsync=self.config.runlog.fsync,
                                   realtime_priority=max(1, prio - 1) if prio else None)
        self.runlog_path = Path(runlog_path)

    def _warm_up(self) -> None:
        """Run the chain once off the loop thread (compiles/loads numba kernels), then reset."""
        try:
            self.pipeline.step(0.0, 0.0, 0.0, self._T_C, (0.0, 0.0, 0.0))
        except Exception as err:  # a model that cannot take 0 nm still works from its range
            log.debug("warm-up step failed: %s", err)
        self.pipeline.reset()

    def stop(self) -> None:
        """Stop: ramp to the safe value (``safety.on_finish = "safe"``) or hold, then
        ``stopped``. Returns immediately; see :meth:`wait`."""
        if self._request != "estop":
            self._request = "stop"
        self._feed_stop = True

    def estop(self) -> None:
        """Emergency stop: ramp to the safe value as fast as the slew limit allows."""
        self._request = "estop"
        self._feed_stop = True

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the run has ended and every record has been dispatched."""
        return self._done.wait(timeout)

    def close(self, timeout: float = 10.0) -> None:
        """Stop if running, wait, close the run log (the amplifier stays open)."""
        if self._thread is not None and self._thread.is_alive():
            self.stop()
        if self._thread is not None:
            self._thread.join(timeout)
        if self._dispatcher is not None:
            self._dispatcher.join(timeout)
        if self._feeder is not None:
            self._feed_stop = True
            self._feeder.join(timeout)
        if self._rc_thread is not None:   # a reconnect attempt still in the driver
            self._rc_thread.join(timeout)
        if self.runlog is not None:
            self.runlog.close()

    def __enter__(self) -> "Controller":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def stats(self) -> dict[str, Any]:
        """Loop statistics: lateness p50/p99/max [s] (histogram of every tick of the run:
        0.5 µs bins below 2 ms, 100 µs above), work per tick p50/p99 [s], missed deadlines,
        samples, errors."""
        p50, p99 = _percentiles(self._hist, (0.50, 0.99))
        w50, w99 = _percentiles(self._whist, (0.50, 0.99))
        pmax = self._late_max
        s = self.safety
        return {
            "state": self._state.value, "rate_Hz": self.config.loop.rate_Hz, "ticks": self._tick,
            "samples": self._seq, "lateness_p50_s": p50, "lateness_p99_s": p99,
            "lateness_max_s": pmax, "missed_deadlines": self._missed,
            "work_p50_s": w50, "work_p99_s": w99,
            "overruns": self._overruns, "errors": self._errors, "faults": self._faults,
            "reconnects": self._reconnects, "watchdog_trips": self._watchdog_trips,
            "slew_limited": s.slew_limited, "clamped": s.clamped, "nonfinite": s.nonfinite,
            "dropped_records": self._dropped, "last_error": self._last_error,
            "missed_recent": [(int(k), float(v)) for k, v in list(self._missed_log)[-8:]],
            "T_C": self._T_C, "runlog_error": self.runlog_error,
            "latency_samples": self.latency_samples, "latency_s": self.latency_s,
            "output": self.config.amplifier.output, "stream": self._stream_stats,
            "wave": self._wave_stats,
        }

    # ------------------------------------------------------------------ internals
    def _reset_stats(self) -> None:
        """Zero every counter of :meth:`stats` (a new run starts from scratch)."""
        self._w = 0
        #: ring rows the dispatcher has handed on (a producer that writes many rows at once
        #: waits for it instead of overrunning the ring)
        self._r_done = 0
        self._hist[:] = 0
        self._whist[:] = 0
        self._missed_log.clear()
        self._late_max = 0.0
        self._missed = self._overruns = self._dropped = 0
        self._errors = self._faults = self._reconnects = self._watchdog_trips = 0
        self._seq = self._tick = 0
        self._last_error: str | None = None
        #: output = "stream": underruns, lowest_level, queued, ... (afmctl.control.stream); else None
        self._stream_stats: dict[str, Any] | None = None
        #: output = "wave": samples, pad, played, ... (afmctl.control.wave_run); else None
        self._wave_stats: dict[str, Any] | None = None
        self.safety.slew_limited = self.safety.clamped = self.safety.nonfinite = 0

    def _set_state(self, state: State, event: str, detail: str | None = None) -> None:
        self._state = state
        self._events.append({"seq": self._seq, "t_s": self._tick * self.dt_s, "wall_time": time.time(),
                             "state": state.value, "event": event, "detail": detail})

    def _event(self, event: str, detail: str | None = None) -> None:
        self._events.append({"seq": self._seq, "t_s": self._tick * self.dt_s, "wall_time": time.time(),
                             "state": self._state.value, "event": event, "detail": detail})

    def _helper_priority(self) -> None:
        """Run the calling helper thread (feeder, dispatcher) as :func:`helper_priority` says."""
        helper_priority(self.config.loop.realtime_priority, self.cpu_plan.others)

    def _feed(self, it: Iterator) -> None:
        self._helper_priority()
        bs = self.config.loop.block_samples
        prefetch = self.config.loop.prefetch_blocks
        dq = self._deque
        try:
            for blk in it:
                rows = _as_block(blk)
                for k in range(0, len(rows), bs):
                    while len(dq) >= prefetch and not self._feed_stop:
                        time.sleep(0.002)
                    if self._feed_stop:
                        return
                    dq.append(_flat(rows[k:k + bs]))
        except Exception as err:  # a trajectory generator failed: end the run safely
            self._feed_error = error_line(err)
            log.error("trajectory: %s", self._feed_error)
        dq.append(_END)

    def _loop_main(self) -> None:
        old_switch = sys.getswitchinterval()
        si = self.config.loop.switch_interval_s
        if si is not None:
            sys.setswitchinterval(si)
        prio = self.config.loop.realtime_priority
        plan = self.cpu_plan
        if plan.loop_cpu is not None and cpu_pinning.pin_this_thread(frozenset({plan.loop_cpu})):
            self._event("cpu", plan.why)
        else:
            self._event("cpu-none", plan.why)
        if prio is not None:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))  # this thread only
                self._event("realtime", f"loop thread SCHED_FIFO priority {prio}")
            except (AttributeError, OSError) as err:
                self._event("realtime-refused", f"SCHED_FIFO {prio} not granted ({err}); normal scheduling")
                log.warning("loop.realtime_priority %s not granted (%s)", prio, err)
        try:
            self._machine_class()(self).run()
        except BaseException as err:  # never leave silently
            self._last_error = f"{type(err).__name__}: {err}"
            self._errors += 1
            log.exception("control loop crashed")
            self._set_state(State.FAULT, "crash", self._last_error)
        finally:
            self._feed_stop = True      # release a feeder waiting for room
            self._deque.clear()         # nothing of this run is played by the next one
            if si is not None:
                sys.setswitchinterval(old_switch)

    def _machine_class(self) -> type:
        """The loop thread's machine for ``amplifier.output``: setpoints (one per tick) or
        stream (samples queued ahead into the device FIFO, :mod:`afmctl.control.stream`)."""
        if self.config.amplifier.output == "stream":
            from .stream import StreamMachine
            return StreamMachine
        if self.config.amplifier.output == "wave":
            from .wave_run import WaveMachine
            return WaveMachine
        return LoopMachine

    def _apply_drift_measurement(self, item: tuple) -> None:
        """Loop thread: fuse one validated measurement (see :meth:`submit_drift_measurement`);
        its age is the controller time since ``t_s`` (0 when not given or in the future)."""
        z, std, t = item
        age = 0.0 if t != t else max(0.0, (self._tick - 1) * self.dt_s - t)
        try:
            self.pipeline.update_drift(z, std, age)
        except Exception as err:  # noqa: BLE001 - a bad measurement must not stop the loop
            self._event("drift-measurement-error", error_line(err))

    def _reconnect_job(self) -> None:
        """One ``amplifier.reconnect()`` attempt (helper thread; may block for the driver's
        reconnect_timeout_s). The loop thread reads the outcome from ``_rc_error``."""
        try:
            self.amplifier.reconnect()
        except Exception as err:  # noqa: BLE001 - reported by the loop thread
            self._rc_error = err

    def _enter_fault(self, err: BaseException) -> None:
        self._errors += 1
        self._faults += 1
        self._last_error = error_line(err)
        log.warning("amplifier fault: %s", self._last_error)
        self._set_state(State.FAULT, "fault", self._last_error)

    # ------------------------------------------------------------------ dispatcher
    def _dispatch_main(self) -> None:
        self._helper_priority()
        r = 0
        next_status = time.monotonic()
        try:
            while True:
                alive = self._thread is not None and self._thread.is_alive()
                r = self._r_done = self._dispatch_records(r)
                self._check_runlog()
                self._dispatch_events()
                if time.monotonic() >= next_status:
                    next_status = time.monotonic() + self.status_interval_s
                    self._call_sinks("on_status", self._status("periodic"))
                if not alive:
                    r = self._dispatch_records(r)
                    self._dispatch_events()
                    self._call_sinks("on_status", self._status("final"))
                    break
                time.sleep(self.dispatch_interval_s)
                self._sleep_to_quiet_window()
        finally:
            if self.runlog is not None:
                self.runlog.write_event({"seq": self._seq, "t_s": self._tick * self.dt_s, "wall_time": time.time(),
                                         "state": self._state.value, "event": "stats",
                                         "detail": self.stats()})
                self.runlog.close()
            self._done.set()

    def _sleep_to_quiet_window(self) -> None:
        """Dispatcher: wait until just after one of the loop's ticks, so that its work (run log,
        sinks, zenoh frames) takes the interpreter lock while the loop thread sleeps, not while
        it waits for a deadline. See :func:`quiet_window_wait_s`."""
        wait = quiet_window_wait_s(time.perf_counter(), self._deadline_s, self.dt_s, self.config.loop.spin_s)
        if wait > 0.0:
            time.sleep(wait)

    def _check_runlog(self) -> None:
        """Dispatcher: a run log that cannot be written stops the run (ramp to the safe value
        at ``safety.ramp_V_per_s``, whatever ``on_finish`` says): no setpoint is sent that no
        record will show, beyond that ramp."""
        err = self.runlog.error if self.runlog is not None else None
        if err is None or self.runlog_error is not None:
            return
        self.runlog_error = str(err)
        self._errors += 1
        self._last_error = self.runlog_error
        self._event("runlog-error", self.runlog_error)
        if self._request != "estop":
            self._request = "runlog-error"
        self._feed_stop = True

    def _dispatch_records(self, r: int) -> int:
        w = self._w
        if w == r:
            return r
        if w - r > _RING:
            lost = w - r - _RING
            self._dropped += lost
            r = w - _RING
        idx = np.arange(r, w) & (_RING - 1)
        rows = self._ring[idx]
        if self._w - r > _RING:  # overwritten while copying
            keep = (self._w - _RING) - r
            rows = rows[keep:] if keep < len(rows) else rows[:0]
            self._dropped += keep
        sp = np.zeros(len(rows), SETPOINT_DTYPE)
        sp["seq"] = rows[:, C_SEQ].astype(np.uint64)
        sp["t_s"] = rows[:, C_TICK] * self.dt_s
        sp["target_nm"] = rows[:, C_TGT:C_TGT + 3]
        sp["corrected_nm"] = rows[:, C_COR:C_COR + 3]
        sp["u_V"] = rows[:, C_U:C_U + 3]
        dr = np.zeros(len(rows), DRIFT_DTYPE)
        dr["seq"] = sp["seq"]
        dr["t_s"] = sp["t_s"]
        dr["T_C"] = rows[:, C_T]
        dr["drift_nm"] = rows[:, C_D:C_D + 3]
        dr["std_nm"] = rows[:, C_S:C_S + 3]      # NaN when the Kalman filter is off
        if self.runlog is not None:
            self.runlog.write_setpoints(sp)
            self.runlog.write_drift(dr)
        if len(sp):
            self._call_sinks("on_setpoints", sp)
            last = dr[-1]
            std = rows[-1, C_S:C_S + 3]
            self._call_sinks("on_drift", {"seq": int(last["seq"]), "t_s": float(last["t_s"]),
                                          "T_C": float(last["T_C"]),
                                          "drift_nm": [float(v) for v in last["drift_nm"]],
                                          "std_nm": None if math.isnan(std[0]) else [float(v) for v in std]})
        return w

    def _dispatch_events(self) -> None:
        while self._events:
            ev = self._events.popleft()
            if self.runlog is not None:
                self.runlog.write_event(ev)
            st = self._status(ev["event"], ev.get("detail"))
            st["state"] = ev["state"]
            self._call_sinks("on_status", st)

    def _status(self, event: str, detail: Any = None) -> dict[str, Any]:
        return {"state": self._state.value, "event": event, "detail": detail, "seq": self._seq,
                "t_s": self._tick * self.dt_s, "stats": self.stats()}

    def _call_sinks(self, method: str, arg: Any) -> None:
        for sink in list(self._sinks):
            fn = getattr(sink, method, None)
            if fn is None:
                continue
            try:
                fn(arg)
            except Exception:  # a sink must not stop the controller
                log.exception("sink %r.%s failed", sink, method)
