"""Iterative learning from files on simulated scanners: iterations to converge.

Per plant (the default scanner's x axis and the variants of ``benchmarks/unseen_plants.py``),
through the command line as a user with an external sensor runs it:

1. ``afmctl excite --kind all`` at 50 kHz → the plant → ``afmctl identify --model auto``
   (the chain), and a straight-line fit of that recording (the linear calibration);
2. a raster target (4 µm lines at 50 lines/s, 1 µm lines at 100 lines/s, narrower where the
   amplifier's slew limit cannot follow them: :func:`feasible_raster`), sampled at 100 kHz;
3. the first table: ``afmctl compensate --model auto.json --limits 0 150 --slew-V-per-s S
   --clip`` (start ``auto``), or the linear calibration, clipped and rate-limited
   (start ``none``); also the auto chain with its modes 30 % too high (``wrong+30%``) and
   a chain whose delay is off by 3/8 of a line period (``bad``: > 90° phase error at the
   line rate);
4. iterations: the table replayed noise-free through a fresh plant (the true x position),
   then ``afmctl learn step --target --sent --measured [--model] --out --limits 0 150
   --slew-V-per-s S --state``; the error of every table: max over the central 80 % of
   each judged line (every raster line but the first, which starts from rest), % of the
   line.

    .venv/bin/python benchmarks/learning.py [--plants default stiff ...] [--rates 50 100]
        [--work DIR] [--no-write] [--figure]

``--work DIR`` keeps the identified models between runs (identification takes 1–3 min per
plant). Writes its section of docs/BENCHMARKS.md between ``<!-- bench:learning -->``
markers and, with ``--figure``, docs/img/learning_convergence.png.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.compensators.dynamics_limits import rate_limit  # noqa: E402
from afmctl.compensators.learning_weights import judged_max_pct  # noqa: E402
from afmctl.compensators.models import load_model, save_model  # noqa: E402
from afmctl.data.datafiles import read_csv, write_csv  # noqa: E402
from afmctl.sim_backend.scanner import default_scanner_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)
from speed_ladder import cli  # noqa: E402
from unseen_plants import PLANTS, play_x  # noqa: E402

NAME = "learning"
DT_S = 1e-5
LIMITS_V = (0.0, 150.0)
#: line widths tried per line rate, widest first [nm]: the first whose lines the amplifier can
#: follow (the auto chain's inverse not slew-limited on the central parts of the lines)
WIDTHS_NM = {50: (4000.0, 2000.0, 1000.0), 100: (1000.0, 500.0), 200: (1000.0, 500.0)}
GOALS = {"auto": (0.3, 10), "none": (0.5, 20), "wrong+30%": (0.3, 10), "bad": (0.3, 10)}


def plant_config(name: str):
    return default_scanner_config() if name == "default" else PLANTS[name][0]


def slew_of(cfg) -> float:
    return float(cfg.x.amplifier.effective_slew_V_per_s() or 1e5)


def raster(cfg, rate: float, width: float, lines: int = 8) -> np.ndarray:
    """x target [nm]: a smooth approach from 0 to a third of the plant's range, a rest,
    ``lines`` trace+retrace lines of ``width`` [nm], a rest."""
    span = float(np.ptp(play_x(cfg, np.linspace(0.0, 150.0, 20000), 1e-3)))
    x0 = span / 3.0
    n = int(round(0.5 / rate / DT_S))
    ramp = np.arange(n) / n
    line = np.concatenate([x0 + width * ramp, x0 + width * (1 - ramp)])
    na = int(0.1 / DT_S)
    approach = x0 * (0.5 - 0.5 * np.cos(np.pi * np.arange(na) / na))
    return np.concatenate([approach, np.full(int(0.1 / DT_S), x0), np.tile(line, lines), np.full(int(0.03 / DT_S), x0)])


def feasible_raster(cfg, rate: float, model_path: Path) -> tuple[np.ndarray, float]:
    """The raster of the widest line in :data:`WIDTHS_NM` that the amplifier can follow:
    the auto chain's inverse within the limits needs no slew limiting on the central 80 %
    of the lines (at a wider line, no table can be right there, learned or not)."""
    from afmctl.compensators.learning_weights import find_lines

    chain, slew = load_model(model_path), slew_of(cfg)
    widths = WIDTHS_NM.get(int(rate), (1000.0,))
    for width in widths:
        tgt = raster(cfg, rate, width)
        u = chain.inverse_within_limits(tgt, DT_S, *LIMITS_V, slew).u_V
        d = np.abs(np.diff(u)) / DT_S
        if all(np.max(d[ln.central(80).start: ln.central(80).stop - 1]) < 0.999 * slew for ln in find_lines(tgt)):
            return tgt, width
    return tgt, width


def identify(name: str, cfg, work: Path) -> tuple[Path, tuple[float, float]]:
    """The ``auto`` chain and the linear calibration (gain nm/V, offset nm), cached."""
    model, calib = work / f"{name}_auto.json", work / f"{name}_calibration.json"
    if not (model.exists() and calib.exists()):
        exc = work / f"{name}_exc.csv"
        cli("excite", "--kind", "all", "--u-min-V", "0", "--u-max-V", "150", "--rate-Hz", "50000",
            "--slew-V-per-s", f"{slew_of(cfg):g}", "--out", str(exc))
        d = read_csv(exc, ("t", "u"))
        y = play_x(cfg, d["u"], 2e-5)
        data = work / f"{name}_data.csv"
        write_csv(data, {"t": d["t"], "u": d["u"], "y": y})
        cli("identify", "--model", "auto", "--data", str(data), "--out", str(model))
        gain, offset = np.polyfit(d["u"], y, 1)
        calib.write_text(json.dumps({"gain_nm_per_V": gain, "offset_nm": offset}))
    c = json.loads(calib.read_text())
    return model, (c["gain_nm_per_V"], c["offset_nm"])


def variant(model_path: Path, kind: str, rate: float, work: Path) -> Path:
    """The auto chain with its dynamics' modes 30 % too high, or its delay 3/8 of a line off."""
    chain = load_model(model_path)
    dyn = chain.dynamics
    if kind == "wrong+30%":
        poles = [(re * 1.3, im * 1.3) if im != 0 else (re, im) for re, im in dyn.poles_rad_per_s]
        dyn = dyn.model_copy(update={"poles_rad_per_s": poles,
                                     "zeros_rad_per_s": [(re * 1.3, im * 1.3) for re, im in dyn.zeros_rad_per_s]})
    else:
        # a lead (the record's end-of-hold reading) goes with no delay: the delay replaces it
        dyn = dyn.model_copy(update={"delay_s": dyn.delay_s + 0.375 / rate, "lead_samples": 0.0})
    out = work / f"{model_path.stem}_{kind.replace('%', 'pct')}_{rate:g}.json"
    save_model(chain.model_copy(update={"dynamics": dyn}), out)
    return out


def first_table(start: str, model: Path, calib: tuple[float, float], target: Path, slew: float, work: Path) -> Path:
    out = work / "u0.csv"
    if start == "none":
        d = read_csv(target, ("t", "y"))
        u = rate_limit((d["y"] - calib[1]) / calib[0], *LIMITS_V, slew * DT_S * 0.999)[0]
        write_csv(out, {"t": d["t"], "u": u})
    else:
        cli("compensate", "--model", str(model), "--target", str(target), "--out", str(out),
            "--limits", *map(str, LIMITS_V), "--slew-V-per-s", f"{slew:g}", "--clip")
    return out


def iterate(cfg, target: Path, sent: Path, model: Path | None, iterations: int, slew: float, work: Path
            ) -> tuple[list[float], str]:
    """Play, measure, learn; the judged error of every table played (max over the central
    80 % of every raster line but the first, % of the line: what ``learn step`` judges and
    prints) and the last status line."""
    tgt = read_csv(target, ("t", "y"))
    state = work / "state.json"
    state.unlink(missing_ok=True)
    errs, status = [], ""
    for k in range(iterations + 1):
        u = read_csv(sent, ("t", "u"))["u"]
        y = play_x(cfg, u, DT_S)
        errs.append(judged_max_pct(y, tgt["y"]))
        if k == iterations:
            break
        meas, nxt = work / "meas.csv", work / f"u{k + 1}.csv"
        write_csv(meas, {"t": tgt["t"], "y": y})
        args = ["learn", "step", "--target", str(target), "--sent", str(sent), "--measured", str(meas),
                "--out", str(nxt), "--limits", *map(str, LIMITS_V), "--slew-V-per-s", f"{slew:g}",
                "--state", str(state)]
        out = cli(*args, *(("--model", str(model)) if model else ()))
        status = next(ln for ln in out.splitlines() if ln.startswith("status"))
        sent = nxt
        if "stopped" in status:
            u = read_csv(sent, ("t", "u"))["u"]
            errs.append(judged_max_pct(play_x(cfg, u, DT_S), tgt["y"]))
            break
    return errs, status.split(":", 1)[1].strip() if status else ""


def run_case(name: str, rate: float, start: str, work: Path) -> dict:
    cfg = plant_config(name)
    slew = slew_of(cfg)
    model, calib = identify(name, cfg, work)
    target = work / "target.csv"
    tgt, width = feasible_raster(cfg, rate, model)
    write_csv(target, {"t": np.arange(tgt.size) * DT_S, "y": tgt})
    learn_model = None if start == "none" else (model if start == "auto" else variant(model, start, rate, work))
    sent = first_table(start, learn_model or model, calib, target, slew, work)
    goal, n_iter = GOALS[start]
    t0 = time.perf_counter()
    errs, status = iterate(cfg, target, sent, learn_model, n_iter, slew, work)
    hit = next((k for k, e in enumerate(errs) if e <= goal), None)
    return {"plant": name, "rate": rate, "width_nm": width, "start": start, "errors": errs, "reached": hit, "goal": goal,
            "status": status, "seconds": time.perf_counter() - t0}


def table(rows: list[dict]) -> str:
    head = ("| plant | lines/s | line | start | first table | best | iterations to goal | errors per iteration | status |\n"
            "|---|---|---|---|---|---|---|---|---|\n")
    body = ""
    for r in rows:
        reached = f"{r['reached']} (≤ {r['goal']:g} %)" if r["reached"] is not None else f"not reached (≤ {r['goal']:g} %)"
        errs = " ".join(f"{e:.2f}" for e in r["errors"])
        body += (f"| {r['plant']} | {r['rate']:g} | {r['width_nm'] / 1000:g} µm | {r['start']} | {r['errors'][0]:.2f} | {min(r['errors']):.2f} | "
                 f"{reached} | {errs} | {r['status'][:90]} |\n")
    return head + body


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    starts = sorted({r["start"] for r in rows}, key=list(GOALS).index)
    fig, axes = plt.subplots(1, len(starts), figsize=(4.2 * len(starts), 3.6), sharey=True, squeeze=False)
    for ax, start in zip(axes[0], starts):
        for r in (r for r in rows if r["start"] == start):
            ax.semilogy(range(len(r["errors"])), r["errors"], marker="o", ms=3, label=f"{r['plant']} {r['rate']:g}/s")
        ax.axhline(GOALS[start][0], color="k", ls="--", lw=0.8)
        ax.set_title(f"start: {start}")
        ax.set_xlabel("table (0 = the first)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("max error, central 80 % of lines [% of line]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def shared_plants(work: Path, names: list[str]) -> list[str]:
    """The reference scanners of ``../shared/plants`` (zoo.py) through their own
    ``check.py`` learn loop (``afmctl learn step --state`` per iteration, with and without
    the chain): one line per plant and mode, max % of the line at 50 | 100 lines/s, the
    first table and the last three. A plant's chain is ``WORK/<plant>/model.json``
    (``check.py --only speed --keep WORK`` identifies it), else identified here."""
    plants_dir = ROOT.parent / "shared" / "plants"
    sys.path.insert(0, str(plants_dir))
    import check  # type: ignore[import-not-found]  # noqa: E402  (../shared/plants/check.py)

    lines = []
    for name in names:
        d = work / name
        d.mkdir(parents=True, exist_ok=True)
        if not (d / "model.json").exists():
            check.speed(name, str(d))
        for mode, its in (("chain", 10), ("none", 20)):
            traces = check.learn(name, str(d), mode, its)
            lines.append(f"| {name} | {mode} ({its}) | " + " | ".join(
                " → ".join(f"{m:.2f}" for m in (tr[0], *tr[-3:])) for tr in traces) + " |")
            print(lines[-1], flush=True)
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plants", nargs="+", choices=["default", *sorted(PLANTS)], default=["default", "stiff", "soft"])
    ap.add_argument("--rates", type=float, nargs="+", default=[50, 100])
    ap.add_argument("--starts", nargs="+", choices=list(GOALS), default=list(GOALS))
    ap.add_argument("--work", type=Path, default=Path("/tmp/afmctl-learning-bench"))
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--figure", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--shared", nargs="*", metavar="PLANT",
                    help="instead: the reference scanners of ../shared/plants (amp-first two-modes lumpy-noisy) "
                         "through their check.py learn loop; print only")
    args = ap.parse_args(argv)
    if args.shared is not None:
        shared_plants(args.work, args.shared or ["amp-first", "two-modes", "lumpy-noisy"])
        return 0
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = []
    for name in args.plants:
        for rate in args.rates:
            for start in args.starts:
                if start in ("wrong+30%", "bad") and rate != args.rates[0]:
                    continue
                r = run_case(name, rate, start, args.work)
                rows.append(r)
                print(f"{name} {rate:g}/s {start}: " + " ".join(f"{e:.3f}" for e in r["errors"])
                      + f"  [{r['status']}] ({r['seconds']:.0f} s)", flush=True)
    tab = table(rows)
    print(tab)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if args.figure:
        figure(rows, ROOT / "docs" / "img" / "learning_convergence.png")
    if not args.no_write:
        write_section(NAME, "## Iterative learning from files (`afmctl learn step`)\n\n"
                      f"`.venv/bin/python benchmarks/learning.py --figure` ({time.perf_counter() - t0:.0f} s, "
                      "models identified once and cached in `--work`). Noise-free replay of each table through a "
                      "fresh simulated plant; max error over the central 80 % of each line, % of the line; "
                      "column 'errors' lists the first table then every learned one (after a stop, the last entry is the best table, which the learner keeps writing). Starts: `auto` = the chain "
                      "from `identify --model auto` (goal ≤ 0.3 % within 10), `none` = linear calibration, no "
                      "model (≤ 0.5 % within 20), `wrong+30%` = the auto chain with its modes 30 % too high, `bad` "
                      "= its delay 3/8 of a line period too long (> 90° phase error at the line rate: the guard must "
                      "stop). Lines of 4 µm at 50 lines/s and 1 µm at 100 lines/s, narrower where the "
                      "amplifier's slew limit cannot follow them (the auto chain's inverse slew-limited on the "
                      "central 80 % of the lines: no table can be right there).\n\n"
                      "![convergence](img/learning_convergence.png)\n\n" + tab)
    return 0


if __name__ == "__main__":
    sys.exit(main())
