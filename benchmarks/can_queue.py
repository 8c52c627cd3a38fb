"""What queueing stream samples costs the host on the CAN amplifier (issue 38: the prefill
of every piece ``afmctl calibrate`` plays, and a 10 kHz stream's 10,000 samples a second).

The simulated CAN amplifier on python-can's virtual bus, CAN FD, in this process (as
``afmctl calibrate`` runs it): ``CANAmplifier.queue`` of ``--rows`` rows (a calibration
piece's prefill: 1,747 at the default water marks), repeated ``--reps`` times, the FIFO
flushed between; then, in the same run, one STREAM_XYZ_FD frame encoded by
:func:`afmctl.drivers.codec_can.encode_stream_block` (quantise, check, pack) against
cantools' ``Message.encode`` alone on the same values.

    .venv/bin/python benchmarks/can_queue.py [--rows 1747] [--reps 7]

Prints medians; docs/BENCHMARKS.md quotes them.
"""
from __future__ import annotations

import argparse
import statistics
import time
import timeit
import uuid

import numpy as np

from afmctl.drivers import codec_can as codec
from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.scanner import Scanner, default_scanner_config
from afmctl.sim_backend.testing import serve_can


def queue_times(rows: list[tuple[float, float, float]], reps: int) -> list[float]:
    """Seconds each ``queue(rows)`` took on a fresh stream."""
    out = []
    channel = f"bench-queue-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, Scanner(default_scanner_config())):
        with open_amplifier("can", f"virtual:{channel}", fd=True) as amp:
            for _ in range(reps):
                amp.set_voltages({"x": rows[0][0], "y": rows[0][1], "z": rows[0][2]})
                amp.start_stream(10_000, prefill=len(rows))
                t0 = time.perf_counter()
                amp.queue(rows)
                out.append(time.perf_counter() - t0)
                amp.flush_stream()
                time.sleep(0.2)
    return out


def frame_times(reps: int) -> tuple[float, float]:
    """Seconds per frame: encode_stream_block, and cantools' encode of the same signals."""
    rows = [(10.0 + 0.01 * k, 20.0, 30.0) for k in range(codec.FD_SAMPLES)]
    lows, highs = [0.0] * 3, [150.0] * 3
    sig: dict[str, float] = {"SEQ": 5, "COUNT": codec.FD_SAMPLES}
    for k, row in enumerate(rows):
        x, y, z = (codec.quantize_inside(v, lo, hi) for v, lo, hi in zip(row, lows, highs))
        sig.update({f"X{k}_V": x, f"Y{k}_V": y, f"Z{k}_V": z})
    msg = codec.message(codec.STREAM_SAMPLE_FD)
    ours, theirs = [], []
    for _ in range(reps):
        ours.append(min(timeit.repeat(lambda: codec.encode_stream_block(rows, 5, lows, highs), number=2000,
                                      repeat=3)) / 2000)
        theirs.append(min(timeit.repeat(lambda: msg.encode(sig, strict=False), number=2000, repeat=3)) / 2000)
    return statistics.median(ours), statistics.median(theirs)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1747)
    ap.add_argument("--reps", type=int, default=7)
    args = ap.parse_args()
    u = 20.0 + 80.0 * (0.5 - 0.5 * np.cos(2 * np.pi * np.arange(args.rows) / args.rows))
    rows = [(float(v), 30.0, 0.0) for v in u]
    t = statistics.median(queue_times(rows, args.reps))
    ours, theirs = frame_times(args.reps)
    print(f"queue {args.rows} rows (CAN FD, simulated amplifier in-process): median {t * 1e3:.1f} ms, "
          f"{t / args.rows * 1e6:.1f} µs a row")
    print(f"one STREAM_XYZ_FD frame: encode_stream_block {ours * 1e6:.1f} µs (quantise, check, pack); "
          f"cantools' encode alone {theirs * 1e6:.1f} µs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
