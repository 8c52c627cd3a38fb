"""Imprint 'NK' on the simulated scanner with and without hysteresis compensation.

The image-based paper (Sec. 4.3, Fig. 10) imprints the letters 'NK' with and without its
Preisach compensator: uncompensated, the letters come out too small and the strokes miss
each other. This script does the same offline on the simulated scanner:

1. identify a PI model per axis from a sweep of the simulated scanner (no position sensor
   needed in the simulation; with hardware use `afmctl identify`);
2. build the 'NK' path (afmctl.inputs.trajectories.text, the single-stroke font);
3. run it through the controller's compensation chain (afmctl.control.pipeline) twice — linear
   calibration only, and the PI inverse models — and through the simulated scanner;
4. plot where the tip really went while the pen was down.

    .venv/bin/python examples/nk_imprint.py --out docs/img/ctl_nk_imprint.png

Units: nm, V, s.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np


def identify_pi(dt_s: float, folder: Path) -> dict[str, Path]:
    """PI models of x and y identified from the default simulated scanner."""
    from afmctl.simulation.link import identify_pi_models
    return identify_pi_models(folder, "xy", dt_s)


def imprint(models: dict[str, Path] | None, height_nm: float, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(target, true tip position) (N, 3) [nm] of the 'NK' path on a fresh scanner."""
    from afmctl.inputs import trajectories as tr
    from afmctl.config import load_config
    from afmctl.control.pipeline import build_pipeline
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    comp = "".join(f'[compensation.{a}]\nmodel = "{p}"\n' for a, p in (models or {}).items())
    cfg = load_config(text=f"[simulation]\nenabled = true\n[loop]\nrate_Hz = {1 / dt_s}\n"
                           "[scanner.calibration.x]\nnm_per_V = 80\n[scanner.calibration.y]\nnm_per_V = 80\n"
                           + comp)
    target = tr.collect(tr.text(dt_s, text="NK", x0_nm=1500, y0_nm=1500, height_nm=height_nm,
                                z_up_nm=0.0, z_down_nm=-50.0, speed_nm_per_s=3000.0))
    _, _, u = build_pipeline(cfg).run(target, 22.0)
    u[:, 2] = 0.0  # z stays at rest in this lateral demonstration
    u = np.clip(u, 0.0, 150.0)
    scanner = Scanner(default_scanner_config())
    settle = np.tile(u[0], (500, 1))                 # start from rest at the first voltage
    tip = scanner.run(np.vstack([settle, u]), dt_s)[500:]
    return target, tip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/img/ctl_nk_imprint.png", help="figure file (PNG)")
    ap.add_argument("--height-nm", type=float, default=6000.0, help="letter height [nm]")
    ap.add_argument("--rate", type=float, default=1000.0, help="sample rate [Hz]")
    args = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    dt = 1.0 / args.rate
    with tempfile.TemporaryDirectory() as d:
        models = identify_pi(dt, Path(d))
        results = {"linear calibration (no model)": imprint(None, args.height_nm, dt),
                   "PI inverse models": imprint(models, args.height_nm, dt)}
    fig, axs = plt.subplots(1, 2, figsize=(9, 4.2), sharex=True, sharey=True)
    for ax, (label, (target, tip)) in zip(axs, results.items()):
        down = target[:, 2] < -25.0
        err = np.linalg.norm((tip - target)[down][:, :2], axis=1)
        t_pen = np.where(down, target[:, 0], np.nan), np.where(down, target[:, 1], np.nan)
        ax.plot(t_pen[0] / 1e3, t_pen[1] / 1e3, color="0.7", lw=4, label="target")
        ax.plot(np.where(down, tip[:, 0], np.nan) / 1e3, np.where(down, tip[:, 1], np.nan) / 1e3,
                color="C3", lw=1.2, label="simulated tip")
        ax.set_title(f"{label}\nerror while imprinting: rms {np.sqrt(np.mean(err ** 2)):.0f} nm, "
                     f"max {err.max():.0f} nm", fontsize=9)
        ax.set_xlabel("x [µm]")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        print(f"{label}: rms {np.sqrt(np.mean(err ** 2)):.1f} nm, max {err.max():.1f} nm")
    axs[0].set_ylabel("y [µm]")
    axs[0].legend(fontsize=8, loc="lower right")
    fig.suptitle("Imprinting 'NK' on the simulated scanner (cf. image-based paper, Fig. 10)", fontsize=10)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
