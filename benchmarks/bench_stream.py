"""Device-timed output over the buffered CAN stream (python-can ``virtual`` bus, our driver,
the simulated CAN amplifier).

1. Throughput: samples queued in bursts until the amplifier has taken them all [frames/s],
   against the ceiling of a classic CAN bus at 1 Mbit/s (8-byte frames, 11-bit id:
   111 bits unstuffed, up to 135 with bit stuffing) — the virtual bus itself has no bitrate.
   Also: the highest play rate streamed for 2 s by StreamProducer with no underrun.
2. Host stalls (20 ms once a second, injected) at 1 kHz, 3 s of a 2 Hz, 100 V sine on x,
   side by side in one run: (a) the host streams one setpoint per tick (``set_voltages``,
   the amplifier applies each on arrival), (b) StreamProducer keeps the FIFO at 100–200 ms.
   Figures: largest deviation of a sample's application time from t0 + k / rate [ms] and the
   largest difference between the held output and the intended waveform [% of 100 V].

Run: ``.venv/bin/python benchmarks/bench_stream.py`` (numbers are noisy on a shared
machine; compare the two columns of one run).
"""
from __future__ import annotations

import time
import uuid

import numpy as np

from afmctl.drivers.can_amp import CANAmplifier
from afmctl.control.safety import SafetyLayer
from afmctl.sim_backend.amplifiers.base import RecordingSink
from afmctl.sim_backend.testing import serve_can
from afmctl.control.stream_producer import StreamProducer

CAN_1M_FRAMES_PER_S = (1e6 / 135, 1e6 / 111)


def _rig(sink):
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    server = serve_can(channel, sink)
    sim = server.__enter__()
    amp = CANAmplifier.open(f"virtual:{channel}")
    amp.connect()
    return server, sim, amp


def _safety(amp, rate_Hz: float) -> SafetyLayer:
    return SafetyLayer(amp, ("x", "y", "z"), {a: (0.0, 150.0) for a in "xyz"}, 1e5, 1 / rate_Hz)


def throughput(n: int = 20_000) -> float:
    sink = RecordingSink(max_history=10)
    server, sim, amp = _rig(sink)
    try:
        amp.start_stream(1_000_000)
        block = [(10.0 + 0.001 * (k % 1000), 5.0, 5.0) for k in range(n)]
        before = sim.received
        t = time.perf_counter()
        for k in range(0, n, 1000):
            amp.queue(block[k:k + 1000])
        while sim.received - before < n and time.perf_counter() - t < 60:
            time.sleep(0.001)
        dt = time.perf_counter() - t  # until the amplifier has taken every frame
        amp.flush_stream()
        return (sim.received - before) / dt
    finally:
        amp.close()
        server.__exit__(None, None, None)


def max_rate(rates=(2000, 5000, 10_000, 20_000)) -> list[tuple[int, int]]:
    out = []
    for rate in rates:
        sink = RecordingSink(max_history=10)
        server, sim, amp = _rig(sink)
        try:
            prod = StreamProducer(amp, _safety(amp, rate), rate, low_water_s=0.05, high_water_s=0.2)
            samples = np.column_stack([np.linspace(0, 100, 2 * rate)] + [np.zeros(2 * rate)] * 2)
            stats = prod.run(samples)
            out.append((rate, stats.underruns))
        finally:
            amp.close()
            server.__exit__(None, None, None)
    return out


def _wave(n: int, rate: int) -> np.ndarray:
    t = np.arange(n) / rate
    return np.column_stack([75 + 50 * np.sin(2 * np.pi * 2 * t), np.full(n, 5.0), np.full(n, 5.0)])


def _stall_hook(t_start: float, stalls: list):
    def stall() -> None:
        if time.monotonic() - t_start >= len(stalls) + 0.5:
            time.sleep(0.020)
            stalls.append(1)
    return stall


def _figures(times: np.ndarray, xs: np.ndarray, t0: float, rate: int) -> tuple[float, float]:
    k = np.arange(len(times))
    jitter_ms = float(np.max(np.abs(times - (t0 + k / rate)))) * 1e3
    grid = t0 + np.arange(len(times) * 10) / (rate * 10)
    held = xs[np.clip(np.searchsorted(times, grid, side="right") - 1, 0, len(xs) - 1)]
    ideal_t = t0 + k / rate  # when each sample was meant to be applied
    ideal = _wave(len(times), rate)[:, 0][np.clip(np.searchsorted(ideal_t, grid, side="right") - 1, 0, len(xs) - 1)]
    return jitter_ms, float(np.max(np.abs(held - ideal)))  # V, = % of the 100 V span


def host_streamed(rate: int = 1000, seconds: float = 3.0) -> tuple[float, float]:
    sink = RecordingSink(max_history=1_000_000)
    server, sim, amp = _rig(sink)
    try:
        wave = _wave(int(rate * seconds), rate)
        amp.set_voltages(dict(zip("xyz", wave[0])))
        t_start, stalls = time.monotonic(), []
        stall, nxt = _stall_hook(t_start, stalls), time.monotonic()
        mark = len(sink.history)
        for row in wave:
            time.sleep(max(nxt - time.monotonic(), 0.0))
            amp.set_voltages(dict(zip("xyz", row)))
            stall()
            nxt += 1 / rate
        amp.flush()
        hist = sink.history[mark:]
        times = np.array([t for t, _ in hist])
        return _figures(times, np.array([v["x"] for _, v in hist]), times[0], rate)
    finally:
        amp.close()
        server.__exit__(None, None, None)


def buffered(rate: int = 1000, seconds: float = 3.0) -> tuple[float, float, int]:
    sink = RecordingSink(max_history=1_000_000)
    server, sim, amp = _rig(sink)
    try:
        wave = _wave(int(rate * seconds), rate)
        amp.set_voltages(dict(zip("xyz", wave[0])))
        amp.flush()
        prod = StreamProducer(amp, _safety(amp, rate), rate, low_water_s=0.1, high_water_s=0.2)
        stats = prod.run(wave, stall=_stall_hook(time.monotonic(), []))
        hist = [(t, v) for t, v in sink.history if t >= sim.stream.t0_s]
        times = np.array([t for t, _ in hist])
        jitter, err = _figures(times, np.array([v["x"] for _, v in hist]), sim.stream.t0_s, rate)
        return jitter, err, stats.underruns
    finally:
        amp.close()
        server.__exit__(None, None, None)


def main() -> None:
    fps = throughput()
    lo, hi = CAN_1M_FRAMES_PER_S
    print(f"queue throughput (virtual bus, driver + simulated amplifier): {fps:,.0f} frames/s; "
          f"1 Mbit/s classic CAN carries {lo:,.0f}-{hi:,.0f} frames/s: {fps / hi * 100:.0f}-{fps / lo * 100:.0f} %")
    for rate, under in max_rate():
        print(f"StreamProducer at {rate} Hz for 2 s: {under} underruns")
    hj, he = host_streamed()
    bj, be, bu = buffered()
    print("1 kHz, 3 s, 20 ms host stall once a second | host-streamed | buffered stream")
    print(f"max sample time deviation [ms]            | {hj:.3f} | {bj:.3f}")
    print(f"max output error vs the intended wave [%]  | {he:.3f} | {be:.3f}")
    print(f"device underruns                           | n/a | {bu}")


if __name__ == "__main__":
    main()
