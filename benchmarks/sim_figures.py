"""Regenerate the simulator figures docs/img/sim_*.png and print the numbers quoted in
docs/SIM.md (all measured here, nothing typed in).

    .venv/bin/python benchmarks/sim_figures.py [--out docs/img] [--pixels 512]

Takes about a minute on one core.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from afmctl.compensators.image_identify import branches_from_scans, feature_points  # noqa: E402
from afmctl.sim_backend.image_scans import DEFAULT_LEVELS, identify_axes_from_images, scan_grating_lines  # noqa: E402
from afmctl.sim_backend.plant import AxisPlant  # noqa: E402
from afmctl.sim_backend.samples import Grating2D, Nanoparticles, StandardSample  # noqa: E402
from afmctl.sim_backend.scanner import CreepConfig, DriftConfig, Scanner, default_scanner_config, linear_scanner_config  # noqa: E402


def save(fig, out: Path, name: str) -> None:
    p = out / name
    fig.tight_layout()
    fig.savefig(p, dpi=110)
    plt.close(fig)
    print(f"wrote {p}")


def fig_plant(out: Path) -> None:
    cfg = default_scanner_config()
    ax = AxisPlant(cfg.x)
    u = np.concatenate([np.linspace(0, 150, 3000), np.linspace(150, 0, 3000), np.linspace(0, 100, 2000),
                        np.linspace(100, 40, 1200), np.linspace(40, 100, 1200), np.linspace(100, 0, 2000)])
    y = ax.run(u, 1e-3)  # 1 kHz samples, ≈ 12 s of loops
    ax.reset()
    step = ax.run(np.r_[np.zeros(100), np.full(30_000, 50.0)], 1e-5)
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    a.plot(u, y / 1000, lw=1)
    a.set_xlabel("u [V]")
    a.set_ylabel("x [µm]")
    a.set_title("default x axis: asymmetric Preisach + creep")
    t = np.arange(step.size) * 1e-5 * 1e3
    b.plot(t, step, lw=0.8)
    b.set_xlabel("t [ms]")
    b.set_ylabel("x [nm]")
    b.set_title("50 V step: slew, 1 kHz mode (Q 20), creep")
    save(fig, out, "sim_plant.png")


def fig_hysteresis(out: Path) -> None:
    smp = StandardSample(section_nm=1000.0, amplitude_nm=1.0)
    fig, axs = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    shifts = None
    for a, (name, cfg) in zip(axs, (("linear model", linear_scanner_config()), ("hysteresis (default scanner)", default_scanner_config()))):
        im = Scanner(cfg).image(smp, scan_size_nm=9000.0, pixels=(512, 3))
        x = im.x_target_nm / 1000
        a.plot(x, im.trace_nm[-1], lw=1, label="forward (trace)")
        a.plot(x, im.retrace_nm[-1], lw=1, ls="--", label="backward (retrace)")
        a.set_title(name)
        a.set_xlabel("x commanded [µm]")
        if cfg.x.creep is not None:
            shifts = (feature_points(im.retrace_nm[-1]) - feature_points(im.trace_nm[-1])) * im.pixel_nm
    axs[0].set_ylabel("height [nm]")
    axs[0].legend(loc="upper right", fontsize=8)
    save(fig, out, "sim_hysteresis_scan.png")
    print("hysteresis: backward − forward asperity position [nm]:", np.round(shifts).astype(int).tolist())


def fig_creep(out: Path) -> None:
    smp = StandardSample(section_nm=1000.0, amplitude_nm=1.0)
    creep = linear_scanner_config()
    creep.z.creep = CreepConfig(fraction=0.2, tau_min_s=0.005, tau_max_s=0.05, n_lags=3)
    kw = dict(scan_size_nm=3000.0, pixels=(384, 2), z_mode="piezo", line_rate_Hz=1.0)
    lin = Scanner(linear_scanner_config()).image(smp, **kw)
    cr = Scanner(creep).image(smp, **kw)
    x = lin.x_target_nm / 1000
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    a.plot(x, lin.trace_nm[-1], lw=1, label="linear model")
    a.plot(x, cr.trace_nm[-1], lw=1, label="creep (z piezo)")
    a.set_xlabel("x [µm]")
    a.set_ylabel("image [nm]")
    a.legend(fontsize=8)
    a.set_title("creep acts like a delay")
    err = cr.trace_nm[-1] - lin.trace_nm[-1]
    b.plot(x, err, lw=1)
    b.set_xlabel("x [µm]")
    b.set_ylabel("creep − linear [nm]")
    b.set_title("error: largest where the profile ascends")
    save(fig, out, "sim_creep_delay.png")
    print(f"creep: largest error {err.min():.3f} nm (profile amplitude 1 nm)")


def fig_drift(out: Path) -> None:
    smp = StandardSample(section_nm=1000.0, amplitude_nm=1.0)

    def T(t):
        return 22.0 + 2.0 * t / 600.0

    kw = dict(scan_size_nm=3000.0, pixels=(64, 64), line_rate_Hz=64 / 600.0, T_C=T)
    ref = Scanner(linear_scanner_config(drift=DriftConfig(kind="none"))).image(smp, **kw)
    im = Scanner(linear_scanner_config(drift=DriftConfig())).image(smp, **kw)
    lat = np.hypot(im.x_trace_nm - ref.x_trace_nm, im.y_trace_nm - ref.y_trace_nm)
    dz = im.trace_nm - ref.trace_nm
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    e = [v / 1000 for v in im.extent_nm]
    m = a.imshow(lat, origin="lower", extent=e, cmap="viridis")
    fig.colorbar(m, ax=a, label="lateral drift error [nm]")
    a.set_title("2 °C over a 10 min scan: lateral error")
    a.set_xlabel("x [µm]")
    a.set_ylabel("y [µm] (line = time)")
    m = b.imshow(dz, origin="lower", extent=e, cmap="magma")
    fig.colorbar(m, ax=b, label="height error (z drift) [nm]")
    b.set_title("height error (z: 40 nm/K axial expansion)")
    b.set_xlabel("x [µm]")
    save(fig, out, "sim_drift.png")
    print(f"drift: lateral error max {lat.max():.2f} nm at the end; row means first/last "
          f"{lat.mean(axis=1)[0]:.2f}/{lat.mean(axis=1)[-1]:.2f} nm; z height error max {np.abs(dz).max():.1f} nm")


def fig_identification(out: Path) -> dict:
    s = Scanner()
    sc = scan_grating_lines(s, axis="x", pixels=1024, lines_per_range=3)
    br = branches_from_scans(sc.arrays())
    from afmctl.compensators.image_identify import identify_from_images
    from afmctl.compensators.preisach import PreisachModel

    m_img = identify_from_images(sc.arrays(), n_operators=DEFAULT_LEVELS)
    tr = sc.truth
    m_true = PreisachModel.identify(tr["t_s"], tr["u_V"], tr["y_nm"], n_operators=DEFAULT_LEVELS, u_min_V=0.0, u_max_V=150.0)
    lo, hi = m_true.output_range_nm()
    y = np.concatenate([np.linspace(lo + 100, hi - 100, 400), np.linspace(hi - 100, 0.3 * hi, 200),
                        np.linspace(0.3 * hi, 0.8 * hi, 200), np.linspace(0.8 * hi, lo + 100, 300)])
    du = np.abs(m_img.inverse().block(y) - m_true.inverse().block(y)).max() / 150 * 100
    u = np.interp(np.linspace(0, 1, 1100), np.linspace(0, 1, 5), [0, 150, 40, 120, 0])
    dy = np.abs(m_img.forward().block(u) - m_true.forward().block(u)).max() / (hi - lo) * 100
    print(f"image-based vs true-position identification ({DEFAULT_LEVELS} levels): compensator max diff {du:.2f} % of 150 V, "
          f"forward max diff {dy:.2f} % of the range")
    fig, axs = plt.subplots(1, 3, figsize=(15, 4))
    line = sc.trace_nm[-1, -1]
    f = feature_points(line)
    axs[0].plot(line, lw=0.7)
    axs[0].plot(f, np.interp(f, np.arange(line.size), line), "o", mfc="none", ms=5)
    axs[0].axhline(line.mean(), color="k", lw=0.8, ls=":")
    axs[0].set_xlim(0, 300)
    axs[0].set_xlabel("pixel")
    axs[0].set_ylabel("height [nm]")
    axs[0].set_title("feature points (eq. 5), threshold (eq. 4)")
    for b in br:
        uu = np.linspace(b.u_min_V, b.u_max_V, 200)
        axs[1].plot(uu, b.ascending(uu) / 1000, "C0", lw=0.8)
        axs[1].plot(uu, b.descending(uu) / 1000, "C1", lw=0.8)
        axs[1].plot(b.ascending.u_V, b.ascending.y_nm / 1000, "C0.", ms=2)
        axs[1].plot(b.descending.u_V, b.descending.y_nm / 1000, "C1.", ms=2)
    axs[1].set_xlabel("u [V]")
    axs[1].set_ylabel("displacement [µm] (period counting)")
    axs[1].set_title("branches per scan range, LS polynomials (eq. 6)")
    w = m_img.cell_masses()
    mm = axs[2].imshow(np.where(np.isnan(w), np.nan, w), origin="lower", cmap="viridis",
                       extent=[0, 150, 0, 150])
    fig.colorbar(mm, ax=axs[2], label="cell mass [nm]")
    axs[2].set_xlabel("β [V]")
    axs[2].set_ylabel("α [V]")
    axs[2].set_title("identified Preisach weights (Fig. 8)")
    save(fig, out, "sim_image_identification.png")
    return {"du": du, "dy": dy}


def fig_grating(out: Path, pixels: int) -> None:
    s = Scanner()
    kw = dict(scan_size_nm=10_000.0, pixels=pixels, line_rate_Hz=1.0, origin_nm=(500.0, 500.0))
    raw = s.image(Grating2D(), **kw)
    models = identify_axes_from_images(s, ("x", "y"))
    comp = s.image(Grating2D(), compensator={a: m.inverse() for a, m in models.items()}, **kw)
    for name, im, fn in (("uncompensated", raw, "sim_grating_uncompensated.png"),
                         ("Preisach-compensated (identified from images)", comp, "sim_grating_compensated.png")):
        px = im.grating_periods_nm("x")
        py = im.grating_periods_nm("y")
        pr = im.grating_periods_nm("x", "retrace")
        dev = max(np.max(np.abs(p / p.mean() - 1)) for p in (px, py, pr)) * 100
        title = f"1.667 µm grating, {pixels}×{pixels}, 1 line/s — {name}\nlocal period x {np.round(px).astype(int).tolist()} nm"
        im.save_png(out / fn, title=title)
        print(f"grating {name}: x trace {np.round(px, 1).tolist()} | x retrace {np.round(pr, 1).tolist()} | "
              f"y {np.round(py, 1).tolist()} nm; max deviation from the mean {dev:.2f} %")


def fig_particles(out: Path) -> None:
    p = Nanoparticles.random(12, (600.0, 600.0), 15.0, seed=2)
    p = Nanoparticles(p.centres_nm + 1000.0, p.diameters_nm)  # in the scan area below
    im = Scanner().image(p, scan_size_nm=600.0, pixels=128, origin_nm=(1000.0, 1000.0), line_rate_Hz=2.0)
    im.save_png(out / "sim_nanoparticles.png", title="15 nm particles on a flat substrate (uncompensated)")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"))
    ap.add_argument("--pixels", type=int, default=512, help="grating image size (paper: 512)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    fig_plant(out)
    fig_hysteresis(out)
    fig_creep(out)
    fig_drift(out)
    fig_identification(out)
    fig_grating(out, a.pixels)
    fig_particles(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
