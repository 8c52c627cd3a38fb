"""The tracking error of a device-timed run (``amplifier.output = "wave"``) measured by the
device's own data recorder, the way ``afmctl learn`` measures each play: the recorder is
armed once the table is on the device (:attr:`Controller.before_wave_start`), records the
measured position and the output of each driven axis whose target moves, one point per
table row (:attr:`Controller.wave_table`), and after a play to the table's end its points
are checked against the table (the output recorded must be the table's: no trigger offset)
and compared with the table's target (:func:`afmctl.data.axis_errors.axis_errors`).

On a simulated device this is the simulated scanner's own sensor during the play (its real
history: the approach ramp and the settle hold on the wall clock); on a real one, its
sensor. Units: nm, V, s.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ..data.axis_errors import MIN_SPAN_NM, ErrorReport

log = logging.getLogger(__name__)

#: recorded output voltages must equal the table within this [V] (the devices' resolution)
OUTPUT_TOL_V = 0.01


class RunRecorder:
    """Records a wave run's table on ``amplifier``'s data recorder (module docstring).
    ``hook`` goes to :attr:`Controller.before_wave_start`; :meth:`errors` reads the
    recording back after the run. ``why_not``: why nothing was measured (None when it was)."""

    def __init__(self, config: Any, amplifier: Any, ctl: Any) -> None:
        self.config, self.amp, self.ctl = config, amplifier, ctl
        self.axes: list[str] = []
        self.setup: Any = None
        self.why_not: str | None = None
        #: after :meth:`errors`: (the table's target (N, 3) [nm], the recorded position (N, 3)
        #: [nm] — the target's own column on an axis not recorded — and the recorded axes)
        self.recorded: tuple[np.ndarray, np.ndarray, str] | None = None

    @staticmethod
    def available(config: Any, amplifier: Any) -> bool:
        return config.amplifier.output == "wave" and bool(getattr(amplifier, "has_recorder", False))

    def hook(self) -> None:
        """Arm the recorder for the table's rows on the axes whose target moves (called by the
        wave player after the upload, before the approach); a recorder that cannot hold them
        leaves the run unmeasured."""
        from .learn_run import arm_recorder
        table = self.ctl.wave_table
        driven = [a for a in self.config.scanner.axes if a in getattr(self.amp, "axes", ())]
        self.axes = [a for a in driven if np.ptp(table.target_nm[:, "xyz".index(a)]) >= MIN_SPAN_NM]
        if not self.axes:
            self.why_not = "no recorded axis moves"
            return
        try:
            capacity = self.amp.recorder_capacity(self.axes)
            if len(table) > capacity:
                self.why_not = f"the table's {len(table)} rows do not fit the recorder's {capacity} points"
                return
            self.setup = arm_recorder(self.amp, self.config, len(table), self.axes)
        except Exception as err:  # noqa: BLE001 - the run plays on; the summary says why
            self.why_not = f"arming the recorder failed: {err}"

    def errors(self, timeout_s: float = 30.0) -> ErrorReport | None:
        """The per-axis errors of the recorded motion against the table's target, or None
        (``why_not``) when the table did not play to its end or the recording is unusable."""
        from afmctl.drivers.recording import align_to_table

        from .learn_run import judged_errors
        table = self.ctl.wave_table
        if self.setup is None:
            self.why_not = self.why_not or "the table did not start"
            return None
        played = int((self.ctl.stats().get("wave") or {}).get("played", 0))
        if played != len(table):
            self.why_not = f"{played} of the table's {len(table)} rows played"
            return None
        try:
            rec = self.amp.read_recording(timeout_s=timeout_s)
            rec = align_to_table(rec, {a: table.u_V[:, "xyz".index(a)] for a in self.axes}, tol_V=OUTPUT_TOL_V)
        except Exception as err:  # noqa: BLE001 - a mismatch, a timeout, a link fault: a summary, never a crash
            self.why_not = f"the recording was not usable: {str(err).removesuffix('; not learned from')}"
            return None
        measured = {a: np.asarray(rec.y_nm[a], dtype=float) for a in self.axes if a in rec.y_nm}
        pos = np.array(table.target_nm, dtype=float)
        for a, y in measured.items():
            pos[:, "xyz".index(a)] = y
        self.recorded = (table.target_nm, pos, "".join(measured))
        return judged_errors(table.target_nm, measured)
