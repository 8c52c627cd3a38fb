"""What a learn run (:mod:`afmctl.control.learn_run`) starts from, before its first play:
the configuration checked for learning on a device, the models as the device's recorder
sees the scanner, the first table, and one :class:`~afmctl.compensators.learning.Learner`
per axis whose target moves. Units: V, nm, s."""
from __future__ import annotations

import logging
from typing import Any

import numpy as np

from afmctl.compensators.learning import Learner, LearnSettings
from afmctl.compensators.learning_weights import HOLD_NM

from ..data.axis_errors import raster_lines
from ..errors import AfmctlError
from ..inputs.trajectories import build, collect
from .approach_history import with_approach_taken_out
from .learn_play import read_at_sample_start
from .pipeline import axis_models, build_pipeline
from .wave_plan import WaveTable, plan_table, planned_models, table_capacity

log = logging.getLogger(__name__)

#: planned tables keep this share of the slew limit in reserve (the players' own checks
#: round to the device's resolution)
SLEW_RESERVE = 0.02
#: a target axis moving less than this [nm] peak to peak is not learned (it holds)
MIN_SPAN_NM = HOLD_NM


class LearnSetup:
    """The start of learning on one open ``amplifier`` (module docstring) for ``config``
    (``amplifier.output = "wave"``, a finite trajectory; refused in one line otherwise);
    ``settings``: the learning law's, its limits set here from the configuration;
    ``use_model``: learn through the configured models (False: model-free)."""

    def __init__(self, config: Any, amplifier: Any, settings: LearnSettings, use_model: bool = True) -> None:
        self.config = config
        self.amp = amplifier
        self.settings = settings
        self.use_model = use_model
        self._models: tuple | None = None
        self.check()
        self.axes = [a for a in config.scanner.axes if a in amplifier.axes]
        self.limits_V = {a: config.limits(a) for a in self.axes}
        self.max_step_V = (1.0 - SLEW_RESERVE) * config.slew_V_per_s() * config.dt_s

    def check(self) -> None:
        """One line naming what keeps this configuration and device from learning."""
        cfg = self.config
        if cfg.trajectory.kind in ("queue", "learned"):
            raise AfmctlError(f"trajectory.kind = '{cfg.trajectory.kind}': afmctl learn needs a finite trajectory "
                              "to learn (raster, moves, indentation, text, spiral or file)")
        if not getattr(self.amp, "has_recorder", False):
            raise AfmctlError(f"amplifier.driver = '{cfg.amplifier.driver}' has no data recorder this driver "
                              "reads: record the motion with an external sensor and learn from the files with "
                              "'afmctl learn step'")
        if cfg.amplifier.output != "wave":
            raise AfmctlError(f"amplifier.output = '{cfg.amplifier.output}': afmctl learn plays each table on the "
                              "amplifier's clock; set output = 'wave' (or AFMCTL_AMPLIFIER__OUTPUT=wave)")

    def recorder_models(self) -> tuple:
        """The configuration's :func:`~afmctl.control.pipeline.axis_models`, each as the
        device's recorder sees the scanner (:func:`read_at_sample_start`), loaded once: the
        first table and the learning filters both use them."""
        if self._models is None:
            models, inv_c, scanner_file = axis_models(self.config)
            self._models = ([(read_at_sample_start(m), src) for m, src in models], inv_c, scanner_file)
        return self._models

    def learned_models(self) -> list[Any]:
        """Per axis x, y, z the learning filter: the recorder's model, or None (model-free)."""
        return [m for m, _ in self.recorder_models()[0]] if self.use_model else [None] * 3

    def first_table(self) -> WaveTable:
        """The configured compensation's table for the trajectory (what ``output = "wave"``
        plays without learning)."""
        cfg = self.config
        targets = collect(build(cfg.trajectory, cfg.dt_s))
        if len(targets) == 0:
            raise AfmctlError("trajectory: it has no samples at the loop period")
        T_C = cfg.compensation.temperature.T_C
        pipeline = build_pipeline(cfg, self.recorder_models())
        table = plan_table(cfg, pipeline, targets, T_C, self.limits_V, self.max_step_V,
                           table_capacity(self.amp, self.axes))
        start = self.present_output(self.axes)
        return with_approach_taken_out(table, cfg, planned_models(cfg, pipeline), [start.get(a, 0.0) for a in "xyz"],
                                       self.limits_V, self.max_step_V, calibration=False)

    def learners(self, table: WaveTable) -> dict[str, Learner]:
        """One learner per axis whose target moves, its limits from the configuration; a
        raster's slow axis learns on the raster's lines (the fast axis's)."""
        models = self.learned_models()
        raster = raster_lines(table.target_nm, "".join(self.axes))
        out: dict[str, Learner] = {}
        for axis in self.axes:
            k = "xyz".index(axis)
            if np.ptp(table.target_nm[:, k]) < MIN_SPAN_NM:
                continue
            lo, hi = self.limits_V[axis]
            settings = LearnSettings(**{**self.settings.__dict__, "u_min_V": lo, "u_max_V": hi,
                                        "slew_V_per_s": self.max_step_V / self.config.dt_s})
            out[axis] = Learner(table.target_nm[:, k], self.config.dt_s, models[k], settings,
                                lines=raster[1] if raster is not None else None)
        if not out:
            raise AfmctlError("trajectory: no driven axis moves; nothing to learn")
        return out

    def present_output(self, axes: list[str]) -> dict[str, float]:
        """The output [V] per axis now (read back), where the history begins."""
        try:
            volts = self.amp.get_voltages()
        except Exception as err:  # noqa: BLE001 - a link fault shows on the first play
            log.warning("learn: reading the output back failed (%s); the history starts at the safe values", err)
            volts = {}
        return {a: float(volts.get(a, self.config.safety.safe_value(a))) for a in axes}
