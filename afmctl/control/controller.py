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
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from afmctl.compensators.temperature import T_MAX_C, T_MIN_C

from . import stats as loop_stats
from ..errors import AfmctlError, error_line
from . import cpu_pinning
from .machine import (CLOCK_BASES_MAX, END_OF_TRAJECTORY, N_COLS, RING_ROWS, LoopMachine, Mode,  # noqa: F401
                      State)
from .dispatcher import Dispatcher, quiet_window_wait_s  # noqa: F401 - re-exported (older import path)
from .path_delay import path_delay
from .learned_table import LearnedSource
from .reconnect import enter_fault
from .run_inputs import (MAX_SEGMENT_SAMPLES, as_block as _as_block, check_drift_measurement,  # noqa: F401
                         check_segment_dt, feed_blocks, flat as _flat, segment_rows, source_blocks)
from .runlog import RunLogWriter
from .safety import SafetyLayer

log = logging.getLogger(__name__)

_RING = RING_ROWS
XYZ_AXES = ("x", "y", "z")
#: drift measurements waiting for the loop thread (more are refused)
MAX_PENDING_DRIFT_MEASUREMENTS = 64
_END = END_OF_TRAJECTORY
# histogram helpers under their former names (see afmctl.control.stats)
_HBINS = loop_stats.N_BINS
_bin = loop_stats.bin_of
_percentiles = loop_stats.percentiles


#: every controller started in this process (weakly held): :func:`started_controllers`
_STARTED: "weakref.WeakSet[Controller]" = weakref.WeakSet()


def started_controllers() -> list["Controller"]:
    """The controllers of this process that were started and are not yet garbage (test
    harnesses close those still running after a test: :func:`afmctl.testing.stop_leaked_threads`)."""
    return list(_STARTED)


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


class Controller:
    """Fixed-rate feedforward controller; see the module docstring.

    Its jobs live in their own pieces: the loop thread's phases and their transitions
    (:mod:`afmctl.control.machine`, :mod:`afmctl.control.transitions`), the fault/reconnect
    policy (:mod:`afmctl.control.reconnect`), the dispatcher — run log, sinks, status
    (:mod:`afmctl.control.dispatcher`) — and the run's inputs (:mod:`afmctl.control.run_inputs`).
    What stays here, and why it is one class of about 400 lines: the public API (start, stop,
    estop, wait, close, stats, submit_*, sinks), the ownership of the run's threads, and the
    run's shared record — the counters, the ring buffer and the event deque that the loop
    thread writes on every tick as plain attributes of this one object (no extra hop on the
    hot path) and the dispatcher reads.

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

    #: ``amplifier.output = "wave"``: called once by the player after the table is uploaded
    #: (or the stream started) and before its first point plays (arming a data recorder)
    before_wave_start: Callable[[], None] | None = None

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
        #: the running machine's phase machine (afmctl.control.transitions), None before a run
        self._fsm: Any = None
        #: the dispatcher (run log, sinks, status; afmctl.control.dispatcher)
        self.dispatcher = Dispatcher(self)
        self._sinks = self.dispatcher.sinks
        self._deque: collections.deque = collections.deque()
        self._queue_mode = False
        self._learned_source: LearnedSource | None = None
        self._queue_end_when_idle = False
        self._thread: threading.Thread | None = None
        self._feeder: threading.Thread | None = None
        self._rc_thread: threading.Thread | None = None
        self._dispatcher: threading.Thread | None = None
        self._feed_stop = False
        self._feed_error: str | None = None
        self._events: collections.deque = collections.deque()
        #: output = "wave": host clock (time.monotonic) of the last play at the approach's
        #: start ("approach"), its end ("settle": the settle hold begins), just before the
        #: device was told to start ("start"), when the host saw the table end ("end") and
        #: when the finish ended ("finished")
        self.wave_times: dict[str, float] = {}
        #: output = "wave": the table planned for the present run (set before the upload)
        self.wave_table: Any = None
        self._drift_meas: collections.deque = collections.deque()
        self._ring = np.zeros((_RING, N_COLS))
        self._hist = loop_stats.new_histogram()
        self._whist = loop_stats.new_histogram()
        self._missed_log: collections.deque = collections.deque(maxlen=32)
        #: run time [s] (ticks × period) of the watchdog's latest trips (:meth:`watchdog_report`)
        self._watchdog_log: collections.deque = collections.deque(maxlen=4)
        self._reset_stats()
        self._T_C = float(config.compensation.temperature.T_C)
        self._T_file: tuple[np.ndarray, np.ndarray] | None = None
        self.runlog: RunLogWriter | None = None
        self.runlog_path: Path | None = None
        #: why the run log failed (the run was stopped), or None
        self.runlog_error: str | None = None
        self._done = threading.Event()
        #: the delay the output path adds, known in advance, and the ticks the loop advances
        #: the setpoints by to take it out (afmctl.control.path_delay)
        self.path_delay = path_delay(config, amplifier)
        #: the loop's clock: (tick, perf_counter time [s] of its deadline) at the start and at
        #: every re-base (an overrun, a resume); later ticks follow one period apart
        self.clock_bases: list[tuple[int, float]] = []
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

    def tick_deadlines_s(self, ticks: np.ndarray) -> np.ndarray | None:
        """The perf_counter time [s] of each tick's deadline (``clock_bases``), None before
        the loop ticked or once it re-based more than CLOCK_BASES_MAX times."""
        if not self.clock_bases or len(self.clock_bases) >= CLOCK_BASES_MAX:
            return None
        base_tick = np.array([b[0] for b in self.clock_bases], dtype=float)
        base_t = np.array([b[1] for b in self.clock_bases], dtype=float)
        ticks = np.asarray(ticks, dtype=float)
        i = np.clip(np.searchsorted(base_tick, ticks, side="right") - 1, 0, len(base_t) - 1)
        return base_t[i] + (ticks - base_tick[i]) * self.dt_s

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

    @property
    def queue_running(self) -> bool:
        """True while a queue-mode run (run-time segments: ``start(None)`` or
        ``trajectory.kind = "queue"``) runs and has not been asked to stop: segments are
        played as they arrive, and another start has nothing to do."""
        return self.running and self._queue_mode and self._request is None

    def watchdog_report(self) -> str | None:
        """Why the watchdog tripped during the last run, one line for a summary (when, what
        it saw, what it did); None when it did not trip."""
        n = self._watchdog_trips
        if not n:
            return None
        sa = self.config.safety
        times = ", ".join(f"{t:.3f}" for t in self._watchdog_log)
        when = f"at {times} s" if n <= len(self._watchdog_log) else f"the last at {times} s"
        why = ("the queue ran empty (queue mode plays each segment as it arrives and waits for the next)"
               if self._queue_mode else "the trajectory source fell behind the loop")
        action = "held the output" if sa.on_stall == "hold" else "ramped the output to the safe value"
        return (f"{n} trip{'' if n == 1 else 's'} ({when}): no trajectory sample for safety.watchdog_s = "
                f"{sa.watchdog_s:g} s, {why}; the loop {action} (safety.on_stall) until the next sample")

    def add_sink(self, sink: Any) -> None:
        """Register an object with ``on_setpoints``/``on_drift``/``on_status`` (any subset)."""
        self.dispatcher.add_sink(sink)

    def remove_sink(self, sink: Any) -> None:
        self.dispatcher.remove_sink(sink)

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
        z, std, t = check_drift_measurement(self.pipeline, measured_drift_nm, std_nm, t_s)
        if not self.running or self._state is State.STOPPED:
            raise AfmctlError(f"drift-measurement: controller is {self._state.value}; "
                              "measurements are accepted while it runs")
        if len(self._drift_meas) >= MAX_PENDING_DRIFT_MEASUREMENTS:
            raise AfmctlError(f"drift-measurement: {MAX_PENDING_DRIFT_MEASUREMENTS} measurements already "
                              "pending; the loop is not consuming them")
        self._drift_meas.append((z, std, t))

    def submit_segment(self, positions_nm: np.ndarray, dt_s: float) -> int:
        """Append a segment (N, 3) [nm] sampled every ``dt_s`` [s] (resampled to the loop
        period) to the run-time queue; returns the number of loop samples queued.

        Accepted when idle or when running in queue mode (``start(None)`` or
        ``trajectory.kind = "queue"``).
        """
        dt = check_segment_dt(dt_s)
        if self.running and not self._queue_mode:
            raise AfmctlError("segment: the controller is running a finite trajectory; segments are "
                              "accepted in queue mode (trajectory.kind = 'queue')")
        rows = segment_rows(positions_nm, dt, self.dt_s)
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
        source = self._learned_or(source)
        self._queue_mode, self._queue_end_when_idle, it = source_blocks(source, self.dt_s,
                                                                        self.config.loop.block_samples)
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
        _STARTED.add(self)
        if it is not None:
            self._feeder = threading.Thread(target=self._feed, args=(it,), name="afmctl-feeder", daemon=True)
            self._feeder.start()
        self._thread = threading.Thread(target=self._loop_main, name="afmctl-loop", daemon=True)
        self._thread.start()
        self._dispatcher = self.dispatcher.start()

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
                "path_delay": self.path_delay.as_dict(), "config": self.config.model_dump(mode="json")}
        prio = self.config.loop.realtime_priority
        self.runlog = RunLogWriter(runlog_path, meta, flush_interval_s=self.config.runlog.flush_interval_s,
                                   fsync=self.config.runlog.fsync,
                                   realtime_priority=max(1, prio - 1) if prio else None)
        self.runlog_path = Path(runlog_path)

    def _warm_up(self) -> None:
        """Run the chain once off the loop thread (compiles/loads numba kernels), then reset;
        at the middle of each axis's voltage range by the linear calibration (a target the
        models reach: at 0 nm a Preisach model whose 0 V gives 85 nm warned of a clamp for a
        sample that is never sent)."""
        mid = [0.0, 0.0, 0.0]
        for i, k in enumerate(self.safety.index):
            cal = self.config.scanner.axis_spec(XYZ_AXES[k])
            mid[k] = cal.nm_per_V * (0.5 * (self.safety.lo[i] + self.safety.hi[i]) - cal.offset_V)
        try:
            self.pipeline.step(mid[0], mid[1], mid[2], self._T_C, (0.0, 0.0, 0.0))
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

    def close(self, timeout: float = 10.0) -> list[str]:
        """End the run from whatever state it is in and join every thread of this controller
        (the amplifier stays open). Stops (ramp to the safe value or hold, as a stop does);
        when the loop has not ended after half of ``timeout`` [s] (a slow finish ramp), an
        estop (ramp at the slew limit). Each thread is joined until ``timeout`` after the
        call; returns the names of those still alive then (a driver call blocked beyond its
        own timeout; also logged as an error) — an empty list when everything ended."""
        deadline = time.monotonic() + timeout
        loop = self._thread
        if loop is not None and loop.is_alive():
            self.stop()
            loop.join(0.5 * timeout)
            if loop.is_alive():
                self.estop()
        self._feed_stop = True
        for t in (loop, self._dispatcher, self._feeder, self._rc_thread):
            if t is not None:       # _rc_thread: a reconnect attempt still in the driver
                t.join(max(deadline - time.monotonic(), 0.0))
        if self.runlog is not None:
            self.runlog.close()
        left = [t.name for t in (loop, self._dispatcher, self._feeder, self._rc_thread)
                if t is not None and t.is_alive()]
        if left:
            log.error("close: threads still running %.1f s after close(): %s (state %s)",
                      timeout, ", ".join(left), self._state.value)
        return left

    def __enter__(self) -> "Controller":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def lateness_histogram(self) -> np.ndarray:
        """A copy of the run's lateness histogram (counts per bin of
        :mod:`afmctl.control.stats`: 0.5 µs bins below 2 ms, 100 µs above), for pooling
        several runs before reading a quantile (benchmarks/lab_router.py)."""
        return self._hist.copy()

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
            "path_delay": self.path_delay.as_dict(),
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
        self._watchdog_log.clear()
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
        """Feeder thread: the trajectory's blocks into the sample deque (:func:`feed_blocks`)."""
        self._helper_priority()
        feed_blocks(self, it)

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

    def _enter_fault(self, err: BaseException) -> None:
        """Count a link error and publish ``fault`` (:func:`afmctl.control.reconnect.enter_fault`)."""
        enter_fault(self, err)

    # ------------------------------------------------------------------ status
    def _status(self, event: str, detail: Any = None) -> dict[str, Any]:
        return {"state": self._state.value, "event": event, "detail": detail, "seq": self._seq,
                "t_s": self._tick * self.dt_s, "stats": self.stats()}
