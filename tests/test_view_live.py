"""Issue 14, ``afmctl view`` acceptance with real parts: ``afmctl sim`` (MDT693B on a pty,
true tip and a grating image on zenoh), ``afmctl run`` (a 1 kHz raster, zenoh with access
control: only the authenticated user ``viewer`` may observe) and ``afmctl view`` as three
processes, zenoh on loopback with free ports, the page loaded in Debian's headless
Chromium. The test waits for live data, checks that numbers update and that every plot
has drawn its series, and saves a screenshot."""
from __future__ import annotations

import re
import time

import pytest

from afmctl.testing import wait_for
from afmctl.view.feed import ViewFeed
from afmctl.view.testing import Browser, LiveStack, canvas_pixels
from afmctl.zenoh_api.settings import ZenohSettings

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]

BLUE, RED, ORANGE = (31, 119, 180), (214, 39, 40), (230, 85, 13)     # x, y, the tip (plot.js)
LIVE_JS = """() => { const s = window.afmView.scanners["stage1"];
  return !!s && s.setpoints.length > 100 && s.drift.length > 10 && !!s.image && s.image.samples > 500
         && s.tips.filter((r) => r[4] !== null).length > 100 && !!s.status; }"""


FILLED_JS = """() => { const cells = window.afmView.scanners["stage1"].image.height_nm.flat();
  return cells.filter((v) => v !== null).length > 0.2 * cells.length; }"""


def _number(page, cell: str) -> int:
    return int(re.sub(r"[^0-9]", "", page.inner_text(f"#v-{cell}")) or -1)


def test_view_page_shows_the_live_scanner_in_headless_chromium(tmp_path):
    with LiveStack(tmp_path, lines=32, line_rate_Hz=2.0, repeat=8) as stack, Browser(tmp_path / "chromium") as browser:
        page = browser.open(stack.url)
        page.wait_for_function(LIVE_JS, timeout=90_000, polling=500)
        # the numbers update: samples of the loop (status) and setpoints received
        # (frames come as fast as the page takes them, at most 10 per s: fewer on a loaded machine)
        n0, f0 = _number(page, "samples"), page.evaluate("window.afmView.frames")
        assert wait_for(lambda: page.evaluate("window.afmView.frames") >= f0 + 10, 30.0, 0.2)
        n1, f1 = _number(page, "samples"), page.evaluate("window.afmView.frames")
        assert n1 > n0 > 0 and f1 >= f0 + 10, (n0, n1, f0, f1)
        assert page.inner_text("#state") == "running"
        assert page.inner_text("#link") == "live"
        # every plot drew its series (pixels of the series' colours inside the canvas)
        for canvas, colour, least in [("plot-volts", BLUE, 300), ("plot-volts", RED, 300),
                                      ("plot-targets", BLUE, 300), ("plot-xy", ORANGE, 300),
                                      ("plot-error", BLUE, 100), ("plot-drift", BLUE, 100)]:
            px = canvas_pixels(page, canvas, colour, tol=30)
            assert px["match"] >= least, (canvas, colour, px)
        # the image: the grating's pillars (viridis' bright end) and the floor between them
        # (its dark end), left of the colour bar; at least a fifth of the pixels filled
        page.wait_for_function(FILLED_JS, timeout=150_000, polling=1000)
        image = page.evaluate('window.afmView.scanners["stage1"].image')
        assert image["h_range_nm"] == pytest.approx([0.0, 100.0], abs=1e-6)   # grating2d: 100 nm pillars
        dark = canvas_pixels(page, "plot-image", (68, 1, 84), tol=40, width_fraction=0.75)
        bright = canvas_pixels(page, "plot-image", (253, 231, 37), tol=40, width_fraction=0.75)
        assert dark["match"] > 1000 and bright["match"] > 1000, (dark, bright)
        # the tracking error is finite and smaller than the scan range (the run has no model,
        # only the linear calibration; its tip and targets are put on one clock from the
        # messages' arrival times, and a CI run on a loaded machine measured 52 % RMS in x)
        tracking = page.evaluate('window.afmView.scanners["stage1"].tracking')
        assert tracking["n"] > 50 and 0 < tracking["rms_pct"][0] < 100, tracking
        page.screenshot(path=str(tmp_path / "view.png"))
        assert (tmp_path / "view.png").stat().st_size > 50_000

        # access control is honoured: a peer without the viewer's credentials sees no
        # setpoints from the service (it may connect, zenoh's ACL drops what it asks for)
        anonymous = ViewFeed(ZenohSettings(listen=[], connect=[stack.run_endpoint]), ["stage1"])
        with anonymous:
            time.sleep(3.0)
            assert wait_for(lambda: page.evaluate("window.afmView.frames") > f1 + 20, 30.0)
            feeds = anonymous.feeds()
            assert "stage1" not in feeds or feeds["stage1"].counts["setpoint_batches"] == 0, feeds
        codes = stack.stop()
    assert codes == {"view": 0, "run": 0, "sim": 0}, (codes, {n: p.stderr()[-1500:] for n, p in stack.procs.items()})
