"""Streaming throughput of the amplifier drivers against the simulated amplifiers.

Serial: each driver streams setpoints over a real pty to its simulated amplifier, which
throttles itself to 115200 baud (8N1, 10 bits/byte). The one-way ceiling of a protocol is
11,520 bytes/s divided by the bytes the driver actually sends per setpoint (measured at
the simulator, including periodic error checks); the figure of merit is the achieved
rate over that ceiling (target >= 90 %). The clock stops after ``flush()`` — every
setpoint applied and checked. "lockstep" waits for a read-back after every setpoint, for
comparison, and the single-axis MDT case is repeated with a USB adapter's 16 ms latency
timer modelled on every reply.

CAN: 3-axis setpoints on a python-can ``virtual`` bus to the simulated CAN amplifier; the
simulator checks that every SEQ follows the previous one (none lost, none reordered).

    .venv/bin/python benchmarks/bench_drivers.py [--reps N]

Writes its section of docs/BENCHMARKS.md (between <!-- bench:drivers --> markers).
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sections import write_section as _write_section  # noqa: E402  (benchmarks/sections.py)

from afmctl.drivers.registry import open_amplifier  # noqa: E402
from afmctl.sim_backend.amplifiers import RecordingSink  # noqa: E402
from afmctl.sim_backend.testing import serve_can, serve_pty  # noqa: E402

BAUD = 115200
BYTES_PER_S = BAUD / 10


def serial_case(protocol: str, axes: tuple[str, ...], n: int, lockstep: bool = False,
                latency_s: float = 0.0) -> dict:
    with serve_pty(protocol, RecordingSink(max_history=10), baud=BAUD, latency_s=latency_s) as server:
        amp = open_amplifier(protocol, server.port, timeout_s=1.0)
        try:
            lim = amp.limits
            # values keep the same number of digits, so every command has the same length
            points = [{a: round(lim[a].min_V + 0.5 * (lim[a].max_V - lim[a].min_V) + (i % 50) * 0.01 + 0.01, 2)
                       for a in axes} for i in range(n)]
            amp.flush()
            b0 = server.bytes_received
            t0 = time.perf_counter()
            for p in points:
                amp.set_voltages(p)
                if lockstep:
                    amp.get_voltages()
            amp.flush()
            elapsed = time.perf_counter() - t0
            sent = server.bytes_received - b0
            applied = server.device.outputs
            assert all(abs(applied[a] - points[-1][a]) < 1e-3 for a in axes), (applied, points[-1])
        finally:
            amp.close()
    rate = n / elapsed
    bytes_per_pt = sent / n
    return {"rate": rate, "bytes_per_pt": bytes_per_pt, "ceiling": BYTES_PER_S / bytes_per_pt,
            "fraction": rate / (BYTES_PER_S / bytes_per_pt)}


def can_case(n: int) -> dict:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    sink = RecordingSink(max_history=10)
    with serve_can(channel, sink, record_seq=True) as sim:
        amp = open_amplifier("can", f"virtual:{channel}", timeout_s=2.0)
        try:
            first = amp._seq  # the sequence continues after the amplifier's LAST_SEQ
            t0 = time.perf_counter()
            for i in range(n):
                amp.set_voltages({"x": 10 + (i % 4000) * 0.01, "y": 20.0 + (i % 7), "z": 30.0})
            amp.flush()  # raises if the amplifier's LAST_SEQ is not the last sent
            elapsed = time.perf_counter() - t0
        finally:
            amp.close()
        expected = [(first + i) & 0xFF for i in range(n)]
        in_order = sim.seq_log == expected
        return {"rate": n / elapsed, "received": sim.received, "gaps": sim.gaps, "in_order": in_order,
                "lost": n - sim.received}


def update_section(text: str) -> None:
    _write_section("drivers", text)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3, help="repetitions per case (median reported)")
    ap.add_argument("--no-write", action="store_true", help="do not update docs/BENCHMARKS.md")
    args = ap.parse_args(argv)

    cases = [
        ("MDT693B, 1 axis (`XVOLTAGE=`)", "mdt693b", ("x",), 1500),
        ("MDT693B, 3 axes (`XYZVOLTAGE=`)", "mdt693b", ("x", "y", "z"), 800),
        ("PI GCS, 1 axis (`SVA 1 v`)", "gcs", ("x",), 1500),
        ("PI GCS, 3 axes (`SVA 1 v 2 v 3 v`)", "gcs", ("x", "y", "z"), 800),
        ("NV200, 1 axis (`set,v`)", "nv200", ("x",), 1500),
    ]
    rows = []
    ok = True
    for label, proto, axes, n in cases:
        runs = [serial_case(proto, axes, n) for _ in range(args.reps)]
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        ok &= med["fraction"] >= 0.9
        rows.append(f"| {label} | {n} | {med['bytes_per_pt']:.1f} | {med['ceiling']:.0f} | {med['rate']:.0f} | "
                    f"{100 * med['fraction']:.1f} % |")
        print(rows[-1], flush=True)
    lock = [serial_case("mdt693b", ("x",), 200, lockstep=True) for _ in range(args.reps)]
    lock_rate = statistics.median(r["rate"] for r in lock)
    print(f"lockstep MDT693B: {lock_rate:.0f}/s", flush=True)
    # the same with a USB-serial adapter's 16 ms latency timer on every reply
    usb_stream = [serial_case("mdt693b", ("x",), 1500, latency_s=0.016) for _ in range(args.reps)]
    usb = {k: statistics.median(r[k] for r in usb_stream) for k in usb_stream[0]}
    usb_lock = statistics.median(serial_case("mdt693b", ("x",), 40, lockstep=True, latency_s=0.016)["rate"]
                                 for _ in range(args.reps))
    ok &= usb["fraction"] >= 0.9
    print(f"16 ms latency: streaming {usb['rate']:.0f}/s ({100 * usb['fraction']:.1f} %), lockstep {usb_lock:.0f}/s",
          flush=True)

    can_n = 20000
    can_runs = [can_case(can_n) for _ in range(args.reps)]
    can_rate = statistics.median(r["rate"] for r in can_runs)
    can_ok = all(r["lost"] == 0 and r["gaps"] == 0 and r["in_order"] for r in can_runs)
    ok &= can_ok and can_rate >= 5000
    print(f"CAN: {can_rate:.0f}/s, lost/gaps/in-order: "
          f"{[(r['lost'], r['gaps'], r['in_order']) for r in can_runs]}", flush=True)

    text = f"""## Amplifier drivers: streaming throughput

`.venv/bin/python benchmarks/bench_drivers.py --reps {args.reps}` — median of {args.reps} runs;
{platform.python_implementation()} {platform.python_version()}, {time.strftime('%Y-%m-%d')}.

Serial: driver → real pty → simulated amplifier throttled to {BAUD} baud (8N1, 10 bits/byte,
{BYTES_PER_S:.0f} B/s). Ceiling = {BYTES_PER_S:.0f} B/s ÷ bytes sent per setpoint (measured at the
simulator, periodic `ERR?` checks included); time includes the final `flush()` (all applied
and error-checked). Target: ≥ 90 % of the ceiling.

| case | setpoints | bytes/setpoint | ceiling /s | achieved /s | of ceiling |
|---|---|---|---|---|---|
""" + "\n".join(rows) + f"""

For contrast, MDT693B in lockstep (every setpoint followed by a read-back, waiting for
both replies): {lock_rate:.0f} setpoints/s over the bare pty.

With a USB-serial adapter's 16 ms latency timer modelled on every reply
(`serve_pty(..., latency_s=0.016)`), MDT693B single axis: streaming **{usb['rate']:.0f}
setpoints/s ({100 * usb['fraction']:.1f} % of the ceiling)** — the 32-command window covers
the latency — versus **{usb_lock:.0f} setpoints/s** in lockstep.

CAN (python-can `virtual` bus, in-process): {can_n} three-axis setpoints, one SETPOINT_XYZ frame
each: **{can_rate:.0f} setpoints/s** (target ≥ 5,000); lost: {max(r['lost'] for r in can_runs)},
SEQ gaps: {max(r['gaps'] for r in can_runs)}, every SEQ in order: {all(r['in_order'] for r in can_runs)}.
(A real 1 Mbit/s bus caps this at ~7,400–9,000 frames/s.)

All targets met: {ok}.
"""
    if not args.no_write:
        update_section(text)
    print(text)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
