"""How a planned table reaches the device's clock (``[amplifier] output = "wave"``).

Two players share one interface — :meth:`~WavePlayer.check` (before anything is sent),
:meth:`~WavePlayer.prepare` (what goes to the device before the approach ramp; False when a
request came first), :meth:`~WavePlayer.play` (blocks until the table has played, a request
stopped it, or an error), :meth:`~WavePlayer.abort` (stop the device now; best effort, for
errors):

* :class:`TablePlayer` — a wave generator (PI GCS ``WAV``/``WGO``, the NV200's waveform
  buffer): every driven column uploaded whole while the output still rests where it was
  (``prepare``: the scanner does not creep at the table's first row for the seconds an
  upload takes, so the play starts from the same state however long the link needed),
  then, right after the approach ramp, all started together, polled until it ends. Which rows have played is counted from the host clock conservatively (from just
  after the start was acknowledged to just before the stop was sent), so a row recorded
  has played; the last few rows before a stop may be missing from the run log.
* :class:`FifoPlayer` — the CAN amplifier's stream FIFO: rows queued ahead between
  ``amplifier.low_water_s`` and ``high_water_s``, recorded as the amplifier reports them
  played (``STREAM_STATUS``).

Errors: :class:`WaveRefused` when the table cannot be played (it does not fit the device,
a check or the driver refused it) — nothing of it was played; any other error once the
device plays ends the run in ``fault`` after :meth:`abort`.
"""
from __future__ import annotations

import math
import time
from typing import Any

from afmctl.drivers import codec_gcs_wave as wcodec
from afmctl.drivers.errors import LimitError

from ..errors import AfmctlError
from .stream import sleep_to_next_wake
from .transitions import Event
from .stream_producer import StreamProducer
from .wave_plan import WaveTable, driven_steps_ok, table_capacity


class WaveRefused(AfmctlError):
    """The trajectory cannot be played as a wave on this device; nothing of it was played."""


class WavePlayer:
    """What both players share (see the module docstring). ``machine``: the
    :class:`afmctl.control.wave_run.WaveMachine` whose rows are recorded."""

    what = "wave"
    max_step_V = math.inf

    def __init__(self, machine: Any) -> None:
        self.m = machine
        self.ctl = machine.ctl
        self.amp = machine.ctl.amplifier
        self.started = False

    def limits_V(self) -> dict[str, tuple[float, float]]:
        """``{axis: (lo, hi)}`` [V] of the driven axes (the safety layer's)."""
        s = self.m.safety
        return {a: (s.lo[i], s.hi[i]) for i, a in enumerate(s.axes)}

    def check(self, table: WaveTable) -> None:
        """Before the approach: every driven column finite, inside the limits and within
        ``max_step_V`` per row, and the table fits the device (:class:`WaveRefused`)."""
        if not driven_steps_ok(table.u_V, self.m.safety.axes, self.limits_V(), self.max_step_V,
                               table.u_V[0, list(self.m.safety.index)]):
            raise WaveRefused("amplifier.output = 'wave': the table breaks the limits or the slew limit "
                              "(nothing was sent)")
        self._check_device(table)

    def _check_device(self, table: WaveTable) -> None:
        """The device-specific part of :meth:`check`."""

    def max_rows(self) -> int | None:
        """The most rows one table may have on this device (None: no such bound)."""
        return None

    def prepare(self, table: WaveTable) -> bool:
        """What goes to the device before the approach ramp, then the controller's
        ``before_wave_start`` hook; False when a request came first (nothing is started)."""
        self._before_start()
        return True

    def arm(self, table: WaveTable) -> None:
        """At the start of the settle hold, the device holding the table's first row: get
        the table's start ready so that :meth:`play` starts it at once when the hold ends."""

    def play(self, table: WaveTable) -> None:
        raise NotImplementedError

    def abort(self) -> None:
        """Stop the device's playback now (an error ends the run); best effort: the device
        may be gone."""
        if self.started:
            try:
                self._stop_device()
            except Exception:  # noqa: BLE001 - best effort
                pass

    def _stop_device(self) -> None:
        """The device-specific part of :meth:`abort`."""

    def _before_start(self) -> None:
        """Call the controller's ``before_wave_start`` hook (e.g. arm the device's data
        recorder, which starts with the wave generator: :mod:`afmctl.control.learn_run`):
        after the upload, before the approach ramp — the time the hook takes is not spent at
        the table's first row; for the CAN stream once the stream has started (its
        recorder counts the stream's ticks)."""
        hook = getattr(self.ctl, "before_wave_start", None)
        if hook is not None:
            hook()

    def _started(self) -> None:
        """Note the host clock just before the device is told to start (``wave_times``)."""
        self.ctl.wave_times["start"] = time.monotonic()


class TablePlayer(WavePlayer):
    """A wave generator: GCS wave tables or the NV200's waveform buffer."""

    #: how often the host asks whether the generator still runs [s]
    poll_s = 0.02

    def __init__(self, machine: Any) -> None:
        super().__init__(machine)
        self.what = f"wave table ({self.ctl.config.amplifier.driver} wave generator)"
        self.max_step_V = machine.safety.max_step_V
        self.t0 = 0.0

    def max_rows(self) -> int | None:
        """The smallest wave table of the driven axes."""
        return table_capacity(self.amp, self.m.safety.axes)

    def _check_device(self, table: WaveTable) -> None:
        cfg = self.ctl.config
        for a in self.m.safety.axes:
            capacity = self.amp.wave_capacity(a)
            if len(table) > capacity:
                raise WaveRefused(f"amplifier.output = 'wave': the trajectory makes {len(table)} samples at "
                                  f"{cfg.loop.rate_Hz:g} Hz, the {cfg.amplifier.driver} wave table of axis {a} "
                                  f"holds {capacity} (shorten the trajectory or lower loop.rate_Hz)")

    def prepare(self, table: WaveTable) -> bool:
        """Upload every driven column (the output rests where it is meanwhile), then the
        ``before_wave_start`` hook."""
        if not self._upload(table):
            return False
        self._before_start()
        return True

    def play(self, table: WaveTable) -> None:
        """Start every driven axis together (uploaded by :meth:`prepare`), record the rows
        as they play."""
        self._started()
        st = self.amp.start_wave(divider=wcodec.divider_for(self.ctl.config.loop.rate_Hz, self.amp.servo_cycle_s()),
                                 cycles=1, axes=list(self.m.safety.axes))
        self.started = True
        self.m.fsm.fire(Event.DONE)        # uploaded and started: UPLOAD -> PLAY
        self.t0 = time.perf_counter()      # after the start was acknowledged: never ahead of the device
        self.m.tick0 = self.ctl._tick + 1
        rate, n = st.rate_Hz, len(table)
        while any(st.running.values()):
            if self.ctl._request is not None:
                t_stop = time.perf_counter()
                self.amp.stop_wave()
                self.m.played_to(self._played_by(t_stop, rate, n), f"{self.ctl._request} during the wave")
                return
            self.m.record_played(self._played_by(time.perf_counter(), rate, n - 1))
            if time.perf_counter() - self.t0 > n / rate + 5.0:
                raise AfmctlError(f"the wave generator still runs {n / rate + 5.0:.1f} s after its start")
            time.sleep(self.poll_s)
            st = self.amp.wave_status()
        self.ctl.wave_times["end"] = time.monotonic()
        self.m.played_to(n, "end")

    def _played_by(self, t: float, rate: float, most: int) -> int:
        """Rows surely played by host time ``t`` (at most ``most``)."""
        return max(0, min(most, int((t - self.t0) * rate)))

    def _upload(self, table: WaveTable) -> bool:
        """Every driven column as its axis's table; False when a request came first (then
        nothing is started)."""
        for a in self.m.safety.axes:
            if self.ctl._request is not None:
                break
            try:
                self.amp.upload_wave(a, table.u_V[:, "xyz".index(a)])
            except LimitError as err:       # refused before sending: nothing was started
                raise WaveRefused(f"amplifier.output = 'wave': {err}") from None
        if self.ctl._request is not None:
            self.ctl._event("wave-stopped", f"{self.ctl._request} while the table was uploaded: not started")
            return False
        return True

    def _stop_device(self) -> None:
        self.amp.stop_wave()


class FifoPlayer(WavePlayer):
    """The CAN amplifier's stream FIFO, played on its clock (module docstring)."""

    def __init__(self, machine: Any) -> None:
        super().__init__(machine)
        cfg = self.ctl.config
        self.what = "stream FIFO (CAN amplifier clock)"
        self.prod = StreamProducer(self.amp, machine.safety, cfg.loop.rate_Hz,
                                   cfg.amplifier.low_water_s, cfg.amplifier.high_water_s)
        self.max_step_V = self.prod.max_step_V
        self.poll_s = max(min(self.prod.high - self.prod.low, self.prod.low) / cfg.loop.rate_Hz / 4, 0.0005)
        self.stall = getattr(self.ctl, "stream_stall_hook", None)
        #: the rows and how many are queued once :meth:`arm` has primed the stream
        self._armed: tuple[Any, int] | None = None

    def prepare(self, table: WaveTable) -> bool:
        """Nothing goes ahead of the stream (its hook runs once the stream has started)."""
        return True

    def arm(self, table: WaveTable) -> None:
        """Start the stream armed and queue all but the last of its prefill rows: the FIFO
        holds them and nothing plays (the output holds the first row) until :meth:`play`
        queues the last one. Sending the prefill took 0.1–0.2 s on the simulated amplifier
        (1,747 rows), a time the scanner spent creeping at the first row before the clock
        started: the table then began 10 nm/s × that much off, different from play to play
        (docs/BENCHMARKS.md, *learning on the simulated devices*). Armed during the settle
        hold, the clock starts when the hold ends."""
        amp, prod = self.amp, self.prod
        rows = self._rows(table)
        prefill = int(min(prod.high, len(rows)))
        amp.start_stream(prod.rate_Hz, prefill=prefill)
        self.started = True
        self._before_start()             # a recorder counts the stream's ticks: armed once it runs
        if prefill > 1:
            amp.queue(rows[:prefill - 1].tolist())
        self._armed = (rows, prefill - 1)

    def _check_device(self, table: WaveTable) -> None:
        capacity = self.amp.buffer_status().capacity
        if self.prod.high > capacity:
            raise WaveRefused(f"amplifier.high_water_s: {self.prod.high} samples do not fit the amplifier's FIFO "
                              f"of {capacity} samples at {self.prod.rate_Hz:g} Hz")

    def play(self, table: WaveTable) -> None:
        """Queue the last prefill row (armed by :meth:`arm`: the clock starts), then the
        rows between the water marks, record them as they play, drain."""
        amp, prod, ctl = self.amp, self.prod, self.ctl
        assert self._armed is not None, "FifoPlayer.play before arm"
        rows, queued = self._armed
        self._armed = None
        n = len(rows)
        self._started()
        amp.queue(rows[queued:queued + 1].tolist())
        self.m.fsm.fire(Event.DONE)        # the FIFO plays: UPLOAD -> PLAY
        prod._queued = queued + 1
        self.m.tick0 = ctl._tick + 1
        next_wake = time.perf_counter()
        while prod._queued < n:
            if ctl._request is not None:
                return self._flush(f"{ctl._request} during the wave")
            level = prod._queued - prod._played()
            if level < prod.low or prod._queued == 0:
                k = min(prod.high - level, n - prod._queued)
                amp.queue(rows[prod._queued:prod._queued + k].tolist())
                prod._queued += k
            self.m.record_played(prod._played())
            if self.stall is not None:
                self.stall()
            next_wake = sleep_to_next_wake(ctl, next_wake, self.poll_s)
            self._stats()
        self._drain(n)

    def _rows(self, table: WaveTable) -> Any:
        """The table's rows x, y, z [V]; an axis the scanner does not drive keeps the
        amplifier's present output."""
        rows = table.u_V.copy()
        held = getattr(self.amp, "last_output", {}) or {}
        for k, a in enumerate("xyz"):
            if a not in self.m.safety.axes and a in held:
                rows[:, k] = held[a]
        return rows

    def _drain(self, n: int) -> None:
        """Everything is queued: let the amplifier play it out, recording as it goes."""
        amp, ctl = self.amp, self.ctl
        amp.drain_stream()
        while (bs := amp.buffer_status()).state not in ("idle", "fault"):
            if ctl._request is not None:
                return self._flush(f"{ctl._request} while the FIFO played out")
            self.m.record_played(self.prod._played())
            time.sleep(0.005)
        self._stats()
        if bs.state == "fault":
            raise AfmctlError("the amplifier stopped the stream (fault)")
        self.ctl.wave_times["end"] = time.monotonic()
        self.m.played_to(n, "end")

    def _flush(self, why: str) -> None:
        """Empty the FIFO at once (the output holds where playing stopped); the rows the
        amplifier reported played go into the run log, the others never do."""
        self.amp.flush_stream()
        played = max(self.prod._played(), self.m.recorded)
        self._stats()
        self.ctl._event("estop-flush" if self.ctl._request == "estop" else "stop-flush",
                        f"FIFO flushed: table rows from about {played} on were not played")
        self.m.played_to(played, why)

    def _stop_device(self) -> None:
        self.amp.flush_stream()

    def _stats(self) -> None:
        self.ctl._stream_stats = self.prod.status()
