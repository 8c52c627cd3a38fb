"""Property: whatever a driver is asked (NaN, ±inf, huge, tiny, just outside a limit), no
value outside its configured limits ever leaves it. Checked at the far end: the simulated
amplifiers record every value a host requested, before their own clamping."""
from __future__ import annotations

import contextlib
import math
import uuid

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.errors import LimitError
from drivers.registry import open_amplifier
from sim_backend.testing import serve_can, serve_pty

# Odd host limits so that rounding to the protocol's resolution is exercised.
HOST = {"x": (10.0037, 49.9963), "y": (0.0011, 0.0049 + 20), "z": (99.99, 100.004)}

edge = st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -5e-324, 0.0, -0.0,
                        10.0037, 49.9963, 10.0036, 49.9964, 100.004, 100.0041, 99.99, 99.989999])
value = st.one_of(edge, st.floats(allow_nan=True, allow_infinity=True), st.floats(-1, 200))


@contextlib.contextmanager
def backend(name: str):
    if name == "can":
        ch = f"limits-{uuid.uuid4().hex[:8]}"
        with serve_can(ch) as sim:
            amp = open_amplifier("can", f"virtual:{ch}", timeout_s=0.5, host_limits=HOST)
            yield amp, sim
    else:
        with serve_pty(name) as server:
            axes = ("x",) if name in ("mdt694b", "nv200") else ("x", "y", "z")
            amp = open_amplifier(name, server.port, timeout_s=0.5,
                                 host_limits={a: HOST[a] for a in axes})
            yield amp, server.device
    amp.close()


@pytest.fixture(scope="module", params=["mdt693b", "gcs", "nv200", "can"])
def amp_and_device(request):
    with backend(request.param) as pair:
        yield pair


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.dictionaries(st.sampled_from(["x", "y", "z"]), value, min_size=1))
def test_no_value_outside_the_limits_leaves_the_driver(amp_and_device, request_values):
    amp, device = amp_and_device
    request_values = {a: v for a, v in request_values.items() if a in amp.axes} or {"x": request_values.popitem()[1]}
    inside = all(math.isfinite(v) and HOST[a][0] <= v <= HOST[a][1] for a, v in request_values.items())
    try:
        amp.set_voltages(request_values)
        accepted = True
    except LimitError:
        accepted = False
    assert accepted == inside
    amp.flush()
    lo = min(lim.min_V for lim in amp.limits.values())
    hi = max(lim.max_V for lim in amp.limits.values())
    assert lo >= min(h[0] for h in HOST.values())
    if device.requested_max_V != -math.inf:
        assert lo <= device.requested_min_V and device.requested_max_V <= hi
    for a, v in device.outputs.items():
        assert amp.limits[a].min_V <= v <= amp.limits[a].max_V or v == 0.0  # 0.0 = power-up value


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
