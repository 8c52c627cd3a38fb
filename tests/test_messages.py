"""Payload schemas: round trips, the binary setpoint layout, and bad input → MessageError
(never another exception)."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from afmctl.zenoh_api.messages import (
    SCHEMA_VERSION,
    SETPOINT_DTYPE,
    SETPOINT_HEADER_BYTES,
    CmdRequest,
    DriftMsg,
    LineMsg,
    MessageError,
    RasterMsg,
    SegmentMsg,
    StatusMsg,
    TemperatureMsg,
    decode_json,
    decode_setpoints,
    decode_trajectory,
    encode_setpoints,
)


def _batch(n: int, first: int = 0) -> np.ndarray:
    b = np.zeros(n, SETPOINT_DTYPE)
    b["seq"] = np.arange(first, first + n)
    b["t_s"] = 1e-3 * b["seq"]
    b["target_nm"] = np.random.default_rng(n).normal(size=(n, 3)) * 1000
    b["corrected_nm"] = b["target_nm"] - 1.5
    b["u_V"] = np.abs(b["target_nm"]) / 80
    return b


def test_setpoint_layout_is_the_documented_one():
    b = _batch(3, first=41)
    payload = encode_setpoints(7, b)
    assert SETPOINT_HEADER_BYTES == 32 and SETPOINT_DTYPE.itemsize == 88
    assert len(payload) == 32 + 3 * 88
    magic, schema, hbytes, seq, first, n, rbytes = struct.unpack_from("<4sHHQQII", payload)
    assert (magic, schema, hbytes, seq, first, n, rbytes) == (b"AFMS", SCHEMA_VERSION, 32, 7, 41, 3, 88)
    # record 1, field u_V[2] at offset 32 + 88 + 8 + 8 + 24 + 24 + 16
    (u2,) = struct.unpack_from("<d", payload, 32 + 88 + 80)
    assert u2 == b["u_V"][1, 2]


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 300), first=st.integers(0, 2**40), seq=st.integers(0, 2**63 - 1))
def test_setpoint_round_trip(n, first, seq):
    b = _batch(n, first)
    got_seq, rec = decode_setpoints(encode_setpoints(seq, b))
    assert got_seq == seq
    assert rec.tobytes() == b.tobytes()


def test_setpoints_from_another_dtype_layout():
    other = np.zeros(2, dtype=[("u_V", "<f8", (3,)), ("seq", "<u8"), ("t_s", "<f8"),
                                ("corrected_nm", "<f8", (3,)), ("target_nm", "<f8", (3,))])
    other["seq"] = [5, 6]
    other["u_V"][:, 0] = [1.0, 2.0]
    _, rec = decode_setpoints(encode_setpoints(0, other))
    assert list(rec["seq"]) == [5, 6] and list(rec["u_V"][:, 0]) == [1.0, 2.0]


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=200))
def test_garbage_setpoint_payload_only_raises_message_error(data):
    try:
        decode_setpoints(data)
    except MessageError:
        pass


def test_truncated_and_wrong_version_setpoints():
    payload = encode_setpoints(0, _batch(4))
    with pytest.raises(MessageError, match="header says"):
        decode_setpoints(payload[:-1])
    bad = bytearray(payload)
    bad[4:6] = struct.pack("<H", 2)
    with pytest.raises(MessageError, match="schema"):
        decode_setpoints(bytes(bad))


@pytest.mark.parametrize("msg", [
    SegmentMsg(seq=1, dt_s=1e-3, positions_nm=[[1, 2, 3], [4, 5, 6]]),
    LineMsg(seq=2, dt_s=1e-3, from_nm=[0, 0, 0], to_nm=[100, 0, 0], duration_s=0.01),
    RasterMsg(seq=3, dt_s=1e-3, center_nm=[5000, 5000, 0], size_nm=[1000, 500], lines=3, line_rate_hz=50),
])
def test_trajectory_round_trip(msg):
    back = decode_trajectory(msg.to_json_bytes())
    assert back == msg
    assert json.loads(msg.to_json_bytes())["schema"] == SCHEMA_VERSION


def test_generated_trajectories():
    line = LineMsg(seq=0, dt_s=1e-3, from_nm=[0, 0, 0], to_nm=[100, 50, 0], duration_s=0.01).positions()
    assert line.shape == (10, 3) and np.allclose(line[-1], [100, 50, 0]) and np.allclose(line[0], [10, 5, 0])
    r = RasterMsg(seq=0, dt_s=1e-3, center_nm=[5000, 5000, 7], size_nm=[1000, 500], lines=3,
                  line_rate_hz=50).positions()
    assert r.shape == (60, 3)
    assert r[:, 0].min() == pytest.approx(4500) and r[:, 0].max() == pytest.approx(5500)
    assert sorted(set(np.round(r[:, 1], 6))) == [4750.0, 5000.0, 5250.0]
    assert np.all(r[:, 2] == 7)
    with pytest.raises(MessageError, match="samples"):
        RasterMsg(seq=0, dt_s=1e-6, center_nm=[0, 0, 0], size_nm=[1, 1], lines=1000,
                  line_rate_hz=0.01).positions(max_samples=10_000)


@pytest.mark.parametrize("payload,field", [
    (b'{"schema":1,"seq":0,"t_s":0,"T_C":151}', "T_C"),
    (b'{"schema":1,"seq":0,"t_s":0,"T_C":Infinity}', "T_C"),
    (b'{"schema":1,"seq":0,"t_s":0}', "T_C"),
    (b'{"schema":1,"seq":-4,"t_s":0,"T_C":20}', "seq"),
    (b'{"schema":1,"seq":0,"t_s":0,"T_C":20,"x":1}', "x"),
    (b'{"schema":3,"seq":0,"t_s":0,"T_C":20}', "schema"),
])
def test_temperature_errors_name_the_field(payload, field):
    with pytest.raises(MessageError, match=field):
        decode_json(payload, TemperatureMsg)


@pytest.mark.parametrize("payload", [
    b'{"schema":1,"seq":' + b"1" * 5000 + b',"t_s":0,"T_C":20}',     # Python refuses > 4300 digits
    b"[" * 100_000 + b"]" * 100_000,                                  # nested too deep
])
def test_pathological_json_is_a_message_error(payload):
    with pytest.raises(MessageError, match="payload"):
        decode_json(payload, TemperatureMsg)
    with pytest.raises(MessageError, match="payload"):
        decode_trajectory(payload)


def test_oversized_json_rejected_before_parsing():
    with pytest.raises(MessageError, match="at most 100"):
        decode_json(b" " * 101, TemperatureMsg, max_bytes=100)


def test_published_messages_validate():
    st_msg = StatusMsg(seq=0, scanner="s", t_s=1.0, state="idle")
    assert decode_json(st_msg.to_json_bytes(), StatusMsg) == st_msg
    d = DriftMsg(seq=0, t_s=1.0, drift_nm=[1, 2, 3], std_nm=None, T_C=22.0)
    assert decode_json(d.to_json_bytes(), DriftMsg) == d
    assert decode_json(CmdRequest(cmd="status").to_json_bytes(), CmdRequest).cmd == "status"


_json = st.recursive(st.none() | st.booleans() | st.floats(allow_nan=False) | st.integers() | st.text(max_size=6),
                     lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4),
                     max_leaves=16)


@settings(max_examples=80, deadline=None)
@given(doc=st.one_of(_json, st.fixed_dictionaries(
    {"schema": st.sampled_from([1, 2, "1"]), "seq": st.integers(-1, 2**64)},
    optional={"type": st.sampled_from(["segment", "line", "raster"]), "dt_s": _json, "positions_nm": _json,
              "center_nm": _json, "size_nm": _json, "lines": _json, "line_rate_hz": _json, "from_nm": _json,
              "to_nm": _json, "duration_s": _json})))
def test_fuzzed_trajectories_raise_only_message_error(doc):
    try:
        msg = decode_trajectory(json.dumps(doc).encode())
    except MessageError:
        return
    pos = None
    try:
        pos = msg.positions(max_samples=100_000)
    except MessageError:
        return
    assert pos.ndim == 2 and pos.shape[1] == 3 and np.all(np.isfinite(pos))
    assert np.all(np.abs(pos) <= 1e6 + 1e-6)


def _documented_layout():
    """The setpoint layout as docs/ZENOH.md states it: header rows (offset, size, field,
    type) and record fields (name, count, type), parsed from the document's text."""
    import re
    from pathlib import Path
    text = (Path(__file__).resolve().parents[1] / "docs" / "ZENOH.md").read_text(encoding="utf-8")
    section = text.split("### `setpoint`", 1)[1].split("### ", 1)[0]
    block = section.split("```", 2)[1]
    header = []
    for line in block.splitlines():
        m = re.match(r"^(\d+)\s+(\d+)\s+(\w+)\s+(b\"\w+\"|uint\d+)", line.strip())
        if m:
            header.append((int(m.group(1)), int(m.group(2)), m.group(3), m.group(4)))
    records = []
    for m in re.finditer(r"^\| `(\w+)` \| (?:(\d+) × )?(uint64|float64) \|", section, re.M):
        records.append((m.group(1), int(m.group(2) or 1), m.group(3)))
    return header, records


def test_setpoints_decode_with_the_documented_layout_alone():
    """Decode an encoded batch with nothing but struct and the offsets/types written in
    docs/ZENOH.md: the document and the code agree byte for byte."""
    header, records = _documented_layout()
    assert [h[2] for h in header] == ["magic", "schema", "header_bytes", "seq", "first_sample", "n",
                                      "record_bytes"]
    assert [r[0] for r in records] == ["seq", "t_s", "target_nm", "corrected_nm", "u_V"]
    fmt = {"uint16": "<H", "uint32": "<I", "uint64": "<Q", "float64": "<d"}
    b = _batch(5, first=1000)
    payload = encode_setpoints(77, b)
    got = {}
    for offset, size, name, kind in header:
        if kind.startswith('b"'):
            got[name] = payload[offset:offset + size]
            assert got[name] == kind[2:-1].encode()
        else:
            assert struct.calcsize(fmt[kind]) == size, name
            (got[name],) = struct.unpack_from(fmt[kind], payload, offset)
    assert (got["schema"], got["seq"], got["first_sample"], got["n"]) == (SCHEMA_VERSION, 77, 1000, 5)
    rec_size = sum(8 * count for _, count, _ in records)
    assert got["record_bytes"] == rec_size and len(payload) == got["header_bytes"] + 5 * rec_size
    for k in range(5):
        pos = got["header_bytes"] + k * rec_size
        for name, count, kind in records:
            values = struct.unpack_from("<" + fmt[kind][1] * count, payload, pos)
            expected = np.atleast_1d(b[name][k]).tolist()
            assert list(values) == expected, (k, name)
            pos += 8 * count
