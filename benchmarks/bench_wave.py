"""Wave tables on the simulated PI GCS controller and the NV200 waveform buffer: upload
throughput and playback timing.

Upload: ``GCSAmplifier.upload_wave`` writes an N-point table over a real pty to the
simulated controller, which throttles itself to 115200 baud (8N1: 11,520 bytes/s). The
figure of merit is bytes received by the simulator per second of upload (clock stops after
the closing ``ERR?`` reply) over 11,520 bytes/s (target >= 90 %).

Playback: the table plays at 10 kHz (divider 2 of the 50 us servo cycle). The times the
simulator hands to its sink are computed on its servo clock (point k at t0 + k * 100 us);
the benchmark reports their spacing error and how late, in wall-clock time on the
simulator's own clock, each point was actually applied (the simulator thread's wake-up
granularity: what a real-time sink such as an oscilloscope emulation would see).

    .venv/bin/python benchmarks/bench_wave.py [--reps N] [--points N] [--no-write]

Writes its section of docs/BENCHMARKS.md (between <!-- bench:wave --> markers).
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

from sections import write_section as _write_section  # noqa: E402  (benchmarks/sections.py)

from afmctl.drivers.registry import open_amplifier  # noqa: E402
from afmctl.sim_backend.testing import serve_pty  # noqa: E402

BAUD = 115200
BYTES_PER_S = BAUD / 10
RATE_HZ = 10_000


class LagSink:
    """Records each applied point's computed time and how late (device clock) it came."""

    def __init__(self) -> None:
        self.now = None
        self.t: list[float] = []
        self.lag: list[float] = []

    def apply(self, volts, t_s=None) -> None:
        self.t.append(t_s)
        self.lag.append(self.now() - t_s)


def one_run(n: int, protocol: str = "gcs") -> dict:
    sink = LagSink()
    with serve_pty(protocol, sink, baud=BAUD) as server:
        sink.now = server.device.now
        with open_amplifier(protocol, server.port, timeout_s=2.0, max_step_V=1.0) as amp:
            for v in np.linspace(0.0, 20.0, 41)[1:]:
                amp.set_voltages({"x": float(v)})
            table = 20.0 + 10.0 * np.sin(np.linspace(0.0, 2 * np.pi * 7, n, endpoint=False)) + 1e-3
            amp.flush()
            time.sleep(0.05)
            b0, k0 = server.bytes_received, len(sink.t)
            t0 = time.perf_counter()
            amp.upload_wave("x", table)
            up_s = time.perf_counter() - t0
            up_bytes = server.bytes_received - b0
            amp.start_wave(rate_Hz=RATE_HZ, cycles=1)
            while amp.wave_status().running["x"]:
                time.sleep(0.02)
    t = np.array(sink.t[k0:])
    lag = np.array(sink.lag[k0:])
    return {"bytes": up_bytes, "upload_s": up_s, "of_ceiling": up_bytes / up_s / BYTES_PER_S,
            "played": len(t), "spacing_err_s": float(np.max(np.abs(np.diff(t) * RATE_HZ - np.round(np.diff(t) * RATE_HZ))) / RATE_HZ),
            "span_err_s": float(abs(t[-1] - t[0] - (n - 1) / RATE_HZ)) if len(t) else float("nan"),
            "lag_med_ms": float(np.median(lag) * 1e3), "lag_p99_ms": float(np.percentile(lag, 99) * 1e3),
            "lag_max_ms": float(lag.max() * 1e3)}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3, help="repetitions (median reported)")
    ap.add_argument("--points", type=int, default=20_000, help="table length")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    args = ap.parse_args(argv)
    runs, nv = [], []
    for _ in range(args.reps):  # the two devices alternated, so both see the same machine load
        runs.append(one_run(args.points))
        nv.append(one_run(1024, "nv200"))
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    mnv = {k: statistics.median(r[k] for r in nv) for k in nv[0]}
    for r in runs + nv:
        print(r)
    body = f"""## Wave tables: PI GCS and NV200 on the simulated devices

`.venv/bin/python benchmarks/bench_wave.py --reps {args.reps} --points {args.points}` — median of {args.reps} runs;
CPython {platform.python_version()}, shared 2-core machine under load from other work.

Upload of a {args.points}-point table (`WAV 1 X|& PNT ...` lines of <= 1000 bytes written back to back,
one `ERR?` at the end) over a real pty to the simulator throttled to 115200 baud (11,520 B/s):
**{med['bytes']:.0f} bytes in {med['upload_s']:.3f} s = {med['of_ceiling'] * 100:.1f} % of the link's ceiling**
(target >= 90 %; per run: {', '.join(f"{r['of_ceiling'] * 100:.1f} %" for r in runs)}).

Playback at {RATE_HZ} Hz (divider 2 x 50 us servo cycle) of the {args.points} points ({med['played']:.0f} change
the output after rounding to 0.1 mV and reach the sink): every output time lies on the 100 us grid
within {med['spacing_err_s']:.1e} s, first to last point {med['span_err_s']:.1e} s off (N-1) x 100 us
(computed on the servo clock);
applied late, on the simulator's own clock, by median {med['lag_med_ms']:.2f} ms, p99
{med['lag_p99_ms']:.2f} ms, max {med['lag_max_ms']:.2f} ms (the pty server thread polls the generator
every 5 ms while the link is idle; the output times themselves do not depend on it).

NV200 waveform buffer, all 1024 samples (`gbarb,i,p` lines written back to back, one `grun` read at
the end), same link: **{mnv['bytes']:.0f} bytes in {mnv['upload_s']:.3f} s = {mnv['of_ceiling'] * 100:.1f} % of the
ceiling** (per run: {', '.join(f"{r['of_ceiling'] * 100:.1f} %" for r in nv)}); played at {RATE_HZ} Hz (sampling
factor 2 x 50 us): output times on the 100 us grid within {mnv['spacing_err_s']:.1e} s, applied late by median
{mnv['lag_med_ms']:.2f} ms, max {mnv['lag_max_ms']:.2f} ms. (The vendor's `nv200` library waits 0.4 s for a
possible error reply after every write, so the same upload through it takes about 1024 x 0.4 s = 7 min.)
"""
    if not args.no_write:
        _write_section("wave", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
