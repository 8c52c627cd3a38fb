"""Reproduce what the soak found: a wave run started while the E-727 still plays the table of a
run that ended on a link error (benchmarks/soak.py, leg ``wave``, fault ``link_lost``).

    nice -n 10 .venv/bin/python benchmarks/wave_after_link_loss.py [--out DIR] [--drop-after-s 0.5]

1. ``afmctl sim --protocol gcs --tcp`` (the simulated E-727, recording every output it applies)
   behind the soak's loopback TCP forwarder;
2. ``afmctl run`` of the soak's wave leg (10 kHz, 2 lines/s; ``--lines`` 40: a 20 s table);
   ``--drop-after-s`` after the amplifier began to play (its record grows by wave rows), the
   forwarder closes the connection:
   the run ends in fault (exit 1) and, as documented, the device plays out the rest of its table;
3. at once a second ``afmctl run`` of the same configuration (as a user, or a supervisor, restarts it).

Prints both exit statuses, the second run's events, and the largest step between consecutive
outputs the amplifier applied (limit: slew / rate = 2 V per sample). Exit status 1 when a step
exceeds the limit.
"""
from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from soak import LEGS, config_text  # noqa: E402
from soak_checks import amp_rows, read_log  # noqa: E402
from soak_procs import AFMCTL, Amp, TcpProxy, free_port  # noqa: E402


def _run(cfg: Path, log: Path) -> subprocess.Popen:
    return subprocess.Popen(AFMCTL + ["run", "--config", str(cfg), "--log", str(log), "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_event(log: Path, event: str, timeout_s: float) -> bool:
    t_end = time.time() + timeout_s
    while time.time() < t_end:
        try:
            if any(e.get("event") == event for e in read_log(log)[1]):
                return True
        except Exception:  # noqa: BLE001  (the log is being written)
            pass
        time.sleep(0.2)
    return False


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=None, help="keep the files here (default: a temporary folder)")
    ap.add_argument("--drop-after-s", type=float, default=0.5,
                    help="cut the link this long after the play was seen to begin [s] (default 0.5)")
    ap.add_argument("--lines", type=int, default=40,
                    help="raster lines at 2 lines/s (default 40: a 20 s table, so that its play-out outlasts the "
                         "first run's exit and the second run's start)")
    args = ap.parse_args(argv)
    spec = dataclasses.replace(LEGS["wave"], lines=args.lines)
    with tempfile.TemporaryDirectory(prefix="wave-link-") as tmp:
        work = (args.out or Path(tmp)).resolve()
        work.mkdir(parents=True, exist_ok=True)
        proxy = TcpProxy()
        amp = Amp(work, "wave", proxy)
        amp.start()
        cfg = work / "wave.toml"
        cfg.write_text(config_text(spec, proxy.url, free_port(), work), encoding="utf-8")
        try:
            first = _run(cfg, work / "first.afmlog")
            if not _wait_event(work / "first.afmlog", "ramp-done", 120):
                print("the first run never started its play", first.communicate()[1][-500:])
                return 2
            base, t_end = amp.record_bytes(), time.time() + 120
            while amp.record_bytes() < base + 500_000 and time.time() < t_end:   # the upload done, the play begun
                time.sleep(0.05)
            time.sleep(args.drop_after_s)
            proxy.drop()
            first.wait(60)
            second = _run(cfg, work / "second.afmlog")
            err = second.communicate(timeout=300)[1]
        finally:
            amp.close()
            proxy.close()
        rows = amp_rows(amp.segments[0])
        steps = abs(rows[1:] - rows[:-1]).max(axis=1)
        worst = float(steps.max()) if len(steps) else 0.0
        print(f"first run: exit {first.returncode}; second run: exit {second.returncode}")
        print("second run events:", [(e["event"], (e.get("detail") or "")[:80] if isinstance(e.get("detail"), str)
                                      else "") for e in read_log(work / "second.afmlog")[1]
                                     if e["event"] not in ("cpu-none", "stats")])
        print("second run stderr:", err.strip().splitlines()[-1:] if err.strip() else "")
        print(f"largest step the amplifier applied: {worst:.4f} V (limit {spec.step_bound_V:g} V per sample); "
              f"steps above it: {int((steps > spec.step_bound_V + 1e-4).sum())}")
        return 1 if worst > spec.step_bound_V + 1e-4 else 0


if __name__ == "__main__":
    sys.exit(main())
