"""The tracking error of a device-timed run (``amplifier.output = "wave"``) measured by the
device's own data recorder, the way ``afmctl learn`` measures each play: the recorder is
armed once the table is on the device (:attr:`Controller.before_wave_start`), records the
measured position and the output of each driven axis, one point per table row, and after
the run its points are checked against the table's rows in the run log (the output
recorded must be the table: no trigger offset) and compared with the table's target
(:func:`afmctl.data.axis_errors.axis_errors`).

On a simulated device this is the simulated scanner's own sensor during the play (its real
history: the approach ramp and the settle hold on the wall clock); on a real one, its
sensor. Units: nm, V, s.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np

from ..data.axis_errors import ErrorReport, axis_errors

log = logging.getLogger(__name__)

#: recorded output voltages must equal the table within this [V] (the devices' resolution)
OUTPUT_TOL_V = 0.01


class RunRecorder:
    """Records a wave run's table on ``amplifier``'s data recorder (module docstring).
    ``hook`` goes to :attr:`Controller.before_wave_start`; :meth:`errors` reads the
    recording back after the run. ``why_not``: why nothing was measured (None when it was)."""

    def __init__(self, config: Any, amplifier: Any, ctl: Any) -> None:
        self.config, self.amp, self.ctl = config, amplifier, ctl
        self.axes = [a for a in config.scanner.axes if a in getattr(amplifier, "axes", ())]
        self.setup: Any = None
        self.why_not: str | None = None

    @staticmethod
    def available(config: Any, amplifier: Any) -> bool:
        return config.amplifier.output == "wave" and bool(getattr(amplifier, "has_recorder", False))

    def hook(self) -> None:
        """Arm the recorder for the table's rows (called by the wave player after the upload,
        before the approach); a recorder that cannot hold them leaves the run unmeasured."""
        from .learn_run import arm_recorder
        points = int((self.ctl.stats().get("wave") or {}).get("samples", 0))
        try:
            capacity = self.amp.recorder_capacity(self.axes)
            if not 0 < points <= capacity:
                self.why_not = f"the table's {points} rows do not fit the recorder's {capacity} points"
                return
            self.setup = arm_recorder(self.amp, self.config, points, self.axes)
        except Exception as err:  # noqa: BLE001 - the run plays on; the summary says why
            self.why_not = f"arming the recorder failed: {err}"

    def errors(self, setpoints: np.ndarray, table_rows: np.ndarray, timeout_s: float = 30.0) -> ErrorReport | None:
        """The per-axis errors of the recorded motion against the target of ``table_rows``
        (a mask of ``setpoints``, the run log's rows of the table), or None (``why_not``)."""
        from afmctl.drivers.recording import align_to_table
        if self.setup is None:
            self.why_not = self.why_not or "the table did not start"
            return None
        rows = setpoints[table_rows]
        if len(rows) != self.setup.points:
            self.why_not = f"{len(rows)} of the table's {self.setup.points} rows played"
            return None
        try:
            rec = self.amp.read_recording(timeout_s=timeout_s)
            tables = {a: rows["u_V"][:, "xyz".index(a)] for a in self.axes}
            rec = align_to_table(rec, tables, tol_V=OUTPUT_TOL_V)
        except Exception as err:  # noqa: BLE001 - a mismatch, a timeout, a link fault: a summary, never a crash
            self.why_not = f"the recording was not usable: {str(err).removesuffix('; not learned from')}"
            return None
        target = np.asarray(rows["target_nm"], dtype=float)
        pos = target.copy()
        axes = [a for a in self.axes if a in rec.y_nm]
        for a in axes:
            pos[:, "xyz".index(a)] = np.asarray(rec.y_nm[a], dtype=float)
        return axis_errors(target, pos, "".join(a for a in "xyz" if a in axes))
