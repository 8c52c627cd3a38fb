"""The simulated wave generators play what fell due as one block (#38: one call per point
cost more than the servo cycle on a loaded host, and a simulator behind its own clock stops
answering). The block path must equal the point-by-point path exactly: the same outputs,
the same record tables, the same changes handed to the load, at the same times."""
from __future__ import annotations

import numpy as np

from afmctl.drivers import codec_gcs_rec as rcodec
from afmctl.drivers import codec_gcs_wave as wcodec
from afmctl.sim_backend.amplifiers.gcs import SimGCS
from afmctl.sim_backend.amplifiers.nv200 import SimNV200
from afmctl.sim_backend.testing import RecordingSink


def _gcs() -> tuple[SimGCS, list[float], RecordingSink]:
    clock, sink = [0.0], RecordingSink()
    dev = SimGCS(sink, now=lambda: clock[0])
    dev.feed(b"SVO 1 0 2 0 3 0\n")
    for table, period in ((1, 40), (2, 80)):
        points = np.round(60 + 40 * np.sin(np.arange(3000) / period), 4)
        points[100:200] = points[100]                       # a hold: no change to hand over
        for line in wcodec.encode_wav_pnt(table, points, 0, 120):
            dev.feed(line)
    for line in rcodec.encode_configure([(1, "1", 2), (2, "1", 14), (3, "1", 7), (4, "2", 14)], 3):
        dev.feed(line)
    dev.feed(b"WOS 2 1.5\n")
    dev.feed(wcodec.encode_start([1, 2], 2, 2))
    return dev, clock, sink


def _nv200() -> tuple[SimNV200, list[float], RecordingSink]:
    clock, sink = [0.0], RecordingSink()
    dev = SimNV200(sink, now=lambda: clock[0], sensor="strain gauge")
    for i in range(300):
        dev.feed(f"gbarb,{i},{50 + 40 * np.sin(i / 20):.3f}\r".encode())
    for cmd in ("goarb,0", "gsarb,10", "gearb,299", "gcarb,3", "gtarb,3", "modsrc,3", "recast,2", "recstr,2",
                "reclen,500", "recsrc,0,1", "recsrc,1,2", "recrun,1", "grun,1"):
        dev.feed(f"{cmd}\r".encode())
    return dev, clock, sink


def _history(sink: RecordingSink) -> list:
    return [(t, tuple(sorted(v.items()))) for t, v in sink.history]


def test_the_e727_plays_a_block_exactly_as_point_by_point():
    block, clock_a, sink_a = _gcs()
    single, clock_b, sink_b = _gcs()
    for k in range(1, 200):                    # polls at times off the servo grid
        clock_a[0] = clock_b[0] = k * 0.0017
        block.poll()
        single.wave.run_until(clock_b[0])      # one _wave_apply per point
    for t in block.recorder.tables:
        a, b = block.recorder.tables[t], single.recorder.tables[t]
        assert a.filled == b.filled and np.array_equal(a.volts, b.volts)
    assert block.recorder.tables[1].filled > 2000
    assert _history(sink_a) == _history(sink_b) and len(sink_a.history) > 5000
    assert block.outputs == single.outputs and block.requested_V == single.requested_V


def test_the_nv200_plays_a_block_exactly_as_sample_by_sample():
    block, clock_a, sink_a = _nv200()
    single, clock_b, sink_b = _nv200()
    for k in range(1, 300):
        clock_a[0] = clock_b[0] = k * 0.00037
        block.poll()
        single.wave.run_until(clock_b[0])
    a, b = block.recorder, single.recorder
    assert a._filled == b._filled == 500
    assert np.array_equal(a._volts, b._volts) and np.array_equal(a._setp, b._setp)
    assert _history(sink_a) == _history(sink_b) and len(sink_a.history) > 500
    assert block.outputs == single.outputs and block.wave.played == single.wave.played
