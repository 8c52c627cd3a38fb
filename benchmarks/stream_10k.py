"""A 10 kHz device-timed stream through the Controller: classic CAN against CAN FD, and
the live producer against ``output = "wave"``.

``afmctl``'s Controller at ``loop.rate_Hz`` 10 000 streams a 50 lines/s raster (4 µm
lines) to the simulated CAN amplifier on python-can's virtual bus: ``output = "stream"``
with one STREAM_XYZ frame per sample (classic CAN) and with STREAM_XYZ_FD frames of 10
samples (``[amplifier.options] fd = true``), and ``output = "wave"`` (the table computed
before the run, played from the FIFO). The variants run interleaved ``--reps`` times; the table gives
medians, with the process's CPU time per streamed sample (producer, driver, simulated
amplifier, run log: everything in the process). The amplifier's sink
only records (no scanner simulation: the simulated scanner costs ≈ 0.15 ms per sample in
this process and could not play 10 kHz itself), so the figures are what the host and the
link carry: device underruns, the lowest FIFO level, the producer's p99 wake-up lateness.
Compensation: a scanner model file (``--model``, e.g. the demo's
``scanner_preisach+creep+dynamics.json``) or the linear calibration.

    .venv/bin/python benchmarks/stream_10k.py [--model FILE.json] [--lines 150] [--no-write]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

from afmctl.drivers.can_amp import CANAmplifier  # noqa: E402
from afmctl.control.controller import Controller  # noqa: E402
from afmctl.sim_backend.amplifiers.base import RecordingSink  # noqa: E402
from afmctl.sim_backend.testing import serve_can  # noqa: E402
from afmctl.testing import make_config  # noqa: E402
from sections import write_section  # noqa: E402  (benchmarks/sections.py)

NAME = "stream_10k"
RATE_HZ = 10_000.0


#: (label, CAN FD, output)
VARIANTS = (("classic CAN, stream", False, "stream"),
            ("CAN FD, stream", True, "stream"),
            ("CAN FD, wave (table before the run)", True, "wave"))


def run(model: Path | None, fd: bool, lines: int, output: str = "stream") -> dict:
    channel = f"bench-10k-{uuid.uuid4().hex[:6]}"
    comp = f'[compensation]\nscanner_model = "{model}"\n' if model else ""
    cfg = make_config(None, comp, loop={"rate_Hz": RATE_HZ},
                      amplifier={"driver": "can", "port": f"virtual:{channel}", "output": output,
                                 "slew_V_per_s": 1e5, "low_water_s": 0.1, "high_water_s": 0.2, "options": {"fd": fd}},
                      safety={"slew_V_per_s": 1e5, "ramp_V_per_s": 2000},
                      trajectory={"kind": "raster", "x0_nm": 1000.0, "y0_nm": 1000.0, "width_nm": 4000.0,
                                  "height_nm": 800.0, "lines": lines, "line_rate_Hz": 50.0, "mode": "trace-retrace"},
                      scanner={"calibration": {"x": {"nm_per_V": 80.0}, "y": {"nm_per_V": 80.0},
                                               "z": {"nm_per_V": 13.3}}})
    with serve_can(channel, RecordingSink(max_history=10)) as sim:
        amp = CANAmplifier.open(f"virtual:{channel}", fd=fd)
        amp.connect()
        try:
            with Controller(cfg, amp) as ctl:
                t0, c0 = time.monotonic(), time.process_time()
                ctl.start(cfg.trajectory)
                if not ctl.wait(600):
                    raise SystemExit("the run did not finish")
                wall, cpu = time.monotonic() - t0, time.process_time() - c0
                st = ctl.stats()
        finally:
            amp.close()
    return {"queued": st["stream"]["queued"], "played": sim.stream.played, "wall_s": round(wall, 2),
            "cpu_us_per_sample": round(1e6 * cpu / max(sim.stream.played, 1), 1),
            "underruns": st["stream"]["underruns"], "lowest_level": st["stream"]["lowest_level"],
            "p99_late_ms": round(st["lateness_p99_s"] * 1e3, 1), "latency_ms": round(st["latency_s"] * 1e3, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, help="scanner model file ([compensation] scanner_model)")
    ap.add_argument("--lines", type=int, default=150, help="raster lines at 50 lines/s (default 150: 3 s)")
    ap.add_argument("--reps", type=int, default=3, help="interleaved repetitions of every variant (default 3)")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    args = ap.parse_args(argv)
    runs: dict[str, list[dict]] = {v[0]: [] for v in VARIANTS}
    for _ in range(args.reps):
        for label, fd, output in VARIANTS:
            r = run(args.model, fd, args.lines, output)
            print(label, r, flush=True)
            runs[label].append(r)
    rows = [{"variant": label, **{k: statistics.median(r[k] for r in rs) for k in rs[0] if k != "latency_ms"},
             "underruns_max": max(r["underruns"] for r in rs)} for label, rs in runs.items()]
    base = next(r for r in rows if r["variant"] == "CAN FD, stream")["cpu_us_per_sample"]
    tab = ("| variant | samples queued | wall [s] | CPU per sample | vs CAN FD stream | device underruns "
           "(median, max) | lowest FIFO level | producer p99 late |\n|---|---|---|---|---|---|---|---|\n" + "".join(
               f"| {r['variant']} | {r['queued']:.0f} | {r['wall_s']} | {r['cpu_us_per_sample']:.1f} µs | "
               f"{r['cpu_us_per_sample'] / base:.2f}× | {r['underruns']:.0f}, {r['underruns_max']} | "
               f"{r['lowest_level']:.0f} | {r['p99_late_ms']} ms |\n" for r in rows))
    print(tab)
    if not args.no_write:
        cmd = " ".join(["benchmarks/stream_10k.py", *(argv if argv is not None else sys.argv[1:])])
        body = ("## 10 kHz device-timed stream through the Controller: classic CAN vs CAN FD, stream vs wave\n\n"
                f"`.venv/bin/python {cmd}` (2 shared cores; medians of {args.reps} interleaved runs). 10 kHz, "
                f"{args.lines} raster lines at 50 lines/s, compensation: "
                f"{args.model.name if args.model else 'linear calibration'}; the simulated CAN amplifier on the "
                "virtual bus with a recording sink (no scanner simulation), so this is what host and link carry; "
                "FIFO marks 0.1 / 0.2 s. Producer lateness counts how late it woke after a top-up (computing up "
                "to 0.1 s of samples takes most of a wake period here); 102 ms is the lateness histogram's last bin "
                "(≥ 102 ms).\n\n" + tab)
        write_section(NAME, body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
