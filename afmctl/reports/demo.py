"""``afmctl demo``: what feedforward compensation does, on the simulated scanner.

A pipeline of small steps (each one a function of a shared :class:`DemoContext`):

1. **setup** — the default simulated scanner (:func:`afmctl.sim_backend.scanner.default_scanner_config`:
   asymmetric Preisach hysteresis, creep, structural modes, x/y cross-coupling, 0–150 V)
   with the *drift scenario* on: the lab warms by ``warming_K`` during the scan and the
   scanner drifts (``compensators.drift`` "physical_tube" transfer functions, gains
   multiplied by ``drift_gain`` — an exaggerated, badly insulated scanner, so that drift is
   visible next to hysteresis);
2. **excite** — per lateral axis (the other axes at 0 V): what ``afmctl excite --kind
   static`` and ``--kind creep`` write (major loop, reversal curves, a creep staircase);
   simulated at 10 kHz and averaged to 1 kHz (a sensor's output rate);
3. **identify** — each compensator kind (``pi``, ``epi``, ``preisach``, ``bouc-wen``, and
   the chain ``preisach+creep``, :class:`afmctl.compensators.chain.ChainModel`) as
   ``afmctl identify`` fits it; the x/y cross-coupling is estimated from the same runs
   (least squares of the passive axis on the driven one); per kind, one scanner model
   file ``OUT/models/scanner_<kind>.json`` (:mod:`afmctl.compensators.scanner_model`);
   kinds not available or failing are *skipped with a message*;
4. **scan** — the 1.667 µm-period calibration grating (:class:`afmctl.sim_backend.samples.Grating2D`)
   raster-scanned at ``size``×``size`` pixels over ``scan_nm`` square, once uncompensated
   (linear calibration: what a plain AFM does) and once per identified compensator
   through :class:`afmctl.control.pipeline.CompensationPipeline` (drift prediction subtracted →
   decoupling → inverse model per axis); then the best
   compensator once more without the drift prediction (what drift correction is worth);
5. **report** — images, hysteresis loops, error histograms, drift over time (PNG) and
   ``metrics.json``: ``max_error_pct`` and ``rms_error_pct`` keyed by compensator,
   errors = |actual − commanded| lateral position over every recorded pixel (trace and
   retrace, x and y), in % of the scan range ``scan_nm``.

Everything is simulated in-process, faster than real time; nothing is sent anywhere.
"""
from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AfmctlError

log = logging.getLogger(__name__)

#: compensator kinds the demo tries, in this order (model KINDS names)
DEFAULT_COMPENSATORS = ("pi", "epi", "preisach", "bouc-wen", "preisach+creep", "preisach+creep+dynamics")
LATERAL = ("x", "y")


@dataclass
class DemoOptions:
    """Knobs of the demo (defaults: the README's run)."""

    out: Path
    size: int = 256                  #: pixels per side
    scan_nm: float = 10_000.0        #: scan range (side of the square) [nm]
    origin_nm: float = 750.0         #: lower-left corner of the scan [nm] (x and y)
    line_rate_Hz: float = 5.0        #: lines per second (trace + retrace)
    samples_per_pixel: int | None = None  #: None: enough that the sample period is ≤ 0.2 ms
    warming_K: float = 3.0           #: ambient temperature rise during the scan [K]
    drift_gain: float = 60.0         #: multiplier on the physical-tube drift gains
    drift: bool = True               #: the drift scenario on/off
    compensators: tuple[str, ...] = DEFAULT_COMPENSATORS
    quick: bool = False              #: shorter excitation (for tests)
    seed: int = 0
    docs_dir: Path | None = None     #: also copy the PNGs here as demo_*.png
    speed_ladder: bool = True        #: the speed ladder (afmctl.reports.speed_ladder) in metrics.json
    ladder_controller: bool = True   #: its rows through the real Controller (50 lines/s as a wave)

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if not 8 <= self.size <= 1024:
            raise AfmctlError(f"--size: {self.size} pixels; allowed 8..1024")
        if not (math.isfinite(self.scan_nm) and 100.0 <= self.scan_nm <= 11_000.0):
            raise AfmctlError(f"scan_nm: {self.scan_nm:g} nm; allowed 100..11000")
        if not (math.isfinite(self.line_rate_Hz) and 0.1 <= self.line_rate_Hz <= 50.0):
            raise AfmctlError(f"--line-rate: {self.line_rate_Hz:g} Hz; allowed 0.1..50")
        if self.samples_per_pixel is None:
            # keep the simulation period ≤ 0.2 ms: far above the 1 kHz structural mode
            self.samples_per_pixel = max(2, math.ceil(1.0 / (2.0 * self.line_rate_Hz * self.size * 2e-4)))

    @property
    def pixel_samples(self) -> int:
        """Samples per pixel (``samples_per_pixel``, chosen in ``__post_init__`` when None)."""
        assert self.samples_per_pixel is not None
        return self.samples_per_pixel


@dataclass
class ScanResult:
    name: str
    image: Any                        # sim_backend.imaging.ScanImage ("none" keeps its signals)
    err_nm: np.ndarray                # (rows, 2 passes, cols, 2 axes) actual − commanded
    drift_pred_nm: np.ndarray | None = None  # (N, 3) per sample, if predicted


@dataclass
class DemoContext:
    options: DemoOptions
    scanner_config: Any = None
    drift_params: Any = None
    excitation: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    dyn_excitation: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    coupling: np.ndarray = field(default_factory=lambda: np.eye(3))
    models: dict[str, Any] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    scans: dict[str, ScanResult] = field(default_factory=dict)
    true_drift_nm: np.ndarray | None = None
    files: list[Path] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    drift_effect: dict[str, Any] | None = None
    speed_ladder: dict[str, Any] | None = None
    messages: list[str] = field(default_factory=list)

    def note(self, text: str) -> None:
        log.info(text)
        self.messages.append(text)

    def scan_T(self) -> Callable[[np.ndarray], np.ndarray] | None:
        """Ambient temperature [°C] as a function of the time since the scan start [s]
        (the drift scenario: a linear rise by ``warming_K`` over the scan); None without
        the drift scenario."""
        o = self.options
        if self.drift_params is None:
            return None
        T0 = float(self.scanner_config.ambient_T_C)
        total = o.size / o.line_rate_Hz
        return lambda t: T0 + o.warming_K * np.clip(np.asarray(t) / total, 0.0, 1.0)


@dataclass
class Step:
    name: str
    run: Callable[[DemoContext], None]


# --------------------------------------------------------------------------- steps
def _new_scanner(ctx: DemoContext, drift: bool) -> Any:
    from afmctl.sim_backend.scanner import DriftConfig, Scanner
    cfg = ctx.scanner_config
    if drift and ctx.drift_params is not None:
        cfg = cfg.model_copy(update={"drift": DriftConfig(kind="params", params=ctx.drift_params.model_dump(mode="json"))})
    else:
        cfg = cfg.model_copy(update={"drift": DriftConfig(kind="none")})
    return Scanner(cfg)


def step_setup(ctx: DemoContext) -> None:
    from afmctl.sim_backend.scanner import default_scanner_config
    o = ctx.options
    ctx.scanner_config = default_scanner_config().model_copy(update={"seed": o.seed})
    if o.drift:
        from afmctl.compensators.drift import DriftParams
        ctx.drift_params = DriftParams.named("physical_tube").scaled(o.drift_gain)
    try:
        o.out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise AfmctlError(f"--out {o.out}: cannot create the output directory ({err.strerror})") from None


def excitation_voltage(dt_s: float, quick: bool) -> np.ndarray:
    """The identification input [V]: what ``afmctl excite --kind static`` and ``--kind creep``
    write (major loop and first-order reversal curves at 150 V/s, then a staircase with
    dwells), joined by a 1 s hold — the product's excitation (``--quick``: 6 reversal curves
    each way and 1 s dwells instead of 12 and 2 s)."""
    from ..data.excitation import ExcitationSpec, concatenate, creep, static
    spec = ExcitationSpec(u_min_V=0.0, u_max_V=150.0, rate_Hz=1.0 / dt_s, dwell_s=1.0 if quick else 2.0)
    return concatenate([static(spec, n_reversals=6 if quick else 12), creep(spec)], spec)


#: identification data: simulated at 10 kHz, averaged over 1 ms (what a sensor with a 1 kHz
#: output rate reports) — the mean over one period of the 1 kHz structural mode removes its
#: ringing instead of aliasing it
EXCITE_SIM_DT_S, EXCITE_DECIMATE = 1e-4, 10


def step_excite(ctx: DemoContext) -> None:
    dt, m = EXCITE_SIM_DT_S, EXCITE_DECIMATE
    u1 = excitation_voltage(dt * m, ctx.options.quick)
    u_fine = np.repeat(u1, m)                      # each 1 ms value held for 10 samples
    for i, axis in enumerate(LATERAL):
        scanner = _new_scanner(ctx, drift=False)
        u = np.zeros((u_fine.size, 3))
        u[:, i] = u_fine
        pos = scanner.run(u, dt).reshape(u1.size, m, 3).mean(axis=1)
        ctx.excitation[axis] = {"t_s": np.arange(u1.size) * dt * m, "u_V": u1.copy(), "y_nm": pos[:, i].copy(),
                                "other_nm": pos[:, 1 - i].copy()}
    # cross-coupling: passive-axis motion per driven-axis motion (both start at 0 V / 0 nm)
    C = np.eye(3)
    for i, axis in enumerate(LATERAL):
        e = ctx.excitation[axis]
        y, o = e["y_nm"] - e["y_nm"][0], e["other_nm"] - e["other_nm"][0]
        C[1 - i, i] = float(np.dot(y, o) / max(np.dot(y, y), 1e-12))
    ctx.coupling = C
    ctx.note(f"cross-coupling estimated: x←y {C[0, 1]:.4f}, y←x {C[1, 0]:.4f}")


def identify_axis(kind: str, t_s: np.ndarray, u_V: np.ndarray, y_nm: np.ndarray, dyn: dict[str, np.ndarray] | None = None,
                  static: Any = None) -> Any:
    """One axis's model of ``kind``: a single kind (``pi``, ``preisach``, …) or a chain
    (``preisach+creep``, …; :class:`afmctl.compensators.chain.ChainModel`) — what
    ``afmctl identify --model KIND`` fits. A ``+dynamics`` chain takes its static stages
    from ``static`` (the same chain without dynamics, already identified) or fits them on
    ``t_s, u_V, y_nm``, and its dynamics on the small-signal record ``dyn`` (t_s, u_V,
    y_nm at the simulator's rate) driven through those static stages."""
    from afmctl.compensators.models import model_class
    if "+" not in kind:
        return model_class(kind).identify(t_s, u_V, y_nm)
    from afmctl.compensators.chain import ChainModel
    if not kind.endswith("+dynamics"):
        return ChainModel.identify(t_s, u_V, y_nm, structure=kind)
    if dyn is None:
        raise AfmctlError(f"compensator {kind!r}: no small-signal excitation recorded")
    if static is None:
        static = identify_axis(kind[:-len("+dynamics")], t_s, u_V, y_nm)
    dt = float(dyn["t_s"][1] - dyn["t_s"][0])
    x = static.forward(dt).block(np.ascontiguousarray(dyn["u_V"]))
    dynamics = model_class("dynamics").identify(dyn["t_s"], x, dyn["y_nm"])
    return ChainModel(hysteresis=static.hysteresis, creep=static.creep, dynamics=dynamics)


def _check_kind(kind: str) -> None:
    """Raise for a kind (or chain) this installation does not know."""
    from afmctl.compensators.models import model_class
    if "+" in kind:
        from afmctl.compensators.chain import parse_structure
        base, stages = parse_structure(kind)
        for k in (base, *stages):
            model_class(k)
    else:
        model_class(kind)


def make_identify_step(kind: str) -> Step:
    """Identify ``kind`` on x and y, combine with the coupling into a scanner model file
    (``OUT/models/scanner_<kind>.json``, loadable by ``afmctl run`` as
    ``[compensation] scanner_model``)."""
    def run(ctx: DemoContext) -> None:
        from afmctl.compensators.fit_health import fit_problems
        from afmctl.compensators.models import save_model
        from afmctl.compensators.scanner_model import ScannerModel
        try:
            _check_kind(kind)
        except Exception as err:  # unknown kind
            ctx.skipped[kind] = " ".join(str(err).split())
            return
        models = {}
        for axis in LATERAL:
            e = ctx.excitation[axis]
            try:
                static = ctx.models.get(kind.removesuffix("+dynamics"))
                models[axis] = identify_axis(kind, e["t_s"], e["u_V"], e["y_nm"], ctx.dyn_excitation.get(axis),
                                             static.axis(axis) if static is not None and kind.endswith("+dynamics")
                                             else None)
                models[axis].inverse(1e-4).reset()   # can it be inverted at all?
                problems = fit_problems(models[axis])
                if problems:      # a failed fit is never used (compensators/fit_health.py)
                    ctx.skipped[kind] = f"{axis} axis: the fit failed: {'; '.join(problems)}"
                    return
            except NotImplementedError:
                ctx.skipped[kind] = "identify() not implemented yet"
                return
            except Exception as err:  # ModelError etc.: report, keep the demo going
                ctx.skipped[kind] = f"{axis} axis: {' '.join(str(err).split())}"
                log.warning("demo: %s skipped: %s", kind, ctx.skipped[kind])
                return
        scanner = ScannerModel(axes={"x": models["x"], "y": models["y"], "z": None}, coupling=ctx.coupling.tolist())
        folder = ctx.options.out / "models"
        folder.mkdir(exist_ok=True)
        path = folder / f"scanner_{kind}.json"
        save_model(scanner, path)
        ctx.files.append(path)
        ctx.models[kind] = scanner
    return Step(f"identify {kind}", run)


def _scan(ctx: DemoContext, name: str, compensator: Any, drift: bool = True) -> Any:
    from afmctl.sim_backend.imaging import raster_image
    from afmctl.sim_backend.samples import Grating2D
    o = ctx.options
    scanner = _new_scanner(ctx, drift=drift)
    return raster_image(scanner, Grating2D(period_nm=1667.0), scan_size_nm=o.scan_nm, pixels=o.size,
                        line_rate_Hz=o.line_rate_Hz, origin_nm=(o.origin_nm, o.origin_nm),
                        samples_per_pixel=o.pixel_samples, compensator=compensator,
                        T_C=ctx.scan_T() if drift else None, settle_lines=1, keep_signals=(name == "none"))


def _errors(image: Any) -> np.ndarray:
    """(rows, 2, cols, 2): actual − commanded lateral position per pixel, trace/retrace, x/y."""
    xt, yt = image.x_target_nm[None, :], image.y_target_nm[:, None]
    ex = np.stack([image.x_trace_nm - xt, image.x_retrace_nm - xt], axis=1)
    ey = np.stack([image.y_trace_nm - yt, image.y_retrace_nm - yt], axis=1)
    return np.stack([ex, ey], axis=-1)


def step_scan_uncompensated(ctx: DemoContext) -> None:
    img = _scan(ctx, "none", None)
    ctx.scans["none"] = ScanResult("none", img, _errors(img))
    if ctx.drift_params is not None:
        # the same voltages without drift: the difference is the true drift
        scanner = _new_scanner(ctx, drift=False)
        dt = float(img.signals["t_s"][1] - img.signals["t_s"][0])
        pos0 = scanner.run(img.signals["u_V"], dt)
        ctx.true_drift_nm = img.signals["position_nm"] - pos0


def step_excite_dynamics(ctx: DemoContext) -> None:
    """Per lateral axis, the small-signal multisine of ``afmctl excite --kind dynamics``
    around mid-range, recorded at the simulator's 10 kHz (no averaging: the structural
    mode must stay in the data)."""
    from ..data.excitation import ExcitationSpec, excitation
    dt = EXCITE_SIM_DT_S
    u1 = excitation("dynamics", ExcitationSpec(u_min_V=0.0, u_max_V=150.0, rate_Hz=1.0 / dt,
                                               periods=4 if ctx.options.quick else 8))
    for i, axis in enumerate(LATERAL):
        u = np.zeros((u1.size, 3))
        u[:, i] = u1
        pos = _new_scanner(ctx, drift=False).run(u, dt)
        ctx.dyn_excitation[axis] = {"t_s": np.arange(u1.size) * dt, "u_V": u1.copy(), "y_nm": pos[:, i].copy()}


class PipelineCompensator:
    """Targets (N, 3) nm → voltages (N, 3) V for one scan through the product's
    :class:`afmctl.control.pipeline.CompensationPipeline` (drift prediction subtracted, x/y
    decoupled with the scanner model's ``C⁻¹``, each axis's inverse model; z and axes
    without a model: the linear calibration). The heat input of the drift predictor is
    the nominal voltage of each target (offline, :meth:`CompensationPipeline.block`)."""

    def __init__(self, pipeline: Any, dt_s: float, gain_nm_per_V: np.ndarray,
                 T_of_t: Callable[[np.ndarray], np.ndarray] | None = None, t0_s: float = 0.0,
                 T_const_C: float = 22.0) -> None:
        self.pipeline = pipeline
        self.dt_s = dt_s
        self.gain = gain_nm_per_V
        self.T_of_t = T_of_t
        self.t0_s = t0_s
        self.T_const_C = T_const_C
        self.drift_pred_nm: np.ndarray | None = None

    def __call__(self, targets: np.ndarray) -> np.ndarray:
        r = np.asarray(targets, dtype=np.float64)
        if self.T_of_t is not None:
            t = self.t0_s + np.arange(r.shape[0]) * self.dt_s
            T = self.T_of_t(np.maximum(t, 0.0))
        else:
            T = np.full(r.shape[0], self.T_const_C)
        self.pipeline.reset()
        d, _, u = self.pipeline.block(r, T, np.clip(r / self.gain, 0.0, 150.0), preview=True)
        self.drift_pred_nm = d if self.pipeline.drift is not None else None
        return u


def scan_pipeline(ctx: DemoContext, kind: str, dt_s: float, drift: bool) -> Any:
    """The product's pipeline for the scanner model of ``kind`` (``none``: the linear
    calibration only) at sample period ``dt_s`` [s]. An axis whose model has a dynamics
    stage inverts each whole scan offline within the simulated amplifier's range and slew
    limit, ramping from the voltage the scanner rests at (:func:`afmctl.control.pipeline.offline_inverse`)."""
    from ..control.pipeline import CompensationPipeline, LinearAxis, offline_inverse
    sim = _new_scanner(ctx, drift=False)
    gain, limits, rest = sim.nominal_gain_nm_per_V(), sim.voltage_limits_V(), sim.held_voltage_V()
    scanner = ctx.models.get(kind)
    inverses, offline = [], []
    for i, axis in enumerate(("x", "y", "z")):
        m = scanner.axis(axis) if scanner is not None else None
        inverses.append(m.inverse(dt_s) if m is not None else LinearAxis(float(gain[i])))
        slew = getattr(ctx.scanner_config, axis).amplifier.effective_slew_V_per_s()
        offline.append(None if m is None else
                       offline_inverse(m, dt_s, float(limits[i, 0]), float(limits[i, 1]), slew, float(rest[i])))
    predictor = ctx.drift_params.predictor(dt_s) if (drift and ctx.drift_params is not None) else None
    inv_c = scanner.inverse_coupling() if scanner is not None else None
    return CompensationPipeline(inverses, predictor, inv_coupling=inv_c, offline=offline)


def _compensator(ctx: DemoContext, kind: str, drift: bool = True) -> PipelineCompensator:
    """The compensator of ``kind`` for one scan (with or without the drift prediction);
    its time origin is the scan's, after the one settling line."""
    o = ctx.options
    ns = o.size * o.pixel_samples
    dt = 1.0 / (2.0 * o.line_rate_Hz * ns)
    gain = _new_scanner(ctx, drift=False).nominal_gain_nm_per_V()
    pipe = scan_pipeline(ctx, kind, dt, drift)
    if drift and ctx.drift_params is not None:
        return PipelineCompensator(pipe, dt, gain, ctx.scan_T(), t0_s=-2 * ns * dt)
    return PipelineCompensator(pipe, dt, gain)


def make_scan_step(kind: str) -> Step:
    def run(ctx: DemoContext) -> None:
        if kind not in ctx.models:
            return
        comp = _compensator(ctx, kind)
        try:
            img = _scan(ctx, kind, comp)
        except Exception as err:  # a compensator failing mid-scan: report, keep going
            ctx.skipped[kind] = f"scan failed: {' '.join(str(err).split())}"
            log.warning("demo: %s skipped: %s", kind, ctx.skipped[kind])
            return
        ctx.scans[kind] = ScanResult(kind, img, _errors(img), comp.drift_pred_nm)
    return Step(f"scan {kind}", run)


def _max_pct(ctx: DemoContext, err_nm: np.ndarray) -> float:
    """Largest |error| over all pixels, passes and axes [% of the scan range]."""
    return round(float(np.max(np.abs(err_nm))) / ctx.options.scan_nm * 100.0, 4)


def _rms_pct(ctx: DemoContext, err_nm: np.ndarray) -> float:
    """Root mean square error over all pixels, passes and axes [% of the scan range]."""
    return round(float(np.sqrt(np.mean(err_nm ** 2))) / ctx.options.scan_nm * 100.0, 4)


def step_drift_effect(ctx: DemoContext) -> None:
    """The best compensator once more with the drift correction switched off: what the
    drift prediction is worth in this scenario."""
    compensated = {k: _max_pct(ctx, r.err_nm) for k, r in ctx.scans.items() if k != "none"}
    if ctx.drift_params is None or not compensated:
        return
    best = min(compensated, key=lambda k: compensated[k])
    img = _scan(ctx, best, _compensator(ctx, best, drift=False))
    ctx.drift_effect = {"compensator": best, "max_error_pct_with_drift_correction": compensated[best],
                        "max_error_pct_without_drift_correction": _max_pct(ctx, _errors(img))}


def ladder_compensators(ctx: DemoContext) -> dict[str, str | None]:
    """``{"none": None, "static": kind, "chain": kind, "chain+dynamics": kind}`` for the
    speed ladder: the static model (preisach if identified, else the first single kind),
    the chain (preisach+creep if identified, else the first chain without dynamics) and the
    first chain with dynamics; missing ones are left out."""
    out: dict[str, str | None] = {"none": None}
    single = [k for k in ctx.models if "+" not in k]
    chains = [k for k in ctx.models if "+" in k and not k.endswith("+dynamics")]
    dyn = [k for k in ctx.models if k.endswith("+dynamics")]
    if single:
        out["static"] = "preisach" if "preisach" in single else single[0]
    if chains:
        out["chain"] = "preisach+creep" if "preisach+creep" in chains else chains[0]
    if dyn:
        out["chain+dynamics"] = dyn[0]
    return out


def _ladder_cell(ctx: DemoContext, kind: str | None, rate: float, folder: Path, scanner_json: Path) -> dict[str, Any]:
    from . import speed_ladder as sl
    o = ctx.options
    rates = sl.PREVIEW_RATE_HZ if kind is not None and kind.endswith("+dynamics") else sl.CONTROLLER_RATE_HZ
    loop_Hz = rates.get(rate) if o.ladder_controller else None
    wave = ""
    if loop_Hz is None and o.ladder_controller and rate in sl.WAVE_RATE_HZ:
        loop_Hz, wave = sl.WAVE_RATE_HZ[rate], sl.WAVE_FD_TOML   # device-timed: computed whole, played by the amplifier
    if loop_Hz is not None:
        gain = _new_scanner(ctx, drift=False).nominal_gain_nm_per_V()
        model = folder.parent / "models" / f"scanner_{kind}.json" if kind else None
        err, info = sl.controller_errors_nm(folder, scanner_json, model, rate, loop_Hz, gain.tolist(),
                                            lines=2 if not wave else 4, amplifier_toml=wave)   # first line settles
        return {**sl.error_pct(err), "path": "controller", **info}
    name = kind or "none"

    def make(dt: float) -> PipelineCompensator:
        return PipelineCompensator(scan_pipeline(ctx, name, dt, drift=False), dt,
                                   _new_scanner(ctx, drift=False).nominal_gain_nm_per_V())
    err = sl.offline_errors_nm(lambda: _new_scanner(ctx, drift=False), make, rate, lines=2 if o.quick else 4)
    return {**sl.error_pct(err), "path": "offline"}


def step_speed_ladder(ctx: DemoContext) -> None:
    """Raster-line accuracy at 1, 4, 16 and 50 lines/s for none, the static model and the
    chain (:mod:`afmctl.reports.speed_ladder`); ``ctx.speed_ladder[rate][label]``."""
    from . import speed_ladder as sl
    from afmctl.sim_backend.scanner import DriftConfig
    folder = ctx.options.out / "ladder"
    folder.mkdir(exist_ok=True)
    scanner_json = sl.write_scanner_json(ctx.scanner_config.model_copy(update={"drift": DriftConfig(kind="none")}),
                                         folder / "scanner.json")
    comps = ladder_compensators(ctx)
    table: dict[str, Any] = {}
    for rate in sl.LINE_RATES_HZ:
        row = {}
        for label, kind in comps.items():
            try:
                row[label] = {"model": kind or "linear calibration", **_ladder_cell(ctx, kind, rate, folder, scanner_json)}
            except Exception as err:  # report, keep the demo going
                row[label] = {"model": kind, "error": " ".join(str(err).split())}
                log.warning("speed ladder %g lines/s %s: %s", rate, label, row[label]["error"])
        table[f"{rate:g}"] = row
        ctx.note(f"speed ladder {rate:g} lines/s: " + ", ".join(
            f"{k} {v.get('max_error_pct', float('nan')):.2f} % max" for k, v in row.items()))
    ctx.speed_ladder = table


def step_metrics(ctx: DemoContext) -> None:
    o = ctx.options
    max_pct = {name: _max_pct(ctx, res.err_nm) for name, res in ctx.scans.items()}
    rms_pct = {name: _rms_pct(ctx, res.err_nm) for name, res in ctx.scans.items()}
    compensated = {k: v for k, v in max_pct.items() if k != "none"}
    best = min(compensated, key=lambda k: compensated[k]) if compensated else None
    ctx.metrics = {
        "max_error_pct": max_pct,
        "rms_error_pct": rms_pct,
        "best": best,
        "improvement_max": (round(max_pct["none"] / max_pct[best], 2) if best and max_pct[best] > 0 else None),
        "skipped": dict(ctx.skipped),
        "scan": {"size_px": o.size, "range_nm": o.scan_nm, "origin_nm": o.origin_nm, "line_rate_Hz": o.line_rate_Hz,
                 "samples_per_pixel": o.pixel_samples, "sample": "grating-2d, 1667 nm period, 100 nm steps"},
        "drift": ({"warming_K": o.warming_K, "model": "physical_tube", "gain": o.drift_gain,
                   "max_true_drift_nm": (round(float(np.max(np.abs(ctx.true_drift_nm[:, :2]))), 3)
                                         if ctx.true_drift_nm is not None else None)}
                  if ctx.drift_params is not None else None),
        "drift_effect": ctx.drift_effect,
        "speed_ladder": ctx.speed_ladder,
        "coupling": {"x_from_y": round(float(ctx.coupling[0, 1]), 6), "y_from_x": round(float(ctx.coupling[1, 0]), 6)},
        "error_definition": "|actual - commanded| lateral position (x and y) over every recorded pixel, "
                            "trace and retrace, in % of the scan range",
        "timings_s": {k: round(v, 3) for k, v in ctx.timings_s.items()},
    }
    path = o.out / "metrics.json"
    path.write_text(json.dumps(ctx.metrics, indent=2) + "\n", encoding="utf-8")
    ctx.files.append(path)


def step_plots(ctx: DemoContext) -> None:
    from . import report
    o = ctx.options
    ctx.files += report.demo_figures(ctx, o.out)


def build_steps(options: DemoOptions) -> list[Step]:
    steps = [Step("setup", step_setup), Step("excite", step_excite)]
    if any(k.endswith("+dynamics") for k in options.compensators):
        steps += [Step("excite dynamics", step_excite_dynamics)]
    steps += [make_identify_step(k) for k in options.compensators]
    steps += [Step("scan none", step_scan_uncompensated)]
    steps += [make_scan_step(k) for k in options.compensators]
    steps += [Step("drift effect", step_drift_effect)]
    if options.speed_ladder:
        steps += [Step("speed ladder", step_speed_ladder)]
    steps += [Step("metrics", step_metrics), Step("plots", step_plots)]
    return steps


def format_table(metrics: dict[str, Any]) -> str:
    """The metrics as a small text table (what ``afmctl demo`` prints)."""
    rows = [("compensator", "max error [% range]", "rms error [% range]")]
    for name, mx in metrics["max_error_pct"].items():
        rows.append((name, f"{mx:.3f}", f"{metrics['rms_error_pct'][name]:.3f}"))
    w = [max(len(r[i]) for r in rows) for i in range(3)]
    lines = [f"{r[0]:<{w[0]}}  {r[1]:>{w[1]}}  {r[2]:>{w[2]}}" for r in rows]
    lines.insert(1, "-" * len(lines[0]))
    if metrics.get("best"):
        lines.append(f"best: {metrics['best']} ({metrics['improvement_max']}x lower max error than uncompensated)")
    d = metrics.get("drift_effect")
    if d:
        lines.append(f"drift correction: {d['compensator']} max error {d['max_error_pct_with_drift_correction']:.3f} % "
                     f"with, {d['max_error_pct_without_drift_correction']:.3f} % without")
    c = metrics.get("coupling")
    if c:
        lines.append(f"cross-coupling estimated: x←y {c['x_from_y']:.4f}, y←x {c['y_from_x']:.4f}")
    for kind, why in metrics.get("skipped", {}).items():
        lines.append(f"skipped {kind}: {why}")
    if metrics.get("speed_ladder"):
        lines += ["", format_ladder(metrics["speed_ladder"])]
    return "\n".join(lines)


def format_ladder(ladder: dict[str, Any]) -> str:
    """The speed ladder as a Markdown table: max / RMS error [% of the line] over the
    central 80 % of each line, per line rate and compensator; cells marked ``(offline)``
    come from the pipeline + simulator, the others from the real controller at the output
    rate of the last column."""
    labels = list(next(iter(ladder.values())).keys())
    head = "| lines/s | " + " | ".join(f"{k} max / rms [%]" for k in labels) + " | controller output |"
    lines = [head, "|" + "---|" * (len(labels) + 2)]
    for rate, row in ladder.items():
        cells: list[str] = []
        loops: dict[str, Any] = {}
        for k in labels:
            c = row.get(k, {})
            if "max_error_pct" not in c:
                cells.append(f"failed: {c.get('error', '?')}")
                continue
            text = f"{c['max_error_pct']:.2f} / {c['rms_error_pct']:.2f}"
            if c.get("path") == "controller":
                loops.setdefault(f"{c['loop_rate_Hz']:g} Hz", []).append(k)
            else:
                text += " (offline)"
            cells.append(text)
        loop = "—" if not loops else next(iter(loops)) if len(loops) == 1 else "; ".join(
            f"{r} ({', '.join(ks)})" for r, ks in loops.items())
        lines.append(f"| {rate} | " + " | ".join(cells) + f" | {loop} |")
    return "\n".join(lines)


def run_demo(options: DemoOptions, progress: bool = True) -> DemoContext:
    """Run every step (with a tqdm bar when ``progress``); returns the context with
    ``metrics`` and ``files``."""
    from tqdm import tqdm
    ctx = DemoContext(options)
    steps = build_steps(options)
    with tqdm(total=len(steps), disable=not progress, unit="step", desc="afmctl demo") as bar:
        for step in steps:
            bar.set_postfix_str(step.name)
            t0 = time.perf_counter()
            step.run(ctx)
            ctx.timings_s[step.name] = time.perf_counter() - t0
            bar.update(1)
    if options.docs_dir is not None:
        import shutil
        options.docs_dir.mkdir(parents=True, exist_ok=True)
        for f in ctx.files:
            if f.suffix == ".png":
                shutil.copy(f, options.docs_dir / f.name)
    return ctx
