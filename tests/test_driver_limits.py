"""Property: whatever a driver is asked (NaN, ±inf, huge, tiny, just outside a limit), no
value outside its configured limits ever leaves it. Checked at the far end: the simulated
amplifiers record every value a host requested, before their own clamping."""
from __future__ import annotations

import contextlib
import math
import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from afmctl.drivers.errors import LimitError
from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.testing import serve_can, serve_pty

# Odd host limits so that rounding to the protocol's resolution is exercised.
HOST = {"x": (10.0037, 49.9963), "y": (0.0011, 0.0049 + 20), "z": (99.99, 100.004)}

edge = st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -5e-324, 0.0, -0.0,
                        10.0037, 49.9963, 10.0036, 49.9964, 100.004, 100.0041, 99.99, 99.989999])
#: things that are not voltages at all: text, bytes, booleans, None, a list, complex, an int
#: too large for a float
weird = st.sampled_from(["5", b"5", "nan", True, False, np.bool_(True), None, [20.0], 1 + 0j, 10**400, -10**400])
numpy_scalar = st.one_of(st.floats(-1, 200).map(np.float64), st.floats(-1, 200, width=32).map(np.float32),
                         st.integers(-5, 200).map(np.int64))
value = st.one_of(edge, st.floats(allow_nan=True, allow_infinity=True), st.floats(-1, 200),
                  st.integers(-10**20, 10**20), numpy_scalar, weird)
#: axis names a caller might use, present or not
axis_name = st.sampled_from(["x", "y", "z", "x", "y", "z", "w", "X", ""])


@contextlib.contextmanager
def backend(name: str):
    if name == "can":
        ch = f"limits-{uuid.uuid4().hex[:8]}"
        with serve_can(ch) as sim:
            amp = open_amplifier("can", f"virtual:{ch}", timeout_s=0.5, host_limits=HOST)
            try:
                yield amp, sim
            finally:
                amp.close()  # while the device still listens
    else:
        with serve_pty(name) as server:
            axes = ("x",) if name in ("mdt694b", "nv200") else ("x", "y", "z")
            amp = open_amplifier(name, server.port, timeout_s=0.5,
                                 host_limits={a: HOST[a] for a in axes})
            try:
                yield amp, server.device
            finally:
                amp.close()


@pytest.fixture(scope="module", params=["mdt693b", "gcs", "nv200", "can"])
def amp_and_device(request):
    with backend(request.param) as pair:
        yield pair


def _is_voltage(v) -> bool:
    """A real number that is no bool (the test's own oracle, independent of the driver)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _inside(axis: str, v) -> bool:
    if not _is_voltage(v):
        return False
    try:
        f = float(v)
    except OverflowError:
        return False
    return math.isfinite(f) and HOST[axis][0] <= f <= HOST[axis][1]


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.dictionaries(axis_name, value, min_size=0, max_size=4))
def test_no_value_outside_the_limits_leaves_the_driver(amp_and_device, request_values):
    amp, device = amp_and_device
    held = amp.last_output
    before = dict(device.outputs)
    accepted_expected = (bool(request_values)
                         and all(a in amp.axes and _inside(a, v) for a, v in request_values.items()))
    if amp.name == "can":  # one frame carries every axis: the held ones must be inside too
        accepted_expected = accepted_expected and all(
            _inside(a, held[a]) for a in amp.axes if a not in request_values)
    try:
        amp.set_voltages(request_values)
        accepted = True
    except LimitError:
        accepted = False
    assert accepted == accepted_expected, (request_values, held)
    amp.flush()
    # at the far end, per axis: every value ever requested lies in that axis' limits
    for a, (lo, hi) in device.requested_V.items():
        assert amp.limits[a].min_V <= lo <= hi <= amp.limits[a].max_V, (a, lo, hi)
        assert HOST[a][0] <= lo <= hi <= HOST[a][1]
    for a, v in device.outputs.items():
        if accepted and a not in request_values:
            assert v == before[a]  # an axis not asked for never moves
        assert amp.limits[a].min_V <= v <= amp.limits[a].max_V or v == 0.0  # 0.0 = power-up value
    if not accepted:
        assert device.outputs == before


def test_max_step_refuses_jumps_before_sending():
    with serve_pty("mdt694b") as server:
        amp = open_amplifier("mdt694b", server.port, timeout_s=0.5, max_step_V=5.0)
        try:
            amp.set_voltages({"x": 4.0})
            with pytest.raises(LimitError, match="max_step_V"):
                amp.set_voltages({"x": 10.0})
            amp.set_voltages({"x": 9.0})
            assert amp.get_voltages()["x"] == 9.0
            assert server.device.requested_max_V == 9.0
        finally:
            amp.close()


def test_host_limits_that_miss_the_device_range_are_refused_at_connect():
    with serve_pty("nv200") as server, pytest.raises(LimitError, match="do not overlap"):
        open_amplifier("nv200", server.port, timeout_s=0.5, host_limits=(200.0, 300.0))


def test_can_never_clamps_a_held_axis_into_the_limits():
    """A CAN frame carries all three axes. After connect the amplifier may hold 0 V under
    host limits of 10-50 V: setting x alone must not silently move y and z to 10 V."""
    ch = f"held-{uuid.uuid4().hex[:8]}"
    with serve_can(ch) as sim:
        amp = open_amplifier("can", f"virtual:{ch}", timeout_s=0.5, host_limits=(10.0, 50.0))
        try:
            assert amp.last_output == {"x": 0.0, "y": 0.0, "z": 0.0}
            with pytest.raises(LimitError, match="axis y holds 0 V"):
                amp.set_voltages({"x": 12.0})
            amp.flush()
            assert sim.outputs == {"x": 0.0, "y": 0.0, "z": 0.0} and sim.received == 0
            amp.set_voltages({"x": 12.0, "y": 20.0, "z": 30.0})
            amp.set_voltages({"x": 13.0})  # now the held axes are inside: fine
            amp.flush()
            assert sim.outputs == {"x": 13.0, "y": 20.0, "z": 30.0}
        finally:
            amp.close()


@pytest.mark.parametrize("name", ["mdt694b", "can"])
def test_max_step_holds_between_concurrent_callers(name):
    """Two threads each asking for a step of max_step_V in opposite directions must not
    add up to a jump of twice the limit at the amplifier."""
    import threading

    from afmctl.sim_backend.amplifiers import RecordingSink
    sink = RecordingSink()
    ch = f"step-{uuid.uuid4().hex[:8]}"
    ctx = serve_can(ch, sink) if name == "can" else serve_pty(name, sink, baud=0)
    with ctx as server:
        port = f"virtual:{ch}" if name == "can" else server.port
        amp = open_amplifier(name, port, timeout_s=0.5, max_step_V=1.0)
        try:
            start = {a: 50.0 for a in amp.axes}
            v = 0.0
            while v < 50.0:  # walk up to 50 V in allowed steps
                v = min(50.0, v + 1.0)
                amp.set_voltages({a: v for a in amp.axes})
            amp.flush()
            n0 = len(sink.history)
            barrier = threading.Barrier(2)

            def worker(sign):
                for _ in range(200):
                    barrier.wait()
                    try:
                        amp.set_voltages({"x": amp.last_output["x"] + sign * 1.0})
                    except LimitError:
                        pass

            threads = [threading.Thread(target=worker, args=(s,)) for s in (1, -1)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            amp.flush()
        finally:
            amp.close()
    xs = [start["x"]] + [h["x"] for _, h in sink.history[n0:]]
    assert len(xs) > 50  # the threads did move the output
    steps = [abs(b - a) for a, b in zip(xs[:-1], xs[1:])]
    assert max(steps) <= 1.0 + 1e-9
