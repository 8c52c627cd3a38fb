"""Speed of the simulated scanner (sim_backend): plant samples per second per axis, imaging,
streaming calls. Writes its section of docs/BENCHMARKS.md (markers ``bench:sim``).

    .venv/bin/python benchmarks/bench_sim.py [--reps N] [--samples N] [--gil-seconds S] [--gil-rounds N] [--no-write]

Target: ≥ 1 M samples/s per axis on one core for the Preisach plant.

GIL part: how late a 1 kHz ticker thread (a stand-in for the controller's real-time loop)
wakes while another thread drives ``Scanner.apply(volts, now())`` every 1 ms like a
simulated amplifier does, with a 1 s idle gap every second (the next apply() then simulates
1 s = 100 000 samples). "before" rebuilds the plant kernels without ``nogil`` and advances
a gap in one block (the code before the review); "now" is the shipped code.
"""
from __future__ import annotations

import argparse
import contextlib
import platform
import threading
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from sections import median_s, write_section as _write_section  # noqa: E402  (benchmarks/sections.py)

from afmctl.sim_backend.config import DriftConfig, ExternalModelConfig, default_preisach, default_scanner_config  # noqa: E402
from afmctl.sim_backend.plant import AxisPlant, GaussianPreisachOperator  # noqa: E402
from afmctl.sim_backend.samples import Grating2D  # noqa: E402
from afmctl.sim_backend.scanner import Scanner  # noqa: E402

NAME = "sim"


def signal(n: int) -> np.ndarray:
    """A wandering triangle with noise over 0…150 V (nested loops, 100 kHz-ish)."""
    rng = np.random.default_rng(0)
    t = np.arange(n) / 1e5
    tri = 2 * np.abs((t * 7.3) % 1 - 0.5)
    env = 0.6 + 0.4 * np.sin(2 * np.pi * 0.37 * t)
    return np.clip(150 * tri * env + rng.normal(0, 0.5, n), 0, 150)


def write_section(text: str) -> None:
    _write_section(NAME, text)


def _tick(stop: threading.Event, late: list[tuple[float, float]], period_s: float = 1e-3) -> None:
    """A 1 kHz loop: records (target time, lateness) of every tick [s]."""
    t0 = time.perf_counter()
    k = 0
    while not stop.is_set():
        k += 1
        target = t0 + k * period_s
        d = target - time.perf_counter()
        if d > 0:
            time.sleep(d)
        now = time.perf_counter()
        late.append((target, now - target))
        k = max(k, int((now - t0) / period_s))  # a missed tick is not counted twice


def _drive(stop: threading.Event, calls: list[tuple[float, float]], s: Scanner, gap_s: float) -> None:
    """Like a simulated amplifier: apply(volts, now()) every 1 ms, a ``gap_s`` pause every
    second; records (start, end) of every apply() call [s]."""
    t0 = time.perf_counter()
    k = 0
    next_gap = 1.0
    while not stop.is_set():
        k += 1
        a = time.perf_counter()
        s.apply({"x": 75.0 + 50.0 * np.sin(k / 100.0), "y": 75.0, "z": 60.0}, a - t0)
        calls.append((a, time.perf_counter()))
        time.sleep(1e-3)
        if gap_s and time.perf_counter() - t0 > next_gap:
            time.sleep(gap_s)
            next_gap += 1.0 + gap_s


@contextlib.contextmanager
def _gil_holding_kernels():
    """The plant kernels as they were before the review: compiled without ``nogil`` and a
    long gap advanced in one block."""
    import numba

    from afmctl.sim_backend import _plant_kernels as K

    saved = {n: getattr(K, n) for n in ("amplifier_nb", "preisach_nb", "creep_dynamics_nb", "expansion_drift_nb")}
    chunk = Scanner.ADVANCE_CHUNK
    try:
        K.amplifier_nb = numba.njit(K.amplifier_py)
        K.preisach_nb = numba.njit(K._rebind(K.preisach_py, _segment=K._segment_nb, _memory_update=K._memory_update_nb))
        K.creep_dynamics_nb = numba.njit(K.creep_dynamics_py)
        K.expansion_drift_nb = numba.njit(K.expansion_drift_py)
        Scanner.ADVANCE_CHUNK = 1 << 62
        yield
    finally:
        for n, f in saved.items():
            setattr(K, n, f)
        Scanner.ADVANCE_CHUNK = chunk


def gil_lateness(seconds: float, with_scanner: bool) -> dict[str, float]:
    """Lateness [ms] of a 1 kHz ticker (p50, p99, max over all ticks; max over the ticks
    due while a long apply() — the one after an idle gap — was running) and the time of
    those long apply() calls [ms]."""
    stop = threading.Event()
    late: list[tuple[float, float]] = []
    calls: list[tuple[float, float]] = []
    threads = [threading.Thread(target=_tick, args=(stop, late), daemon=True)]
    if with_scanner:
        s = Scanner()
        s.apply({"x": 10.0})
        s.advance(s.time_s + 0.01)
        s.reset()
        threads.append(threading.Thread(target=_drive, args=(stop, calls, s, 1.0), daemon=True))
    for t in threads:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join()
    tk = np.array(late[20:])
    lat = tk[:, 1] * 1e3
    r = {"p50": float(np.median(lat)), "p99": float(np.percentile(lat, 99)), "max": float(lat.max())}
    long_calls = [(a, b) for a, b in calls if b - a > 5e-3]
    if long_calls:
        inside = np.zeros(len(tk), dtype=bool)
        for a, b in long_calls:
            inside |= (tk[:, 0] >= a) & (tk[:, 0] < b)
        r["during_max"] = float(lat[inside].max()) if inside.any() else float("nan")
        r["long_call"] = float(np.median([b - a for a, b in long_calls]) * 1e3)
    return r


def gil_rows(seconds: float, rounds: int = 3) -> list[tuple[str, str, str, str]]:
    """The three cases, interleaved ``rounds`` times; medians over the rounds."""
    cases = [("ticker alone", False, None),
             ("ticker + scanner thread, before (kernels hold the GIL, gap in one block)", True, _gil_holding_kernels),
             ("ticker + scanner thread, now (nogil kernels, gap in 2048-sample chunks)", True, None)]
    results: dict[str, list[dict[str, float]]] = {c[0]: [] for c in cases}
    for _ in range(rounds):
        for label, with_scanner, ctx in cases:
            with ctx() if ctx else contextlib.nullcontext():
                results[label].append(gil_lateness(seconds, with_scanner))
            print(label, results[label][-1], flush=True)
    rows = []
    for label, _, _ in cases:
        med = {k: statistics.median(r[k] for r in results[label]) for k in results[label][0]}
        val = f"{med['p50']:.3g} / {med['p99']:.3g} / {med['max']:.3g}"
        if "during_max" in med:
            val += f" / {med['during_max']:.3g} (apply() after a gap: {med['long_call']:.3g})"
        rows.append((label, val))
    return rows


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=5, help="repetitions per case (median reported)")
    ap.add_argument("--samples", type=int, default=1_000_000, help="samples per block")
    ap.add_argument("--gil-seconds", type=float, default=6.0, help="duration of each GIL lateness case [s]; 0 = skip")
    ap.add_argument("--gil-rounds", type=int, default=3, help="rounds of the GIL cases (median reported)")
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/BENCHMARKS.md")
    a = ap.parse_args(argv)
    n, reps = a.samples, a.reps
    u1 = signal(n)
    u3 = np.column_stack([u1, u1[::-1].copy(), np.roll(u1, n // 3)])
    rows = []

    def per_axis(seconds: float, axes: int = 1) -> str:
        return f"{n * axes / seconds / 1e6:.3g}"

    op = GaussianPreisachOperator(default_preisach("x"))
    t = median_s(lambda: (op.reset(), op.block(u1)), reps, warm_up=True)
    rows.append(("Gaussian-mixture Preisach (151-node Everett table) forward", f"block of {n}", per_axis(t), "M samples/s"))

    cfg = default_scanner_config()
    ax = AxisPlant(cfg.x)
    t = median_s(lambda: (ax.reset(), ax.run(u1, 1e-5)), reps, warm_up=True)
    rows.append(("one axis: amplifier + Preisach + creep (5 lags) + mode", f"block of {n}", per_axis(t), "M samples/s per axis"))

    nodrift = default_scanner_config()
    nodrift.drift = DriftConfig(kind="none")
    s = Scanner(nodrift)
    t = median_s(lambda: (s.reset(), s.run(u3, 1e-5)), reps, warm_up=True)
    rows.append(("Scanner.run, 3 axes, no drift", f"block of {n} × 3", per_axis(t, 3), "M samples/s per axis"))

    s = Scanner(default_scanner_config())
    t = median_s(lambda: (s.reset(), s.run(u3, 1e-5)), reps, warm_up=True)
    rows.append(("Scanner.run, 3 axes, default (drift: physical_tube predictor)", f"block of {n} × 3", per_axis(t, 3),
                 "M samples/s per axis"))

    try:
        from afmctl.compensators.preisach import PreisachModel

        m = PreisachModel.from_density(lambda al, be: np.exp(-((al - 80) ** 2 + (be - 40) ** 2) / 800.0),
                                       u_min_V=0.0, u_max_V=150.0, levels=32)
        ext = default_scanner_config()
        ext.drift = DriftConfig(kind="none")
        for axn in ("x", "y", "z"):
            ext.axis(axn).hysteresis = ExternalModelConfig(model=m.model_dump(mode="json"))
        s = Scanner(ext)
        t = median_s(lambda: (s.reset(), s.run(u3, 1e-5)), reps, warm_up=True)
        rows.append(("Scanner.run, 3 axes, compensators PreisachModel (32 levels) as plant", f"block of {n} × 3",
                     per_axis(t, 3), "M samples/s per axis"))
    except ImportError:  # pragma: no cover
        pass

    s = Scanner()
    t = median_s(lambda: (s.reset(), s.image(Grating2D(), scan_size_nm=10_000.0, pixels=256)), max(1, reps // 2),
                 warm_up=True)
    rows.append(("Scanner.image, 1.667 µm grating, uncompensated", "256×256 px, 2 samples/px, trace+retrace", f"{t:.3g}", "s"))
    try:
        from afmctl.sim_backend.image_scans import identify_axes_from_images

        models = identify_axes_from_images(s, ("x", "y"))

        def comp_image():
            s.reset()
            s.image(Grating2D(), scan_size_nm=10_000.0, pixels=256, compensator={k: v.inverse() for k, v in models.items()})

        t = median_s(comp_image, max(1, reps // 2), warm_up=True)
        rows.append(("Scanner.image, same, Preisach-compensated (x, y)", "256×256 px", f"{t:.3g}", "s"))
        t = median_s(lambda: identify_axes_from_images(s, ("x",)), 1, warm_up=True)
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

    t = median_s(stream, reps, warm_up=True)
    rows.append(("streaming apply() + advance() (1 ms of held input = 100 samples)", "per call", f"{t / 2000 * 1e6:.3g}", "µs"))

    gil = gil_rows(a.gil_seconds, a.gil_rounds) if a.gil_seconds > 0 else []

    lines = [
        "## Simulated scanner (sim_backend)",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_sim.py --reps {reps} --gil-seconds {a.gil_seconds:g} "
        f"--gil-rounds {a.gil_rounds}` (median of {reps} runs; one core; "
        f"CPython {platform.python_version()}, {platform.machine()}). Target: ≥ 1 M samples/s per axis for the "
        "Preisach plant. Signal: wandering triangle with noise over 0…150 V at 100 kHz (nested minor loops).",
        "",
        "| what | conditions | median | unit |",
        "|---|---|---|---|",
    ]
    lines += [f"| {w} | {c} | {v} | {u} |" for w, c, v, u in rows]
    if gil:
        lines += [
            "",
            "GIL: a 1 kHz ticker thread (stand-in for the controller loop) while another thread calls "
            "`Scanner.apply(volts, now())` every 1 ms like a simulated amplifier, with a 1 s idle gap every "
            "second (the next apply() simulates 100 000 samples × 3 axes). \"before\" = kernels without "
            f"`nogil` and a gap in one block (the code before the review). {a.gil_seconds:g} s per case, "
            f"cases interleaved, median over {a.gil_rounds} rounds. Lateness of the ticker [ms]: p50 / p99 / max "
            "over all ticks / max over the ticks due while a long apply() (after a gap) ran; in brackets the "
            "duration of that apply() [ms].",
            "",
            "| case | ticker lateness p50 / p99 / max / max during long apply() [ms] |",
            "|---|---|",
        ]
        lines += [f"| {w} | {v} |" for w, v in gil]
    text = "\n".join(lines) + "\n"
    print(text)
    if not a.no_write:
        write_section(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
