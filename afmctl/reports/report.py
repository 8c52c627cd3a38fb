"""Plots a person can look at: for ``afmctl demo`` and for run logs (``afmctl report RUN``).

All figures are matplotlib (Agg backend, imported inside the functions), PNG, with axes in
the project's units (V, nm, s, °C, % of range).

Run-log report (:func:`run_report`), from :class:`afmctl.control.runlog.RunLogReader`:

* ``report_loops.png`` — voltage sent vs target per axis (the compensator's inverse
  hysteresis loops);
* ``report_tracking.png`` — target, corrected target and voltage over time;
* ``report_errors.png`` — histograms of the correction (corrected − target, i.e. the
  drift correction applied) and, with ``simulate=True``, of the positioning error the
  run's simulated scanner (or the default one) would make with these voltages, over the
  samples that track the trajectory (start/stop ramps excluded), in % of the target range;
* ``report_drift.png`` — drift estimate per axis and temperature over time;
* ``report_summary.json`` — counts, duration, voltage ranges, states, and the same error
  numbers; with ``simulate``, ``tracking_per_axis``: the tracking error per axis in nm and in
  % of that axis's line (or step) over the central 80 % of a raster's lines
  (:func:`afmctl.data.axis_errors.axis_errors`, as ``afmctl run`` prints it).
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AfmctlError

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")
#: the two per-sample quantities a run report shows [% of the target range]
DRIFT_CORRECTION = "drift correction"     # corrected target - target: what the drift compensation added
TRACKING_ERROR = "tracking error"         # simulated tip position - target
#: what each quantity is, for the command line
QUANTITIES = {DRIFT_CORRECTION: "corrected target - target, the drift compensation applied",
              TRACKING_ERROR: "tip position - target, the voltages replayed through the simulated scanner"}
#: colours per compensator name in every demo figure
_COLOURS = {"none": "tab:red", "pi": "tab:blue", "epi": "tab:green", "preisach": "tab:purple",
            "bouc-wen": "tab:orange", "creep": "tab:brown", "preisach+creep": "black",
            DRIFT_CORRECTION: "tab:blue", TRACKING_ERROR: "tab:red"}
_SPARE = ("tab:cyan", "tab:olive", "tab:pink", "tab:gray")


def _plt():
    from ..figures import pyplot
    return pyplot()


def _save(fig: Any, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def _colour(name: str, index: int = 0) -> str:
    """A fixed colour per known name; others get distinct spare colours by position."""
    return _COLOURS.get(name, _SPARE[index % len(_SPARE)])


# --------------------------------------------------------------------------- shared plots
def plot_error_histograms(ax: Any, errors_pct: dict[str, np.ndarray], title: str) -> None:
    """Histograms (log count) of errors [% of range], one per name."""
    finite = [np.abs(e[np.isfinite(e)]) for e in errors_pct.values() if e.size]
    if not finite:
        ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
        return
    lim = max(float(np.max(f)) if f.size else 0.0 for f in finite) or 1.0
    bins = np.linspace(-lim, lim, 121)
    for k, (name, e) in enumerate(errors_pct.items()):
        ax.hist(e.ravel(), bins=bins, histtype="step", lw=1.4, color=_colour(name, k), label=name)
    ax.set_yscale("log")
    ax.set_xlabel("error [% of range]")
    ax.set_ylabel("count")
    ax.set_title(title)
    ax.legend(fontsize=8)


# --------------------------------------------------------------------------- demo
def demo_figures(ctx: Any, out: Path) -> list[Path]:
    """All demo PNGs (``demo_images``, ``demo_hysteresis``, ``demo_errors``, ``demo_drift``,
    ``demo_lines``) from a :class:`afmctl.reports.demo.DemoContext`."""
    files = [_demo_images(ctx, out / "demo_images.png"),
             _demo_hysteresis(ctx, out / "demo_hysteresis.png"),
             _demo_errors(ctx, out / "demo_errors.png"),
             _demo_lines(ctx, out / "demo_lines.png")]
    if ctx.true_drift_nm is not None:
        files.append(_demo_drift(ctx, out / "demo_drift.png"))
    if getattr(ctx, "speed_ladder", None):
        files.append(_demo_speed_ladder(ctx.speed_ladder, out / "demo_speed_ladder.png"))
    return files


def _demo_speed_ladder(ladder: dict[str, Any], path: Path) -> Path:
    """Max and RMS error [% of the line] vs line rate, one line per compensator."""
    plt = _plt()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 4))
    rates = [float(r) for r in ladder]
    labels = list(next(iter(ladder.values())).keys())
    for i, label in enumerate(labels):
        cells = [ladder[r].get(label, {}) for r in ladder]
        mx = [c.get("max_error_pct", np.nan) for c in cells]
        rms = [c.get("rms_error_pct", np.nan) for c in cells]
        model = next((c.get("model") for c in cells if c.get("model")), label)
        a0.plot(rates, mx, marker="o", color=_colour(label, i), label=f"{label} ({model})")
        a1.plot(rates, rms, marker="o", color=_colour(label, i), label=f"{label} ({model})")
    for ax, what in ((a0, "max"), (a1, "RMS")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("line rate [lines/s]")
        ax.set_ylabel(f"{what} error [% of the line]")
        ax.axhline(1.0 if what == "max" else 0.5, color="k", ls=":", lw=0.8)
        ax.grid(alpha=0.3, which="both")
    a0.set_title("speed ladder: central 80 % of each 4 µm line")
    a1.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def _flatten_lines(img: np.ndarray) -> np.ndarray:
    """Line levelling [nm]: subtract each scan line's substrate level (its 10th percentile),
    which removes the slow z drift without the stripes a line median leaves on a grating."""
    return img - np.percentile(img, 10, axis=1, keepdims=True)


def _demo_images(ctx: Any, path: Path) -> Path:
    """Top: line-levelled trace images with the grating's true pillar centres (dashed
    lattice) — a perfect scanner puts every pillar on a crossing. Bottom: the lateral
    position error per pixel [% of range]."""
    plt = _plt()
    names = list(ctx.scans)
    n = len(names)
    fig, axs = plt.subplots(2, n, figsize=(3.0 * n + 1.0, 7.4), squeeze=False, layout="constrained")
    m = ctx.metrics.get("max_error_pct", {})
    rng = ctx.options.scan_nm
    period = 1667.0
    emax = max(float(np.max(np.hypot(r.err_nm[:, 0, :, 0], r.err_nm[:, 0, :, 1]))) for r in ctx.scans.values())
    emax = emax / rng * 100.0
    for k, name in enumerate(names):
        img = ctx.scans[name].image
        ext = [e / 1000.0 for e in img.extent_nm]
        ax = axs[0][k]
        ax.imshow(_flatten_lines(img.trace_nm), origin="lower", extent=ext, cmap="afmhot", interpolation="nearest")
        centres = (np.arange(-1, int(ext[1] * 1000 / period) + 2) + 0.5) * period / 1000.0
        for c in centres:
            if ext[0] <= c <= ext[1]:
                ax.axvline(c, color="cyan", lw=0.6, ls="--")
            if ext[2] <= c <= ext[3]:
                ax.axhline(c, color="cyan", lw=0.6, ls="--")
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_title(f"{name}\nmax error {m.get(name, float('nan')):.2f} % of range", fontsize=9)
        ax.set_xlabel("x commanded [µm]", fontsize=8)
        res = ctx.scans[name]
        err = np.hypot(res.err_nm[:, 0, :, 0], res.err_nm[:, 0, :, 1]) / rng * 100.0
        im = axs[1][k].imshow(err, origin="lower", extent=ext, cmap="viridis", vmin=0.0, vmax=emax,
                              interpolation="nearest")
        axs[1][k].set_xlabel("x commanded [µm]", fontsize=8)
        axs[1][k].set_title("trace: |lateral error| [% of range]", fontsize=9)
    axs[0][0].set_ylabel("y commanded [µm]")
    axs[1][0].set_ylabel("y commanded [µm]")
    fig.colorbar(im, ax=list(axs[1]), shrink=0.8, label="|error| [% of range]")
    fig.suptitle("1.667 µm calibration grating, trace images; dashed: where the pillars really are", fontsize=10)
    return _save(fig, path)


def _demo_hysteresis(ctx: Any, path: Path) -> Path:
    plt = _plt()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 4.4))
    e = ctx.excitation.get("x")
    if e is not None:
        a0.plot(e["u_V"], e["y_nm"] / 1000.0, color="k", lw=1.0, label="simulated scanner (measured)")
        for kind, models in ctx.models.items():
            try:
                op = models.axis("x").forward(float(e["t_s"][1] - e["t_s"][0]))
                y = op.block(np.ascontiguousarray(e["u_V"]))
                rms = float(np.sqrt(np.mean((y - e["y_nm"]) ** 2)))
                a0.plot(e["u_V"], y / 1000.0, lw=0.8, ls="--", color=_colour(kind),
                        label=f"{kind} model (rms {rms:.0f} nm)")
            except Exception as err:  # a model without forward() still gets the rest
                log.info("no forward plot for %s: %s", kind, err)
        a0.legend(fontsize=8)
    a0.set_xlabel("u_x [V]")
    a0.set_ylabel("x [µm]")
    a0.set_title("identification: hysteresis loops of the x axis")
    # scan: actual x vs commanded x over the middle line, per compensator
    for name, res in ctx.scans.items():
        img = res.image
        row = img.x_trace_nm.shape[0] // 2
        xt = img.x_target_nm / 1000.0
        a1.plot(np.concatenate([xt, xt[::-1]]),
                np.concatenate([img.x_trace_nm[row], img.x_retrace_nm[row][::-1]]) / 1000.0,
                color=_colour(name), lw=1.0, label=name)
    a1.set_xlabel("x commanded [µm]")
    a1.set_ylabel("x actual [µm]")
    a1.set_title("scan: actual vs commanded x (one line, trace + retrace)")
    a1.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def _demo_errors(ctx: Any, path: Path) -> Path:
    plt = _plt()
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.0))
    rng = ctx.options.scan_nm
    for i, axis in enumerate(("x", "y")):
        plot_error_histograms(axs[i], {n: r.err_nm[..., i] / rng * 100.0 for n, r in ctx.scans.items()},
                              f"{axis} position error, all pixels")
    fig.tight_layout()
    return _save(fig, path)


def _demo_lines(ctx: Any, path: Path) -> Path:
    plt = _plt()
    fig, axs = plt.subplots(2, 1, figsize=(10, 5.6), sharex=True)
    rng = ctx.options.scan_nm
    for name, res in ctx.scans.items():
        img = res.image
        t = img.t_trace_s.ravel()
        for i, axis in enumerate(("x", "y")):
            axs[i].plot(t, res.err_nm[:, 0, :, i].ravel() / rng * 100.0, lw=0.6, color=_colour(name), label=name)
    for i, axis in enumerate(("x", "y")):
        axs[i].set_ylabel(f"{axis} error [% range]")
        axs[i].grid(alpha=0.3)
    handles, labels = axs[0].get_legend_handles_labels()
    axs[1].set_xlabel("time since scan start [s] (trace pixels)")
    fig.suptitle("positioning error over the scan (actual − commanded, trace pixels)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.96), ncol=len(labels), fontsize=8,
               frameon=False)
    return _save(fig, path)


def _demo_drift(ctx: Any, path: Path) -> Path:
    """Ambient temperature, then true vs predicted drift: lateral (x, y) and vertical (z)
    in separate panels (z is ~20× larger)."""
    plt = _plt()
    none = ctx.scans["none"].image
    t = none.signals["t_s"]
    keep = t >= 0
    step = max(1, int(keep.sum() // 4000))
    tk = t[keep][::step]
    fig, (a0, a1, a2) = plt.subplots(3, 1, figsize=(10, 7.0), sharex=True)
    T_of_t = ctx.scan_T()
    if T_of_t is not None:
        a0.plot(tk, T_of_t(tk), color="k")
    a0.set_ylabel("ambient T [°C]")
    a0.set_title("drift scenario: the lab warms during the scan")
    colours = ("tab:blue", "tab:orange", "tab:green")
    best = ctx.metrics.get("best")
    pred = ctx.scans[best].drift_pred_nm if best and ctx.scans[best].drift_pred_nm is not None else None
    for i, axis in enumerate(("x", "y", "z")):
        ax = a2 if axis == "z" else a1
        ax.plot(tk, ctx.true_drift_nm[keep][::step, i], color=colours[i], lw=3.0, alpha=0.45, label=f"{axis} true")
        if pred is not None:
            ax.plot(tk, pred[keep][::step, i], color=colours[i], ls="--", lw=1.2, label=f"{axis} predicted")
    a1.set_ylabel("lateral drift [nm]")
    a2.set_ylabel("z drift [nm]")
    a2.set_xlabel("time since scan start [s]")
    for ax in (a1, a2):
        ax.legend(fontsize=8, ncol=2, loc="upper left")
        ax.grid(alpha=0.3)
    if pred is not None:
        a1.set_title("predicted from the measured temperature with the plant's own drift model "
                     "(known model, no fit)", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


# --------------------------------------------------------------------------- run logs
def run_report(run: str | Path, out: str | Path, *, simulate: bool | None = None
               ) -> tuple[list[Path], dict[str, Any]]:
    """Plots and a summary for one run log; see the module docstring. ``simulate``: replay
    the voltages through the simulated scanner for the tracking error; None (default) does
    so when the run drove the simulator (its tracking error is then known)."""
    from ..control.runlog import RunLogReader
    reader = RunLogReader(run)
    if simulate is None:
        simulate = bool(((reader.meta().get("config") or {}).get("simulation") or {}).get("enabled"))
    sp = reader.setpoints()
    dr = reader.drift()
    out = Path(out)
    if len(sp) == 0:
        raise AfmctlError(f"{run}: the run log holds no setpoints; nothing to plot")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise AfmctlError(f"--out {out}: cannot create the output directory ({err.strerror})") from None
    if len(sp) == 0:
        raise AfmctlError(f"{run}: the run log holds no setpoints; nothing to plot")
    summary = reader.summary()
    plt = _plt()
    files: list[Path] = []
    t = sp["t_s"] - sp["t_s"][0]
    step = max(1, len(sp) // 20000)
    active = [i for i in range(3) if np.ptp(sp["u_V"][:, i]) > 0 or np.ptp(sp["target_nm"][:, i]) > 0] or [0]

    fig, axs = plt.subplots(1, len(active), figsize=(4.2 * len(active), 4.0), squeeze=False)
    for ax, i in zip(axs[0], active):
        ax.plot(sp["target_nm"][::step, i] / 1000.0, sp["u_V"][::step, i], lw=0.7)
        ax.set_xlabel(f"target {AXES[i]} [µm]")
        ax.set_ylabel(f"u_{AXES[i]} [V]")
        ax.set_title(f"{AXES[i]}: voltage vs target")
    fig.suptitle(f"{Path(run).name}: compensator loops", fontsize=10)
    fig.tight_layout()
    files.append(_save(fig, out / "report_loops.png"))

    fig, axs = plt.subplots(2, 1, figsize=(10, 5.6), sharex=True)
    for i in active:
        axs[0].plot(t[::step], sp["target_nm"][::step, i], lw=0.8, label=f"target {AXES[i]}")
        axs[0].plot(t[::step], sp["corrected_nm"][::step, i], lw=0.8, ls="--", label=f"corrected {AXES[i]}")
        axs[1].plot(t[::step], sp["u_V"][::step, i], lw=0.8, label=f"u_{AXES[i]}")
    axs[0].set_ylabel("position [nm]")
    axs[1].set_ylabel("voltage [V]")
    axs[1].set_xlabel("time since first setpoint [s]")
    for ax in axs:
        ax.legend(fontsize=8, ncol=3)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    files.append(_save(fig, out / "report_tracking.png"))

    sel = _tracking_samples(sp, reader.events())
    span = float(max(np.ptp(sp["target_nm"][sel, i]) for i in active)) or 1.0
    errors: dict[str, np.ndarray] = {
        DRIFT_CORRECTION: (sp["corrected_nm"] - sp["target_nm"])[sel][:, active] / span * 100.0}
    if simulate:
        from ..data.axis_errors import axis_errors
        pos = _simulate(sp, reader.meta())
        errors[TRACKING_ERROR] = (pos - sp["target_nm"])[sel][:, active] / span * 100.0
        summary["tracking_per_axis"] = axis_errors(sp["target_nm"][sel], pos[sel],
                                                   "".join(AXES[i] for i in active)).as_dict()
        summary["lag"] = replayed_lag(sp, pos, sel, reader.meta(), "".join(AXES[i] for i in active))
    summary["error_samples"] = int(np.count_nonzero(sel))
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    plot_error_histograms(ax, {k: v for k, v in errors.items()}, "per-sample errors (all active axes)")
    fig.tight_layout()
    files.append(_save(fig, out / "report_errors.png"))
    summary["errors_pct_of_range"] = {k: {"max": float(np.max(np.abs(v))), "rms": float(np.sqrt(np.mean(v ** 2)))}
                                      for k, v in errors.items()}
    summary["range_nm"] = span

    if len(dr):
        fig, (a0, a1) = plt.subplots(2, 1, figsize=(10, 5.6), sharex=True)
        td = dr["t_s"] - sp["t_s"][0]
        a0.plot(td, dr["T_C"], color="k")
        a0.set_ylabel("T [°C]")
        for i in range(3):
            a1.plot(td, dr["drift_nm"][:, i], label=AXES[i])
        a1.set_ylabel("drift estimate [nm]")
        a1.set_xlabel("time since first setpoint [s]")
        a1.legend(fontsize=8)
        a1.grid(alpha=0.3)
        fig.tight_layout()
        files.append(_save(fig, out / "report_drift.png"))

    spath = out / "report_summary.json"
    spath.write_text(json.dumps(summary, indent=2, default=str) + "\n", encoding="utf-8")
    files.append(spath)
    return files, summary


def replayed_lag(sp: np.ndarray, pos: np.ndarray, sel: np.ndarray, meta: dict[str, Any], axes: str) -> dict[str, Any]:
    """The lag per axis of the replayed positions ``pos`` behind the logged target over the
    tracked samples ``sel`` (:func:`afmctl.data.lag.measure_lags`), beside the output path's
    delay the run knew and took out (the log's ``path_delay``; none in logs from before it)."""
    from ..data.lag import measure_lags
    dt = float(meta.get("dt_s") or np.median(np.diff(sp["t_s"])))
    path = meta.get("path_delay") or {"delay_s": 0.0, "advance_samples": 0, "path": "not recorded in this log"}
    return {"path_delay": path, "dt_s": dt,
            "replayed": [g.as_dict() for g in measure_lags(sp["target_nm"][sel], pos[sel], dt, axes)]}


def _tracking_samples(sp: np.ndarray, events: list[dict[str, Any]]) -> np.ndarray:
    """Mask of the samples that track the trajectory: after the start ramp ("ramp-done")
    and before the run ends ("end", "stop", "estop"); the ramps have no target to track."""
    seq = sp["seq"].astype(np.int64)
    lo, hi = int(seq[0]), int(seq[-1]) + 1
    for ev in events:
        name, s = ev.get("event"), ev.get("seq")
        if not isinstance(s, int):
            continue
        if name == "ramp-done" and s <= (lo + hi) // 2:
            lo = max(lo, s)
        elif name in ("end", "stop", "estop"):
            hi = min(hi, s)
    mask = (seq >= lo) & (seq < hi)
    return mask if mask.any() else np.ones(len(sp), bool)


def _simulate(sp: np.ndarray, meta: dict[str, Any]) -> np.ndarray:
    """Replay the logged voltages through the run's simulated scanner (its
    ``simulation.scanner`` file from the log's configuration, else the default scanner),
    from rest, each held for the logged loop period: the true positions [nm] that scanner
    would reach (:func:`afmctl.simulation.link.replay_voltages_nm`, as ``afmctl run`` reports)."""
    from ..simulation.link import replay_voltages_nm
    t = sp["t_s"]
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1e-3
    if not np.isfinite(dt) or dt <= 0:
        raise AfmctlError("run log: setpoint times are not increasing; cannot simulate")
    path = ((meta.get("config") or {}).get("simulation") or {}).get("scanner")
    advance = int((meta.get("path_delay") or {}).get("advance_samples", 0))
    return replay_voltages_nm(sp["u_V"], dt, Path(path) if path else None, delay_ticks=advance)
