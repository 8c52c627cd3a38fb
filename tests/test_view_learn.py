"""``afmctl view`` plots a learning run's convergence: iterations published on
``afm/<scanner>/learn`` (a real zenoh session on loopback) reach the page in Debian's
headless Chromium, which draws them; a second learning run replaces the first."""
from __future__ import annotations

import sys
import time

import pytest

from afmctl.testing import wait_for
from afmctl.view.testing import Browser, ChildProcess, canvas_pixels
from afmctl.zenoh_api.learn import LearnPublisher
from afmctl.zenoh_api.settings import loopback_pair

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

ORANGE = (230, 85, 13)      # central max (view.js LEARN_SERIES)
ERRORS = [(5.0, 2.0, 4.0, 1.5), (2.0, 0.8, 1.5, 0.5), (0.9, 0.3, 0.6, 0.2), (0.4, 0.1, 0.2, 0.08)]


def _publish_until_seen(pub, page, errors, state_last: str) -> None:
    for k, (mx, rms, cmx, crms) in enumerate(errors):
        state = state_last if k == len(errors) - 1 else "learning"
        pub.publish(k, {"max_pct": mx, "rms_pct": rms, "central_max_pct": cmx, "central_rms_pct": crms},
                    step=0.9, state=state, detail="noise floor" if state != "learning" else "")
        time.sleep(0.2)


def test_view_plots_the_convergence_of_a_learning_run(tmp_path):
    srv, _cli = loopback_pair()
    with LearnPublisher(srv, "s1") as pub:
        view = ChildProcess([sys.executable, "-m", "afmctl", "view", "--http", "127.0.0.1:0", "--scanner", "s1",
                      "--connect", srv.listen[0]], tmp_path, "view")
        try:
            url = view.wait_line("afmctl view: http://", 120.0).split(": ", 1)[1]
            with Browser(tmp_path / "chromium") as browser:
                page = browser.open(url)
                seen = 'window.afmView.scanners["s1"] && window.afmView.scanners["s1"].learn.length'
                # the first messages may go before zenoh has routed the view's subscription
                assert wait_for(lambda: (_publish_until_seen(pub, page, ERRORS[:1], "learning"),
                                         page.evaluate(f"() => {seen} || 0"))[1] >= 1, 60.0, 0.5)
                _publish_until_seen(pub, page, ERRORS, "converged")
                page.wait_for_function(f"() => {seen} === {len(ERRORS)}", timeout=30_000, polling=200)
                rows = page.evaluate('window.afmView.scanners["s1"].learn')
                assert [r[0] for r in rows] == list(range(len(ERRORS)))
                assert [r[3] for r in rows] == [e[2] for e in ERRORS]
                assert page.evaluate('window.afmView.scanners["s1"].learnState.state') == "converged"
                px = canvas_pixels(page, "plot-learn", ORANGE, tol=30)
                assert px["match"] >= 100, px
                page.screenshot(path=str(tmp_path / "learn.png"))
                # a new learning run (iteration 0 again) replaces the old one on the page
                _publish_until_seen(pub, page, ERRORS[:2], "learning")
                page.wait_for_function(f"() => {seen} === 2", timeout=30_000, polling=200)
        finally:
            code = view.stop()
    assert code == 0, view.stderr()[-2000:]
