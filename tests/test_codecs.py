"""Property tests of the pure codecs: plain bytes in and out, no I/O (caproto style).

Round trips, numbers as sent never outside the limits, and malformed replies (garbage,
truncated, wrong prompt, device error codes) always give a ProtocolError that carries the
bytes — never a hang and never a wrong value. Where a simulator exists, its own
(independent) parser must agree with the host codec."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.drivers import codec_can, codec_gcs, codec_mdt, codec_nv200
from afmctl.drivers.codec_common import format_all_inside, format_inside
from afmctl.drivers.errors import LimitError, ProtocolError
from afmctl.sim_backend.amplifiers.gcs import SimGCS
from afmctl.sim_backend.amplifiers.mdt693b import SimMDT693B
from afmctl.sim_backend.amplifiers.nv200 import SimNV200

volts = st.floats(min_value=0.0, max_value=150.0, allow_nan=False)
any_float = st.floats(allow_nan=True, allow_infinity=True)
limits = st.tuples(st.floats(-200, 200), st.floats(0, 200)).map(lambda t: (t[0], t[0] + t[1]))


# ---------------- number formatting ----------------

@settings(deadline=None, max_examples=50)
@given(st.lists(any_float, min_size=0, max_size=20), limits, st.sampled_from([2, 3, 4]), st.booleans())
def test_format_all_inside_gives_the_texts_format_inside_gives(values, lim, decimals, strip):
    """The one-pass formatting of a wave table is the per-value one, limits and errors alike."""
    lo, hi = lim
    try:
        want = [format_inside(v, lo, hi, decimals, strip=strip) for v in values]
    except LimitError:
        with pytest.raises(LimitError):
            format_all_inside(values, lo, hi, decimals, strip=strip)
        return
    assert format_all_inside(values, lo, hi, decimals, strip=strip) == want


@settings(deadline=None)
@given(any_float, limits, st.sampled_from([2, 3, 4]))
def test_format_inside_never_leaves_the_limits(v, lim, decimals):
    lo, hi = lim
    try:
        text = format_inside(v, lo, hi, decimals)
    except LimitError:
        assert not math.isfinite(v) or math.ceil(lo * 10**decimals) > math.floor(hi * 10**decimals) or hi - lo < 2e-4
        return
    sent = float(text)
    assert lo <= sent <= hi
    assert not text.startswith("-0.") or sent != 0.0
    if lo <= v <= hi:
        assert abs(sent - v) <= 10.0 ** -decimals + 1e-9


# ---------------- MDT693B ----------------

@settings(deadline=None)
@given(st.sampled_from("xyz"), volts)
def test_mdt_set_round_trip_and_the_simulator_agrees(axis, v):
    data = codec_mdt.encode_set(axis, v, 0.0, 150.0)
    assert data.endswith(b"\r") and len(data) == len(f"XVOLTAGE={v:.2f}\r")
    got = codec_mdt.decode_set(data)[axis]
    assert got == pytest.approx(v, abs=0.005 + 1e-9)
    sim = SimMDT693B(echo=False)
    assert sim.feed(data) == b">"
    assert sim.outputs[axis] == got


@settings(deadline=None)
@given(st.tuples(volts, volts, volts))
def test_mdt_xyz_round_trip(values):
    data = codec_mdt.encode_set_xyz(values, [0.0] * 3, [150.0] * 3)
    got = codec_mdt.decode_set(data)
    for a, v in zip("xyz", values):
        assert got[a] == pytest.approx(v, abs=0.005 + 1e-9)


@settings(deadline=None)
@given(st.lists(st.integers(0, 15000), min_size=1, max_size=3), st.booleans())
def test_mdt_value_reply_round_trip(centivolts, echo):
    values = [c / 100 for c in centivolts]
    cmd = b"XYZVOLTAGE?\r" if len(values) == 3 else b"XVOLTAGE?\r"
    reply = codec_mdt.encode_values_reply(values)
    if echo:
        reply = cmd + reply
    assert codec_mdt.parse_values(cmd, reply, len(values)) == values


def test_mdt_replies_of_the_simulator_parse():
    sim = SimMDT693B(echo=True)
    r = sim.feed(b"ECHO=0\r")
    codec_mdt.parse_ack(b"ECHO=0\r", r)
    sim.feed(b"XYZVOLTAGE=1.5,2.25,3\r")
    got = codec_mdt.parse_values(b"XYZVOLTAGE?\r", sim.feed(b"XYZVOLTAGE?\r"), 3)
    assert got == pytest.approx([1.5, 2.25, 3.0], abs=0.05)  # measured at 0.1 V resolution
    assert codec_mdt.parse_value(b"VLIMIT?\r", sim.feed(b"VLIMIT?\r")) == 150.0
    assert codec_mdt.parse_lines(b"ID?\r", sim.feed(b"ID?\r"))[0] == "Model MDT693B"


@pytest.mark.parametrize("reply", [
    b"[ 24.8",            # truncated: no prompt
    b"[ 24.8]\r#",        # wrong prompt
    b"[ 24.8\r>",         # unbalanced bracket
    b"[ abc]\r>",         # not a number
    b"[ 1e999]\r>",       # not finite
    b"[ 1.0, 2.0]\r>",    # wrong count
    b"[]\r>",
    b"\x00\xff>",
    b"[ 24.8]\r[ 1.0]\r>",  # two lines
])
def test_mdt_malformed_value_replies_raise_protocol_error_with_the_bytes(reply):
    with pytest.raises(ProtocolError) as info:
        codec_mdt.parse_value(b"XVOLTAGE?\r", reply)
    assert info.value.data == reply
    assert repr(reply)[2:-1][:6] in str(info.value)


def test_mdt_cmd_not_defined_carries_the_device_text():
    with pytest.raises(ProtocolError) as info:
        codec_mdt.parse_ack(b"XVOLTAGE=1\r", b"CMD_NOT_DEFINED>")
    assert info.value.code == "CMD_NOT_DEFINED" and info.value.data == b"CMD_NOT_DEFINED>"


@settings(deadline=None)
@given(st.binary(max_size=64))
def test_mdt_garbage_never_gives_a_wrong_value(garbage):
    reply = garbage + b">"
    try:
        value = codec_mdt.parse_value(b"XVOLTAGE?\r", reply)
    except ProtocolError as err:
        assert err.data == reply
        return
    # accepted only if the body really is one number in optional brackets
    body = reply[:-1].strip(b"\r\n").strip()
    inner = body[1:-1] if body.startswith(b"[") else body
    assert float(inner) == value and math.isfinite(value)


@settings(deadline=None)
@given(st.binary(max_size=300))
def test_mdt_split_never_hangs(buf):
    n = codec_mdt.split_reply(bytearray(buf))
    assert n == -1 or (0 < n <= len(buf) and buf[n - 1:n] in (b">", b"*"))


def test_mdt_split_rejects_endless_garbage():
    with pytest.raises(ProtocolError) as info:
        codec_mdt.split_reply(bytearray(b"x" * (codec_mdt.MAX_REPLY + 1)))
    assert info.value.data.startswith(b"xxx")


# ---------------- PI GCS ----------------

@settings(deadline=None)
@given(st.dictionaries(st.sampled_from(["1", "2", "3"]), volts, min_size=1))
def test_gcs_sva_round_trip_and_the_simulator_agrees(values):
    data = codec_gcs.encode_sva(values, {k: 0.0 for k in values}, {k: 150.0 for k in values})
    got = codec_gcs.decode_sva(data)
    for k, v in values.items():
        assert got[k] == pytest.approx(v, abs=5e-5 + 1e-9)
    sim = SimGCS(vmax_V=150.0)
    sim.feed(b"SVO 1 0 2 0 3 0\n")
    assert sim.feed(data) == b""
    assert sim.feed(b"ERR?\n") == b"0\n"
    for k, a in zip("123", "xyz"):
        if k in got:
            assert sim.outputs[a] == got[k]


@settings(deadline=None)
@given(st.dictionaries(st.sampled_from(["1", "2", "3", "A", "B"]), st.integers(-10**6, 10**6), min_size=1))
def test_gcs_items_round_trip(items):
    values = {k: v / 1e4 for k, v in items.items()}
    reply = codec_gcs.encode_items_reply(values)
    assert codec_gcs.split_reply(bytearray(reply + b"1=2\n")) == len(reply)
    assert codec_gcs.parse_items(reply, list(values)) == pytest.approx(values)


@pytest.mark.parametrize("code", [1, 2, 15, 17, 302, 303, 999])
def test_gcs_error_codes_become_protocol_errors(code):
    reply = f"{code}\n".encode()
    with pytest.raises(ProtocolError) as info:
        codec_gcs.check_error_reply(reply)
    assert info.value.code == code and info.value.data == reply
    assert info.value.text == codec_gcs.ERRORS.get(code, "unknown error")
    codec_gcs.check_error_reply(b"0\n")


@pytest.mark.parametrize("reply", [b"1=49.98\n2=1\n", b"1=\n", b"=5\n", b"1=abc\n", b"1=5", b"1=nan\n",
                                   b"garbage\n", b"1=5 \n"])
def test_gcs_malformed_items_raise(reply):
    with pytest.raises(ProtocolError) as info:
        codec_gcs.parse_items(reply, ["1"])
    assert info.value.data == reply


@settings(deadline=None)
@given(st.binary(max_size=40))
def test_gcs_garbage_error_reply_never_passes_as_no_error(garbage):
    reply = garbage + b"\n"
    try:
        code = codec_gcs.parse_error_code(reply)
    except ProtocolError as err:
        assert err.data == reply
        return
    assert reply.strip() == str(code).encode() or reply.strip().lstrip(b"0") == str(code).encode().lstrip(b"0")


def test_gcs_simulator_replies_parse():
    sim = SimGCS()
    assert codec_gcs.parse_axes(sim.feed(b"SAI?\n")) == ["1", "2", "3"]
    sim.feed(b"SVA 1 10\n")
    assert codec_gcs.parse_error_code(sim.feed(b"ERR?\n")) == 303  # servo on at power-up
    assert codec_gcs.parse_items(sim.feed(b"VMA? 1 2 3\n"), ["1", "2", "3"]) == {"1": 120.0, "2": 120.0, "3": 120.0}


# ---------------- NV200 ----------------

@settings(deadline=None)
@given(st.floats(-20.0, 130.0))
def test_nv200_set_round_trip_and_the_simulator_agrees(v):
    data = codec_nv200.encode_set(v, -20.0, 130.0)
    got = codec_nv200.decode_set(data)
    assert got == pytest.approx(v, abs=5e-4 + 1e-9)
    sim = SimNV200()
    sim.feed(b"modsrc,0\r\n")
    assert sim.feed(data) == b""
    assert codec_nv200.parse_value("meas", sim.feed(b"meas\r\n")) == pytest.approx(got, abs=5e-4)


@settings(deadline=None)
@given(st.integers(-10**7, 10**7), st.sampled_from(["meas", "set", "avmin", "avmax"]))
def test_nv200_read_reply_round_trip(milli, name):
    assert codec_nv200.parse_value(name, codec_nv200.encode_read_reply(name, milli / 1000)) == milli / 1000


@pytest.mark.parametrize("code", list(range(1, 11)) + [42])
def test_nv200_error_frames_carry_code_and_text(code):
    reply = f"error,{code}\r\n".encode() + b"\x11"
    with pytest.raises(ProtocolError) as info:
        codec_nv200.parse_value("meas", reply)
    assert info.value.code == code and info.value.data == reply
    assert info.value.text == codec_nv200.ERRORS.get(code, "unknown error")


@pytest.mark.parametrize("reply", [b"meas,12.5\r\n", b"set,12.5\r\n\x11", b"meas\r\n\x11", b"meas,abc\x11",
                                   b"meas,1,2\x11", b"\x11", b"meas,1\r\nmeas,2\x11", b"error,x\x11"])
def test_nv200_malformed_replies_raise(reply):
    with pytest.raises(ProtocolError) as info:
        codec_nv200.parse_value("meas", reply)
    assert info.value.data == reply


@settings(deadline=None)
@given(st.binary(max_size=40))
def test_nv200_garbage_never_gives_a_wrong_value(garbage):
    reply = garbage + b"\x11"
    try:
        value = codec_nv200.parse_value("meas", reply)
    except ProtocolError as err:
        assert err.data == reply
        return
    body = reply[:-1].strip(b"\r\n ")
    assert body.startswith(b"meas,") and float(body[5:]) == value


# ---------------- CAN ----------------

@settings(deadline=None)
@given(st.tuples(volts, volts, volts), st.integers(0, 1000))
def test_can_setpoint_round_trip(values, seq):
    data = codec_can.encode_setpoint(values, seq, [0.0] * 3, [150.0] * 3)
    assert len(data) == 8
    sig = codec_can.decode(codec_can.SETPOINT, data)
    assert sig["SEQ"] == seq % 256
    for k, v in zip(("X_V", "Y_V", "Z_V"), values):
        assert sig[k] == pytest.approx(v, abs=0.00125 + 1e-9)
        assert 0.0 <= sig[k] <= 150.0


@settings(deadline=None)
@given(any_float, st.floats(0, 160), st.floats(0, 3))
def test_can_quantize_inside(v, lo, width):
    hi = lo + width
    try:
        q = codec_can.quantize_inside(v, lo, hi)
    except LimitError:
        assert not math.isfinite(v) or width < 0.0025
        return
    assert lo <= q <= hi
    assert q == _quantize_inside_slowly(v, lo, hi)      # the fast path inside the limits is the same value


def _quantize_inside_slowly(value_V: float, lo_V: float, hi_V: float) -> float:
    """The plain statement of :func:`codec_can.quantize_inside` (no fast path): clamp, round
    to the step, move inside the limits by whole steps."""
    step_V = codec_can.volts_per_bit()
    raw = round(min(max(value_V, lo_V), hi_V) / step_V)
    while raw * step_V > hi_V:
        raw -= 1
    while raw * step_V < lo_V:
        raw += 1
    return raw * step_V


def test_can_recorder_block_round_trip_in_plain_bytes():
    """REC_DATA_FD: 8 points of one axis in 64 bytes, the layout of the DBC (INDEX 0|16,
    AXIS 16|2, COUNT 24|8, then per point Y 24 bit signed 0.01 nm, U and V 16 bit 2.5 mV)."""
    pts = [(-5000.0 + 1234.56 * k, 10.0 + k, 20.0 + 0.5 * k) for k in range(8)]
    data = codec_can.encode_rec_block(300, 1, pts)
    assert len(data) == 64 and data[:4] == bytes([44, 1, 1, 8])          # 300 = 0x012C, axis 1, 8 points
    assert int.from_bytes(data[4:7], "little", signed=True) == -500000   # -5000 nm in 0.01 nm
    assert int.from_bytes(data[7:9], "little") == 4000 and int.from_bytes(data[9:11], "little") == 8000
    first, axis, back = codec_can.decode_rec_block(data)
    assert (first, axis) == (300, 1)
    np.testing.assert_allclose(back, pts, atol=0.00125 + 1e-9)
    first, axis, back = codec_can.decode_rec_block(codec_can.encode_rec_block(7, 2, [(1e9, 200.0, -3.0)] * 3))
    assert (first, axis, len(back)) == (7, 2, 3)
    assert back[0] == pytest.approx((83886.07, 163.8375, 0.0))          # clamped into the DBC's ranges
    assert codec_can.encode_rec_read_fd(8, 1024) == bytes([8, 0, 0, 4])
    with pytest.raises(ProtocolError, match="1..8"):
        codec_can.encode_rec_block(0, 0, [])
    with pytest.raises(ProtocolError, match="COUNT 0"):
        codec_can.decode_rec_block(bytes(64))
    with pytest.raises(ProtocolError, match="64"):
        codec_can.decode_rec_block(data[:8])


def test_can_decode_rejects_wrong_length_and_unknown_ids():
    with pytest.raises(ProtocolError) as info:
        codec_can.decode(codec_can.STATUS, b"\x00\x01")
    assert info.value.data == b"\x00\x01"
    with pytest.raises(ProtocolError):
        codec_can.decode(0x7FF, b"")


def test_can_error_frame_maps_to_protocol_error():
    data = codec_can.message(codec_can.ERROR).encode({"CODE": 2, "DETAIL": 7, "SEQ": 9})
    err = codec_can.error_from(codec_can.decode(codec_can.ERROR, data), data)
    assert err.code == 2 and "sequence" in err.text and err.data == data


def test_can_encoder_refuses_values_that_do_not_fit_the_frame():
    with pytest.raises(LimitError):
        codec_can.encode_setpoint([170.0, 0, 0], 0, [0.0] * 3, [200.0] * 3)


# ---------------- truncation: every strict prefix of a valid reply is refused ----------------

@settings(deadline=None)
@given(st.lists(st.integers(0, 15000), min_size=3, max_size=3), st.data())
def test_mdt_truncated_replies_are_refused(centivolts, data):
    reply = codec_mdt.encode_values_reply([c / 100 for c in centivolts])
    cut = data.draw(st.integers(0, len(reply) - 1))
    prefix = reply[:cut]
    assert codec_mdt.split_reply(bytearray(prefix)) == -1  # never taken for a complete reply
    with pytest.raises(ProtocolError) as info:
        codec_mdt.parse_values(b"XYZVOLTAGE?\r", prefix, 3)
    assert info.value.data == prefix


@settings(deadline=None)
@given(st.lists(st.integers(0, 10**6), min_size=2, max_size=3), st.data())
def test_gcs_truncated_replies_are_refused(values, data):
    items = {str(k + 1): v / 1e4 for k, v in enumerate(values)}
    reply = codec_gcs.encode_items_reply(items)
    cut = data.draw(st.integers(0, len(reply) - 1))
    prefix = reply[:cut]
    n = codec_gcs.split_reply(bytearray(prefix))
    assert n == -1 or n < len(reply)
    with pytest.raises(ProtocolError):
        codec_gcs.parse_items(prefix, list(items))


@settings(deadline=None)
@given(st.integers(-10**6, 10**6), st.data())
def test_nv200_truncated_replies_are_refused(milli, data):
    reply = codec_nv200.encode_read_reply("meas", milli / 1000)
    prefix = reply[: data.draw(st.integers(0, len(reply) - 1))]
    assert codec_nv200.split_reply(bytearray(prefix)) == -1
    with pytest.raises(ProtocolError) as info:
        codec_nv200.parse_value("meas", prefix)
    assert info.value.data == prefix


def test_can_frame_ids_and_scale_come_from_the_dbc_by_name():
    """Driver codec and simulator read ids and the voltage step from one DBC by message name."""
    import cantools

    from afmctl.sim_backend.amplifiers.can_amp import load_database
    ref = cantools.database.load_file(str(Path(codec_can.__file__).with_name(codec_can.DBC_RESOURCE)))
    sim_db = load_database()
    for name in ("SETPOINT_XYZ", "HEARTBEAT", "STATUS", "ERROR", "LIMITS"):
        assert codec_can.frame_id(name) == ref.get_message_by_name(name).frame_id
        assert sim_db.get_message_by_name(name).frame_id == ref.get_message_by_name(name).frame_id
    assert codec_can.volts_per_bit() == ref.get_message_by_name("SETPOINT_XYZ").get_signal_by_name("X_V").scale
