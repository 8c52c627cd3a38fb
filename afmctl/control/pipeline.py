"""The compensation chain of one tick, composed from compensators (no model math here).

Per sample, for the target ``r`` [nm] (x, y, z):

1. drift estimate ``d̂`` [nm] from :class:`afmctl.compensators.drift.DriftParams.predictor`,
   driven by the ambient temperature [°C] and the voltages already sent [V] (heat); with
   a Kalman filter (:class:`afmctl.compensators.drift_kalman.DriftKalman`,
   ``compensation.drift.kalman``) ``d̂ = model + bias``, the bias tracked from drift
   measurements fused by :meth:`CompensationPipeline.update_drift`;
2. corrected target ``r' = r − d̂`` [nm];
3. with a scanner model's coupling matrix ``C``, the decoupled axis targets
   ``r'' = C⁻¹ r'`` [nm] (otherwise ``r'' = r'``);
4. per axis, the inverse model ``u = model.inverse(dt_s).step(r'')`` [V] (any kind, a
   hysteresis+creep+dynamics chain included), or, without a model, the linear calibration
   ``u = offset_V + r'' / nm_per_V``.

:attr:`CompensationPipeline.provenance` says, per axis, which model came from which file
(``afmctl run`` prints it at start).

The result goes to :class:`afmctl.control.safety.SafetyLayer`, never straight to an amplifier.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any
from pathlib import Path

import numpy as np

from afmctl.compensators.base import StreamingOperator

from .preview import Delayed, equalise_latency

log = logging.getLogger(__name__)


class LinearAxis(StreamingOperator):
    """``u_V = offset_V + y_nm / nm_per_V`` (the uncompensated linear calibration)."""

    def __init__(self, nm_per_V: float, offset_V: float = 0.0) -> None:
        self.inv_gain = 1.0 / float(nm_per_V)
        self.offset_V = float(offset_V)

    def reset(self) -> None:
        pass

    def step(self, x: float) -> float:
        return self.offset_V + x * self.inv_gain

    def block(self, x: np.ndarray) -> np.ndarray:
        return self.offset_V + np.asarray(x, dtype=np.float64) * self.inv_gain


class CompensationPipeline:
    """Drift correction followed by a per-axis inverse model.

    ``inverses``: three operators y[nm] → u[V] for x, y, z. ``drift``: an object with
    ``reset()`` and ``step(T_C, u_V (3,)) -> (3,) nm`` (interface of
    compensators.drift.DriftPredictor) or None. ``kalman``: a
    :class:`afmctl.compensators.drift_kalman.DriftKalman` stepped once per sample (its ``dt_s``
    must be the loop period) on the model's drift, or None (needs ``drift``).
    """

    def __init__(self, inverses: Sequence[StreamingOperator], drift: Any | None = None,
                 kalman: Any | None = None, inv_coupling: np.ndarray | None = None,
                 provenance: Mapping[str, str] | None = None,
                 offline: Sequence[Callable[[np.ndarray], np.ndarray] | None] | None = None) -> None:
        if len(inverses) != 3:
            raise ValueError("inverses: one operator per axis x, y, z")
        if kalman is not None and drift is None:
            raise ValueError("kalman: needs a drift predictor")
        #: per axis, the inverse the pipeline steps; an axis whose preview latency is
        #: shorter than the longest is fed its input that much later (:mod:`afmctl.control.preview`)
        self.inverses, lat = equalise_latency(list(inverses))
        #: samples by which every axis's output lags its target (the preview horizon the
        #: loop reads ahead, :mod:`afmctl.control.preview`); 0 without a dynamics stage
        self.latency_samples: int = lat
        #: per axis, a whole-target inverse nm → V within the amplifier's limits (or None),
        #: used by :meth:`block` with ``preview`` (see :func:`offline_inverse`)
        self.offline: list[Any] = list(offline) if offline is not None else [None, None, None]
        if len(self.offline) != 3:
            raise ValueError("offline: one entry per axis x, y, z")
        self.drift = drift
        self.kalman = kalman
        #: C⁻¹ (3, 3) applied to the corrected target [nm/nm], or None (identity)
        self.inv_coupling = None if inv_coupling is None else np.asarray(inv_coupling, dtype=np.float64).copy()
        #: axis → "preisach+creep from x.json" / "linear calibration 80 nm/V"; "coupling" when used
        self.provenance: dict[str, str] = dict(provenance or {})
        #: per axis x, y, z the model its inverse came from, or None (the linear calibration,
        #: or not known: :func:`build_pipeline` fills it in) — for whole-trajectory planning
        self.models: list[Any] = [None, None, None]
        self._u_prev = np.zeros(3)

    def reset(self) -> None:
        for op in self.inverses:
            op.reset()
        if self.drift is not None:
            self.drift.reset()
        if self.kalman is not None:
            self.kalman.reset()
        self._u_prev[:] = 0.0

    def update_drift(self, measured_drift_nm: Sequence[float], std_nm: float, age_s: float = 0.0) -> None:
        """Fuse a drift measurement [nm] (3,; NaN = axis not measured) with 1-σ ``std_nm``
        [nm], taken ``age_s`` [s] before the last sample (the model drift of the last
        sample stands for the measured instant). No-op without a Kalman filter."""
        if self.kalman is not None:
            self.kalman.update(measured_drift_nm, std_nm, age_s=age_s)

    def drift_std_nm(self) -> tuple[float, float, float] | None:
        """1-σ of the drift estimate [nm] per axis (the filter's), None without a filter."""
        if self.kalman is None:
            return None
        vx, vy, vz = self.kalman.P[:, 0, 0].tolist()
        return (math.sqrt(max(vx, 0.0)), math.sqrt(max(vy, 0.0)), math.sqrt(max(vz, 0.0)))

    def step(self, x: float, y: float, z: float, T_C: float, u_sent: Sequence[float]
             ) -> tuple[float, float, float, float, float, float, float, float, float]:
        """One tick. ``u_sent``: voltages already sent (x, y, z) [V] for the heat input.

        Returns ``(dx, dy, dz, cx, cy, cz, ux, uy, uz)``: drift estimate [nm], corrected
        target [nm], voltages [V].
        """
        if self.drift is not None:
            up = self._u_prev
            up[0] = u_sent[0]
            up[1] = u_sent[1]
            up[2] = u_sent[2]
            d = self.drift.step(T_C, up)
            if self.kalman is not None:
                d = self.kalman.predict(d)
            dx, dy, dz = float(d[0]), float(d[1]), float(d[2])
        else:
            dx = dy = dz = 0.0
        cx, cy, cz = x - dx, y - dy, z - dz
        inv = self.inverses
        M = self.inv_coupling
        if M is None:
            return (dx, dy, dz, cx, cy, cz, inv[0].step(cx), inv[1].step(cy), inv[2].step(cz))
        ax = M[0, 0] * cx + M[0, 1] * cy + M[0, 2] * cz
        ay = M[1, 0] * cx + M[1, 1] * cy + M[1, 2] * cz
        az = M[2, 0] * cx + M[2, 1] * cy + M[2, 2] * cz
        return (dx, dy, dz, cx, cy, cz, inv[0].step(float(ax)), inv[1].step(float(ay)), inv[2].step(float(az)))

    def block(self, targets_nm: np.ndarray, T_C: np.ndarray | float, u_sent_V: np.ndarray,
              preview: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vectorised: the numbers :meth:`step` gives per sample with ``u_sent`` taken from
        ``u_sent_V`` (N, 3) [V] (the heat input) instead of the pipeline's own previous
        output — for offline use where the voltages already sent are known or estimated.
        ``targets_nm`` (N, 3) [nm], ``T_C`` (N,) or scalar [°C]. Returns drift (N, 3) [nm],
        corrected (N, 3) [nm], u (N, 3) [V]. Not with a Kalman filter (measurements arrive
        per sample).

        ``preview``: the whole target is known. An axis with an ``offline`` inverse (a
        chain with dynamics, :func:`offline_inverse`) gets its decoupled target through it
        (stable non-causal inverse within the amplifier's limits); otherwise an axis whose
        inverse has ``latency_samples`` = L is fed its decoupled target L samples ahead
        (the last sample repeated at the end): its output is aligned with the target
        instead of lagging it."""
        if self.kalman is not None:
            raise ValueError("block: not with a Kalman filter; use run()")
        r = np.asarray(targets_nm, dtype=np.float64)
        n = r.shape[0]
        if self.drift is not None:
            T = np.broadcast_to(np.asarray(T_C, dtype=np.float64), (n,))
            d = self.drift.block(T, np.asarray(u_sent_V, dtype=np.float64))
        else:
            d = np.zeros((n, 3))
        c = r - d
        M = self.inv_coupling
        if M is None:
            a = c
        else:   # the same operations, in the same order, as step()
            a = np.empty_like(c)
            for i in range(3):
                a[:, i] = M[i, 0] * c[:, 0] + M[i, 1] * c[:, 1] + M[i, 2] * c[:, 2]
        u = np.empty_like(c)
        for i in range(3):
            if preview and n and self.offline[i] is not None:
                u[:, i] = self.offline[i](np.ascontiguousarray(a[:, i]))
                continue
            op = self.inverses[i]
            if preview and isinstance(op, Delayed):
                op = op.op    # the whole target is known: no need to wait for the longest preview
            lat = int(getattr(op, "latency_samples", 0)) if (preview and n) else 0
            col = a[:, i] if lat == 0 else np.concatenate([a[lat:, i], np.full(min(lat, n), a[-1, i])])[:n]
            u[:, i] = op.block(np.ascontiguousarray(col))
        return d, c, u

    def describe(self) -> str:
        """One line: ``x: preisach+creep from x.json; y: linear calibration 80 nm/V; …``."""
        return "; ".join(f"{k}: {v}" for k, v in self.provenance.items())

    def run(self, targets_nm: np.ndarray, T_C: np.ndarray | float,
            measurements: Mapping[int, tuple[Sequence[float], float]] | None = None,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offline: the whole chain over ``targets_nm`` (N, 3), heat from its own output.
        ``measurements``: ``{i: (measured_drift_nm (3,), std_nm)}`` fused (see
        :meth:`update_drift`) just before sample ``i``, as the loop does.

        Returns drift (N, 3) [nm], corrected (N, 3) [nm], u (N, 3) [V]; the same numbers as
        calling :meth:`step` per sample with ``u_sent`` = the previous output.
        """
        meas = measurements or {}
        r = np.asarray(targets_nm, dtype=np.float64)
        n = r.shape[0]
        T = np.broadcast_to(np.asarray(T_C, dtype=np.float64), (n,))
        d = np.zeros((n, 3))
        c = np.zeros((n, 3))
        u = np.zeros((n, 3))
        prev = (0.0, 0.0, 0.0)
        for i in range(n):
            if i in meas:
                self.update_drift(*meas[i])
            out = self.step(float(r[i, 0]), float(r[i, 1]), float(r[i, 2]), float(T[i]), prev)
            d[i] = out[0:3]
            c[i] = out[3:6]
            u[i] = out[6:9]
            prev = out[6:9]
        return d, c, u


def offline_inverse(model: Any, dt_s: float, u_min_V: float, u_max_V: float, slew_V_per_s: float | None,
                    u_start_V: float | None = None) -> Callable[[np.ndarray], np.ndarray] | None:
    """For :class:`CompensationPipeline`'s ``offline``: a whole-target inverse nm → V of
    ``model`` at ``dt_s`` [s] within [u_min_V, u_max_V] [V] and ``slew_V_per_s`` [V/s],
    ramping from ``u_start_V`` [V] (the voltage the amplifier holds before the first
    sample) — ``model.inverse_within_limits`` — or None when the model has no dynamics
    stage (its streaming inverse is already exact offline)."""
    if getattr(model, "dynamics", None) is None:
        return None

    def invert(target_nm: np.ndarray) -> np.ndarray:
        res = model.inverse_within_limits(target_nm, dt_s, u_min_V, u_max_V, slew_V_per_s, u_start_V)
        log.info("offline inverse (%s): %s", _model_name(model), res.report())
        return res.u_V
    return invert


def load_drift_params(name_or_file: str, overrides: dict[str, Any] | None = None):
    """A :class:`afmctl.compensators.drift.DriftParams` from a named set or a JSON file, with
    field overrides (:meth:`~afmctl.compensators.drift.DriftParams.from_spec`)."""
    from afmctl.compensators.drift import DriftParams
    return DriftParams.from_spec(name_or_file, overrides, where="compensation.drift.params")


def _model_name(model: Any) -> str:
    return getattr(model, "structure", None) or model.kind


def axis_models(config) -> tuple[list[tuple[Any, str | None]], np.ndarray | None, str | None]:
    """Per axis x, y, z the model of the configuration's ``[compensation]`` and the file it
    came from — ``[compensation.<axis>] model`` first, then the axis of ``scanner_model`` —
    or ``(None, None)`` (the linear calibration); then C⁻¹ of the scanner model (None when
    there is none or it is the identity) and the scanner model's file."""
    from afmctl.compensators.base import ModelError
    from afmctl.compensators.models import load_model
    comp = config.compensation
    scanner: Any = None   # a ScannerModel
    if comp.scanner_model is not None:
        scanner = load_model(comp.scanner_model, expect=("scanner",))
    models: list[tuple[Any, str | None]] = []
    for axis in ("x", "y", "z"):
        spec = comp.axis(axis)
        model: Any = None
        source: str | None = None
        if spec.model is not None:
            try:
                model, source = load_model(spec.model), spec.model
            except ModelError as err:
                raise ModelError(f"compensation.{axis}.model: {err}") from None
            if model.kind == "scanner":
                model = model.axis(axis)
        elif scanner is not None and scanner.axis(axis) is not None:
            model, source = scanner.axis(axis), comp.scanner_model
        models.append((model, source))
    inv_c = None
    if scanner is not None and not np.allclose(scanner.inverse_coupling(), np.eye(3)):
        inv_c = scanner.inverse_coupling()
    return models, inv_c, comp.scanner_model


def axis_inverses(config, found: tuple | None = None
                  ) -> tuple[list[StreamingOperator], dict[str, str], np.ndarray | None]:
    """Per-axis inverse operators, their provenance and C⁻¹ (or None) from the
    configuration's ``[compensation]`` (``found``: what :func:`axis_models` returned, else
    it is called), else the linear calibration of ``[scanner.calibration]``."""
    dt = config.dt_s
    models, inv_c, scanner_file = found if found is not None else axis_models(config)
    inverses: list[StreamingOperator] = []
    prov: dict[str, str] = {}
    for axis, (model, source) in zip(("x", "y", "z"), models):
        if model is not None:
            op = model.inverse(dt)
            inverses.append(op)
            prov[axis] = f"{_model_name(model)} from {Path(source).name}"
            lat = int(getattr(op, "latency_samples", 0))
            if lat:   # the loop reads the trajectory this far ahead (afmctl.control.preview)
                prov[axis] += f" (preview inverse: reads the target {lat} samples, {lat * dt * 1e3:.3g} ms, ahead)"
        else:
            cal = config.scanner.axis_spec(axis)
            inverses.append(LinearAxis(cal.nm_per_V, cal.offset_V))
            prov[axis] = f"linear calibration {cal.nm_per_V:g} nm/V (uncompensated)"
    if inv_c is not None:
        prov["coupling"] = f"inverse 3x3 from {Path(scanner_file).name}"
    return inverses, prov, inv_c


def build_pipeline(config, found: tuple | None = None) -> CompensationPipeline:
    """The pipeline described by an :class:`afmctl.config.Config`; ``found``: its
    :func:`axis_models` when the caller has them (e.g. adjusted) already."""
    dt = config.dt_s
    found = axis_models(config) if found is None else found
    inverses, prov, inv_c = axis_inverses(config, found)
    for axis, text in prov.items():
        log.info("compensation %s: %s", axis, text)
    drift = None
    if config.compensation.drift.enabled:
        params = load_drift_params(config.compensation.drift.params, config.compensation.drift.overrides)
        drift = params.predictor(dt)
        prov["drift"] = f"predicted ({config.compensation.drift.params})"
    kalman = None
    if config.compensation.drift.kalman:
        from afmctl.compensators.drift_kalman import DriftKalman
        kalman = DriftKalman(dt, config.compensation.drift.kalman_params())
        log.info("drift: Kalman bias filter on (%s)", kalman.params)
    pipe = CompensationPipeline(inverses, drift, kalman, inv_coupling=inv_c, provenance=prov)
    pipe.models = [model for model, _source in found[0]]
    return pipe
