"""Sans-I/O codec for the NV200 data recorder, as the vendor's ``nv200`` library
(``DataRecorder``) and piezosystem jena's command list describe it.

* ``recsrc,<ch>,<src>``: channel 0 or 1 records source 0 piezo position (µm with a sensor),
  1 setpoint, 2 piezo voltage [V], 3 position error, 4 its absolute value, 6/7 currents.
* ``recstr,<n>``: a point every n samples of the 20 kHz base rate (50 µs);
  ``reclen,<n>``: points per channel, 1..6144.
* ``recast,<mode>``: what starts it — 0 ``recrun,1`` itself, 1 the next ``set``, 2 the
  waveform generator's start (``grun,1``); ``recrun,1`` arms, ``recrun`` reads 1 while
  armed or recording, 0 once it holds every point.
* ``recoutf,<ch>`` → ``recoutf,<ch>,v0,v1,...`` + XON: every point of the channel.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .codec_common import parse_number
from .codec_nv200 import XON, encode, error_from, frame_fields, is_error
from .errors import ProtocolError

BASE_SAMPLE_S = 50e-6
BUFFER_SIZE = 6144
#: the recorder's source per signal: the position, the setpoint (in open loop the voltage
#: commanded: the waveform generator's sample or ``set``), the piezo voltage (what the
#: amplifier stage puts on the piezo)
SOURCES = {"y_nm": 0, "u_V": 1, "v_V": 2}
#: the recorder's channels (signals one recording holds at most)
CHANNELS = 2
AUTOSTART_WAVEFORM = 2
#: the longest ``recoutf`` reply accepted [bytes] (6144 values of up to 24 characters)
MAX_RECOUTF = BUFFER_SIZE * 24 + 64


def encode_configure(sources: Mapping[int, int], stride: int, points: int) -> bytes:
    """Stop a running recording, set sources, stride and length, start with the waveform
    generator (``recast,2``) and arm (``recrun,1``): one write."""
    cmds = ["recrun,0", f"recast,{AUTOSTART_WAVEFORM}"]
    cmds += [f"recsrc,{ch},{src}" for ch, src in sorted(sources.items())]
    cmds += [f"recstr,{int(stride)}", f"reclen,{int(points)}", "recrun,1"]
    return b"".join(encode(c) for c in cmds)


def split_recoutf(buffer: bytes | bytearray) -> int:
    """Length of the first frame (through XON) or -1; a ``recoutf`` reply may be long."""
    i = buffer.find(XON)
    if i >= 0:
        return i + 1
    if len(buffer) > MAX_RECOUTF:
        raise ProtocolError(f"no XON in {len(buffer)} bytes", data=bytes(buffer[:200]))
    return -1


def parse_recoutf(reply: bytes, channel: int) -> np.ndarray:
    """``recoutf,<ch>,v0,v1,...`` → the values as a float array."""
    if is_error(reply):
        raise error_from(reply)
    fields = frame_fields(reply)
    if len(fields) < 2 or fields[0] != b"recoutf" or fields[1].strip() != str(channel).encode():
        raise ProtocolError(f"reply to 'recoutf,{channel}' does not name it", data=bytes(reply[:200]))
    return np.array([parse_number(f, f"recoutf,{channel}", reply) for f in fields[2:]], dtype=np.float64)
