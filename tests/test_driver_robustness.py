"""A driver facing a misbehaving device ends with a clear AmplifierError quickly: garbage,
wrong prompts, error replies and a port nobody reads never hang it or produce a value."""
from __future__ import annotations

import math
import os
import time
import tty

import pytest

from afmctl.drivers.errors import AmplifierError, AmplifierTimeout, ProtocolError
from afmctl.drivers.registry import open_amplifier
from afmctl.drivers.transport import SerialTransport
from afmctl.sim_backend.amplifiers.pty_server import PtyServer


@pytest.fixture(autouse=True)
def _no_leaks():
    """Every failure path must still close its port, pty, threads and notifiers."""
    from afmctl.sim_backend.testing import no_leaks
    with no_leaks():
        yield


class Canned:
    """A device that answers every line with the same bytes."""

    protocol = "canned"

    def __init__(self, reply: bytes) -> None:
        self.reply = reply

    def feed(self, data: bytes) -> bytes:
        return self.reply * (data.count(b"\r") + data.count(b"\n") - data.count(b"\r\n"))


@pytest.mark.parametrize("driver,reply,expected", [
    ("mdt693b", b"", AmplifierTimeout),                  # silent
    ("mdt693b", b"[ 1.0]\r#", AmplifierTimeout),          # wrong prompt: never a complete reply
    ("mdt693b", b"CMD_NOT_DEFINED>", ProtocolError),
    ("mdt693b", b"x" * 5000, ProtocolError),              # endless garbage
    ("gcs", b"1=abc\n", ProtocolError),
    ("gcs", b"17\n", ProtocolError),
    ("nv200", b"error,2\r\n\x11", ProtocolError),
    ("nv200", b"avmin,abc\x11", ProtocolError),
])
def test_misbehaving_devices_give_a_clear_error_fast(driver, reply, expected):
    with PtyServer(Canned(reply), baud=0) as server:
        t0 = time.monotonic()
        with pytest.raises(expected) as info:
            open_amplifier(driver, server.port, timeout_s=0.2)
        assert time.monotonic() - t0 < 4.0  # bounded by the timeout (generous: busy machine)
        assert isinstance(info.value, AmplifierError)
        if expected is ProtocolError and reply:
            assert info.value.data  # the offending bytes are in the error


def test_write_to_a_port_nobody_reads_times_out():
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        t = SerialTransport(os.ttyname(slave), timeout_s=0.2, write_timeout_s=0.2)
        t.open()
        t0 = time.monotonic()
        with pytest.raises(AmplifierTimeout):
            t.write(b"x" * 200_000)
        assert time.monotonic() - t0 < 4.0  # bounded by the timeout (generous: busy machine)
        t.close()
    finally:
        os.close(master)
        os.close(slave)


def test_unknown_driver_and_missing_port_are_connection_errors():
    from afmctl.drivers.errors import AmplifierConnectionError
    with pytest.raises(AmplifierConnectionError, match="unknown driver"):
        open_amplifier("nope", "/dev/null")
    with pytest.raises(AmplifierConnectionError, match="cannot open"):
        open_amplifier("mdt693b", "/nonexistent/ttyUSB9", timeout_s=0.1)
    with pytest.raises(AmplifierConnectionError, match="INTERFACE:CHANNEL"):
        open_amplifier("can", "afm0")


def test_a_failing_can_bus_reaches_the_driver_through_on_error():
    import uuid

    from afmctl.drivers.base import ConnectionState
    from afmctl.sim_backend.testing import serve_can
    channel = f"onerr-{uuid.uuid4().hex[:8]}"
    with serve_can(channel):
        amp = open_amplifier("can", f"virtual:{channel}", timeout_s=0.3)
        try:
            amp.set_voltages({"x": 5.0})
            amp.transport._bus.shutdown()  # the bus dies under the notifier
            deadline = time.monotonic() + 2.0
            while amp.state is not ConnectionState.DISCONNECTED and time.monotonic() < deadline:
                time.sleep(0.01)
            assert amp.state is ConnectionState.DISCONNECTED
            amp.reconnect()
            assert amp.get_voltages()["x"] == 5.0
        finally:
            amp.close()


def test_older_mdt_firmware_prompt_is_learned_at_connect():
    from afmctl.sim_backend.testing import serve_pty
    with serve_pty("mdt693b", prompt=b"*") as server:
        amp = open_amplifier("mdt693b", server.port, timeout_s=0.3)
        try:
            assert amp.info()["prompt"] == "*"
            amp.set_voltages({"x": 1.0, "y": 2.0, "z": 3.0})
            assert amp.get_voltages() == {"x": 1.0, "y": 2.0, "z": 3.0}
        finally:
            amp.close()


@pytest.mark.parametrize("protocol,partial", [("mdt693b", b"XVOLTA"), ("gcs", b"SVA 1"), ("nv200", b"se")])
def test_connect_survives_a_partial_command_left_in_the_device(protocol, partial):
    from afmctl.sim_backend.testing import serve_pty
    with serve_pty(protocol) as server:
        server.device.feed(partial)  # e.g. left over from a link lost mid-command
        amp = open_amplifier(protocol, server.port, timeout_s=0.3)
        try:
            amp.set_voltages({"x": 3.0})
            assert amp.get_voltages()["x"] == 3.0
        finally:
            amp.close()


def test_a_garbled_reply_puts_the_driver_in_fault_until_reconnect():
    from afmctl.drivers.base import ConnectionState
    from afmctl.drivers.errors import AmplifierConnectionError
    from afmctl.sim_backend.testing import serve_pty
    with serve_pty("mdt694b") as server:
        amp = open_amplifier("mdt694b", server.port, timeout_s=0.3)
        try:
            real = server.device.command
            server.device.command = lambda line: b"[ garbage]\r>"
            with pytest.raises(ProtocolError) as info:
                amp.get_voltages()
            assert info.value.code is None and b"garbage" in info.value.data
            assert amp.state is ConnectionState.FAULT
            with pytest.raises(AmplifierConnectionError):
                amp.set_voltages({"x": 1.0})
            server.device.command = real
            amp.reconnect()
            amp.set_voltages({"x": 1.0})
            assert amp.get_voltages() == {"x": 1.0}
        finally:
            amp.close()


def test_a_serial_port_is_locked_against_a_second_program():
    from afmctl.drivers.errors import AmplifierConnectionError
    from afmctl.sim_backend.testing import serve_pty
    with serve_pty("nv200") as server:
        amp = open_amplifier("nv200", server.port, timeout_s=0.3)
        try:
            with pytest.raises(AmplifierConnectionError, match="cannot open"):
                open_amplifier("nv200", server.port, timeout_s=0.3)
        finally:
            amp.close()
        open_amplifier("nv200", server.port, timeout_s=0.3).close()  # free again after close


@pytest.mark.parametrize("protocol", ["mdt693b", "gcs"])
def test_concurrent_callers_are_serialised(protocol):
    import threading

    from afmctl.sim_backend.testing import serve_pty
    with serve_pty(protocol, baud=0) as server:
        amp = open_amplifier(protocol, server.port, timeout_s=0.5)
        errors = []

        def worker(axis, base):
            try:
                for i in range(150):
                    amp.set_voltages({axis: base + i * 0.01})
                    if i % 50 == 0:
                        amp.get_voltages()
            except Exception as err:  # noqa: BLE001 - collected and asserted below
                errors.append(err)

        threads = [threading.Thread(target=worker, args=("x", 10.0)), threading.Thread(target=worker, args=("y", 20.0))]
        try:
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            assert not errors
            got = amp.get_voltages()
            tol = amp.readback_resolution_V / 2 + 1e-9  # MDT: its measured output at 0.1 V
            assert got["x"] == pytest.approx(11.49, abs=tol) and got["y"] == pytest.approx(21.49, abs=tol)
        finally:
            amp.close()


# ---- any reply at all: a clear AmplifierError (with the bytes) or a sane connection ----

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_ENDS = {"mdt693b": [b">", b"*", b"\r"], "gcs": [b"\n", b" \n"], "nv200": [b"\x11", b"\r\n"]}


class Flood:
    """A device that answers every chunk it receives with ``reply`` repeated ``times``
    (``times`` large: a device that floods the line)."""

    protocol = "flood"

    def __init__(self, reply: bytes = b"", times: int = 1) -> None:
        self.reply, self.times = reply, times

    def feed(self, data: bytes) -> bytes:
        return self.reply * self.times


@pytest.fixture(scope="module")
def flood_server():
    with PtyServer(Flood(), baud=0) as server:
        yield server


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(driver=st.sampled_from(["mdt693b", "gcs", "nv200"]), data=st.data())
def test_any_reply_gives_an_amplifier_error_or_a_sane_connection(flood_server, driver, data):
    body = data.draw(st.one_of(
        st.binary(max_size=40),
        st.sampled_from([b"[ 1.0]", b"[ nan]", b"1=1e999", b"error,4", b"avmin,-1e400", b"CMD_NOT_DEFINED",
                         b"1=5 ", b"meas,1,2", b"\x00" * 30, b"[" * 300])))
    reply = body + data.draw(st.sampled_from(_ENDS[driver] + [b""]))
    times = data.draw(st.sampled_from([1, 1, 3, 5000]))  # 5000: a device flooding the line
    flood_server.device.reply, flood_server.device.times = reply, times
    t0 = time.monotonic()
    try:
        amp = open_amplifier(driver, flood_server.port, timeout_s=0.1, reconnect_timeout_s=0.1)
    except AmplifierError as err:
        if isinstance(err, ProtocolError) and err.code is None:
            assert err.data is not None  # what the device said is in the error
    else:  # the garbage happened to parse: the limits it gave must still be sane ranges
        try:
            for lim in amp.limits.values():
                assert math.isfinite(lim.min_V) and math.isfinite(lim.max_V) and lim.min_V <= lim.max_V
        finally:
            amp.close()
    assert time.monotonic() - t0 < 5.0  # bounded (generous: busy machine)


def test_mdt_raw_sends_one_query_line_only():
    from afmctl.sim_backend.testing import serve_pty
    with serve_pty("mdt693b") as server:
        amp = open_amplifier("mdt693b", server.port, timeout_s=0.3)
        try:
            assert amp.raw("SERIAL?") == "SIM00001"
            commands = server.device.commands
            for sneaky in ("XVOLTAGE=200\rID?", "XVOLTAGE=200\nID?", "XVOLTAGE=200?", "SYSMAX=160?", "ID"):
                with pytest.raises(ProtocolError, match="one query line"):
                    amp.raw(sneaky)
            assert server.device.commands == commands  # nothing was sent
            assert amp.get_voltages() == {"x": 0.0, "y": 0.0, "z": 0.0}
        finally:
            amp.close()
