"""One contract, every backend: the same tests run against MDT693B, MDT694B, PI GCS and
NV200 (over real ptys to the simulated amplifiers, throttled to 115200 baud) and the CAN
driver (python-can virtual bus). Like python-can's back-to-back suite."""
from __future__ import annotations

import contextlib
import math
import threading
import time
import uuid

import pytest

from afmctl.drivers.base import ConnectionState, VoltageLimits
from afmctl.drivers.errors import AmplifierConnectionError, AmplifierTimeout, LimitError, ProtocolError
from afmctl.drivers.registry import open_amplifier
from afmctl.sim_backend.amplifiers import RecordingSink
from afmctl.sim_backend.testing import no_leaks, serve_can, serve_pty

BACKENDS = ["mdt693b", "mdt694b", "gcs", "nv200", "can"]
#: resolution of the numbers each protocol sends [V]
QUANTUM = {"mdt693b": 0.005, "mdt694b": 0.005, "gcs": 5e-5, "nv200": 5e-4, "can": 0.00125}
TIMEOUT_S = 0.3


class Backend:
    def __init__(self, name: str, server, sink: RecordingSink, port: str) -> None:
        self.name, self.server, self.sink, self.port = name, server, sink, port

    def open(self, **options):
        options.setdefault("timeout_s", TIMEOUT_S)
        options.setdefault("reconnect_timeout_s", 3.0)
        return open_amplifier(self.name, self.port, **options)

    @property
    def device(self):
        return self.server if self.name == "can" else self.server.device

    def device_limits(self) -> dict[str, tuple[float, float]]:
        d = self.device
        if self.name.startswith("mdt"):
            return {a: (d.min_V[a], min(d.max_V[a], d.vlimit_V)) for a in d.axes}
        if self.name == "gcs":
            return {a: (d.vmi[k], d.vma[k]) for k, a in zip("123", "xyz")}
        if self.name == "nv200":
            return {"x": (d.params["avmin"], d.params["avmax"])}
        return {a: (d.min_V, d.max_V[a]) for a in d.axes}

    def outputs(self) -> dict[str, float]:
        return dict(self.device.outputs)


@contextlib.contextmanager
def make_backend(name: str):
    sink = RecordingSink()
    if name == "can":
        channel = f"contract-{uuid.uuid4().hex[:8]}"
        with serve_can(channel, sink) as sim:
            yield Backend(name, sim, sink, f"virtual:{channel}")
    else:
        with serve_pty(name, sink) as server:
            yield Backend(name, server, sink, server.port)


@pytest.fixture(params=BACKENDS)
def backend(request):
    # every test of the contract must leave no thread, pty, port or CAN notifier behind
    with no_leaks(), make_backend(request.param) as b:
        yield b


@pytest.fixture
def amp(backend):
    a = backend.open()
    yield a
    a.close()


def midpoints(amp, frac: float = 0.5) -> dict[str, float]:
    return {a: lim.min_V + frac * (lim.max_V - lim.min_V) for a, lim in amp.limits.items()}


def test_set_and_read_back(backend, amp):
    assert amp.state is ConnectionState.CONNECTED
    for frac in (0.25, 0.5, 0.8):
        want = midpoints(amp, frac)
        amp.set_voltages(want)
        got = amp.get_voltages()
        assert set(got) == set(amp.axes)
        for axis, v in want.items():
            assert got[axis] == pytest.approx(v, abs=QUANTUM[backend.name])
            assert backend.outputs()[axis] == pytest.approx(v, abs=QUANTUM[backend.name])
    assert backend.sink.last["x"] == pytest.approx(want["x"], abs=QUANTUM[backend.name])


def test_single_axis_set_keeps_the_others(backend, amp):
    start = midpoints(amp, 0.3)
    amp.set_voltages(start)
    amp.set_voltages({"x": midpoints(amp, 0.6)["x"]})
    got = amp.get_voltages()
    for axis in amp.axes:
        want = midpoints(amp, 0.6 if axis == "x" else 0.3)[axis]
        assert got[axis] == pytest.approx(want, abs=QUANTUM[backend.name])


def test_limits_are_read_from_the_device(backend, amp):
    dev = backend.device_limits()
    assert set(amp.limits) == set(dev) == set(amp.axes)
    for axis, (lo, hi) in dev.items():
        assert amp.limits[axis] == VoltageLimits(lo, hi)


def test_host_limits_narrow_the_device_range_and_refuse_before_sending(backend):
    amp = backend.open(host_limits=(10.0, 50.0))
    try:
        for axis, (lo, hi) in backend.device_limits().items():
            assert amp.limits[axis] == VoltageLimits(max(lo, 10.0), min(hi, 50.0))
        amp.set_voltages({a: 20.0 for a in amp.axes})  # every axis from 0 V into the host range
        amp.flush()
        count = backend.sink.count
        for bad in (50.5, 9.99, math.nan, math.inf, -math.inf, 1e300):
            with pytest.raises(LimitError):
                amp.set_voltages({"x": bad})
        with pytest.raises(LimitError):
            amp.set_voltages({"w": 20.0})
        amp.flush()
        time.sleep(0.05)
        assert backend.sink.count == count
        assert backend.outputs()["x"] == pytest.approx(20.0, abs=QUANTUM[backend.name])
        # nothing outside the host limits ever reached the device
        assert 10.0 <= backend.device.requested_min_V <= backend.device.requested_max_V <= 50.0
    finally:
        amp.close()


def test_device_errors_map_to_protocol_error_with_the_device_code(backend, amp):
    amp.set_voltages(midpoints(amp, 0.4))
    amp.flush()
    backend.device.inject_error()
    amp.set_voltages(midpoints(amp, 0.5))
    with pytest.raises(ProtocolError) as info:
        amp.flush()
    assert info.value.code is not None
    assert str(info.value.code) in str(info.value)
    # the link stays usable
    amp.set_voltages(midpoints(amp, 0.6))
    got = amp.get_voltages()
    assert got["x"] == pytest.approx(midpoints(amp, 0.6)["x"], abs=QUANTUM[backend.name])


def test_timeout_when_the_device_goes_silent(backend, amp):
    amp.set_voltages(midpoints(amp, 0.3))
    amp.flush()
    backend.server.silence()
    t0 = time.monotonic()
    with pytest.raises(AmplifierTimeout):
        amp.get_voltages()
    assert time.monotonic() - t0 < 4.0  # bounded by the timeout (generous: busy machine)
    assert amp.state is ConnectionState.FAULT
    with pytest.raises(AmplifierConnectionError):  # refuses until reconnect
        amp.set_voltages(midpoints(amp, 0.4))
    backend.server.resume()
    amp.reconnect()
    assert amp.state is ConnectionState.CONNECTED
    assert amp.get_voltages()["x"] == pytest.approx(midpoints(amp, 0.3)["x"], abs=QUANTUM[backend.name])


def test_reconnect_after_the_device_disappears_and_returns(backend, amp):
    before = midpoints(amp, 0.7)
    amp.set_voltages(before)
    amp.flush()
    count = backend.sink.count
    backend.server.disappear()
    with pytest.raises((AmplifierConnectionError, AmplifierTimeout)):
        amp.get_voltages()
    assert amp.state in (ConnectionState.DISCONNECTED, ConnectionState.FAULT)
    timer = threading.Timer(0.3, backend.server.reappear)
    timer.start()
    try:
        amp.reconnect()  # retries with backoff until the device is back
    finally:
        timer.join()
    assert amp.state is ConnectionState.CONNECTED
    assert amp.reconnects == 1
    got = amp.get_voltages()
    for axis, v in before.items():
        assert got[axis] == pytest.approx(v, abs=QUANTUM[backend.name])
    assert backend.sink.count == count  # reconnect sent no setpoint: the output did not jump
    amp.set_voltages(midpoints(amp, 0.2))
    assert amp.get_voltages()["x"] == pytest.approx(midpoints(amp, 0.2)["x"], abs=QUANTUM[backend.name])


def test_reconnect_gives_up_with_a_connection_error(backend):
    amp = backend.open(reconnect_timeout_s=0.3)
    try:
        backend.server.disappear()
        with pytest.raises(AmplifierConnectionError):
            amp.reconnect()
        assert amp.state is ConnectionState.DISCONNECTED
    finally:
        amp.close()


def test_close_is_idempotent(backend, amp):
    amp.set_voltages(midpoints(amp, 0.5))
    amp.close()
    amp.close()
    assert amp.state is ConnectionState.CLOSED
    with pytest.raises(AmplifierConnectionError):
        amp.set_voltages(midpoints(amp, 0.5))
    with pytest.raises(AmplifierConnectionError):
        amp.get_voltages()


def test_info_names_driver_limits_and_state(backend, amp):
    info = amp.info()
    assert info["driver"] == backend.name
    assert info["state"] == "connected"
    assert set(info["limits_V"]) == set(amp.axes)
