"""afmctl view, the server side: bounded rings, clock alignment and tracking error, the
image grid, the zenoh feed (real sessions on loopback) and the command line's errors."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.zenoh_api.messages import SETPOINT_DTYPE, DriftMsg, SimImageMsg, SimTipMsg, StatusMsg, encode_setpoints
from afmctl.testing import wait_for
from afmctl.view.align import ClockOffset, TargetHistory
from afmctl.view.feed import MAX_SCANNERS, ViewFeed
from afmctl.view.image import HeightImage
from afmctl.view.ring import Ring
from afmctl.view.scanner_feed import ScannerFeed
from afmctl.zenoh_api.settings import loopback_pair

import zenoh

pytestmark = pytest.mark.timeout(120)


def _batch(first: int, n: int, dt_s: float = 1e-3, speed_nm_per_s: float = 1000.0) -> np.ndarray:
    rec = np.zeros(n, SETPOINT_DTYPE)
    rec["seq"] = np.arange(first, first + n)
    rec["t_s"] = rec["seq"] * dt_s
    rec["target_nm"][:, 0] = rec["t_s"] * speed_nm_per_s
    rec["target_nm"][:, 1] = 500.0
    rec["u_V"][:, 0] = rec["target_nm"][:, 0] / 80.0
    return rec


def test_ring_is_bounded_and_serves_each_reader_what_it_has_not_seen():
    ring = Ring(5)
    ring.extend(range(3))
    rows, nxt = ring.since(0)
    assert rows == [0, 1, 2] and nxt == 3
    ring.extend(range(3, 12))
    assert len(ring) == 5 and ring.next_index == 12
    assert ring.since(nxt) == ([7, 8, 9, 10, 11], 12)    # fell behind: the oldest still held
    assert ring.since(10) == ([10, 11], 12)
    assert ring.since(12) == ([], 12)


def test_clock_offset_is_a_windowed_minimum_that_follows_a_slipping_sender():
    off = ClockOffset(window_s=1.0)
    assert off.offset_s is None
    for k, jitter in enumerate([0.004, 0.001, 0.006, 0.002]):
        off.update(100.0 + 0.1 * k + jitter, 0.1 * k)
    assert off.offset_s == pytest.approx(100.001)
    # the sender's clock falls 0.5 s behind (a loop missing deadlines): after the window
    # the old, smaller offsets are gone
    for k in range(30):
        off.update(101.0 + 0.1 * k + 0.002, 0.5 + 0.1 * k)
    assert off.offset_s == pytest.approx(100.502)


def test_target_history_interpolates_and_forgets():
    hist = TargetHistory(keep_s=1.0)
    for k in range(10):
        rec = _batch(k * 256, 256)
        hist.add(rec["t_s"], rec["target_nm"])
    lo, hi = hist.span_s
    assert hi == pytest.approx(2.559) and 1.0 <= hi - lo <= 1.0 + 2 * 0.256
    got = hist.at(np.array([2.0005, lo - 0.1, hi + 0.1]))
    assert got[0, 0] == pytest.approx(2000.5) and got[0, 1] == 500.0
    assert np.all(np.isnan(got[1:]))


def test_scanner_feed_decimates_setpoints_and_measures_the_tracking_error():
    feed = ScannerFeed("s1", display_rate_Hz=100.0, history_s=30.0)
    lag_s, t0 = 0.020, 50.0                 # the tip lags its target by 20 ms; tip clock starts later
    for k in range(8):                      # 8 × 256 samples at 1 kHz = 2.048 s
        rec = _batch(k * 256, 256)
        feed.on_setpoints(encode_setpoints(k, rec), arrival_s=1000.0 + rec["t_s"][-1] + 0.003)
        for t in np.arange(k * 0.256, (k + 1) * 0.256, 0.005):
            pos = [1000.0 * (t - lag_s), 500.0, 0.0]
            msg = SimTipMsg(seq=0, t_s=t - t0, position_nm=pos)
            feed.on_tip(msg.to_json_bytes(), arrival_s=1000.0 + t + 0.001)
    rows, _ = feed.setpoints.since(0)
    assert 200 <= len(rows) <= 206                     # 2.048 s at 100 Hz
    assert np.allclose(np.diff([r[0] for r in rows]), 0.01, atol=1.5e-3)
    tips, _ = feed.tips.since(0)
    errs = np.array([r[4] for r in tips if r[4] is not None])
    assert len(errs) > 150
    # tip − target = −20 nm of lag, less 2 nm: the setpoints' fastest delivery (3 ms) is
    # 2 ms slower than the tips' (1 ms), which no receiver can tell from a clock offset
    assert np.allclose(errs[5:], -1000.0 * (lag_s - 0.002), atol=0.01)
    assert tips[0][4] is None and tips[1][4] is not None   # before the first target: no error
    summary = feed.tracking_summary()
    assert summary["rms_nm"][0] == pytest.approx(18.0, abs=0.01)
    assert summary["range_nm"][0] == pytest.approx(2047.0, abs=0.5)
    assert summary["rms_pct"][0] == pytest.approx(100 * 18.0 / 2047.0, rel=0.01)


def test_scanner_feed_drift_status_image_and_a_frame_per_reader():
    feed = ScannerFeed("s1")
    feed.on_drift(DriftMsg(seq=0, t_s=1.0, drift_nm=[1.0, 2.0, 3.0], std_nm=[0.1, 0.2, 0.3]).to_json_bytes())
    feed.on_drift(DriftMsg(seq=1, t_s=1.1, drift_nm=[1.0, 2.0, 3.0]).to_json_bytes())
    feed.on_status(StatusMsg(seq=0, scanner="s1", t_s=1.0, state="running",
                             stats={"samples": 5}).to_json_bytes())
    feed.on_setpoints(encode_setpoints(0, _batch(0, 1000, speed_nm_per_s=1000.0)))   # x 0…999, y 500
    for x in range(0, 1000, 10):
        feed.on_image(SimImageMsg(seq=x, t_s=0.0, position_nm=[x, x / 2, 0.0], height_nm=x / 100,
                                  sample="g").to_json_bytes())
    cursor: dict[str, int] = {}
    f = feed.frame(cursor, with_image=True)
    assert f["drift"] == [[1.0, 1.0, 2.0, 3.0, 0.1, 0.2, 0.3], [1.1, 1.0, 2.0, 3.0, None, None, None]]
    assert f["status"]["state"] == "running" and f["status"]["stats"]["samples"] == 5
    img = f["image"]
    # the area: the targets' extent (x 0…999 nm, y 500 nm: no extent, so no area yet) — the
    # y targets are constant, so nothing is binned until they span an area
    assert img is None
    feed.on_setpoints(encode_setpoints(1, _batch(1000, 10)))
    rec = _batch(1010, 10)
    rec["target_nm"][:, 1] = 0.0
    feed.on_setpoints(encode_setpoints(2, rec))                     # now y 0…500 nm
    for x in range(0, 1000, 10):
        feed.on_image(SimImageMsg(seq=x, t_s=0.0, position_nm=[x, x / 2, 0.0], height_nm=x / 100,
                                  sample="g").to_json_bytes())
    img = feed.frame(cursor, with_image=True)["image"]
    assert img["samples"] == 200 and img["outside"] == 100 and img["sample"] == "g"
    assert img["h_range_nm"] == [0.0, 9.9]
    assert len(img["height_nm"]) == 64 and len(img["height_nm"][0]) == 128
    assert img["x_nm"][0] < 0 and img["x_nm"][1] > 1009               # + 10 % margin
    assert json.dumps(f)                                # plain JSON (no NaN)
    cursor = {}
    f = feed.frame(cursor, with_image=False)
    assert feed.frame(cursor, with_image=False)["drift"] == []     # seen already
    assert "image" not in feed.frame(cursor, with_image=False)


def test_height_image_keeps_the_latest_height_per_pixel_and_regrows_with_what_it_held():
    img = HeightImage(cols=10, rows=5)
    img.add(5.0, 5.0, 1.0)
    assert img.grid() is None and img.outside == 1                  # no area yet
    img.set_area([[0.0, 0.0], [10.0, 5.0]])
    img.add(5.5, 2.5, 1.0)
    img.add(5.6, 2.6, 2.0)                                          # same pixel: the latest wins
    img.add(0.5, 0.5, 7.0)
    g = img.grid()
    assert g["height_nm"][2][5] == 2.0 and g["height_nm"][0][0] == 7.0
    assert sum(v is not None for row in g["height_nm"] for v in row) == 2
    img.set_area([[0.0, 0.0], [8.0, 4.0]])                          # inside: nothing changes
    assert img.grid()["x_nm"] == [0.0, 10.0]
    img.set_area([[0.0, 0.0], [10.0, 10.0]])                        # the raster grew in y
    g = img.grid()
    assert g["y_nm"][0] == 0.0 and g["y_nm"][1] == 12.5               # only y's top grew, with headroom
    assert g["x_nm"] == [0.0, 10.0]
    for top in range(11, 200):                                      # a raster growing line by line
        img.set_area([[0.0, 0.0], [10.0, float(top)]])
    assert img.grid()["x_nm"] == [0.0, 10.0] and 199.0 <= img.grid()["y_nm"][1] <= 1.25 * 199.0
    held = [(r, c, v) for r, row in enumerate(g["height_nm"]) for c, v in enumerate(row) if v is not None]
    assert sorted(v for _, _, v in held) == [2.0, 7.0]              # re-binned, nothing lost
    assert img._h.shape == (5, 10)                                  # memory: the grid only


def _publish_all(session, scanner: str, k: int) -> None:
    key = f"afm/{scanner}"
    session.put(f"{key}/setpoint", encode_setpoints(k, _batch(k * 100, 100)))
    session.put(f"{key}/status", StatusMsg(seq=k, scanner=scanner, t_s=0.0, state="running").to_json_bytes())
    session.put(f"{key}/drift", DriftMsg(seq=k, t_s=0.1 * k, drift_nm=[0, 0, 1.0]).to_json_bytes())
    session.put(f"{key}/sim/tip", SimTipMsg(seq=k, t_s=0.1 * k, position_nm=[1, 2, 3]).to_json_bytes())
    session.put(f"{key}/sim/image", SimImageMsg(seq=k, t_s=0.1 * k, position_nm=[k, k, 0],
                                                height_nm=1.0).to_json_bytes())


def test_view_feed_over_zenoh_finds_scanners_and_rejects_bad_payloads():
    srv, cli = loopback_pair()
    with zenoh.open(srv.to_zenoh_config()) as publisher, ViewFeed(cli) as view:
        def all_seen() -> bool:
            for k in range(3):
                _publish_all(publisher, "alpha", k)
                _publish_all(publisher, "beta", k)
            feeds = view.feeds()
            return len(feeds) == 2 and all(f.counts["image"] and f.counts["tips"] for f in feeds.values())
        assert wait_for(all_seen, 30.0, 0.2), {n: f.counts for n, f in view.feeds().items()}
        alpha = view.feeds()["alpha"]
        assert alpha.counts["rejected"] == 0
        bad = [("setpoint", b"AFMS garbage", "the header alone is 32"),
               ("status", b"{not json", "status: "),
               ("drift", json.dumps({"schema": 1, "seq": 0, "t_s": 0, "drift_nm": [0, 0]}).encode(), "drift_nm"),
               ("sim/tip", json.dumps({"schema": 2, "seq": 0, "t_s": 0, "position_nm": [0, 0, 0]}).encode(),
                "schema")]
        for n, (leaf, payload, words) in enumerate(bad, start=1):
            publisher.put(f"afm/alpha/{leaf}", payload)
            assert wait_for(lambda: alpha.counts["rejected"] == n, 10.0)
            assert alpha.last_rejected.startswith(leaf) and words in alpha.last_rejected, alpha.last_rejected
        # a scanner name no service could have (markup) is ignored, not shown
        publisher.put("afm/<b>x/status", StatusMsg(seq=0, scanner="x", t_s=0.0, state="idle").to_json_bytes())
        assert wait_for(lambda: view.ignored >= 1, 10.0)
        assert sorted(view.feeds()) == ["alpha", "beta"]
        # a wildcard viewer tracks at most MAX_SCANNERS scanners
        for n in range(MAX_SCANNERS + 3):
            publisher.put(f"afm/extra{n}/status", StatusMsg(seq=0, scanner="x", t_s=0.0,
                                                            state="idle").to_json_bytes())
        assert wait_for(lambda: view.ignored >= 6, 10.0)
        assert len(view.feeds()) == MAX_SCANNERS


def test_view_feed_with_scanner_names_subscribes_to_those_only():
    srv, cli = loopback_pair()
    with zenoh.open(srv.to_zenoh_config()) as publisher, ViewFeed(cli, ["beta"]) as view:
        assert view.keys()[0] == "afm/beta/setpoint"
        assert wait_for(lambda: _publish_all(publisher, "alpha", 0) or _publish_all(publisher, "beta", 0)
                        or "beta" in view.feeds(), 30.0, 0.2)
        time.sleep(0.3)
        assert list(view.feeds()) == ["beta"]


@pytest.mark.parametrize("argv, message", [
    (["--connect", "tcp/127.0.0.1:7447", "--http", "localhost"], "--http: 'localhost' must be HOST:PORT"),
    (["--connect", "tcp/127.0.0.1:7447", "--http", "127.0.0.1:70000"], "port 0..65535"),
    ([], "--connect: give at least one zenoh endpoint"),
    (["--connect", "tcp/nohost"], "--connect: endpoint 'tcp/nohost': needs HOST:PORT"),
    (["--connect", "tcp/127.0.0.1:7447", "--scanner", "a/b"], "--scanner: scanner name 'a/b'"),
    (["--connect", "tcp/127.0.0.1:7447", "--display-rate", "5000"], "--display-rate: 5000 Hz must be between 1"),
    (["--connect", "tcp/127.0.0.1:7447", "--history", "0"], "--history: 0 s must be between 1 and 600"),
])
def test_view_cli_bad_input_is_one_line_and_exit_2(capsys, argv, message):
    assert main(["view", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("afmctl: error: ") and message in err and "\n" not in err, err


def test_view_cli_bad_config_names_the_file_and_field(tmp_path, capsys):
    cfg = tmp_path / "viewer.toml"
    cfg.write_text("[zenoh]\nprefix = 'a b'\n")
    assert main(["view", "--config", str(cfg), "--connect", "tcp/127.0.0.1:7447"]) == 2
    err = capsys.readouterr().err.strip()
    assert str(cfg) in err and "field zenoh.prefix" in err and "\n" not in err, err
    cfg.write_text("[zenoh\n")
    assert main(["view", "--config", str(cfg), "--connect", "tcp/127.0.0.1:7447"]) == 2
    assert "not valid TOML" in capsys.readouterr().err
    assert main(["view", "--config", str(tmp_path / "none.toml"), "--connect", "tcp/127.0.0.1:7447"]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_view_help_teaches(capsys):
    with pytest.raises(SystemExit) as ex:
        main(["view", "--help"])
    assert ex.value.code == 0
    out = capsys.readouterr().out
    for words in ("--connect tcp/127.0.0.1:7447", "http://127.0.0.1:8765/", "observers", "[zenoh.tls]",
                  "--sample grating2d"):
        assert words in out, words


def test_scanner_feed_holds_a_bounded_amount_whatever_the_run_length():
    feed = ScannerFeed("s1", display_rate_Hz=50.0, history_s=2.0)      # rings of 100 rows
    cursor: dict[str, int] = {}
    for k in range(600):                                                # 12 s of 1 kHz setpoints
        now = 100.0 + 0.02 * k
        feed.on_setpoints(encode_setpoints(k, _batch(20 * k, 20)), arrival_s=now + 0.003)
        feed.on_drift(DriftMsg(seq=k, t_s=0.02 * k, drift_nm=[0, 0, 1.0]).to_json_bytes())
        for j in range(10):                                             # 500 tips/s and image pixels
            t = 0.02 * k + 0.002 * j
            feed.on_tip(SimTipMsg(seq=0, t_s=t, position_nm=[t, 1, 0]).to_json_bytes(), arrival_s=now + 0.002 * j)
            feed.on_image(SimImageMsg(seq=0, t_s=t, position_nm=[t, t, 0], height_nm=1.0).to_json_bytes())
        if k % 10 == 0:
            feed.frame(cursor, with_image=True)
    assert len(feed.setpoints) == len(feed.tips) == len(feed.drift) == 100
    assert feed.image._h.shape == (64, 128) and feed.image.samples == 6000
    assert len(feed._pending) <= 100 and len(feed._errors) <= 100
    assert sum(len(t) for t in feed._targets._t) <= 5.0 * 1000 + 40     # 5 s of targets at full rate
    assert feed.counts["setpoint_samples"] == 12_000 and feed.counts["tips"] == 6000
