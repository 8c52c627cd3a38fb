"""Calibrate a scanner on its device in one call (``afmctl calibrate`` runs this code):
excite, record through the device's recorder, identify, validate on a second play, write
the model with its provenance.

:func:`calibrate` (or :class:`Calibration` for a run that another thread may stop):

1. **excite** — per axis, what ``afmctl excite --kind all`` writes for the configured
   amplifier (range = the axis's limits, ``loop.rate_Hz``, half the slew limit), cut into
   pieces the device's wave table and recorder hold
   (:mod:`afmctl.control.calibrate_pieces`; a device that cannot hold the shortest piece is
   refused before anything moves), played and recorded piece by piece
   (:mod:`afmctl.control.calibrate_run`), the pieces joined with the holds between them;
   the other axes hold their safe value;
2. **identify** — the joined recording is written as CSV (``t,u,y`` and ``v``, the piezo
   voltage, where the device records it) as soon as it is recorded, and identified from that
   file as ``afmctl identify --model KIND --data`` does (:func:`afmctl.api.identify.identify`),
   in a process of its own while the validation and the other axes play
   (:mod:`.identify_worker`);
3. **validate** — a second, different play: triangles across the range at the
   configuration's line rate (a raster's fast axis) and nested minor loops (reversals at
   falling amplitudes), recorded the same way; the model runs over the excitation and then
   the validation (its memory set by what the scanner saw) and its error over the
   validation is the held-out error, max and RMS in % of the validation's measured span;
4. **write** — the model (a scanner of one axis: its model; of several: a scanner file,
   kind ``scanner``, with the calibrated axes — ready for ``[compensation] scanner_model``)
   with ``provenance``: device, identity (``*IDN?`` or what the driver reads), recorder
   rate, settle hold, date, afmctl version, the excitation and the pieces.

Units: V, nm, s; errors in % of the span.
"""
from __future__ import annotations

import contextlib
import datetime
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..control.calibrate_pieces import (Joined, PiecePlan, cut_points, excitation_all, join, plan_pieces,
                                        ramp_priorities, shortest_piece)
from ..control.calibrate_run import (CalibrationFault, CalibrationRun, CalibrationStopped, Progress, device_capacity,
                                     readback_rows, recorder_signals, share_recorder)
from ..data.datafiles import write_csv
from ..simulation.link import configured_amplifier
from ..data.excitation import ExcitationSpec
from ..errors import AfmctlError
from .identify import Identified

log = logging.getLogger(__name__)

#: what the validation's triangles last at least [s], and at most [lines]
VALIDATION_S, MAX_VALIDATION_LINES = 2.0, 100
#: the nested minor loops' amplitudes, as shares of the range
MINOR_LOOPS = (1.0, 0.8, 0.6, 0.4, 0.2)
#: ``auto``'s worker processes (``jobs``), unless the caller's params name them or the
#: environment variable :data:`FIT_JOBS_ENV` does: the same model, sooner (the E-727's
#: calibrate recording: see docs/BENCHMARKS.md)
FIT_JOBS = 2
#: the environment variable that sets :data:`FIT_JOBS` (``make test`` sets 1: its two pytest
#: workers keep both cores busy already)
FIT_JOBS_ENV = "AFMCTL_FIT_JOBS"


def fit_jobs() -> int:
    """The ``jobs`` calibrate's ``auto`` runs with (:data:`FIT_JOBS`, :data:`FIT_JOBS_ENV`)."""
    import os
    from .identify import MAX_JOBS
    text = os.environ.get(FIT_JOBS_ENV, "").strip()
    if not text:
        return FIT_JOBS
    if not text.isdigit() or not 1 <= int(text) <= MAX_JOBS:
        raise AfmctlError(f"{FIT_JOBS_ENV}: {text!r}; allowed a whole number 1 … {MAX_JOBS} "
                          "(worker processes for the identification)")
    return int(text)


@dataclass
class AxisCalibration:
    """One axis: the ``identified`` fit (its held-out ``table`` with ``auto``), the
    recording ``csv`` it came from, the joined recordings, and the ``validation`` figures
    per part (``raster``, ``minor loops``, ``all``): ``max_pct``, ``rms_pct`` of ``span_nm``."""

    axis: str
    identified: Identified
    csv: Path
    recording: Joined
    validation_record: Joined
    validation: dict[str, dict[str, float]]
    #: the joined validation row where the minor loops begin
    minor_row: int
    pieces: int


@dataclass
class Calibrated:
    """What :func:`calibrate` did: the ``model`` written to ``path``, per axis an
    :class:`AxisCalibration`, the ``provenance`` stored in the model, the excitation's
    duration ``excitation_s`` and the wall time ``elapsed_s`` [s]."""

    model: Any
    path: Path | None
    axes: dict[str, AxisCalibration]
    provenance: dict[str, Any]
    excitation_s: float
    elapsed_s: float
    #: wall time of the device part (open, excite, validate, return to safe) [s]
    recording_s: float = 0.0
    #: what the validation plays last [s]
    validation_s: float = 0.0
    notes: list[str] = field(default_factory=list)


def excitation_spec(config: Any, axis: str, amp: Any = None, **options: Any) -> ExcitationSpec:
    """What ``afmctl excite --kind all`` takes for ``axis`` under ``config``: the axis's
    limits (within the device's own, with ``amp``), ``loop.rate_Hz``, the slew limit;
    ``options``: the other fields of :class:`~afmctl.data.excitation.ExcitationSpec`
    (``dwell_s``, ``gap_s``, ``periods``, ``f_min_Hz``, ``f_max_Hz``, ``sweep_V_per_s``,
    ``amplitude_frac``, ``seed``)."""
    lo, hi = config.limits(axis)
    dev = dict(amp.limits).get(axis) if amp is not None else None
    if dev is not None:
        lo, hi = max(lo, dev.min_V), min(hi, dev.max_V)
    try:
        return ExcitationSpec(u_min_V=lo, u_max_V=hi, rate_Hz=float(config.loop.rate_Hz),
                              slew_V_per_s=config.slew_V_per_s(), **options)
    except TypeError as err:
        raise AfmctlError(f"excitation: {err}") from None


def validation_voltages(config: Any, spec: ExcitationSpec) -> tuple[np.ndarray, int]:
    """The validation play [V] at ``spec.rate_Hz`` and where its second part begins:
    triangles across the range at the configuration's line rate (one line per ramp, at most
    half the slew limit), then nested minor loops from the bottom of the range (reversals at
    :data:`MINOR_LOOPS` of it) at the excitation's sweep speed; it starts and ends at the
    bottom of the range."""
    from ..data.excitation import through
    lo, hi = spec.u_min_V, spec.u_max_V
    line_rate = float(getattr(config.trajectory, "line_rate_Hz", 1.0) or 1.0)
    fast = min(spec.span_V * line_rate, 0.5 * spec.slew_V_per_s if spec.slew_V_per_s else math.inf)
    lines = int(min(MAX_VALIDATION_LINES, max(4, 2 * math.ceil(0.5 * VALIDATION_S * line_rate))))
    raster = ExcitationSpec(**{**spec.__dict__, "sweep_V_per_s": fast})
    pts = [lo] + [hi if k % 2 == 0 else lo for k in range(lines)]
    minor = [lo]
    for share in MINOR_LOOPS:
        minor += [lo + share * spec.span_V, lo]
    first = np.concatenate([[lo], through(pts, raster)])
    return np.concatenate([first, through(minor, spec)]), len(first)


def provenance(config: Any, amp: Any, spec: ExcitationSpec, plans: dict[str, PiecePlan], kind: str) -> dict[str, Any]:
    """What the model file keeps of how it was made (module docstring, step 4)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        afmctl_version = version("afmctl")
    except PackageNotFoundError:       # a source tree that was not installed
        afmctl_version = "unknown"
    try:
        info = dict(amp.info())
    except Exception as err:  # noqa: BLE001 - the identity is a courtesy, not a requirement
        info = {"driver": config.amplifier.driver, "info_error": str(err)}
    identity = {k: v for k, v in info.items() if k in ("identity", "device_type", "sensor", "status_word", "serial")}
    return {
        "made_by": "afmctl calibrate",
        "afmctl_version": afmctl_version,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "device": {"driver": config.amplifier.driver, "port": str(info.get("port", config.amplifier.port)),
                   "simulated": bool(config.simulation.enabled), **{k: str(v) for k, v in identity.items()}},
        "recorder_rate_Hz": float(config.loop.rate_Hz),
        "settle_s": float(config.amplifier.settle_s) if config.amplifier.settle_s is not None else 2.0,
        "kind": kind,
        "excitation": {k: v for k, v in spec.__dict__.items() if k not in ("u_min_V", "u_max_V")},
        "axes": {a: {"u_range_V": [float(p.exc.u_V.min()), float(p.exc.u_V.max())], "samples": int(len(p.exc.u_V)),
                     "pieces": len(p.bounds), "piece_rows": int(max(b - a0 for a0, b in p.bounds))}
                 for a, p in plans.items()},
    }


class Calibration:
    """One calibration (module docstring); :meth:`run` does it, :meth:`stop` (any thread)
    ends it: the piece playing stops, the output ramps to the safe value.

    ``config``: a run configuration (path or loaded) with ``amplifier.output = "wave"``;
    ``out``: the model file to write (None: not written); ``axes``: the axes to calibrate
    (default: the scanner's); ``kind``: a model kind, a chain or ``auto``; ``report_dir``:
    where the recordings (CSV) go (default: beside ``out``); ``excitation``: options of
    :func:`excitation_spec`; ``on_progress``: called with each
    :class:`~afmctl.control.calibrate_run.Progress`; ``params``: the kind's options."""

    def __init__(self, config: Any, out: str | Path | None = None, *, axes: list[str] | None = None,
                 kind: str = "auto", report_dir: str | Path | None = None,
                 excitation: dict[str, Any] | None = None,
                 on_progress: Callable[[Progress], None] | None = None, **params: Any) -> None:
        from ..config import load_config
        self.config = load_config(config) if isinstance(config, (str, Path)) else config
        self.out = Path(out) if out is not None else None
        self.kind = kind
        # auto's worker processes: an unusable AFMCTL_FIT_JOBS is refused before anything moves
        self.params = {"jobs": fit_jobs(), **params} if kind == "auto" else params
        self.report_dir = Path(report_dir) if report_dir is not None else (
            self.out.parent if self.out is not None else Path("."))
        self.excitation = dict(excitation or {})
        self.on_progress = on_progress
        axes = list(axes) if axes else list(self.config.scanner.axes)
        unknown = [a for a in axes if a not in self.config.scanner.axes]
        if unknown or not axes:
            raise AfmctlError(f"--axes: {','.join(axes)}; allowed: one or more of the scanner's axes "
                              f"({','.join(self.config.scanner.axes)})")
        self.axes = axes
        self.run_: CalibrationRun | None = None
        self._stop_asked = False
        self.partial: list[Path] = []
        self.specs: dict[str, ExcitationSpec] = {}
        #: the device part is over (the output at the safe value): a stop now interrupts the identification
        self.device_done = False
        self._worker: Any = None
        #: the axes whose recordings are written and handed to the identification
        self.fitting: list[str] = []
        #: wall clock [s since the epoch] when each axis's validation ended, and the plays' end
        self.played_unix_s: dict[str, float] = {}
        self.finished_unix_s = 0.0

    # ------------------------------------------------------------------ the steps
    def stem(self) -> str:
        return self.out.stem if self.out is not None else "calibration"

    def csv_path(self, axis: str, what: str = "recording") -> Path:
        return self.report_dir / f"{self.stem()}.{axis}-{what}.csv"

    def plans(self, amp: Any, stack: contextlib.ExitStack
              ) -> tuple[dict[str, PiecePlan], dict[str, tuple[str, ...]], ExcitationSpec]:
        """Per axis its pieces and the signals its recorder takes; refused in one line
        before anything moves when a piece cannot fit. The recorder's memory is shared
        among as few tables as a piece records (:func:`share_recorder`), put back as it was
        when ``stack`` closes."""
        plans = {}
        spec = excitation_spec(self.config, self.axes[0], amp, **self.excitation)
        self.specs = {}
        signals = {axis: recorder_signals(amp, axis) for axis in self.axes}
        restore = share_recorder(amp, max(len(s) for s in signals.values()))
        if restore is not None:
            stack.callback(restore)
        for axis in self.axes:
            spec = self.specs[axis] = excitation_spec(self.config, axis, amp, **self.excitation)
            exc = excitation_all(spec)
            capacity = device_capacity(amp, axis, signals[axis])
            most = readback_rows(amp, signals[axis])
            if most is not None:        # never below one multisine period: that is refused below
                capacity = min(capacity, max(most, shortest_piece(exc)))
            plans[axis] = plan_pieces(exc, axis, capacity, f"{self.config.amplifier.driver} "
                                      f"({', '.join(signals[axis])})")
        return plans, signals, spec

    def run(self) -> Calibrated:
        """Excite, record, identify, validate, write (module docstring). Raises
        :class:`~afmctl.control.calibrate_run.CalibrationStopped` after a stop and
        :class:`~afmctl.control.calibrate_run.CalibrationFault` after a lost link (the
        partial recordings written: :attr:`partial`)."""
        t0 = time.monotonic()
        if self.config.amplifier.output != "wave":
            raise AfmctlError("amplifier.output: afmctl calibrate plays the excitation on the amplifier's clock; "
                              "set output = 'wave' (gcs, nv200 or can)")
        with contextlib.ExitStack() as worker:
            worker.callback(self._close_worker)
            self._start_worker()               # its imports while the excitation plays
            with contextlib.ExitStack() as stack:
                amp = configured_amplifier(stack, self.config)
                plans, signals, spec = self.plans(amp, stack)
                run = CalibrationRun(self.config, amp, self.on_progress)
                self.run_ = run
                if self._stop_asked:
                    run.stop()
                joined = self._record(run, plans, signals)
                prov = provenance(run.config, amp, spec, plans, self.kind)
            recording_s = time.monotonic() - t0
            self.device_done = True
            self._write_validations(joined)
            csvs = {a: self.csv_path(a) for a in joined}
            if self._stop_asked:
                self.partial = list(csvs.values())
                raise CalibrationStopped("afmctl calibrate: stopped after the recording")
            validation_s = sum(len(j[1].u_V) - sum(g for _, g in j[1].holds) for j in joined.values()) * run.dt_s
            try:
                results = {a: self._identify(a, csvs[a], *joined[a], plans[a]) for a in self.axes}
            except KeyboardInterrupt:       # the device is done: Ctrl-C or a stop interrupts the identification
                self.partial = list(csvs.values())
                raise CalibrationStopped("afmctl calibrate: stopped during the identification") from None
        model = self._model(results, prov)
        if self.out is not None:
            from afmctl.compensators.models import save_model
            self.out.parent.mkdir(parents=True, exist_ok=True)
            save_model(model, self.out)
        excitation_s = sum(len(p.exc.u_V) for p in plans.values()) / float(self.config.loop.rate_Hz)
        return Calibrated(model, self.out, results, prov, excitation_s, time.monotonic() - t0, recording_s,
                          validation_s)

    def _record(self, run: CalibrationRun, plans: dict[str, PiecePlan],
                signals: dict[str, tuple[str, ...]]) -> dict[str, tuple[Joined, Joined, int]]:
        """Every axis's excitation and validation played and recorded; the output ramped to
        the safe value at the end, after a stop, after an error it could still reach."""
        out: dict[str, tuple[Joined, Joined, int]] = {}
        total = sum(len(p.exc.u_V) for p in plans.values()) / float(self.config.loop.rate_Hz)
        done = [0.0]
        try:
            for axis, plan in plans.items():
                out[axis] = self._record_axis(run, plan, signals[axis], total, done)
                self.played_unix_s[axis] = time.time()
        except CalibrationFault:
            self._keep_partial(run)
            raise
        except BaseException:
            self._keep_partial(run)
            with contextlib.suppress(Exception):
                run.finish()
            raise
        if self.config.safety.on_finish == "safe":
            run.finish()
        self.finished_unix_s = time.time()
        return out

    def _record_axis(self, run: CalibrationRun, plan: PiecePlan, signals: tuple[str, ...], total_s: float,
                     done: list[float]) -> tuple[Joined, Joined, int]:
        dt = run.dt_s
        axis = plan.axis
        exc = run.play(f"excite {axis}", axis, signals, [plan.table(k) for k in range(len(plan.bounds))],
                       [a for a, _ in plan.bounds],
                       lambda k: total_s - done[0] - plan.bounds[k][0] * dt,
                       [plan.exc.priority[a:b] for a, b in plan.bounds])     # a multisine's periods stay whole
        done[0] += len(plan.exc.u_V) * dt
        rec = join(exc, dt)
        self._fit_later(axis, rec)
        val_u, n_raster = validation_voltages(self.config, self.specs[axis])
        capacity = max(b - a for a, b in plan.bounds)
        bounds = cut_points(ramp_priorities(val_u), capacity)
        # the validation starts where the excitation ended (the bottom of the range): no jump
        val = run.play(f"validate {axis}", axis, signals, [val_u[a:b] for a, b in bounds], [a for a, _ in bounds],
                       lambda k: max(total_s - done[0], 0.0))
        # the joined excitation is the start of the joined whole; the hold before the
        # validation's first piece begins the validation
        both = join(exc + val, dt)
        split = len(rec.t_s)
        minor = _row_of_measured(both, sum(len(p.u_V) for p in exc) + n_raster) - split
        return rec, _slice(both, split, len(both.t_s)), minor

    def _fit_later(self, axis: str, rec: Joined) -> None:
        """Start the axis's identification in the worker process (:mod:`.identify_worker`),
        handing it the recording's arrays, then write the recording: the fit runs while the
        file is written and the validation and the other axes play."""
        self.report_dir.mkdir(parents=True, exist_ok=True)
        self._start_worker()
        self._worker.submit(axis, self.kind, self.csv_path(axis), self.params, rec.columns())
        write_csv(self.csv_path(axis), rec.columns())    # the same values, while the fit runs
        self.fitting.append(axis)      # written whole: a stop from here on keeps this file

    def _start_worker(self) -> None:
        from .identify_worker import IdentifyWorker
        if self._worker is None:
            self._worker = IdentifyWorker()

    def _close_worker(self) -> None:
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def _keep_partial(self, run: CalibrationRun) -> None:
        """Write what was recorded so far as CSV (``...-partial.csv``), one file per play."""
        for what, pieces in run.pieces.items():
            if not pieces:
                continue
            axis = what.split()[-1]
            if what == f"excite {axis}" and axis in self.fitting:
                self.partial.append(self.csv_path(axis))        # recorded whole, written already
                continue
            path = self.csv_path(axis, f"{what.split()[0]}-partial")
            self.report_dir.mkdir(parents=True, exist_ok=True)
            write_csv(path, join(pieces, run.dt_s).columns())
            self.partial.append(path)

    def _write_validations(self, joined: dict[str, tuple[Joined, Joined, int]]) -> None:
        """Every axis's validation as CSV (its recording was written when it was recorded)."""
        for axis, (_rec, val, _minor) in joined.items():
            write_csv(self.csv_path(axis, "validation"), val.columns())

    def _identify(self, axis: str, csv: Path, rec: Joined, val: Joined, minor: int,
                  plan: PiecePlan) -> AxisCalibration:
        """The identification of the recording ``csv`` (started when it was recorded),
        validated on the second play."""
        assert self._worker is not None
        fitted = self._worker.result(axis, stop=lambda: self._stop_asked)
        return AxisCalibration(axis, fitted, csv, rec, val, validate(fitted.model, rec, val, minor), minor,
                               len(plan.bounds))

    def _model(self, results: dict[str, AxisCalibration], prov: dict[str, Any]) -> Any:
        prov = {**prov, "validation": {a: r.validation for a, r in results.items()}}
        history = {a: h for a, r in results.items() if (h := self._history(a, r)) is not None}
        if history:
            prov["history"] = history
        if len(self.config.scanner.axes) == 1:      # a one-axis scanner: its model
            model = next(iter(results.values())).identified.model
            return model.model_copy(update={"provenance": prov})
        from afmctl.compensators.scanner_model import ScannerModel
        return ScannerModel(axes={a: r.identified.model for a, r in results.items()}, provenance=prov)

    def _history(self, axis: str, result: AxisCalibration) -> dict[str, Any] | None:
        """What the calibration's plays leave in the axis model's creep stage when they end
        (None without one): its lag states [nm] at ``ended_unix_s`` (wall clock), the output
        at ``at_V``. ``afmctl learn`` on this device starts its history from them
        (:meth:`afmctl.control.learn_history.PlayTimeline.resume`): right after a
        calibration the scanner still creeps from it (86 nm at 0 V after the E-727's
        excitation, with lags up to minutes)."""
        from afmctl.compensators.base import quiet_clamps
        from afmctl.compensators.learning_history import VoltageHistory, creep_stages
        model = result.identified.model
        if creep_stages(model) is None or axis not in self.played_unix_s:
            return None
        cfg = self.config
        rate = min(float(cfg.safety.ramp_V_per_s), float(cfg.slew_V_per_s()))
        h = VoltageHistory(model, 1.0 / float(cfg.loop.rate_Hz), float(result.recording.u_V[0]), settle_s=1.0)
        with quiet_clamps(*(op for op in (h.hyst, h.creep) if op is not None)):
            h.play(result.recording.u_V)
            h.play(result.validation_record.u_V)
            safe = cfg.safety.safe_value(axis) if cfg.safety.on_finish == "safe" else h.last_V
            ramp_s = abs(h.last_V - safe) / rate
            h.hold(self.finished_unix_s - self.played_unix_s[axis] - ramp_s)
            h.ramp(safe, rate)
        state = h.creep_state()
        return {"ended_unix_s": self.finished_unix_s, "at_V": h.last_V, "creep_state_nm": state} if state else None

    def stop(self) -> None:
        """End the calibration (any thread): the piece playing stops at once, the output
        ramps to the safe value, :meth:`run` raises ``CalibrationStopped``."""
        self._stop_asked = True
        if self.run_ is not None:
            self.run_.stop()


def _row_of_measured(j: Joined, n_rows: int) -> int:
    """The joined row of recorded row ``n_rows`` (the holds between pieces skipped)."""
    measured = np.flatnonzero(j.measured)
    return int(measured[n_rows]) if n_rows < len(measured) else len(j.t_s)


def _slice(j: Joined, a: int, b: int) -> Joined:
    """Rows ``a .. b`` of ``j``, its time from 0."""
    return Joined(j.t_s[a:b] - j.t_s[a], j.u_V[a:b], j.y_nm[a:b], None if j.v_V is None else j.v_V[a:b],
                  j.measured[a:b], [(r - a, g) for r, g in j.holds if a <= r < b])


def validate(model: Any, rec: Joined, val: Joined, minor: int) -> dict[str, dict[str, float]]:
    """The model over the excitation then the validation (the hold between them included);
    its error over the validation's measured rows (less their mean: an offset is not a
    shape error), per part (``raster``: the triangles, ``minor loops`` from row ``minor``,
    ``all``), max and RMS in % of the validation's measured span [nm]."""
    from ..data.prediction import predict_nm
    u = np.concatenate([rec.u_V, val.u_V])
    t = np.arange(len(u)) * (rec.t_s[1] - rec.t_s[0])
    y_hat = predict_nm(model, t, u, "calibration")[len(rec.u_V):]
    err = val.y_nm - y_hat
    span = float(np.ptp(val.y_nm[val.measured]))
    err = err - float(np.mean(err[val.measured]))
    parts = {"raster": slice(0, minor), "minor loops": slice(minor, len(err)), "all": slice(0, len(err))}
    out: dict[str, dict[str, float]] = {}
    for name, sl in parts.items():
        e = err[sl][val.measured[sl]]
        if e.size:
            out[name] = {"max_pct": float(100 * np.max(np.abs(e)) / span),
                         "rms_pct": float(100 * np.sqrt(np.mean(e ** 2)) / span), "span_nm": span}
    return out


def calibrate(config: Any, out: str | Path | None = None, *, axes: list[str] | None = None, kind: str = "auto",
              report_dir: str | Path | None = None, excitation: dict[str, Any] | None = None,
              on_progress: Callable[[Progress], None] | None = None, **params: Any) -> Calibrated:
    """Calibrate the configured scanner on its device (module docstring; the arguments are
    :class:`Calibration`'s) and return what was done; ``afmctl calibrate`` runs this."""
    return Calibration(config, out, axes=axes, kind=kind, report_dir=report_dir, excitation=excitation,
                       on_progress=on_progress, **params).run()


__all__ = ["AxisCalibration", "Calibrated", "Calibration", "CalibrationFault", "CalibrationStopped", "calibrate",
           "excitation_spec", "validation_voltages"]
