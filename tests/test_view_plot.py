"""The page's line drawing (afmctl/view/static/plot.js ``tracePath``), run in Debian's
headless Chromium against a recording context: runs of points inside one pixel column
become at most four vertices (first, lowest, highest, last) in the data's order, so the
drawn trace keeps every column's extremes; a null point lifts the pen."""
from __future__ import annotations

import math

import pytest

from afmctl.view.app import static_dir
from afmctl.view.testing import Browser

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

#: the vertices tracePath emits for points (x[i], y[i]) [px], identity scales
TRACE_JS = """([xs, ys]) => {
  const out = [];
  const ctx = { moveTo: (x, y) => out.push(["M", x, y]), lineTo: (x, y) => out.push(["L", x, y]) };
  tracePath(ctx, xs.length, (i) => xs[i], (i) => ys[i], (v) => v, (v) => v);
  return out;
}"""


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    with Browser(tmp_path_factory.mktemp("chromium")) as browser:
        pg = browser.open("about:blank")
        pg.add_script_tag(path=f"{static_dir()}/plot.js")
        yield pg


def _trace(page, xs: list[float], ys: list[float | None]) -> list[list]:
    return page.evaluate(TRACE_JS, [xs, ys])


def test_each_column_keeps_its_first_last_and_extremes_in_order(page):
    n = 6000                                       # 6000 points over 300 px: 20 a column
    xs = [300.0 * i / n for i in range(n)]
    ys = [50 * math.sin(i * 0.37) + 20 * math.sin(i * 0.011) for i in range(n)]
    out = _trace(page, xs, ys)
    assert out[0][0] == "M" and all(v[0] == "L" for v in out[1:])
    assert len(out) <= 4 * 300 and len(out) >= 2 * 300
    for c in range(300):
        idx = [i for i in range(n) if math.floor(xs[i]) == c]
        col = [(v[1], v[2]) for v in out if math.floor(v[1]) == c]
        want = {(xs[idx[0]], ys[idx[0]]), (xs[idx[-1]], ys[idx[-1]])}
        lo, hi = min(idx, key=lambda i: ys[i]), max(idx, key=lambda i: ys[i])
        want |= {(xs[lo], ys[lo]), (xs[hi], ys[hi])}
        assert set(col) == want, c
        order = [next(i for i in idx if (xs[i], ys[i]) == p) for p in col]
        assert order == sorted(order), c             # in the data's order: the path is the trace's


def test_sparse_points_are_drawn_as_they_are(page):
    xs, ys = [0.0, 3.0, 7.5, 12.0], [1.0, -2.0, 4.0, 0.5]
    assert _trace(page, xs, ys) == [["M", 0, 1], ["L", 3, -2], ["L", 7.5, 4], ["L", 12, 0.5]]


def test_a_null_point_lifts_the_pen(page):
    xs, ys = [0.0, 1.0, 2.0, 3.0, 4.0], [1.0, 2.0, None, 3.0, 4.0]
    assert _trace(page, xs, ys) == [["M", 0, 1], ["L", 1, 2], ["M", 3, 3], ["L", 4, 4]]
