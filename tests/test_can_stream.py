"""Buffered CAN stream (device-timed output): codec with plain bytes, the sans-I/O FIFO player,
and our driver against the simulated amplifier over python-can's ``virtual`` bus."""
from __future__ import annotations

import threading
import time
import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from afmctl.drivers import codec_can
from afmctl.drivers.can_amp import CANAmplifier
from afmctl.drivers.errors import LimitError, ProtocolError
from afmctl.sim_backend.amplifiers.base import RecordingSink
from afmctl.sim_backend.amplifiers.can_stream import StreamPlayer, StreamState
from afmctl.sim_backend.testing import serve_can
from afmctl.testing import assert_few_underruns, ticks_on_the_device_clock, wait_for


# -- codec (plain bytes) --
def test_stream_sample_bytes_are_little_endian_with_a_16_bit_seq():
    data = codec_can.encode_stream_sample([0.0025, 1.0, 163.8375], 0x1234, [0.0] * 3, [200.0] * 3)
    assert data == bytes([0x01, 0x00, 0x90, 0x01, 0xFF, 0xFF, 0x34, 0x12])
    sig = codec_can.decode(codec_can.STREAM_SAMPLE, data)
    assert (sig["X_V"], sig["Y_V"], sig["Z_V"], sig["SEQ"]) == (0.0025, 1.0, 163.8375, 0x1234)


def test_stream_ctrl_bytes_and_refusals():
    assert codec_can.encode_stream_ctrl(codec_can.CMD_START, 10_000) == bytes([0x01, 0x10, 0x27, 0x00, 1, 0])
    assert codec_can.encode_stream_ctrl(codec_can.CMD_START, 1000, 300) == bytes([0x01, 0xE8, 0x03, 0, 0x2C, 1])
    assert codec_can.encode_stream_ctrl(codec_can.CMD_FLUSH) == bytes([0x02, 0, 0, 0, 0, 0])
    with pytest.raises(LimitError, match="prefill"):
        codec_can.encode_stream_ctrl(codec_can.CMD_START, 1000, 0)
    for bad in (0, 0.5, 1e7, float("nan"), 100.5):
        with pytest.raises(LimitError, match="whole number of Hz"):
            codec_can.encode_stream_ctrl(codec_can.CMD_START, bad)
    with pytest.raises(ProtocolError):
        codec_can.encode_stream_ctrl(7)


def test_stream_status_decodes():
    raw = bytes([0x05, 0x00, 0x02, 0x00, 0x09, 0x00, 0xC2, 0x03])
    sig = codec_can.decode(codec_can.STREAM_STATUS, raw)
    assert (sig["LEVEL"], sig["UNDERRUNS"], sig["PLAYED_SEQ"], sig["STREAM_STATE"], sig["CAPACITY_LOG2"],
            sig["OVERFLOWS"]) == (5, 2, 9, 2, 12, 3)


# -- the FIFO player, on a clock the test drives --
def _player(capacity_log2: int = 12):
    played: list[tuple[float, tuple]] = []
    return StreamPlayer(lambda v, t: played.append((t, v)), capacity_log2), played


def test_player_plays_sample_k_at_t0_plus_k_over_rate():
    p, played = _player()
    p.start(1000.0)
    for k in range(10):
        p.push(k, (float(k), 0.0, 0.0), 2.0)  # all arrive at once, t0 = 2.0 s
    p.run_until(2.0045)
    assert [t for t, _ in played] == [2.0 + k / 1000.0 for k in range(5)]
    p.run_until(2.02)  # 5 more played, then 11 ticks with an empty FIFO
    assert len(played) == 10 and p.underruns == 11 and p.played_seq == 9


def test_a_sample_that_arrives_after_its_tick_is_an_underrun():
    p, played = _player()
    p.start(100.0)
    p.push(0, (1.0, 0.0, 0.0), 0.0)
    p.push(1, (2.0, 0.0, 0.0), 0.015)  # tick 1 is at 0.010 s: too late for it
    p.run_until(0.03)
    assert [t for t, _ in played] == [0.0, 0.02] and p.underruns == 2  # ticks 1 and 3


def test_the_clock_starts_when_the_prefill_is_queued():
    p, played = _player()
    p.start(1000.0, prefill=3)
    p.push(0, (1.0, 0.0, 0.0), 0.0)
    p.push(1, (2.0, 0.0, 0.0), 0.004)  # slower than the rate: no underrun while armed
    p.run_until(0.005)
    assert p.state is StreamState.ARMED and not played
    p.push(2, (3.0, 0.0, 0.0), 0.006)
    p.run_until(0.008)
    assert [t for t, _ in played] == [0.006, 0.007, 0.008] and p.underruns == 0
    p.start(1000.0, prefill=10)
    p.push(0, (1.0, 0.0, 0.0), 1.0)
    p.drain(1.5)  # fewer than the prefill: drain starts the clock
    p.run_until(2.0)
    assert played[-1] == (1.5, (1.0, 0.0, 0.0)) and p.state is StreamState.IDLE


def test_drain_flush_overflow_and_gap():
    p, played = _player(capacity_log2=2)
    assert p.push(0, (0.0,) * 3, 0.0) == "idle"
    p.start(10.0)
    assert [p.push(k, (0.0,) * 3, 0.0) for k in (0, 1, 2, 3)] == [None] * 4
    assert p.push(4, (0.0,) * 3, 0.0) == "overflow" and p.overflows == 1
    p.drain(0.0)
    p.run_until(10.0)
    assert p.state is StreamState.IDLE and len(played) == 4 and p.underruns == 0
    p.start(10.0)
    assert p.push(5, (0.0,) * 3, 0.0) == "gap"
    p.flush()
    assert p.status().level == 0 and p.state is StreamState.IDLE


# -- driver against the simulated amplifier --
@pytest.fixture
def link():
    channel = f"stream-{uuid.uuid4().hex[:8]}"
    sink = RecordingSink(max_history=1_000_000)
    with serve_can(channel, sink, record_seq=True) as sim:
        amp = CANAmplifier.open(f"virtual:{channel}", max_step_V=0.5)
        amp.connect()
        try:
            yield amp, sim, sink
        finally:
            amp.close()


def _move_to(amp: CANAmplifier, x_V: float, y_V: float, z_V: float) -> None:
    """Put the output at a start point in one step (the 0.5 V step limit is for the stream)."""
    step, amp.max_step_V = amp.max_step_V, None
    try:
        amp.set_voltages({"x": x_V, "y": y_V, "z": z_V})
        amp.flush()
    finally:
        amp.max_step_V = step


def _ramp(n: int, start_V: float = 0.0, step_V: float = 0.01) -> list[tuple[float, float, float]]:
    return [(start_V + k * step_V, 10.0, 20.0) for k in range(n)]


def test_driver_streams_a_block_played_on_the_amplifier_clock(link):
    amp, sim, sink = link
    _move_to(amp, 0.0, 10.0, 20.0)
    assert amp.start_stream(1000, prefill=300).state == "armed"
    block = _ramp(300)
    assert amp.queue(block) == 300
    amp.drain_stream()  # play what is queued, then stop (no underruns counted at the end)
    assert wait_for(lambda: amp.buffer_status().state == "idle", 5.0)
    played = [(t, v) for t, v in sink.history if sim.stream.t0_s <= t]
    times = [t for t, _ in played]
    assert len(times) == 300
    assert times == [sim.stream.t0_s + k / 1000.0 for k in range(300)]  # zero jitter
    assert [v["x"] for _, v in played] == pytest.approx([x for x, _, _ in block], abs=0.00125)
    st = amp.buffer_status()
    assert st.underruns == 0 and st.overflows == 0 and st.capacity == 4096 and st.played_seq == 299


def test_a_stalling_producer_with_a_buffer_causes_no_underrun(link):
    """1 kHz; the producer sees only what the amplifier reports (STREAM_STATUS every 10 ms),
    tops the FIFO up to 300 samples when it falls under 200, and stalls 20 ms every 200 ms:
    every played sample on a tick t0 + k / rate. The low water mark covers the stall, the
    status age and ordinary scheduling delays: no underrun on a quiet machine (the timing
    figures are benchmarks'); a heavily loaded one may starve the producer beyond it, so the
    count is bounded here, not zero."""
    amp, sim, sink = link
    _move_to(amp, 0.0, 10.0, 20.0)
    amp.start_stream(1000, prefill=300)
    rate, n_total, low, high = 1000, 1500, 200, 300

    def samples(k0: int, n: int) -> list[tuple[float, float, float]]:
        return [(0.001 * ((k0 + i) % 500), 10.0, 20.0) for i in range(n)]

    amp.queue(samples(0, high))
    queued, t_start, next_stall, stalls = high, time.monotonic(), 0.2, 0
    while queued < n_total:
        if time.monotonic() - t_start >= next_stall:
            time.sleep(0.020)  # injected host stall
            next_stall += 0.2
            stalls += 1
        st = amp.latest_buffer_status()
        played = 0 if st is None or st.played_seq == 0xFFFF else st.played_seq + 1
        if queued - played < low:
            n = min(high - (queued - played), n_total - queued)
            amp.queue(samples(queued, n))
            queued += n
        time.sleep(0.002)
    amp.drain_stream()
    assert wait_for(lambda: sim.stream.state is StreamState.IDLE, 5.0)
    times = [t for t, _ in sink.history if t >= sim.stream.t0_s]
    assert stalls >= 3 and len(times) == n_total
    assert ticks_on_the_device_clock(times, sim.stream.t0_s, rate) <= sim.stream.underruns
    assert_few_underruns(sim.stream.underruns, n_total)


def test_flush_stream_stops_at_once_and_reports_the_held_output(link):
    amp, sim, sink = link
    _move_to(amp, 0.0, 10.0, 20.0)
    amp.start_stream(1000)
    amp.queue(_ramp(2000, step_V=0.01))
    time.sleep(0.05)
    held = amp.flush_stream()
    n = sim.stream.played
    assert 0 < n < 2000 and sim.stream.state is StreamState.IDLE
    assert held["x"] == pytest.approx(sink.last["x"], abs=1e-9)
    time.sleep(0.02)
    assert sim.stream.played == n
    assert amp.last_output["x"] == held["x"]


def test_queue_refuses_a_block_with_one_bad_sample_and_sends_none(link):
    amp, sim, _ = link
    _move_to(amp, 0.0, 10.0, 20.0)
    amp.start_stream(1000)
    before = sim.received
    with pytest.raises(LimitError, match="stream sample 3, axis x: step"):
        amp.queue(_ramp(3) + [(5.0, 10.0, 20.0)])
    with pytest.raises(LimitError, match="stream sample 1, axis y.*outside the limits"):
        amp.queue([(0.0, 10.0, 20.0), (0.0, 200.0, 20.0)])
    with pytest.raises(LimitError, match="not a finite"):
        amp.queue([(float("nan"), 10.0, 20.0)])
    time.sleep(0.02)
    assert sim.received == before


_odd = st.sampled_from([float("nan"), float("inf"), -float("inf"), 200.0, -5.0, 150.0001])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(*(st.one_of(st.floats(-0.6, 0.6), _odd),) * 3), min_size=1, max_size=20))
def test_no_block_makes_the_driver_queue_a_value_outside_limits_or_slew(link, deltas):
    """Whatever the block, every sample the amplifier receives lies in the limits and within
    max_step_V (0.5 V, plus the frame's 2.5 mV quantum) of the one before."""
    amp, sim, _ = link
    if amp.stream_rate_Hz is None:
        _move_to(amp, 75.0, 75.0, 75.0)
        amp.start_stream(100_000)
    prev = dict(amp.last_output)
    block, cur = [], [prev[a] for a in "xyz"]
    for row in deltas:  # small numbers are steps from the previous sample, odd ones absolute
        cur = [c + d if -1 < d < 1 else d for c, d in zip(cur, row)]
        block.append(tuple(cur))
    before = len(sim.stream_log)
    try:
        amp.queue(block)
    except LimitError:
        time.sleep(0.005)
        assert len(sim.stream_log) == before and amp.last_output == prev
        return
    assert wait_for(lambda: len(sim.stream_log) == before + len(block), 5.0)
    got = [tuple(prev[a] for a in "xyz")] + sim.stream_log[before:]
    for r0, r1 in zip(got, got[1:]):
        for v0, v1 in zip(r0, r1):
            assert 0.0 <= v1 <= 150.0 and abs(v1 - v0) <= 0.5 + 1e-9


def test_simulator_stream_frames_on_the_raw_bus():
    """Raw frames (cantools from the DBC file, no driver): start answers STREAM_STATUS armed,
    a sample out of range stops the stream (ERROR 1, state fault), a SEQ gap is reported."""
    import can
    import cantools
    from pathlib import Path

    db = cantools.database.load_file(str(Path(codec_can.__file__).with_name(codec_can.DBC_RESOURCE)))
    ctrl, sample = db.get_message_by_name("STREAM_CTRL"), db.get_message_by_name("STREAM_XYZ")
    channel = f"raw-{uuid.uuid4().hex[:8]}"

    def send(bus, msg, **sig):
        bus.send(can.Message(arbitration_id=msg.frame_id, is_extended_id=False, data=msg.encode(sig)))

    def recv(bus, name):
        while (m := bus.recv(1.0)) is not None:
            if m.arbitration_id == db.get_message_by_name(name).frame_id:
                return db.decode_message(m.arbitration_id, m.data, decode_choices=False)
        raise AssertionError(f"no {name}")

    with serve_can(channel) as sim, can.Bus(interface="virtual", channel=channel) as bus:
        send(bus, ctrl, CMD=1, RATE_HZ=100, PREFILL=5)
        st = recv(bus, "STREAM_STATUS")
        assert (st["STREAM_STATE"], st["LEVEL"], st["CAPACITY_LOG2"]) == (1, 0, 12)
        send(bus, sample, X_V=1.0, Y_V=1.0, Z_V=1.0, SEQ=0)
        send(bus, sample, X_V=1.0, Y_V=1.0, Z_V=1.0, SEQ=2)
        assert (recv(bus, "ERROR")["CODE"], sim.gaps) == (2, 1)
        send(bus, sample, X_V=160.0, Y_V=1.0, Z_V=1.0, SEQ=3)
        assert recv(bus, "ERROR")["CODE"] == 1
        send(bus, ctrl, CMD=0, RATE_HZ=0, PREFILL=0)
        st = recv(bus, "STREAM_STATUS")
        assert (st["STREAM_STATE"], st["LEVEL"]) == (4, 0) and sim.stream.played == 0


# ---------------------------------------------------------------- CAN FD: several samples per frame
def test_fd_block_codec_round_trip_on_plain_bytes():
    from afmctl.drivers import codec_can as codec
    rows = [(0.0025 * k, 10.0 + 0.0025 * k, 150.0) for k in range(7)]
    data = codec.encode_stream_block(rows, 65533, [0.0] * 3, [150.0] * 3)
    assert len(data) == 64
    assert data[:3] == bytes([0xFD, 0xFF, 7])                  # SEQ 65533 little-endian, COUNT 7
    assert data[3:5] == (0).to_bytes(2, "little")               # X0 = 0 V
    assert data[5:7] == round(10.0 / 0.0025).to_bytes(2, "little")
    assert data[3 + 6 * 7:] == bytes(64 - 3 - 6 * 7)            # unused slots are zero
    seq, back = codec.decode_stream_block(data)
    assert seq == 65533 and back == [pytest.approx(r, abs=1e-12) for r in rows]
    with pytest.raises(codec.ProtocolError, match="1..10"):
        codec.encode_stream_block([], 0, [0.0] * 3, [150.0] * 3)
    with pytest.raises(codec.ProtocolError, match="COUNT 0"):
        codec.decode_stream_block(bytes(64))
    with pytest.raises(codec.LimitError):
        codec.encode_stream_block([(float("nan"), 0.0, 0.0)], 0, [0.0] * 3, [150.0] * 3)
    assert codec.message("STREAM_XYZ_FD").is_fd and not codec.message("STREAM_XYZ").is_fd


def test_fd_block_packed_from_the_dbc_is_what_cantools_encodes():
    """The struct packing of STREAM_XYZ_FD (read from the DBC's layout) gives cantools' bytes
    for every count, sequence number and voltage, the limits' own steps included."""
    from afmctl.drivers import codec_can as codec
    assert codec.stream_block_struct() is not None and codec.stream_block_struct().size == 64
    rng = np.random.default_rng(38)
    lows, highs = [0.0, 10.0, 0.0], [150.0, 120.0, 163.8375]
    for n in range(1, codec.FD_SAMPLES + 1):
        for seq in (0, 1, 65535, 70000):
            rows = [tuple(rng.uniform(lo, hi) for lo, hi in zip(lows, highs)) for _ in range(n)]
            rows[0] = tuple(lows)
            rows[-1] = tuple(highs)
            sig = {"SEQ": seq & 0xFFFF, "COUNT": n}
            for k in range(codec.FD_SAMPLES):
                q = ([codec.quantize_inside(v, lo, hi) for v, lo, hi in zip(rows[k], lows, highs)] if k < n
                     else [0.0] * 3)
                sig.update({f"X{k}_V": q[0], f"Y{k}_V": q[1], f"Z{k}_V": q[2]})
            want = codec.message("STREAM_XYZ_FD").encode(sig, strict=False)
            assert codec.encode_stream_block(rows, seq, lows, highs) == want, (n, seq)


def test_fd_stream_plays_every_sample_on_the_amplifier_clock():
    """The driver with fd=True sends 10 samples per CAN FD frame; the simulated amplifier
    plays them exactly as single-sample frames (seq, timing)."""
    import uuid

    from afmctl.drivers.can_amp import CANAmplifier
    from afmctl.sim_backend.amplifiers.base import RecordingSink
    from afmctl.sim_backend.testing import serve_can
    channel = f"fd-{uuid.uuid4().hex[:8]}"
    sink = RecordingSink(max_history=100_000)
    with serve_can(channel, sink, record_seq=True) as sim:
        amp = CANAmplifier.open(f"virtual:{channel}", fd=True)
        amp.connect()
        try:
            rate, n = 10_000, 2_000
            amp.start_stream(rate, prefill=500)
            xs = 50.0 + 0.0025 * (np.arange(n) % 400)
            for k in range(0, n, 250):
                amp.queue([(float(x), 20.0, 30.0) for x in xs[k:k + 250]])
            amp.drain_stream()
            deadline = time.monotonic() + 10
            while amp.buffer_status().state != "idle" and time.monotonic() < deadline:
                time.sleep(0.01)
            assert amp.sent == n
        finally:
            amp.close()
    assert sim.seq_log == list(range(n)) and sim.gaps == 0 and sim.rejected == 0
    played = [(t, v) for t, v in sink.history if t >= sim.stream.t0_s]
    assert len(played) == n
    assert ticks_on_the_device_clock([t for t, _ in played], sim.stream.t0_s, rate) <= sim.stream.underruns
    assert_few_underruns(sim.stream.underruns, n)
    np.testing.assert_allclose([v["x"] for _, v in played], xs, atol=1e-9)


def test_the_simulated_amplifier_keeps_its_scanner_current_while_the_stream_is_armed():
    """While the host primes the FIFO (armed: nothing plays, the output holds), time passes
    for the scanner too, so the clock's first tick does not simulate the whole wait in one
    call under the stream lock (after a 2 s settle hold that sent no STREAM_STATUS for
    ~75 ms, and the host refilled the FIFO too late)."""
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    scanner = Scanner(default_scanner_config())
    channel = f"armed-{uuid.uuid4().hex[:8]}"
    with serve_can(channel, scanner):
        amp = CANAmplifier.open(f"virtual:{channel}")
        amp.connect()
        try:
            amp.start_stream(1000, prefill=100)
            amp.queue([[1.0, 0.0, 0.0]] * 10)
            t0 = scanner.time_s
            time.sleep(0.5)
            assert scanner.time_s - t0 > 0.3, scanner.time_s - t0
        finally:
            amp.flush_stream()
            amp.close()
