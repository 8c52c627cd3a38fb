"""One recorded play on each device link: upload the table, arm the recorder, play, read the
recording back — the time each step takes, and the read-back against the link's ceiling.

GCS (E-727 simulator) and NV200 over real ptys throttled to 115200 baud (11,520 B/s), GCS over
loopback TCP (the E-727's Ethernet port, ``socket://``: no baud rate), CAN on
python-can's ``virtual`` bus (no bit timing: a real 1 Mbit/s bus carries ~8,000 frames/s, the
ceiling quoted). The simulated default scanner with its position sensor is the sink. The
recording holds ``--points`` points of x's position and voltage at the table's rate (GCS and
NV200 20 kHz / 2 = 10 kHz; CAN 10 kHz). Figures: medians of ``--reps`` runs.

    .venv/bin/python benchmarks/bench_recorder.py [--reps N] [--points N] [--no-write]

Writes its section of docs/BENCHMARKS.md (between <!-- bench:recorder --> markers).
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sections import write_section as _write_section  # noqa: E402  (benchmarks/sections.py)

from afmctl.drivers.registry import open_amplifier  # noqa: E402
from afmctl.sim_backend.scanner import Scanner, default_scanner_config  # noqa: E402
from afmctl.sim_backend.testing import serve_can, serve_pty  # noqa: E402

BYTES_PER_S = 115200 / 10
CAN_FRAMES_PER_S = 8000.0


def _table(n: int) -> np.ndarray:
    return 20.0 + 80.0 * (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / n))


def _served(protocol: str, tcp: bool, **options):
    """The simulated device with the default scanner as its load, on a pty or on loopback TCP."""
    sink = Scanner(default_scanner_config())
    if not tcp:
        return serve_pty(protocol, sink=sink, **options)
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    return TcpServer(make_device(protocol, sink, **options))


def _serial_run(protocol: str, n: int, tcp: bool = False) -> dict[str, float]:
    table = _table(n)
    options = {"sensor": "strain gauge"} if protocol == "nv200" else {}
    with _served(protocol, tcp, **options) as server:
        with open_amplifier(protocol, server.port) as amp:
            amp.set_voltages({"x": float(table[0])})
            t0 = time.perf_counter()
            amp.upload_wave("x", table)
            t1 = time.perf_counter()
            amp.configure_recorder(["x"], points=n, divider=2)
            t2 = time.perf_counter()
            amp.start_wave(divider=2)
            while amp.recorded_points() < n:
                time.sleep(0.005)
            t3 = time.perf_counter()
            rec = amp.read_recording()
            t4 = time.perf_counter()
            while amp.wave_status().running["x"]:
                time.sleep(0.005)
    return {"upload_s": t1 - t0, "arm_s": t2 - t1, "play_s": t3 - t2, "read_s": t4 - t3, "points": len(rec),
            "bytes": float(_reply_bytes(protocol, rec))}


def _reply_bytes(protocol: str, rec) -> int:
    """The bytes of the read-back replies, formatted as the simulators send them."""
    y_um, u = rec.y_nm["x"] / 1000.0, rec.u_V["x"]
    if protocol == "gcs":              # DRR?: header (~200 B) + one "pos volts \n" line a point
        return 200 + sum(len(f"{a:.6f} {b:.6f} \n") for a, b in zip(y_um, u))
    return sum(len("recoutf,0," + ",".join(f"{v:.3f}" for v in col) + "\r\n\x11") for col in (y_um, u))


def _can_run(n: int) -> dict[str, float]:
    table = _table(n)
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, Scanner(default_scanner_config())):
        with open_amplifier("can", f"virtual:{channel}") as amp:
            amp.set_voltages({"x": float(table[0]), "y": 0.0, "z": 0.0})
            t0 = time.perf_counter()
            amp.start_stream(10_000, prefill=min(n, 4096))
            t1 = time.perf_counter()
            amp.configure_recorder(["x"], points=n)
            t2 = time.perf_counter()
            amp.queue([(float(v), 0.0, 0.0) for v in table])
            amp.drain_stream()
            while amp.recorded_points() < n:
                time.sleep(0.005)
            t3 = time.perf_counter()
            rec = amp.read_recording()
            t4 = time.perf_counter()
    return {"upload_s": t1 - t0, "arm_s": t2 - t1, "play_s": t3 - t2, "read_s": t4 - t3, "points": len(rec),
            "bytes": 8.0 * len(rec)}


def _ceiling_s(device: str, n: int, reply_bytes: float) -> float:
    if device == "can":
        return n / CAN_FRAMES_PER_S      # one REC_DATA frame per point (one axis)
    return reply_bytes / BYTES_PER_S


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--devices", nargs="+", default=["gcs", "gcs-tcp", "nv200", "can"],
                    choices=["gcs", "gcs-tcp", "nv200", "can"], help="links to measure (a subset: printed only)")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    rows = []
    for device in args.devices:
        runs = [(_can_run(args.points) if device == "can" else
                 _serial_run(device.split("-")[0], args.points, tcp=device.endswith("-tcp")))
                for _ in range(args.reps)]
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        ceiling = _ceiling_s(device, args.points, med["bytes"]) if device != "gcs-tcp" else float("nan")
        rows.append((device, med, ceiling))
        print(device, {k: round(v, 4) for k, v in med.items()}, "ceiling", round(ceiling, 3), flush=True)
    body = [
        "## Recorded play per device link (upload, arm, play, read-back)",
        "",
        f"`.venv/bin/python benchmarks/bench_recorder.py --reps {args.reps} --points {args.points}` — median of "
        f"{args.reps} runs; CPython {platform.python_version()}, shared 2-core machine.",
        "",
        f"{args.points} points of x (position from the simulated scanner's sensor and output voltage), "
        "recorded at the table rate (10 kHz). GCS/NV200 over ptys throttled to 115200 baud; gcs-tcp: the "
        "E-727 over loopback TCP (`socket://`, no baud rate: no ceiling); CAN on "
        "python-can's virtual bus (the ceiling column assumes a real 1 Mbit/s bus, ~8,000 frames/s). "
        "Upload = `upload_wave` (CAN: `start_stream`; its samples go with the play); play = until the "
        "recorder holds every point; read-back = `read_recording`.",
        "",
        "| link | upload | arm | play | read-back | read-back ceiling | read-back / ceiling |",
        "|---|---|---|---|---|---|---|",
    ]
    for device, med, ceiling in rows:
        ceil = "–" if ceiling != ceiling else f"{ceiling:.3f} s"
        ratio = "–" if ceiling != ceiling else f"{med['read_s'] / ceiling:.2f}×"
        body.append(f"| {device} | {med['upload_s']:.3f} s | {med['arm_s'] * 1e3:.1f} ms | {med['play_s']:.3f} s | "
                    f"{med['read_s']:.3f} s | {ceil} | {ratio} |")
    got = {device: med for device, med, _ in rows}
    if "gcs" in got and "nv200" in got:
        gcs_b, nv_b = got["gcs"]["bytes"], got["nv200"]["bytes"]
        body += ["", f"Read-back ceiling: the replies' bytes at 11,520 B/s (GCS `DRR?` {gcs_b:.0f} B = "
                 f"{gcs_b / args.points:.1f} B per two-table point; NV200 two `recoutf` {nv_b:.0f} B = "
                 f"{nv_b / args.points:.1f} B per point); CAN one REC_DATA frame per point and axis."]
    text = "\n".join(body)
    print(text)
    if len(rows) == 4 and not args.no_write:
        _write_section("recorder", text)


if __name__ == "__main__":
    main()
