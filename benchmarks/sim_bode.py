"""Bode plot of the default simulated scanner's linear stages (docs/img/sim_bode.png):
the simulator's exact small-signal response (``AxisPlant.linear_response``: amplifier
low-pass → creep → structural mode, at 50 kHz), the response measured from an
``afmctl excite --kind dynamics`` recording (Welch), and the model ``afmctl identify
--model dynamics`` fits to it. Prints the fitted figures quoted in docs/SIM.md.

    .venv/bin/python benchmarks/sim_bode.py [--out docs/img]

About half a minute on one core.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from afmctl.compensators.dynamics import LinearDynamicsModel  # noqa: E402
from afmctl.compensators.dynamics_identify import measure_frf, record_parts  # noqa: E402
from afmctl.data.excitation import ExcitationSpec, excitation  # noqa: E402
from afmctl.sim_backend.scanner import Scanner, default_scanner_config  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RATE_HZ = 50_000.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    args = ap.parse_args(argv)
    cfg = default_scanner_config()
    scanner = Scanner(cfg)
    f = np.geomspace(1, 20_000, 600)
    dt = 1.0 / RATE_HZ
    u = excitation("dynamics", ExcitationSpec(0, 150, RATE_HZ, slew_V_per_s=cfg.x.amplifier.slew_V_per_s))
    U = np.zeros((u.size, 3))
    U[:, 0] = u
    y = scanner.run(U, dt)[:, 0]
    t = np.arange(u.size) * dt
    model = LinearDynamicsModel.identify(t, u, y)
    parts = record_parts(u, t, "auto")
    gain = float(model.fit_info["static_gain_y_per_u"])
    frf = measure_frf(u, y, dt, 1 << 14, 0.0, 0.4 * RATE_HZ, 0.9, parts)
    fig, (am, ap_) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for axis, ls in (("x", "-"), ("z", "--")):
        g = Scanner(cfg).axes[axis].linear_response(f, dt)
        am.semilogx(f, 20 * np.log10(np.abs(g)), ls, lw=1.2, label=f"simulator {axis} (exact, 50 kHz)")
        ap_.semilogx(f, np.degrees(np.unwrap(np.angle(g))), ls, lw=1.2)
    am.semilogx(frf.f_Hz, 20 * np.log10(np.abs(frf.G) / gain), ".", ms=1.5, alpha=0.4, label="x measured (Welch)")
    ap_.semilogx(frf.f_Hz, np.degrees(np.unwrap(np.angle(frf.G))), ".", ms=1.5, alpha=0.4)
    gm = model.discrete(dt).frequency_response(f)
    am.semilogx(f, 20 * np.log10(np.abs(gm)), ":", lw=1.5, label="x identified model (causal: no same-sample lead)")
    ap_.semilogx(f, np.degrees(np.unwrap(np.angle(gm))), ":", lw=1.5)
    am.set_ylabel("magnitude [dB], DC = 0")
    am.set_ylim(-60, 35)
    am.legend(fontsize=8)
    ap_.set_ylabel("phase [°]")
    ap_.set_xlabel("f [Hz]")
    ap_.set_ylim(-400, 20)
    am.set_title("default scanner: amplifier 5 kHz, mode 1 kHz (Q 20) in x/y, 5 kHz (Q 10) in z")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "sim_bode.png", dpi=110)
    plt.close(fig)
    mode = [p for p in model.poles() if p.imag > 0][0]
    lag = [p for p in model.poles() if p.imag == 0]
    print(f"wrote {args.out / 'sim_bode.png'}")
    print(f"identified x: mode {abs(mode) / (2 * math.pi):.1f} Hz, zeta {-mode.real / abs(mode):.4f}, "
          f"lag {abs(lag[0]) / (2 * math.pi) if lag else float('nan'):.0f} Hz, delay {model.delay_s * 1e6:.1f} us, "
          f"small-signal gain {gain:.2f} nm/V (fitted lead {model.fit_info['fitted_delay_s'] * 1e6:.1f} us)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
