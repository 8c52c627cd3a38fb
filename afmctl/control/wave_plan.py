"""A finite trajectory as one table of voltages, computed whole before the run
(``[amplifier] output = "wave"``, :mod:`afmctl.control.wave_run`).

When the whole trajectory is known, the controller does not need to compute as it goes:
the table is what ``afmctl compensate`` computes for the same target, and it is played on
the amplifier's own clock. :func:`plan_table`:

1. pads the target with ``pad`` samples of its first point before and of its last point
   after (the scanner rests there; the non-causal dynamics inverse acts ahead of each
   move and settles after the last one: ``pad`` is the pipeline's preview horizon);
2. runs the controller's :class:`afmctl.control.pipeline.CompensationPipeline` over it with the
   whole target known (:meth:`~afmctl.control.pipeline.CompensationPipeline.block`, ``preview``):
   drift correction, the inverse coupling, then per axis the chain's one offline inverse
   within the amplifier's range and slew
   (:meth:`afmctl.compensators.chain.ChainModel.inverse_within_limits`: turnarounds rounded
   or the band limit lowered where the exact inverse would ask too much, and reported), or
   the streaming inverse of any other model kind. With a drift predictor the heat input
   is the table's own output (a second pass on the first pass's voltages, one sample late
   as in the loop);
3. passes every row through the safety limits once more (inside the range, at most
   ``max_step_V`` from the row before) and counts what had to be changed.

Nothing here sends anything; units: nm, V, s, °C.
"""
from __future__ import annotations

import copy
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from afmctl.compensators.dynamics_limits import rate_limit

from ..errors import AfmctlError
from .pipeline import axis_models

log = logging.getLogger(__name__)

#: longest table [samples] (about 0.2 GB of rows with their targets; a GCS controller or an
#: NV200 holds far less and the player says so before anything is sent)
MAX_TABLE_SAMPLES = 2_000_000
#: why a Kalman drift filter and a wave do not go together
KALMAN_REFUSAL = ("amplifier.output = 'wave': the table is computed before the run, so drift measurements "
                  "cannot reach it; set compensation.drift.kalman = false or use output = 'setpoints' or 'stream'")


@dataclass
class WaveTable:
    """The rows of a planned run, one per output sample at the loop period.

    ``target_nm`` (N, 3) what each row aims at; ``corrected_nm`` (N, 3) after the drift
    correction; ``drift_nm`` (N, 3) the predicted drift; ``u_V`` (N, 3) the voltages x, y,
    z (undriven axes 0); ``T_C`` (N,) the ambient temperature assumed [°C]; ``pad`` rows of
    held start (and end) point around the trajectory;
    ``report`` one line per axis on how its inverse fitted the limits; ``clamped`` /
    ``slew_limited`` samples the final safety pass changed."""

    target_nm: np.ndarray
    corrected_nm: np.ndarray
    drift_nm: np.ndarray
    u_V: np.ndarray
    T_C: np.ndarray
    pad: int
    report: list[str] = field(default_factory=list)
    clamped: int = 0
    slew_limited: int = 0

    def __len__(self) -> int:
        return len(self.u_V)

    def describe(self) -> str:
        """One line for the user: rows, padding, how each axis fitted, the safety pass."""
        txt = f"{len(self)} samples ({self.pad} held before and after the trajectory)"
        if self.report:
            txt += "; " + "; ".join(self.report)
        if self.clamped or self.slew_limited:
            txt += f"; safety pass: {self.clamped} sample(s) clamped, {self.slew_limited} slew-limited"
        return txt


def padded(targets_nm: np.ndarray, pad: int) -> np.ndarray:
    """``targets_nm`` (N, 3) with its first row repeated ``pad`` times before it and its
    last row ``pad`` times after it."""
    t = np.asarray(targets_nm, dtype=np.float64)
    return np.concatenate([np.repeat(t[:1], pad, axis=0), t, np.repeat(t[-1:], pad, axis=0)])


def _offline_inverses(config, models: Sequence[Any], limits_V: dict[str, tuple[float, float]],
                      slew_V_per_s: float, report: list[str]) -> list[Callable[[np.ndarray], np.ndarray] | None]:
    """Per axis x, y, z a whole-target inverse nm → V within that axis's limits (``models``:
    the axis's model, one with a dynamics stage), else None; each call appends its report
    line."""
    dt = config.dt_s
    out: list[Callable[[np.ndarray], np.ndarray] | None] = []
    for axis, model in zip("xyz", models):
        if model is None or getattr(model, "dynamics", None) is None or axis not in limits_V:
            out.append(None)
            continue
        lo, hi = limits_V[axis]

        def invert(y: np.ndarray, model: Any = model, axis: str = axis, lo: float = lo,
                   hi: float = hi) -> np.ndarray:
            res = model.inverse_within_limits(y, dt, lo, hi, slew_V_per_s)
            report.append(f"{axis}: {res.report()}")
            return res.u_V
        out.append(invert)
    return out


def table_capacity(amplifier: Any, axes: Sequence[str]) -> int | None:
    """The most rows one table may have on ``amplifier`` for ``axes``: the smallest wave
    table of those axes (a wave generator), None without one (the CAN stream FIFO)."""
    if not hasattr(amplifier, "wave_capacity"):
        return None
    return min(int(amplifier.wave_capacity(a)) for a in axes)


def planned_models(config, pipeline) -> list[Any]:
    """Per axis x, y, z the model :func:`plan_table` inverts with (or None): the
    pipeline's, or the configuration's for a pipeline not built from it."""
    models: Any = getattr(pipeline, "models", None)
    if not any(m is not None for m in models or ()):   # a pipeline not built from the config
        models = [model for model, _source in axis_models(config)[0]]
    return list(models)


def plan_table(config, pipeline, targets_nm: np.ndarray, T_C: float | np.ndarray,
               limits_V: dict[str, tuple[float, float]], max_step_V: float,
               max_rows: int | None = None) -> WaveTable:
    """The table for ``targets_nm`` (N, 3) [nm] at the loop period (module docstring).

    ``pipeline``: the controller's; it is not changed (a copy gets the offline inverses;
    its operators are reset before and after). ``T_C``: ambient temperature [°C], scalar
    or per target sample. ``limits_V``: ``{axis: (lo, hi)}`` of the driven axes [V];
    ``max_step_V``: largest change between rows [V] (the slew limit per sample);
    ``max_rows``: the most rows the device's table holds — a preview padding that would
    not fit is shortened to fit (the offline inverse then anticipates the first move over
    fewer held rows; the report says so)."""
    if getattr(pipeline, "kalman", None) is not None:
        raise AfmctlError(KALMAN_REFUSAL)
    r = np.asarray(targets_nm, dtype=np.float64)
    if r.ndim != 2 or r.shape[1] != 3 or len(r) == 0:
        raise AfmctlError(f"amplifier.output = 'wave': the trajectory must be positions (N, 3) [nm], got {r.shape}")
    pad = int(getattr(pipeline, "latency_samples", 0))
    report: list[str] = []
    if max_rows is not None and len(r) + 2 * pad > max_rows and len(r) < max_rows:
        report.append(f"padding: {(max_rows - len(r)) // 2} held rows before and after instead of the preview "
                      f"horizon's {pad}, so that the table fits the device's {max_rows}")
        pad = (max_rows - len(r)) // 2
    if len(r) + 2 * pad > MAX_TABLE_SAMPLES:
        raise AfmctlError(f"amplifier.output = 'wave': the trajectory has {len(r)} samples at the loop period; "
                          f"at most {MAX_TABLE_SAMPLES - 2 * pad} fit one table (shorten it or lower loop.rate_Hz)")
    tgt = padded(r, pad)
    T = np.asarray(T_C, dtype=np.float64)
    T = (np.concatenate([np.repeat(T[:1], pad), T, np.repeat(T[-1:], pad)]) if T.ndim
         else np.full(len(tgt), float(T)))
    padding = list(report)
    slew = max_step_V / config.dt_s
    models = planned_models(config, pipeline)
    pipe = copy.copy(pipeline)
    pipe.offline = _offline_inverses(config, models, limits_V, slew, report)
    u_sent = np.zeros_like(tgt)
    passes = 2 if getattr(pipe, "drift", None) is not None else 1
    for _ in range(passes):
        pipeline.reset()
        report[:] = padding
        d, c, u = pipe.block(tgt, T, u_sent, preview=True)
        u_sent = np.concatenate([np.zeros((1, 3)), u[:-1]])
    pipeline.reset()
    table = WaveTable(tgt, c, d, np.zeros_like(u), T, pad, report)
    for axis in limits_V:
        k = "xyz".index(axis)
        lo, hi = limits_V[axis]
        table.u_V[:, k], clipped, limited = rate_limit(u[:, k], lo, hi, max_step_V, None)
        table.clamped += clipped
        table.slew_limited += limited
    return table


def driven_steps_ok(u_V: np.ndarray, axes: Sequence[str], limits_V: dict[str, tuple[float, float]],
                    max_step_V: float, start_V: Sequence[float] | np.ndarray) -> bool:
    """Whether every driven column of ``u_V`` is inside its limits and changes by at most
    ``max_step_V`` per row, starting from ``start_V`` (per driven axis) — the invariant the
    players rely on (checked again before anything is sent)."""
    tol = 1e-9 * max(1.0, max_step_V)
    for i, a in enumerate(axes):
        col = u_V[:, "xyz".index(a)]
        lo, hi = limits_V[a]
        if np.any(~np.isfinite(col)) or np.any(col < lo) or np.any(col > hi):
            return False
        steps = np.abs(np.diff(np.concatenate([[start_V[i]], col])))
        if np.any(steps > max_step_V + tol):
            return False
    return True
