"""Speed of the simulated scanner (sim_backend): plant samples per second per axis, imaging,
streaming calls. Writes its section of docs/BENCHMARKS.md (markers ``bench:sim``).

    .venv/bin/python benchmarks/bench_sim.py [--reps N] [--samples N] [--no-write]

Target: ≥ 1 M samples/s per axis on one core for the Preisach plant.
"""
from __future__ import annotations

import argparse
import platform
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sim_backend.config import DriftConfig, ExternalModelConfig, default_preisach, default_scanner_config  # noqa: E402
from sim_backend.plant import AxisPlant, GaussianPreisachOperator  # noqa: E402
from sim_backend.samples import Grating2D  # noqa: E402
from sim_backend.scanner import Scanner  # noqa: E402

NAME = "sim"


def median_time(fn, reps: int) -> float:
    fn()  # warm up (numba compile / cache load)
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def signal(n: int) -> np.ndarray:
    """A wandering triangle with noise over 0…150 V (nested loops, 100 kHz-ish)."""
    rng = np.random.default_rng(0)
    t = np.arange(n) / 1e5
    tri = 2 * np.abs((t * 7.3) % 1 - 0.5)
    env = 0.6 + 0.4 * np.sin(2 * np.pi * 0.37 * t)
    return np.clip(150 * tri * env + rng.normal(0, 0.5, n), 0, 150)


def write_section(text: str) -> None:
    path = ROOT / "docs" / "BENCHMARKS.md"
    doc = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n"
    block = f"<!-- bench:{NAME} -->\n{text.rstrip()}\n<!-- /bench:{NAME} -->"
    pat = re.compile(rf"<!-- bench:{NAME} -->.*?<!-- /bench:{NAME} -->", re.S)
    doc = pat.sub(lambda _: block, doc) if pat.search(doc) else doc.rstrip() + "\n\n" + block + "\n"
    path.write_text(doc, encoding="utf-8")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=5, help="repetitions per case (median reported)")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per block")
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/BENCHMARKS.md")
    a = ap.parse_args(argv)
    n, reps = a.samples, a.reps
    u1 = signal(n)
    u3 = np.column_stack([u1, u1[::-1].copy(), np.roll(u1, n // 3)])
    rows = []

    def per_axis(seconds: float, axes: int = 1) -> str:
        return f"{n * axes / seconds / 1e6:.3g}"

    op = GaussianPreisachOperator(default_preisach("x"))
    t = median_time(lambda: (op.reset(), op.block(u1)), reps)
    rows.append(("Gaussian-mixture Preisach (151-node Everett table) forward", f"block of {n}", per_axis(t), "M samples/s"))

    cfg = default_scanner_config()
    ax = AxisPlant(cfg.x)
    t = median_time(lambda: (ax.reset(), ax.run(u1, 1e-5)), reps)
    rows.append(("one axis: amplifier + Preisach + creep (5 lags) + mode", f"block of {n}", per_axis(t), "M samples/s per axis"))

    nodrift = default_scanner_config()
    nodrift.drift = DriftConfig(kind="none")
    s = Scanner(nodrift)
    t = median_time(lambda: (s.reset(), s.run(u3, 1e-5)), reps)
    rows.append(("Scanner.run, 3 axes, no drift", f"block of {n} × 3", per_axis(t, 3), "M samples/s per axis"))

    s = Scanner(default_scanner_config())
    t = median_time(lambda: (s.reset(), s.run(u3, 1e-5)), reps)
    rows.append(("Scanner.run, 3 axes, default (drift: physical_tube predictor)", f"block of {n} × 3", per_axis(t, 3),
                 "M samples/s per axis"))

    try:
        from compensators.preisach import PreisachModel

        m = PreisachModel.from_density(lambda al, be: np.exp(-((al - 80) ** 2 + (be - 40) ** 2) / 800.0),
                                       u_min_V=0.0, u_max_V=150.0, levels=32)
        ext = default_scanner_config()
        ext.drift = DriftConfig(kind="none")
        for axn in ("x", "y", "z"):
            ext.axis(axn).hysteresis = ExternalModelConfig(model=m.model_dump(mode="json"))
        s = Scanner(ext)
        t = median_time(lambda: (s.reset(), s.run(u3, 1e-5)), reps)
        rows.append(("Scanner.run, 3 axes, compensators PreisachModel (32 levels) as plant", f"block of {n} × 3",
                     per_axis(t, 3), "M samples/s per axis"))
    except ImportError:  # pragma: no cover
        pass

    s = Scanner()
    t = median_time(lambda: (s.reset(), s.image(Grating2D(), scan_size_nm=10_000.0, pixels=256)), max(1, reps // 2))
    rows.append(("Scanner.image, 1.667 µm grating, uncompensated", "256×256 px, 2 samples/px, trace+retrace", f"{t:.3g}", "s"))
    try:
        from sim_backend.image_scans import identify_axes_from_images

        models = identify_axes_from_images(s, ("x", "y"))

        def comp_image():
            s.reset()
            s.image(Grating2D(), scan_size_nm=10_000.0, pixels=256, compensator={k: v.inverse() for k, v in models.items()})

        t = median_time(comp_image, max(1, reps // 2))
        rows.append(("Scanner.image, same, Preisach-compensated (x, y)", "256×256 px", f"{t:.3g}", "s"))
        t = median_time(lambda: identify_axes_from_images(s, ("x",)), 1)
        rows.append(("image-based identification of one axis (scans + fit)", "15 ranges × 3 lines × 1024 px", f"{t:.3g}", "s"))
    except ImportError:  # pragma: no cover
        pass

    s = Scanner()
    state = {"k": 0}

    def stream():
        for _ in range(2000):
            state["k"] += 1
            s.apply({"x": float(state["k"] % 150)})
            s.advance(state["k"] * 1e-3)

    t = median_time(stream, reps)
    rows.append(("streaming apply() + advance() (1 ms of held input = 100 samples)", "per call", f"{t / 2000 * 1e6:.3g}", "µs"))

    lines = [
        "## Simulated scanner (sim_backend)",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_sim.py --reps {reps}` (median of {reps} runs; one core; "
        f"CPython {platform.python_version()}, {platform.machine()}). Target: ≥ 1 M samples/s per axis for the "
        "Preisach plant. Signal: wandering triangle with noise over 0…150 V at 100 kHz (nested minor loops).",
        "",
        "| what | conditions | median | unit |",
        "|---|---|---|---|",
    ]
    lines += [f"| {w} | {c} | {v} | {u} |" for w, c, v, u in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if not a.no_write:
        write_section(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
