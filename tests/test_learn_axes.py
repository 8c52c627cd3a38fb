"""Per-axis bookkeeping of ``afmctl learn --config`` (afmctl.control.learn_axes): each axis
keeps its own best column and stalls on its own figure."""
from __future__ import annotations

import numpy as np

from afmctl.control.learn_axes import AxisBook
from afmctl.control.wave_plan import WaveTable
from afmctl.data.axis_errors import AxisError, ErrorReport


def _table(x_V: float, y_V: float, n: int = 4) -> WaveTable:
    u = np.zeros((n, 3))
    u[:, 0], u[:, 1] = x_V, y_V
    z = np.zeros((n, 3))
    return WaveTable(z, z, z, u, np.full(n, 22.0), 0, [])


def _judged(x_nm: float, y_nm: float) -> ErrorReport:
    return ErrorReport("all", 4, [AxisError("x", x_nm, x_nm / 2, "line", 4000.0),
                                  AxisError("y", y_nm, y_nm / 2, "step", 90.0)])


def test_each_axis_keeps_its_own_best_column_and_the_table_is_made_of_them():
    book = AxisBook(["x", "y"])
    # x improves all along; y is best on the first play (its % of a short step is large throughout)
    for k, (x_nm, y_nm) in enumerate([(800.0, 60.0), (200.0, 70.0), (80.0, 90.0)]):
        book.record(k, _table(float(k), 10.0 + k), _judged(x_nm, y_nm))
    best = book.best_table(_table(-1.0, -1.0))
    assert best.u_V[0, 0] == 2.0 and best.u_V[0, 1] == 10.0      # x from play 2, y from play 0
    assert best.u_V[0, 2] == 0.0                                 # an axis not learned is as given
    assert "(iteration 2)" in book.best_text() and "(iteration 0)" in book.best_text()


def test_an_axis_stalls_on_its_own_figure_and_a_finished_one_plays_its_best_again():
    book = AxisBook(["x", "y"])
    for k, (x_nm, y_nm) in enumerate([(100.0, 50.0), (50.0, 49.9), (25.0, 49.8)]):
        book.record(k, _table(float(k), 10.0 + k), _judged(x_nm, y_nm))
    assert book.axes["y"].stalled() and not book.axes["x"].stalled()
    book.finish("y", "no further improvement")
    assert book.learning() == ["x"] and not book.all_done()
    book.record(3, _table(3.0, 20.0), _judged(12.0, 1.0))          # a replay of y's best: not a new best
    assert book.axes["y"].best_iteration == 2 and book.best_column("y")[0] == 12.0
    assert "y keeps iteration 2: no further improvement" in book.done_text()
    book.finish("x", "at the noise floor")
    assert book.all_done() and not book.any_diverged()
