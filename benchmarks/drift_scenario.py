"""The nonlinearities paper's drift scenario in the simulator, with and without drift
compensation — writes docs/img/drift_*.png and the scenario section of docs/DRIFT.md.

Scenario (Sadeghzadeh & Korayem 2017, Sec. 4-3: "2 °C temperature change during a 10 min
scan ... maximum thermal drift error of about 3.3 nm"):

* the ambient temperature ramps by 2 K over 600 s (``TemperatureProfile(shape="ramp")``);
* the plant is ``sim_backend.scanner.Scanner`` with the linear scanner configuration
  (no hysteresis/creep/dynamics, so the error is drift only) and drift from
  ``DriftParams.named("physical_tube")`` — the same structures afmctl predicts with
  (falls back to the predictor itself as plant if the simulator cannot be imported);
* the tip rasters a 320 nm × 320 nm area of 15 nm nanoparticles at the centre of the
  range: 10 frames of 64 lines (trace + retrace, 0.94 s per line) fill the 10 minutes;
  loop rate 1 kHz;
* drift compensation subtracts the predicted drift from the target before converting
  to voltages (the linear scanner needs no hysteresis inverse); the predictor is fed the
  ambient temperature and the voltages actually commanded (second pass; the heat
  difference to the first pass is reported);
* online correction: after every frame the frame image is phase-correlated with the
  first frame (x, y) and its mean height compared (z); that measurement plus the
  correction applied during the frame is the measured drift, fused by
  :class:`afmctl.compensators.drift_kalman.DriftKalman` with the model's mean drift over the
  same frame.

Residual drift = RMS over the whole scan of (actual − target) position, relative to the
RMS without compensation, per axis.

    .venv/bin/python benchmarks/drift_scenario.py          # writes figures + docs section
"""
from __future__ import annotations

import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from afmctl.compensators.drift import DriftParams, TransferPath  # noqa: E402
from afmctl.compensators.drift_kalman import DriftKalman, KalmanParams  # noqa: E402
from afmctl.inputs.drift_images import FrameDriftMeter, ImageDriftFeeder  # noqa: E402
from afmctl.compensators.temperature import TemperatureProfile  # noqa: E402


@dataclass
class Setup:
    dt_s: float = 1e-3
    duration_s: float = 600.0
    n_frames: int = 10
    lines: int = 64
    pixels: int = 64
    scan_nm: float = 320.0
    centre_V: float = 75.0
    ramp_K: float = 2.0
    T0_C: float = 22.0
    meas_std_nm: float = 0.3
    seed: int = 0


@dataclass
class Result:
    plant: str
    t_s: np.ndarray
    T_C: np.ndarray
    errors: dict[str, np.ndarray] = field(default_factory=dict)   # case -> (N, 3) actual − target [nm]
    rms: dict[str, np.ndarray] = field(default_factory=dict)      # case -> (3,)
    max_abs: dict[str, np.ndarray] = field(default_factory=dict)
    kalman_measurements: list[dict] = field(default_factory=list)
    images: dict[str, list[np.ndarray]] = field(default_factory=dict)
    heat_pass_diff_nm: float = 0.0
    runtime_s: float = 0.0

    def ratio(self, case: str) -> np.ndarray:
        return self.rms[case] / self.rms["uncompensated"]


def perturbed(params: DriftParams, gain: float, time_constants: float) -> DriftParams:
    """A copy with every gain times ``gain`` and every time constant times ``time_constants``."""
    p = params.scaled(gain)
    for name in type(p.paths).model_fields:
        path = getattr(p.paths, name)
        if isinstance(path, TransferPath):  # discrete state-space paths keep their dynamics
            path.poles_s = [tp * time_constants for tp in path.poles_s]
            path.zeros_s = [tz * time_constants for tz in path.zeros_s]
    p.name = f"{params.name}(gain×{gain:g}, τ×{time_constants:g})"
    return p


def raster(setup: Setup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target positions (N, 3) [nm] relative to the range centre, the frame index and a
    trace mask per sample."""
    n = int(round(setup.duration_s / setup.dt_s))
    per_frame = n // setup.n_frames
    per_line = per_frame // setup.lines
    half = per_line // 2
    x_line = np.concatenate([np.linspace(-0.5, 0.5, half, endpoint=False),
                             np.linspace(0.5, -0.5, per_line - half, endpoint=False)]) * setup.scan_nm
    trace_line = np.zeros(per_line, dtype=bool)
    trace_line[:half] = True
    ys = (np.arange(setup.lines) / setup.lines - 0.5 + 0.5 / setup.lines) * setup.scan_nm
    frame_x = np.tile(x_line, setup.lines)
    frame_y = np.repeat(ys, per_line)
    frame_tr = np.tile(trace_line, setup.lines)
    r = np.zeros((n, 3))
    frame = np.full(n, -1, dtype=np.int64)
    trace = np.zeros(n, dtype=bool)
    for f in range(setup.n_frames):
        s = slice(f * per_frame, f * per_frame + frame_x.size)
        r[s, 0], r[s, 1] = frame_x, frame_y
        frame[s] = f
        trace[s] = frame_tr
    # samples after the last full frame (rounding) hold the last position
    last = setup.n_frames * per_frame - (per_frame - frame_x.size)
    if last < n:
        r[last:, :2] = r[last - 1, :2]
    return r, frame, trace


class Plant:
    """The simulated scanner (linear axes + drift from ``true_params``)."""

    def __init__(self, true_params: DriftParams, setup: Setup) -> None:
        self.setup = setup
        self.true_params = true_params
        try:
            from afmctl.sim_backend.config import DriftConfig, linear_scanner_config
            from afmctl.sim_backend.scanner import Scanner
            cfg = linear_scanner_config(ambient_T_C=setup.T0_C,
                                        drift=DriftConfig(kind="params", params=true_params.model_dump(mode="json")))
            self._scanner_cls, self._cfg = Scanner, cfg
            sc = Scanner(cfg)
            self.gain = sc.nominal_gain_nm_per_V()
            self.name = "afmctl.sim_backend.scanner.Scanner (linear axes, drift from DriftParams)"
        except Exception as err:  # pragma: no cover - fallback when the simulator is unavailable
            self._scanner_cls = None
            self.gain = np.array([80.0, 80.0, 80.0 / 6.0])
            self.name = f"own plant: DriftParams predictor + linear axes (simulator unavailable: {err})"
        self.offset_nm = self.gain * setup.centre_V

    def start(self) -> None:
        """A fresh scanner at rest (t = 0); :meth:`cont` then continues it."""
        if self._scanner_cls is not None:
            self._sc = self._scanner_cls(self._cfg)
        else:  # pragma: no cover
            self._pred = self.true_params.predictor(self.setup.dt_s)
            self._pred.reset(self.setup.T0_C)

    def cont(self, u_V: np.ndarray, T_C: np.ndarray) -> np.ndarray:
        """Continue the scan: true tip positions (N, 3) [nm] relative to the range centre."""
        if self._scanner_cls is not None:
            pos = self._sc.run(u_V, self.setup.dt_s, T_C=T_C)
        else:  # pragma: no cover
            pos = u_V * self.gain + self._pred.block(T_C, u_V)
        return pos - self.offset_nm

    def run(self, u_V: np.ndarray, T_C: np.ndarray) -> np.ndarray:
        """A whole scan from rest."""
        self.start()
        return self.cont(u_V, T_C)


class _Spheres:
    """Fallback sample (spheres on a flat substrate) if sim_backend.samples is missing."""

    name = "spheres"

    def __init__(self, centres_nm: np.ndarray, diameters_nm: np.ndarray) -> None:
        self.centres_nm, self.diameters_nm = centres_nm, diameters_nm

    def height_nm(self, x_nm: np.ndarray, y_nm: np.ndarray) -> np.ndarray:
        h = np.zeros(np.broadcast(x_nm, y_nm).shape)
        for (cx, cy), d in zip(self.centres_nm, self.diameters_nm):
            r = 0.5 * d
            d2 = (x_nm - cx) ** 2 + (y_nm - cy) ** 2
            inside = d2 < r * r
            h[inside] = np.maximum(h[inside], r + np.sqrt(r * r - d2[inside]))
        return h


def _particles(setup: Setup):
    """60 particles of 15 nm (±30 %) over 1.3× the scan area, centred on the scan."""
    rng = np.random.default_rng(setup.seed)
    side = setup.scan_nm * 1.3
    centres = rng.uniform((0.0, 0.0), (side, side), size=(60, 2)) - side / 2
    diameters = 15.0 * (1.0 + 0.3 * rng.uniform(-1.0, 1.0, 60))
    try:
        from afmctl.sim_backend.samples import Nanoparticles
        return Nanoparticles(centres, diameters)
    except Exception:  # pragma: no cover - fallback when the simulator is unavailable
        return _Spheres(centres, diameters)


def _image(sample, pos: np.ndarray, frame: np.ndarray, trace: np.ndarray, f: int, setup: Setup,
           rng: np.random.Generator) -> np.ndarray:
    """Trace image of frame ``f``: heights at the ACTUAL positions, averaged per pixel of
    the TARGET raster (what the AFM believes)."""
    idx = np.flatnonzero((frame == f) & trace)
    per_line = idx.size // setup.lines
    idx = idx[: per_line * setup.lines]
    h = sample.height_nm(pos[idx, 0], pos[idx, 1]) + pos[idx, 2]
    h = h.reshape(setup.lines, per_line)
    edges = np.linspace(0, per_line, setup.pixels + 1).astype(int)
    img = np.add.reduceat(h, edges[:-1], axis=1) / np.diff(edges)
    return img + rng.normal(0.0, 0.05, img.shape)


def run_scenario(setup: Setup | None = None, true_params: DriftParams | None = None,
                 model_error: float = 0.3) -> Result:
    setup = setup or Setup()
    t0 = time.perf_counter()
    true_params = true_params or DriftParams.named("physical_tube")
    plant = Plant(true_params, setup)
    r, frame, trace = raster(setup)
    n = r.shape[0]
    t = np.arange(n) * setup.dt_s
    T = TemperatureProfile(shape="ramp", T0_C=setup.T0_C, delta_K=setup.ramp_K,
                           duration_s=setup.duration_s).at(t)
    gain, off = plant.gain, plant.offset_nm

    def volts(target: np.ndarray) -> np.ndarray:
        return (target + off) / gain

    res = Result(plant=plant.name, t_s=t, T_C=T)
    rng = np.random.default_rng(setup.seed)
    sample = _particles(setup)

    def predicted(params: DriftParams, u: np.ndarray) -> np.ndarray:
        p = params.predictor(setup.dt_s)
        p.reset(setup.T0_C)
        return p.block(T, u)

    # 1. uncompensated
    u0 = volts(r)
    res.errors["uncompensated"] = plant.run(u0, T) - r
    # 2. prediction with the true parameters (second pass: heat from the corrected voltages)
    d1 = predicted(true_params, u0)
    u1 = volts(r - d1)
    d2 = predicted(true_params, u1)
    res.heat_pass_diff_nm = float(np.max(np.abs(d2 - d1)))
    res.errors["predicted (true params)"] = plant.run(volts(r - d2), T) - r
    # 3. parameters 30 % off, no measurement
    wrong = perturbed(true_params, 1.0 + model_error, 1.0 - model_error)
    dw = predicted(wrong, volts(r - predicted(wrong, u0)))
    res.errors[f"predicted (params {model_error:.0%} off)"] = plant.run(volts(r - dw), T) - r
    # 4. parameters 30 % off + Kalman, one measurement per frame. The model drift dw is
    #    the same as in case 3 (its heat input differs from the final voltages by the
    #    bias correction only, < 0.02 V); the Kalman bias is extrapolated with its rate
    #    through each frame (no measurement arrives inside a frame, so that is exactly
    #    what per-sample predict() calls would give) and updated after the frame.
    kf = DriftKalman(setup.dt_s, KalmanParams(bias_std0_nm=5.0, rate_std0_nm_per_s=0.02,
                                              q_bias_nm2_per_s=1e-4, q_rate_nm2_per_s3=1e-8))
    corr = np.empty((n, 3))
    frame_len = int(np.sum(frame == 0))
    bounds = [(f * frame_len, (f + 1) * frame_len) for f in range(setup.n_frames)]
    bounds[-1] = (bounds[-1][0], n)
    images: list[np.ndarray] = []
    px, py = setup.scan_nm / setup.pixels, setup.scan_nm / setup.lines
    pos = np.empty((n, 3))
    plant.start()
    # the product's glue (afmctl.inputs.drift_images): frame f against frame 0 by phase correlation,
    # plus the change of the mean correction applied during the frames (the image shows the
    # residual drift), compared with the model's m_f − m_0 (the bias at frame 0 is taken as 0)
    masks: list[np.ndarray] = []
    submitted: list[list[float]] = []

    def submit(z: np.ndarray, t_meas: float) -> None:
        z = z.copy()
        z[2] = float(np.mean(images[-1] - images[0])) + corr[masks[-1], 2].mean() - corr[masks[0], 2].mean()
        model_rel = dw[masks[-1]].mean(axis=0) - dw[masks[0]].mean(axis=0)
        kf.update(z, setup.meas_std_nm, model_drift_nm=model_rel, age_s=float(t_end - t_meas))
        submitted.append(z.tolist())

    feeder = ImageDriftFeeder(FrameDriftMeter((py, px), upsample=200, reference="first"), submit)
    for f, (a, b) in enumerate(bounds):
        corr[a:b] = dw[a:b] + _bias_path(kf, t[a:b] - t[a])
        kf.predict(dw[b - 1], dt_s=(b - a) * setup.dt_s)
        pos[a:b] = plant.cont(volts(r[a:b] - corr[a:b]), T[a:b])
        img = _image(sample, pos[:b], frame[:b], trace[:b], f, setup, rng)
        images.append(img)
        masks.append(np.flatnonzero((frame[:b] == f) & trace[:b]))
        t_end = float(t[b - 1])
        feeder.feed(img, float(t[masks[-1]].mean()), corr[masks[-1], :2].mean(axis=0))
        if f == 0:
            continue
        mask, mask0 = masks[-1], masks[0]
        true_mean = (pos[mask] - r[mask] + corr[mask]).mean(axis=0) - (pos[mask0] - r[mask0] + corr[mask0]).mean(axis=0)
        res.kalman_measurements.append({"frame": f, "t_s": t_end, "measured_nm": submitted[-1],
                                        "true_mean_nm": true_mean.tolist(),
                                        "bias_nm": kf.bias_nm.tolist(), "std_nm": kf.std_nm.tolist()})
    res.errors[f"params {model_error:.0%} off + Kalman (1 meas./frame)"] = pos - r
    res.images["kalman"] = images
    pos_u = res.errors["uncompensated"] + r
    res.images["uncompensated"] = [_image(sample, pos_u, frame, trace, f, setup, rng) for f in (0, setup.n_frames - 1)]
    for case, e in res.errors.items():
        res.rms[case] = np.sqrt(np.mean(e * e, axis=0))
        res.max_abs[case] = np.max(np.abs(e), axis=0)
    res.runtime_s = time.perf_counter() - t0
    return res


def _bias_path(kf: DriftKalman, tau_s: np.ndarray) -> np.ndarray:
    """The Kalman filter's bias extrapolated over a frame with its rate (no measurement
    arrives inside a frame, so this is what per-sample predict() calls would give)."""
    return kf.bias_nm[None, :] + np.outer(tau_s, kf.rate_nm_per_s)


# --------------------------------------------------------------------------- output
def write_outputs(res: Result, setup: Setup) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img_dir = ROOT / "docs" / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    t = res.t_s
    step = max(1, t.size // 4000)
    fig, axs = plt.subplots(4, 1, sharex=True, figsize=(8, 9))
    axs[0].plot(t[::step], res.T_C[::step], color="tab:red")
    axs[0].set_ylabel("T [°C]")
    for j, ax in enumerate(axs[1:]):
        for case, e in res.errors.items():
            ax.plot(t[::step], e[::step, j], label=case, lw=1)
        ax.set_ylabel(f"{'xyz'[j]} error [nm]")
    axs[1].legend(fontsize=7, loc="upper left")
    axs[-1].set_xlabel("t [s]")
    axs[0].set_title("2 °C over a 10 min raster scan: position error (actual − target)")
    fig.tight_layout()
    fig.savefig(img_dir / "drift_scenario_errors.png", dpi=100)
    plt.close(fig)

    imgs = res.images.get("kalman", [])
    unc = res.images.get("uncompensated", [])
    if imgs and unc:
        fig, axs = plt.subplots(1, 3, figsize=(12, 3.8))
        ext = [-setup.scan_nm / 2, setup.scan_nm / 2] * 2
        h = axs[0].imshow(unc[0], origin="lower", extent=ext, cmap="viridis")
        axs[0].set_title("frame 1: height [nm]", fontsize=10)
        fig.colorbar(h, ax=axs[0])
        d_unc, d_kal = unc[1] - unc[0], imgs[-1] - imgs[0]
        z_unc, z_kal = float(d_unc.mean()), float(d_kal.mean())
        d_unc, d_kal = d_unc - z_unc, d_kal - z_kal
        lim = float(np.max(np.abs(d_unc)))
        for ax, d, title, z in ((axs[1], d_unc, "uncompensated", z_unc),
                                (axs[2], d_kal, "30 % off + Kalman", z_kal)):
            h = ax.imshow(d, origin="lower", extent=ext, cmap="RdBu_r", vmin=-lim, vmax=lim)
            ax.set_title(f"{title}: frame 10 − 1 [nm]\n(mean {z:+.2f} nm removed)", fontsize=9)
            fig.colorbar(h, ax=ax)
        for ax in axs:
            ax.set_xlabel("x target [nm]")
        axs[0].set_ylabel("y target [nm]")
        fig.tight_layout()
        fig.savefig(img_dir / "drift_scenario_images.png", dpi=100)
        plt.close(fig)

    lines = ["<!-- drift:scenario -->",
             "Generated by `.venv/bin/python benchmarks/drift_scenario.py` "
             f"(plant: {res.plant}; {t.size} samples at {1 / setup.dt_s:g} Hz, runtime {res.runtime_s:.1f} s).",
             "",
             "| case | RMS x [nm] | RMS y [nm] | RMS z [nm] | max x [nm] | max y [nm] | max z [nm] | RMS / uncompensated (x, y, z) |",
             "|---|---|---|---|---|---|---|---|"]
    for case in res.errors:
        rms, mx, ra = res.rms[case], res.max_abs[case], res.ratio(case)
        g = lambda v: f"{v:.3g}"  # noqa: E731
        lines.append(f"| {case} | {g(rms[0])} | {g(rms[1])} | {g(rms[2])} | {g(mx[0])} | {g(mx[1])} | {g(mx[2])} | "
                     + ", ".join(f"{100 * v:.3g} %" if v < 0.995 else "100 %" for v in ra) + " |")
    lines += ["", f"Heat input: the predicted drift changes by at most {res.heat_pass_diff_nm:.2e} nm between "
              "feeding the predictor the uncorrected and the corrected voltages.", "",
              "Kalman measurements (one per frame from frame 2 on; x, y by phase correlation with frame 1, "
              "z from the mean height difference):", "",
              "| frame | t [s] | measured drift change since frame 1, x, y, z [nm] | true change [nm] | bias after update [nm] | σ [nm] |",
              "|---|---|---|---|---|---|"]
    for m in res.kalman_measurements:
        f3 = lambda v: ", ".join(f"{x:.2f}" for x in v)  # noqa: E731
        lines.append(f"| {m['frame'] + 1} | {m['t_s']:.0f} | {f3(m['measured_nm'])} | {f3(m['true_mean_nm'])} | "
                     f"{f3(m['bias_nm'])} | {f3(m['std_nm'])} |")
    lines += ["", "![errors](img/drift_scenario_errors.png)", "", "![images](img/drift_scenario_images.png)",
              "<!-- /drift:scenario -->"]
    return "\n".join(lines)


def path_magnitudes(dt_s: float = 0.1, hours: float = 1.0) -> tuple[str, dict]:
    """Drift of each path of each named set 10 min and 1 h after a 1 K ambient step and
    after a 1 mW heat step (the paths' own scale, in nm), and a figure of the ambient
    step responses."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from afmctl.compensators.drift import PATH_NAMES, DriftPaths

    n = int(round(hours * 3600 / dt_s)) + 1
    t = np.arange(n) * dt_s
    i10 = int(round(600 / dt_s))
    rows = ["<!-- drift:magnitudes -->",
            "Generated by `.venv/bin/python benchmarks/drift_scenario.py`: drift of each path "
            "10 min and 1 h after a step of its source (1 K ambient, or 1 mW of heat), in nm.", "",
            "| set | path | 10 min [nm] | 1 h [nm] |", "|---|---|---|---|"]
    curves = {}
    for name in DriftParams.names():
        full = DriftParams.named(name)
        for pname in PATH_NAMES:
            path = getattr(full.paths, pname)
            if path is None:
                continue
            one = full.model_copy(deep=True)
            one.paths = DriftPaths(**{pname: path})
            T = np.full(n, 20.0)
            U = np.zeros((n, 3))
            src = pname[1:]
            if src == "T":
                T[1:] = 21.0
                d = one.predictor(dt_s).block(T, U)
                curves[(name, pname)] = d[:, "xyz".index(pname[0])]
            else:
                # a constant heat of 1 mW: bypass eq. 8 by setting S_EE so that V = 1 V gives −1 mW
                from afmctl.compensators.heat import AxisHeat, HeatParams
                one.heat = AxisHeat(**{a: HeatParams(S_EE_W_per_V2=-0.0 if a != src[1] else 1e-3) for a in "xyz"})
                U[1:, "xyz".index(src[1])] = 1.0
                d = -one.predictor(dt_s).block(T, U)
            k = "xyz".index(pname[0])
            rows.append(f"| {name} | G_{pname} | {d[i10, k]:.4g} | {d[-1, k]:.4g} |")
    rows.append("<!-- /drift:magnitudes -->")
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, name in zip(axs, DriftParams.names()):
        for (nm, pname), y in curves.items():
            if nm == name:
                ax.plot(t / 60, y, label=f"G_{pname}")
        ax.set_title(f"{name}: 1 K ambient step")
        ax.set_xlabel("t [min]")
        ax.set_ylabel("drift [nm]")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.legend(fontsize=8)
    fig.tight_layout()
    img_dir = ROOT / "docs" / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    fig.savefig(img_dir / "drift_step_responses.png", dpi=100)
    plt.close(fig)
    return "\n".join(rows), curves


def update_doc_section(section: str, tag: str = "scenario") -> None:
    doc = ROOT / "docs" / "DRIFT.md"
    body = doc.read_text(encoding="utf-8") if doc.exists() else "# Thermal drift\n"
    pat = re.compile(rf"<!-- drift:{tag} -->.*?<!-- /drift:{tag} -->", re.S)
    if pat.search(body):
        body = pat.sub(lambda _m: section, body)
    else:
        body = body.rstrip("\n") + "\n\n" + section + "\n"
    doc.write_text(body, encoding="utf-8")


def main() -> int:
    setup = Setup()
    res = run_scenario(setup)
    section = write_outputs(res, setup)
    update_doc_section(section)
    mags, _ = path_magnitudes()
    update_doc_section(mags, "magnitudes")
    print(mags)
    for case in res.errors:
        print(f"{case:45s} RMS {np.array2string(res.rms[case], precision=3)} nm  "
              f"ratio {np.array2string(res.ratio(case), precision=3)}")
    print(f"plant: {res.plant}; runtime {res.runtime_s:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
