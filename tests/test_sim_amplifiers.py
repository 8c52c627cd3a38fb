"""The simulated amplifiers, tested with raw bytes over their pty — no afmctl driver code.
They must answer exactly as docs/PROTOCOLS.md documents and be no faster than their baud."""
from __future__ import annotations

import os
import time
import uuid

import pytest
import serial

from afmctl.sim_backend.amplifiers import RecordingSink
from afmctl.sim_backend.testing import serve_can, serve_pty


def read_until(port: serial.Serial, end: bytes, timeout_s: float = 1.0, count: int = 1) -> bytes:
    buf = b""
    deadline = time.monotonic() + timeout_s
    while buf.count(end) < count and time.monotonic() < deadline:
        buf += port.read(max(1, port.in_waiting))
    return buf


def ask(port: serial.Serial, cmd: bytes, end: bytes = b">", timeout_s: float = 1.0) -> bytes:
    port.write(cmd)
    return read_until(port, end, timeout_s)


@pytest.fixture
def mdt():
    with serve_pty("mdt693b") as server:
        port = serial.serial_for_url(server.port, baudrate=115200, timeout=0.05, write_timeout=1.0)
        yield server, port
        port.close()


def test_mdt_documented_replies(mdt):
    server, port = mdt
    assert ask(port, b"ECHO=0\r") == b"ECHO=0\r>"          # echo on at power-up, then off
    assert ask(port, b"XVOLTAGE=12.5\r") == b">"
    assert ask(port, b"xvoltage?\r") == b"[ 12.5]\r>"       # case-insensitive, measured at 0.1 V
    assert ask(port, b"XYZVOLTAGE=[1,2,3]\n") == b">"       # LF and brackets accepted
    assert ask(port, b"XYZVOLTAGE=4,5,6\r\n") == b">"       # CRLF: no extra prompt
    assert ask(port, b"XYZVOLTAGE?\r") == b"[  4.0,  5.0,  6.0]\r>"
    assert ask(port, b"FOO?\r") == b"CMD_NOT_DEFINED>"
    assert ask(port, b"XVOLTAGE=abc\r") == b"CMD_NOT_DEFINED>"
    assert ask(port, b"XMAX?\r") == b"150.50\r>"                # bare number
    assert ask(port, b"VLIMIT?\r") == b"[150]\r>"
    reply = ask(port, b"ID?\r")
    assert b"Model MDT693B\r" in reply and b"Firmware Version: " in reply and reply.endswith(b"\r\n>")
    assert ask(port, b"ECHO?\r") == b"Echo Off\r>"
    assert ask(port, b"\n\r") == b"CMD_NOT_DEFINED>"               # an empty line is answered once
    assert server.sink.last == {"x": 4.0, "y": 5.0, "z": 6.0}


def test_mdt_readback_is_measured_at_0_1_V_and_compatibility_mode(mdt):
    server, port = mdt
    ask(port, b"ECHO=0\r")
    assert ask(port, b"XVOLTAGE=12.37\r") == b">"
    assert ask(port, b"XVOLTAGE?\r") == b"[ 12.4]\r>"       # not the setpoint 12.37
    assert server.sink.last["x"] == 12.37                    # the output itself is exact
    assert ask(port, b"cm=1\n\r") == b">"                     # answered in the old mode
    assert ask(port, b"cm?\n\r", b"*") == b"Compatibility Mode On\r*"
    assert ask(port, b"YV20.0\n\r", b"*") == b"*"
    assert ask(port, b"YR\n\r", b"*") == b"[ 20.0]\r*"
    assert ask(port, b"ZH100.0\n\r", b"*") == b"*"
    assert ask(port, b"ZH?\n\r", b"*") == b"100.00\r*"
    assert ask(port, b"%\n\r", b"*") == b"[150]\r*"
    assert ask(port, b"XVOLTAGE?\r", b"*") == b"[ 12.4]\r*"  # long commands still work
    assert ask(port, b"cm=0\r", b"*") == b"*"
    assert ask(port, b"FOO\r") == b"CMD_NOT_DEFINED>"


def test_mdt_panel_and_master_scan_replies(mdt):
    server, port = mdt
    ask(port, b"ECHO=0\r")
    assert ask(port, b"INTENSITY?\r") == b"15\r>"             # bare integers, like the limits
    assert ask(port, b"intensity=4\r") == b">"
    assert ask(port, b"INTENSITY?\r") == b"4\r>"
    assert ask(port, b"INTENSITY=16\r") == b"CMD_NOT_DEFINED>"   # 0..15
    assert ask(port, b"MSENABLE?\r") == b"0\r>"
    assert ask(port, b"MSENABLE=2\r") == b"CMD_NOT_DEFINED>"
    assert ask(port, b"ROTARYMODE=2\r") == b">" and ask(port, b"ROTARYMODE?\r") == b"2\r>"
    assert ask(port, b"PUSHDISABLE=1\r") == b">" and ask(port, b"PUSHDISABLE?\r") == b"1\r>"
    assert ask(port, b"friendly=Stage B\r") == b">"             # the name keeps its case
    assert ask(port, b"FRIENDLY?\r") == b"Stage B\r>"
    assert b"Name: Stage B\r" in ask(port, b"ID?\r")
    assert ask(port, b"FRIENDLY=a>b\r") == b"CMD_NOT_DEFINED>"  # no prompt characters in a name
    help_reply = ask(port, b"?\r")
    assert help_reply.count(b">") == 1 and b"MSENABLE?" in help_reply and b"INTENSITY?" in help_reply
    ask(port, b"XYZVOLTAGE=10,20,140\r")
    assert ask(port, b"MSVOLTAGE=30\r") == b">"                 # held until master scan is on
    assert server.sink.last == {"x": 10.0, "y": 20.0, "z": 140.0}
    assert ask(port, b"MSENABLE=1\r") == b">" and ask(port, b"MSENABLE?\r") == b"1\r>"
    assert server.sink.last == {"x": 40.0, "y": 50.0, "z": 150.0}  # added, each within its limits
    assert ask(port, b"XVOLTAGE?\r") == b"[ 40.0]\r>" and ask(port, b"MSVOLTAGE?\r") == b"[ 30.0]\r>"
    assert ask(port, b"YVOLTAGE=5\r") == b">" and server.sink.last["y"] == 35.0
    assert ask(port, b"MSVOLTAGE=500\r") == b">" and ask(port, b"MSVOLTAGE?\r") == b"[150.0]\r>"
    assert ask(port, b"MSENABLE=0\r") == b">"
    assert server.sink.last == {"x": 10.0, "y": 5.0, "z": 140.0}
    assert server.device.requested_V["master"] == (30.0, 500.0)


def test_mdt_clamps_to_its_limits(mdt):
    server, port = mdt
    ask(port, b"ECHO=0\r")
    assert ask(port, b"YVOLTAGE=200\r") == b">"
    assert ask(port, b"YVOLTAGE?\r") == b"[150.0]\r>"      # VLIMIT 150 wins over XMAX 150.5
    assert ask(port, b"ZVOLTAGE=-5\r") == b">"
    assert ask(port, b"ZVOLTAGE?\r") == b"[  0.0]\r>"
    assert ask(port, b"XMAX=100\r") == b">"
    ask(port, b"XVOLTAGE=120\r")
    assert ask(port, b"XVOLTAGE?\r") == b"[100.0]\r>"
    assert server.device.requested_max_V == 200.0 and server.device.requested_min_V == -5.0


def test_mdt_is_no_faster_than_115200_baud(mdt):
    server, port = mdt
    ask(port, b"ECHO=0\r")
    lines = b"".join(f"XVOLTAGE={i % 150:.2f}\r".encode() for i in range(400))
    t0 = time.monotonic()
    port.write(lines)
    replies = read_until(port, b">", timeout_s=15.0, count=400)
    elapsed = time.monotonic() - t0
    assert replies == b">" * 400
    assert elapsed >= len(lines) * 10 / 115200
    # and not absurdly slow either (generous: the test machine may be busy)
    assert elapsed < 8 * len(lines) * 10 / 115200
    assert server.sink.last["x"] == 399 % 150


def test_silence_disappear_and_return_keep_the_path_and_the_output(mdt):
    server, port = mdt
    ask(port, b"ECHO=0\r")
    ask(port, b"XVOLTAGE=33\r")
    server.silence()
    assert ask(port, b"XVOLTAGE?\r", timeout_s=0.2) == b""
    server.resume()
    assert ask(port, b"XVOLTAGE?\r") == b"[ 33.0]\r>"
    server.disappear()
    assert not os.path.exists(server.port)
    with pytest.raises(serial.SerialException):
        for _ in range(3):
            port.write(b"XVOLTAGE?\r")
            port.read(10)
    port.close()
    server.reappear()
    port2 = serial.serial_for_url(server.port, timeout=0.05, write_timeout=1.0)
    try:
        assert ask(port2, b"XVOLTAGE?\r") == b"[ 33.0]\r>"
    finally:
        port2.close()


def test_gcs_raw_protocol():
    with serve_pty("gcs") as server:
        port = serial.serial_for_url(server.port, timeout=0.05, write_timeout=1.0)
        try:
            assert ask(port, b"SAI?\n", b"3\n") == b"1 \n2 \n3\n"
            port.write(b"SVA 1 10\n")
            assert ask(port, b"ERR?\n", b"\n") == b"303\n"      # servo on at power-up
            assert ask(port, b"ERR?\n", b"\n") == b"0\n"        # cleared by reading
            port.write(b"SVO 1 0 2 0 3 0\nSVA 1 10 2 20.5\n")
            assert ask(port, b"VOL? 1 2\n", b"00\n") == b"1=10.0000 \n2=20.5000\n"
            port.write(b"SVA 1 500\nFOO\n")
            assert ask(port, b"ERR?\n", b"\n") == b"302\n"      # first error latched
            port.write(b"SVA 9 1\n")
            assert ask(port, b"ERR?\n", b"\n") == b"15\n"
            assert server.sink.last == {"x": 10.0, "y": 20.5, "z": 0.0}
        finally:
            port.close()


def test_nv200_raw_protocol():
    with serve_pty("nv200") as server:
        port = serial.serial_for_url(server.port, timeout=0.05, write_timeout=1.0)
        try:
            port.write(b"set,10\r\n")                            # modsrc 1 at power-up: no effect
            assert ask(port, b"meas\r\n", b"\x11") == b"meas,0.000\r\n\x11"
            port.write(b"cl,0\r\nmodsrc,0\r\nset,12.5\r\n")
            assert ask(port, b"meas\r\n", b"\x11") == b"meas,12.500\r\n\x11"
            assert ask(port, b"set,500\r\n", b"\x11") == b"error,4\r\n\x11"
            assert ask(port, b"meas,1\r\n", b"\x11") == b"error,6\r\n\x11"
            assert ask(port, b"bogus\r\n", b"\x11") == b"error,2\r\n\x11"
            assert ask(port, b"avmin\r\n", b"\x11") == b"avmin,-20.000\r\n\x11"
            assert ask(port, b"\r\n", b"\n") == b"NV200/D_NET\r\n"     # device type, no XON
            assert ask(port, b"sr\r\n", b"\x11") == b"sr,2000.000\r\n\x11"
            assert ask(port, b"desc\r\n", b"\x11") == b"desc,PSH15\r\n\x11"
            assert ask(port, b"stat\r\n", b"\x11") == b"stat,1\r\n\x11"   # no sensor bits
            assert server.sink.last == {"x": 12.5}
        finally:
            port.close()


def test_nv200_with_sensor_reports_position_and_piezo_voltage_through_the_recorder():
    with serve_pty("nv200", sensor="strain gauge") as server:
        port = serial.serial_for_url(server.port, timeout=0.05, write_timeout=1.0)
        try:
            port.write(b"cl,0\r\nmodsrc,0\r\nset,55\r\n")
            assert ask(port, b"stat\r\n", b"\x11") == b"stat,3\r\n\x11"   # bits 1-2: strain gauge
            assert ask(port, b"meas\r\n", b"\x11") == b"meas,50.000\r\n\x11"  # µm: (55+20)/150*100
            port.write(b"recast,0\r\nrecsrc,0,2\r\nrecstr,1\r\nreclen,1\r\nrecrun,1\r\n")
            assert ask(port, b"recout,0,0,1\r\n", b"\x11") == b"recout,0,0,55.000\r\n\x11"
            assert server.device.stored_writes == [("cl", 0), ("modsrc", 0)]
        finally:
            port.close()


def test_can_simulator_answers_dbc_frames():
    import can
    import cantools

    from afmctl.sim_backend.amplifiers.can_amp import load_database
    db = load_database()
    channel = f"raw-{uuid.uuid4().hex[:8]}"
    sink = RecordingSink()
    with serve_can(channel, sink) as sim, can.Bus(interface="virtual", channel=channel) as bus:
        sp = db.get_message_by_name("SETPOINT_XYZ")
        bus.send(can.Message(arbitration_id=sp.frame_id, is_extended_id=False,
                             data=sp.encode({"X_V": 1.5, "Y_V": 2.5, "Z_V": 3.5, "SEQ": 0, "FLAGS": 1})))
        msg = bus.recv(1.0)
        assert msg.arbitration_id == 0x190
        status = db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)
        assert (status["X_V"], status["Y_V"], status["Z_V"], status["LAST_SEQ"]) == (1.5, 2.5, 3.5, 0)
        bus.send(can.Message(arbitration_id=sp.frame_id, is_extended_id=False,
                             data=sp.encode({"X_V": 160.0, "Y_V": 0, "Z_V": 0, "SEQ": 5, "FLAGS": 0})))
        codes = []
        for _ in range(2):
            msg = bus.recv(1.0)
            assert msg.arbitration_id == 0x191
            codes.append(db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)["CODE"])
        assert codes == [2, 1]  # sequence gap (expected 1), then out of range
        assert sim.gaps == 1 and sim.rejected == 1
        assert sink.last == {"x": 1.5, "y": 2.5, "z": 3.5}


def test_a_scanner_is_a_sink_and_sees_the_driver_output():
    import afmctl.sim_backend.scanner as scanner_mod
    from afmctl.drivers.registry import open_amplifier
    scanner = scanner_mod.Scanner(scanner_mod.default_scanner_config())
    with serve_pty("mdt693b", sink=scanner) as server:
        amp = open_amplifier("mdt693b", server.port, timeout_s=0.5)
        try:
            amp.set_voltages({"x": 40.0, "y": 20.0, "z": 10.0})
            amp.flush()
        finally:
            amp.close()
    assert list(scanner.held_voltage_V()) == [40.0, 20.0, 10.0]
    assert 0.0 < scanner.time_s < 30.0  # the sink clock starts at 0 when the device is made


def test_adapter_latency_is_modelled_on_replies():
    with serve_pty("mdt694b", latency_s=0.05) as server:
        port = serial.serial_for_url(server.port, timeout=0.01, write_timeout=1.0)
        try:
            ask(port, b"ECHO=0\r")
            t0 = time.monotonic()
            assert ask(port, b"XVOLTAGE?\r") == b"[  0.0]\r>"
            assert time.monotonic() - t0 >= 0.05
        finally:
            port.close()


def test_no_leaks_notices_a_server_left_running_and_passes_once_it_stopped():
    from afmctl.sim_backend.amplifiers.pty_server import PtyServer
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.testing import no_leaks
    server = PtyServer(make_device("nv200"))
    try:
        with pytest.raises(AssertionError, match="threads left running"), no_leaks(grace_s=0.1):
            server.start()
    finally:
        server.stop()
    with no_leaks():
        with serve_pty("gcs") as s:
            link = s.port
        with serve_can(f"leak-{uuid.uuid4().hex[:8]}"):
            pass
    assert not os.path.exists(link) and not os.path.exists(os.path.dirname(link))  # symlink and temp dir gone


def test_a_link_that_cannot_be_made_raises_and_leaks_nothing(tmp_path):
    from afmctl.sim_backend.amplifiers import make_device
    from afmctl.sim_backend.amplifiers.pty_server import PtyServer
    from afmctl.sim_backend.testing import no_leaks
    with no_leaks(grace_s=0.5):
        server = PtyServer(make_device("mdt693b"), link=tmp_path / "missing-dir" / "tty")
        with pytest.raises(OSError):
            server.start()
        server.stop()


def test_the_recorder_writes_a_played_block_and_hands_it_on(tmp_path):
    """A wave generator's block (``play``) is recorded row by row (``afmctl sim --record``)
    and reaches the inner sink, whose ``play`` simulates it in one call."""
    from afmctl.sim_backend.amplifiers.base import CsvRecorder

    class Inner:
        def __init__(self):
            self.blocks = []

        def play(self, t, rows):
            self.blocks.append((list(t), [list(r) for r in rows]))

    inner = Inner()
    rec = CsvRecorder(str(tmp_path / "rec.csv"), inner)
    rec.play([0.1, 0.2], [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    rec.close()
    lines = (tmp_path / "rec.csv").read_text().splitlines()
    assert lines[-2:] == ["0.1,1.0,2.0,3.0", "0.2,4.0,5.0,6.0"]
    assert inner.blocks == [([0.1, 0.2], [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])]
