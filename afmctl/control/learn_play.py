"""Playing a table on a device and reading back what its recorder measured — the ``play``,
``arm`` and ``read`` steps of ``afmctl learn --config`` (:mod:`afmctl.control.learn_run`).

:class:`TablePlayer` plays one table exactly as ``afmctl run`` plays a learned table (a
:class:`~afmctl.control.controller.Controller` with ``output = "wave"``: upload, approach
ramp and settle hold, the table on the amplifier's clock, the finish ramp, every safety
check of a run), arms the device's recorder once the table is on the device and before
the approach (:func:`arm_recorder`), and reads the recording back, refusing one that does
not match the table (:func:`read_aligned`). A stop or an estop during the play stops the
device and ramps within the slew limit. Units: nm, V, s.
"""
from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import AfmctlError
from .controller import Controller, State
from .learned_after import AS_RECORDED_REST_S, AsRecorded, rest_left_s
from .learned_table import LearnedSource, make_learned
from .wave_plan import WaveTable

log = logging.getLogger(__name__)

#: recorded output voltages must equal the table within this [V] (the devices' resolution)
OUTPUT_TOL_V = 0.01


class Step(enum.Enum):
    """Where an iteration is (:mod:`afmctl.control.learn_run`)."""
    CHECK = "check"
    ARM = "arm"
    PLAY = "play"
    READ = "read"
    LEARN = "learn"
    CALIBRATE = "calibrate"
    REPLAY = "replay"


class RecordingRefused(AfmctlError):
    """A recording that does not match the table it was taken with (length, trigger)."""


def arm_recorder(amp: Any, config: Any, points: int, axes: list[str]) -> Any:
    """Arm ``amp``'s data recorder for ``points`` points of the measured position and the
    output of ``axes``, one per table row (the recorder's divider = the loop period)."""
    clock = amp.recorder_clock_s()
    divider = max(1, round(config.dt_s / clock))
    if abs(divider * clock - config.dt_s) > 1e-9 * config.dt_s + 1e-12:
        raise AfmctlError(f"loop.rate_Hz: {config.loop.rate_Hz:g} Hz is not a whole number of the "
                          f"recorder's {clock:g} s ticks")
    return amp.configure_recorder(axes, points=points, divider=divider, signals=("y_nm", "u_V"))


def read_at_sample_start(model: Any) -> Any:
    """``model`` as a device's data recorder sees the scanner: it reads each position as the
    next sample starts (the response to the samples before it; PI's and the NV200's
    recorders, the simulated devices'), where a model identified on positions read at the
    end of each hold (``afmctl sim`` records, the simulated scanner's) leads by up to a
    sample (its dynamics' ``lead_samples``), which the learning filter must not assume."""
    dyn = getattr(model, "dynamics", None)
    if dyn is None or not dyn.lead_samples:
        return model
    return model.model_copy(update={"dynamics": dyn.model_copy(update={"lead_samples": 0.0})})


def read_aligned(amp: Any, table: WaveTable, setup: Any, timeout_s: float) -> dict[str, np.ndarray]:
    """The measured position [nm] per recorded axis, one point per table row; a recording
    whose length or recorded output voltages do not match the table (a trigger offset) is
    refused (:func:`afmctl.drivers.recording.align_to_table`)."""
    from afmctl.drivers.recording import RecordingMismatch, align_to_table
    rec = amp.read_recording(timeout_s=timeout_s)
    tables: dict[str, Any] = {a: table.u_V[:, "xyz".index(a)] for a in setup.axes}
    try:
        rec = align_to_table(rec, tables, tol_V=OUTPUT_TOL_V)
    except RecordingMismatch as err:
        raise RecordingRefused(f"learn: {err}") from None
    missing = [a for a in setup.axes if a not in rec.y_nm]
    if missing:
        raise RecordingRefused(f"learn: the recording has no measured position of axis {missing[0]}; "
                               "not learned from")
    return {a: np.asarray(rec.y_nm[a], dtype=float) for a in setup.axes}


def play_recorded(config: Any, amp: Any, source: LearnedSource, axes: list[str],
                  timeout_s: float = 30.0) -> dict[str, np.ndarray]:
    """Play a learned table as ``afmctl run`` does (``config``: a run configuration with
    ``output = "wave"``) and record it with the device's recorder: the measured position
    [nm] per axis of ``axes``, one point per table row — how a learned table is checked
    after learning (the same sensor, the same protocol)."""
    table = source.learned.table
    armed: list[Any] = []
    ctl = Controller(config, amp)
    ctl.before_wave_start = lambda: armed.append(arm_recorder(amp, config, len(table), axes))
    try:
        ctl.start(source)
        while not ctl.wait(0.05):
            pass
    finally:
        ctl.close()
    if ctl.state is not State.STOPPED or not armed:
        raise AfmctlError(f"the learned table did not play to the end ({ctl.state.value}: "
                          f"{ctl.trajectory_error or ctl.stats().get('last_error')})")
    return read_aligned(amp, table, armed[0], timeout_s)




class TablePlayer:
    """Plays tables on the open ``amp`` with ``config`` (``output = "wave"``) and reads back
    the measured motion (module docstring). ``spec``: the trajectory's specification (the
    learned-table fingerprint); ``on_played(table, rows, wave_times)``: called after each
    play (the learn run's voltage history); ``timeout_s``: longest wait for a recording;
    ``rest``: called before each play (an in-process simulator brought to rest:
    :class:`afmctl.control.learn_run.LearnOptions`)."""

    def __init__(self, config: Any, amp: Any, spec: dict, on_played: Callable[[WaveTable, int, dict], None],
                 timeout_s: float = 30.0, rest: Callable[[], None] | None = None) -> None:
        self.config, self.amp, self.spec = config, amp, spec
        self.on_played = on_played
        self.timeout_s = timeout_s
        self.rest = rest
        self.step = Step.CHECK
        self._ctl: Controller | None = None
        self._stop = threading.Event()
        #: when the last play (its finish ramp) ended, wall clock [s since the epoch]; None before
        self.ended_unix_s: float | None = None
        #: the axes learned as recorded on a device (:class:`AsRecorded`): each play then
        #: starts :data:`AS_RECORDED_REST_S` after the one before ended, as ``afmctl run`` does
        self.spaced_axes: tuple[str, ...] = ()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def play_and_read(self, table: WaveTable, axes: list[str]) -> dict[str, np.ndarray] | tuple[str, str]:
        """The measured motion per axis, or ``(state, why)`` when the play or the read-back
        did not complete."""
        from afmctl.drivers.errors import AmplifierConnectionError, AmplifierTimeout
        self.step = Step.PLAY
        if self.rest is not None:
            self.rest()
        armed: list[Any] = []
        ended = self._play(table, lambda: armed.append(arm_recorder(self.amp, self.config, len(table), axes)))
        if ended is not None:
            return ended
        if not armed:
            raise AfmctlError("learn: the play ended without arming the recorder")
        self.step = Step.READ
        try:
            return read_aligned(self.amp, table, armed[0], self.timeout_s)
        except (AmplifierTimeout, AmplifierConnectionError) as err:
            return "fault", f"reading the recording failed: {err}"
        except RecordingRefused as err:       # not learned from: the table plays again
            return "fault", str(err)

    def _play(self, table: WaveTable, arm: Callable[[], None]) -> tuple[str, str] | None:
        """Play ``table`` as a run plays a learned table, ``arm`` called once it is on the
        device, before the approach (step ``arm``); None when it played to the end, else ``(state, why)``."""
        if self._stop.is_set():
            return "stopped", "stopped before the play"
        from afmctl.drivers.errors import AmplifierConnectionError, AmplifierTimeout
        source = LearnedSource(make_learned(self.config, table, self.spec, as_recorded=self._spacing()),
                               "the table being learned")
        ctl = Controller(self.config, self.amp)
        ctl.before_wave_start = lambda: self._set_step(Step.ARM, arm)
        self._ctl = ctl
        try:
            try:
                ctl.start(source)
            except (AmplifierTimeout, AmplifierConnectionError) as err:     # a link still down: reconnect, play again
                return "fault", f"the play did not start: {err}"
            if self._stop.is_set():
                ctl.stop()
            while not ctl.wait(0.05):
                pass
            self.ended_unix_s = time.time()
            stats = ctl.stats()
        finally:
            ctl.close()
            self._ctl = None
        wave = stats.get("wave") or {}
        self.on_played(table, int(wave.get("played", 0)), dict(ctl.wave_times))
        if ctl.trajectory_error is not None:
            raise AfmctlError(f"learn: the table cannot be played: {ctl.trajectory_error}")
        if ctl.state is not State.STOPPED:
            return "fault", f"the play ended in {ctl.state.value}: {stats.get('last_error') or 'see the log'}"
        if wave.get("played") != len(table):
            return "stopped", f"stopped during the play ({wave.get('played', 0)} of {len(table)} samples)"
        return None

    def rest_after_last_play(self, rest_s: float) -> None:
        """Hold (the device keeps its output) until ``rest_s`` [s] after the last play
        ended; a stop ends the wait at once (the next play then does not start)."""
        if self.ended_unix_s is not None:
            self._stop.wait(rest_left_s(self.ended_unix_s, rest_s))

    def _spacing(self) -> AsRecorded | None:
        """The rest the next play keeps after the last (the run's approach holds the present
        output until then: :meth:`AsRecorded.wait_s`); None without as-recorded axes, before
        the first play, or once the rest has passed."""
        if not self.spaced_axes or self.ended_unix_s is None:
            return None
        spacing = AsRecorded(self.spaced_axes, self.ended_unix_s, AS_RECORDED_REST_S)
        return spacing if spacing.wait_s() > 0.0 else None

    def _set_step(self, step: Step, then: Callable[[], None]) -> None:
        self.step = step
        then()
        self.step = Step.PLAY

    def reconnect(self) -> None:
        """After a link fault: reconnect (the driver reads the output back; the next play's
        approach ramps from there)."""
        try:
            self.amp.reconnect()
        except Exception as err:  # noqa: BLE001 - the next play reports the link's state
            log.warning("learn: reconnect failed: %s", err)

    def stop(self) -> None:
        """The table playing (if any) stops as a run stops; no further play starts."""
        self._stop.set()
        ctl = self._ctl
        if ctl is not None:
            ctl.stop()

    def estop(self) -> None:
        """Emergency stop: the device stops at once and the output ramps to the safe value
        at the slew limit; no further play starts."""
        self._stop.set()
        ctl = self._ctl
        if ctl is not None:
            ctl.estop()
