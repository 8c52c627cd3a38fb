"""What ``afmctl learn`` prints against what ``afmctl run`` then plays, on the shipped
example configurations, with and without the demo's chain model (issue 40: within 20 %).

Per example and model, two commands, as a user runs them:

1. ``afmctl learn --config EXAMPLE.toml --iterations N --out X.afmwave`` (with
   ``AFMCTL_SIMULATION__ENABLED=true``, and ``AFMCTL_COMPENSATION__SCANNER_MODEL`` for the
   chain): its last line gives, per axis, the max / RMS error [nm] over the judged lines of
   the learned table played once more at the end (step ``replay``), then the play each
   axis's best column comes from;
2. ``afmctl run`` of a copy of the example whose ``[trajectory]`` is ``kind = "learned"``,
   played as a wave (``AFMCTL_AMPLIFIER__OUTPUT=wave``): its summary's tracking error per
   axis, measured by the device's recorder.

``e727_tcp`` and ``nv200_tcp`` run against ``afmctl sim --tcp`` on a free loopback port
(``AFMCTL_AMPLIFIER__PORT``), and ``afmctl run`` plays on the simulator that served the
learning, as a user runs it right after on a device (``--fresh-run``: on a fresh one, a
scanner at rest). The in-process simulators start fresh with every command. Every driver waits up to 5 s for a reply
(``AFMCTL_AMPLIFIER__OPTIONS``): a loaded machine's simulators answer late. The
configurations run in a scratch folder.

    .venv/bin/python benchmarks/learn_vs_run.py [--model demo-out/models/scanner_preisach+creep+dynamics.json]
        [--examples sim_wave_gcs sim_inprocess e727_tcp] [--iterations 10] [--work DIR]

Prints a Markdown table (max nm learned → run, and the ratio) and writes nothing else.
"""
from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
AFMCTL = [sys.executable, "-m", "afmctl"]
DEFAULT_MODEL = ROOT / "demo-out" / "models" / "scanner_preisach+creep+dynamics.json"
#: examples served by ``afmctl sim --tcp``: the simulator's options (an NV200 actuator with a
#: position sensor: without one its recorder has no motion to record)
TCP = {"e727_tcp": ["--protocol", "gcs"], "nv200_tcp": ["--protocol", "nv200", "--sensor", "capacitive"]}
#: an axis's figures in a progress, final or summary line: axis, max [nm], RMS [nm]
AXIS = re.compile(r"\b([xyz]) max ([\d.e+-]+) nm(?: \([^)]*\))? / RMS ([\d.e+-]+) nm")
#: the learn's last line names each axis's best play
BEST = re.compile(r"\(iteration (\d+)\)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def learned_copy(example: Path, table: Path, out: Path) -> Path:
    """``example`` with its ``[trajectory]`` section replaced by the learned table."""
    text = example.read_text()
    section = re.compile(r"^\[trajectory\][^\n]*\n(?:(?!\[).*\n?)*", re.M)
    text = section.sub(f'[trajectory]\nkind = "learned"\nfile = "{table.name}"\n\n', text, count=1)
    out.write_text(text)
    return out


def figures(text: str, marker: str) -> dict[str, tuple[float, float]]:
    """Per axis (max, RMS) [nm] from the first line of ``text`` that holds ``marker``, and
    the lines after it (a run's summary puts one axis per line)."""
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if marker in ln), None)
    if start is None:
        return {}
    out: dict[str, tuple[float, float]] = {}
    for ln in lines[start:start + 4]:
        for axis, mx, rms in AXIS.findall(ln):
            out.setdefault(axis, (float(mx), float(rms)))
    return out


def run(cmd: list[str], env: dict[str, str], cwd: Path, log: Path) -> tuple[int, str]:
    proc = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    log.write_text(proc.stdout + proc.stderr)
    return proc.returncode, proc.stdout + proc.stderr


def one(example: str, model: Path | None, args: argparse.Namespace, work: Path) -> dict:
    """Learn, then run, one example with one model (None: the linear calibration)."""
    tag = f"{example}-{'chain' if model else 'none'}"
    src = ROOT / "examples" / f"{example}.toml"
    cfg = work / f"{tag}.toml"
    cfg.write_text(src.read_text())
    env = {**os.environ, "AFMCTL_SIMULATION__ENABLED": "true", "PYTHONPATH": str(ROOT),
           "AFMCTL_AMPLIFIER__OPTIONS": '{"timeout_s": 5}'}        # a busy machine answers late
    if model is not None:
        env["AFMCTL_COMPENSATION__SCANNER_MODEL"] = str(model)
    sim = _serve(example, env, work)
    try:
        table = work / f"{tag}.afmwave"
        t0 = time.monotonic()
        rc, out = run(AFMCTL + ["learn", "--config", cfg.name, "--iterations", str(args.iterations),
                                "--out", table.name], env, work, work / f"{tag}.learn.txt")
        learn_s = time.monotonic() - t0
        learned = figures(out, "afmctl: learned table")
        plays = len(re.findall(r"afmctl: learn +\d+:", out))
        best_line = next((ln for ln in out.splitlines() if "afmctl: learned table" in ln), "")
        rc_run, out_run = -1, ""
        if rc == 0 and table.exists():
            if sim is not None and args.fresh_run:      # a scanner at rest (module docstring)
                _stop(sim)
                sim = _serve(example, env, work)
            played = learned_copy(cfg, table, work / f"{tag}_learned.toml")
            rc_run, out_run = run(AFMCTL + ["run", "--config", played.name], {**env, "AFMCTL_AMPLIFIER__OUTPUT": "wave"},
                                  work, work / f"{tag}.run.txt")
        return {"tag": tag, "learn_rc": rc, "run_rc": rc_run, "learned": learned, "plays": plays,
                "best": BEST.findall(best_line), "run": figures(out_run, "tracking error"), "learn_s": learn_s}
    finally:
        if sim is not None:
            _stop(sim)


def _serve(example: str, env: dict[str, str], work: Path) -> subprocess.Popen | None:
    """``afmctl sim --tcp`` on a free port for a TCP example (``env`` points to it), else None."""
    if example not in TCP:
        return None
    port = free_port()
    env["AFMCTL_SIMULATION__ENABLED"] = "false"
    env["AFMCTL_AMPLIFIER__PORT"] = f"socket://127.0.0.1:{port}"
    sim = subprocess.Popen(AFMCTL + ["sim", *TCP[example], "--tcp", f"127.0.0.1:{port}"],
                           cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _wait_port(port)
    return sim


def _stop(sim: subprocess.Popen) -> None:
    sim.terminate()
    sim.wait(timeout=10)


def _wait_port(port: int, timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.2)
    raise SystemExit(f"afmctl sim did not listen on 127.0.0.1:{port} within {timeout_s:g} s")


def table(rows: list[dict]) -> str:
    out = ["| example | model | plays | axis (best play) | learned max / RMS [nm] | `afmctl run` max / RMS [nm] "
           "| run / learned (max) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        example, model = r["tag"].rsplit("-", 1)
        if r["learn_rc"] != 0 or not r["learned"]:
            out.append(f"| {example} | {model} | {r['plays']} | learn exited {r['learn_rc']} | | | |")
            continue
        for i, (axis, (mx, rms)) in enumerate(sorted(r["learned"].items())):
            best = r["best"][i] if i < len(r["best"]) else "?"
            got = r["run"].get(axis)
            ran = f"{got[0]:.3g} / {got[1]:.3g}" if got else f"run exited {r['run_rc']}"
            ratio = f"{got[0] / mx:.2f}" if got and mx > 0 else ""
            out.append(f"| {example} | {model} | {r['plays']} | {axis} ({best}) | {mx:.3g} / {rms:.3g} | {ran} | {ratio} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", default=str(DEFAULT_MODEL), help="the chain model (default: the demo's)")
    p.add_argument("--examples", nargs="+", default=["sim_wave_gcs", "sim_inprocess", "e727_tcp"])
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--work", help="scratch folder (default: a temporary one, removed)")
    p.add_argument("--fresh-run", action="store_true", help="TCP examples: afmctl run on a fresh simulator")
    p.add_argument("--models", nargs="+", choices=("chain", "none"), default=["chain", "none"],
                   help="with the chain model, without a model, or both (default)")
    args = p.parse_args(argv)
    model = Path(args.model).resolve()
    if not model.exists():
        raise SystemExit(f"--model {model}: no such file (make demo writes it)")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work).resolve() if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rows = []
        for example in args.examples:
            for m in [model if name == "chain" else None for name in args.models]:
                rows.append(one(example, m, args, work))
                print(f"{rows[-1]['tag']}: learn {rows[-1]['learn_s']:.0f} s, {rows[-1]['plays']} plays",
                      file=sys.stderr, flush=True)
        print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
