"""Preisach and Bouc–Wen benchmark: streaming throughput (one core) and feedforward accuracy.

Measures, median over ``--repeats`` runs of a ``--samples`` block (compiled kernels
warmed up first):

* Preisach forward and exact inverse at 32 and 64 levels (targets at 32 levels:
  ≥ 10 M samples/s forward, ≥ 3 M samples/s inverse);
* Bouc–Wen forward and inverse, and the rate-dependent Bouc–Wen's;
* feedforward accuracy on the fine asymmetric relay plant of ``tests/plants.py``
  (Preisach vs. PI identified from the same data), with a plot
  ``docs/img/preisach_feedforward.png`` and the identified Everett surface
  ``docs/img/preisach_everett.png``.

Rewrites the ``bench:preisach`` section of docs/BENCHMARKS.md:

    .venv/bin/python benchmarks/bench_preisach.py [--repeats N] [--samples N] [--no-accuracy] [--no-write]
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from sections import write_section  # noqa: E402  (benchmarks/sections.py)
COMMAND = ".venv/bin/python benchmarks/bench_preisach.py"


def _density(a, b):
    return np.exp(-((a - b - 40.0) ** 2) / (2 * 30.0 ** 2) - ((a + b) / 2 - 10.0) ** 2 / (2 * 80.0 ** 2)) + 0.3


def _signal(n: int, lo: float, hi: float) -> np.ndarray:
    """Scan-like input: a 1 Hz triangle (1 kHz samples) whose amplitude wanders, plus
    small random wiggles — many reversals and nested minor loops."""
    rng = np.random.default_rng(0)
    t = np.arange(n) * 1e-3
    tri = 1.0 - np.abs(2.0 * ((t * 1.0) % 1.0) - 1.0)
    amp = 0.55 + 0.4 * np.sin(2 * np.pi * t / 37.0)
    x = 0.5 + amp * (tri - 0.5) + 0.01 * rng.standard_normal(n)
    return lo + (hi - lo) * np.clip(x, 0.0, 1.0)


def _median_rate(fn, n: int, repeats: int) -> tuple[float, float]:
    """(wall-clock rate, CPU-time rate) in samples/s, medians over ``repeats`` runs."""
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return n / statistics.median(wall), n / max(statistics.median(cpu), 1e-9)


def _m(rates: tuple[float, float]) -> tuple[float, float]:
    return rates[0] / 1e6, rates[1] / 1e6


def _us(rates: tuple[float, float]) -> tuple[float, float]:
    """samples/s → µs per call (wall, CPU)."""
    return 1e6 / rates[0], 1e6 / rates[1]


def measure_throughput(samples: int, repeats: int) -> list[tuple[str, str, float, str]]:
    from afmctl.compensators.bouc_wen import BoucWenModel
    from afmctl.compensators.preisach import PreisachModel
    from afmctl.compensators.rate_bouc_wen import RateBoucWenModel

    rows = []
    for levels in (32, 64):
        m = PreisachModel.from_density(_density, -160.0, 160.0, levels)
        u = _signal(samples, -160.0, 160.0)
        f, inv = m.forward(), m.inverse()
        f.block(u[:1000]); inv.block(f.block(u[:1000]))  # compile / load cache
        f.reset()
        y = f.block(u)

        def run_fwd() -> None:
            f.reset()
            f.block(u)

        def run_inv() -> None:
            inv.reset()
            inv.block(y)

        rows.append((f"Preisach forward, {levels} levels", f"block of {samples} samples", _m(_median_rate(run_fwd, samples, repeats)), "M samples/s"))
        rows.append((f"Preisach inverse, {levels} levels", f"block of {samples} samples", _m(_median_rate(run_inv, samples, repeats)), "M samples/s"))
        n_step = 20000
        us, ys = u[:n_step].tolist(), y[:n_step].tolist()

        def steps(op, xs):
            op.reset()
            for x in xs:
                op.step(x)

        rows.append((f"Preisach forward, {levels} levels", "per-sample step() from Python",
                     _us(_median_rate(lambda: steps(f, us), n_step, repeats)), "µs/call"))
        rows.append((f"Preisach inverse, {levels} levels", "per-sample step() from Python",
                     _us(_median_rate(lambda: steps(inv, ys), n_step, repeats)), "µs/call"))
    bw = BoucWenModel(d_nm_per_V=100.0, A_nm_per_V=30.0, beta=0.004, gamma=0.0015, n=1.2)
    u = _signal(samples // 4, 0.0, 150.0)
    bf, bi = bw.forward(), bw.inverse()
    yb = bf.block(u)
    bi.block(yb[:100])
    rows.append(("Bouc–Wen forward", f"block of {u.size} samples", _m(_median_rate(lambda: (bf.reset(), bf.block(u)), u.size, repeats)), "M samples/s"))
    rows.append(("Bouc–Wen inverse", f"block of {u.size} samples", _m(_median_rate(lambda: (bi.reset(), bi.block(yb)), u.size, repeats)), "M samples/s"))
    rbw = RateBoucWenModel(**bw.model_dump(exclude={"kind"}), rate_gain_s_per_V=2e-5, rate_max_V_per_s=2e4,
                           rate_tau_s=0.03)
    rf, ri = rbw.forward(1e-4), rbw.inverse(1e-4)          # 10 kHz: the 1 Hz triangle at ~300 V/s
    yr = rf.block(u)
    ri.block(yr[:100])
    rows.append(("rate-dependent Bouc–Wen forward", f"block of {u.size} samples at 10 kHz",
                 _m(_median_rate(lambda: (rf.reset(), rf.block(u)), u.size, repeats)), "M samples/s"))
    rows.append(("rate-dependent Bouc–Wen inverse", f"block of {u.size} samples at 10 kHz",
                 _m(_median_rate(lambda: (ri.reset(), ri.block(yr)), u.size, repeats)), "M samples/s"))
    ul, yl = u[:20000].tolist(), yb[:20000].tolist()
    bf.step(ul[0])
    bi.step(yl[0])
    for name, op, xs in (("Bouc–Wen forward", bf, ul), ("Bouc–Wen inverse", bi, yl)):
        def run_steps(op=op, xs=xs) -> None:
            op.reset()
            for x in xs:
                op.step(x)
        rows.append((name, "per-sample step() from Python", _us(_median_rate(run_steps, len(xs), repeats)), "µs/call"))
    return rows


def measure_accuracy(plots: bool = True) -> tuple[list[tuple[str, float, float]], str]:
    """Feedforward on the asymmetric relay plant: Preisach vs PI."""
    sys.path.insert(0, str(ROOT / "tests"))
    from plants import RelayPreisachPlant, decaying_triangle, triangle  # noqa: E402

    from afmctl.compensators.preisach import PreisachModel

    plant = RelayPreisachPlant(grid=300)
    lo, hi = plant.output_range_nm()
    span = hi - lo
    _, u1 = decaying_triangle(1e-3, 10, 0.0, 150.0, samples_per_cycle=1200)
    ext = [100.5, 60.0, 90.0, 70.5, 120.0, 40.5, 79.5, 30.0, 130.5, 0.0]
    pts = np.r_[u1[-1], ext]
    minor = np.concatenate([np.linspace(a, b, int(abs(b - a) * 400 / 150) + 2)[1:] for a, b in zip(pts[:-1], pts[1:])])
    u_id = np.r_[u1, minor]
    t_id = np.arange(u_id.size) * 1e-3
    y_id = plant.run(u_id) + np.random.default_rng(0).normal(0.0, 5e-4 * span, u_id.size)
    t = np.arange(3000) * 1e-3
    target = triangle(t, 1.0, lo + 0.1 * span, lo + 0.9 * span)
    results = []
    curves = {}
    pre = PreisachModel.identify(t_id, u_id, y_id, n_operators=32, u_min_V=0.0, u_max_V=150.0)
    models = [("Preisach, 32 levels (NNLS)", pre)]
    try:
        from afmctl.compensators.pi import PIModel
        models.append(("PI, 16 play operators", PIModel.identify(t_id, u_id, y_id, n_operators=16)))
    except ImportError:  # pragma: no cover
        pass
    plant.reset()
    y_open = plant.run(np.interp(target, [lo, hi], [0.0, 150.0]))
    e = y_open - target
    results.append(("none (linear scaling u = 150 V·y/range)", 100 * np.max(np.abs(e)) / span, 100 * np.sqrt(np.mean(e * e)) / span))
    curves["none"] = e
    for name, m in models:
        plant.reset()
        e = plant.run(m.inverse().block(target)) - target
        results.append((name, 100 * np.max(np.abs(e)) / span, 100 * np.sqrt(np.mean(e * e)) / span))
        curves[name] = e
    if plots:
        _plots(t, target, curves, span, pre)
    note = (f"Plant: `tests/plants.py` RelayPreisachPlant(grid=300) — relays on a 0.5 V lattice over 0…150 V, asymmetric "
            f"Gaussian-mixture density, 40 nm/V reversible part, range {span:.0f} nm. Identification: decaying "
            f"triangle (10 cycles) + 10 minor loops, {u_id.size} samples, 0.05 % Gaussian noise. Test: 1 Hz triangle "
            f"over 10…90 % of the range, 3 periods at 1 kHz, errors in % of range.")
    return results, note


def _plots(t, target, curves, span, model) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img = ROOT / "docs" / "img"
    img.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(8, 3.6))
    for name, e in curves.items():
        ax.plot(t, 100 * e / span, lw=0.8, label=name)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("tracking error [% of range]")
    ax.set_title("Feedforward on an asymmetric relay-Preisach plant (1 Hz triangle, 80 % of range)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(img / "preisach_feedforward.png", dpi=110)
    plt.close(fig)

    w = model.cell_masses()
    v = model.nodes_V()
    fig, ax = plt.subplots(figsize=(5, 4.2))
    du = v[1] - v[0]
    dens = w / (du * du)
    dens[np.diag_indices_from(dens)] *= 2.0  # diagonal cells are half cells
    off = dens[np.tril_indices_from(dens, -1)]
    vmax = float(np.percentile(off, 99)) if off.size else None
    im = ax.imshow(dens, origin="lower", extent=[v[0], v[-1], v[0], v[-1]], cmap="viridis", vmin=0.0, vmax=vmax)
    ax.set_xlabel("β [V]")
    ax.set_ylabel("α [V]")
    ax.set_title("Identified Preisach density\n(diagonal = reversible part, off scale)", fontsize=10)
    fig.colorbar(im, ax=ax, label="μ(α, β) [nm/V²]")
    fig.tight_layout()
    fig.savefig(img / "preisach_everett.png", dpi=110)
    plt.close(fig)


def format_section(rows, acc, note, repeats: int) -> str:
    lines = ["## Preisach and Bouc–Wen", "",
             f"Command: `{' '.join([COMMAND] + sys.argv[1:])}` (median of {repeats} runs; one core; "
             f"{platform.python_implementation()} {platform.python_version()}, {platform.machine()}). "
             "Targets at 32 levels: ≥ 10 M samples/s forward, ≥ 3 M samples/s exact inverse. "
             "Signal: wandering 1 Hz triangle with noise over the whole −160…160 V grid.", "",
             "Wall-clock and CPU-time medians are both given: on a shared machine the CPU time of "
             "this single-threaded process is the fairer one-core figure.", "",
             "| what | conditions | median (wall clock) | median (CPU time) | unit |", "|---|---|---|---|---|"]
    for what, cond, (wall, cpu), unit in rows:
        lines.append(f"| {what} | {cond} | {wall:.3g} | {cpu:.3g} | {unit} |")
    if acc:
        lines += ["", "Feedforward accuracy (same command). " + note, "",
                  "| compensator | max error [% of range] | RMS error [% of range] |", "|---|---|---|"]
        for name, mx, rms in acc:
            lines.append(f"| {name} | {mx:.3g} | {rms:.3g} |")
        lines += ["", "![feedforward errors](img/preisach_feedforward.png)"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=7, help="timed runs per figure (median is quoted)")
    ap.add_argument("--samples", type=int, default=2_000_000, help="samples per timed block")
    ap.add_argument("--no-accuracy", action="store_true", help="skip the feedforward accuracy comparison")
    ap.add_argument("--no-write", action="store_true", help="print only; do not touch docs/BENCHMARKS.md or docs/img")
    args = ap.parse_args(argv)
    rows = measure_throughput(args.samples, args.repeats)
    acc, note = ([], "") if args.no_accuracy else measure_accuracy(plots=not args.no_write)
    section = format_section(rows, acc, note, args.repeats)
    print(section)
    if not args.no_write:
        path = write_section("preisach", section)
        print(f"updated {path.relative_to(ROOT)} section preisach")
    return 0


if __name__ == "__main__":
    sys.exit(main())
