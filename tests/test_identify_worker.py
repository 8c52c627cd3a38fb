"""The identification process ``afmctl calibrate`` starts while the device still plays (#38,
:mod:`afmctl.api.identify_worker`): the same model as ``identify`` in the caller's process,
a failure as one line, and a close that does not wait for a fit."""
from __future__ import annotations

import time

import numpy as np
import pytest

from afmctl.api.identify import identify
from afmctl.api.identify_worker import IdentifyWorker
from afmctl.data.datafiles import write_csv
from afmctl.errors import AfmctlError


def _recording(path, seconds: float = 4.0, rate_Hz: float = 2000.0):
    """Nested triangles through a PI-like scanner: t [s], u [V], y [nm]."""
    t = np.arange(int(seconds * rate_Hz)) / rate_Hz
    amp = 60.0 * (1.0 - 0.2 * np.floor(t))                  # one amplitude a second, falling
    u = amp * (1.0 - np.abs(2.0 * (t % 1.0) - 1.0))
    y = np.empty_like(u)
    play, r = 0.0, 8.0
    for k, v in enumerate(u):
        play = min(max(play, v - r), v + r)
        y[k] = 70.0 * v + 30.0 * play
    write_csv(path, {"t": t, "u": u, "y": y})
    return path


def test_the_worker_returns_the_model_identify_gives_in_the_callers_process(tmp_path):
    csv = _recording(tmp_path / "rec.csv")
    with IdentifyWorker() as worker:
        worker.submit("x", "pi", csv, {"n_operators": 6})
        there = worker.result("x")
    here = identify("pi", csv, n_operators=6)
    assert there.model.model_dump_json() == here.model.model_dump_json()
    assert there.rms_nm == here.rms_nm and np.array_equal(there.y_fit_nm, here.y_fit_nm)


def test_handed_the_recordings_arrays_the_worker_gives_the_model_of_its_csv(tmp_path):
    """``afmctl calibrate`` hands the worker the arrays and writes the CSV while it fits: the
    file holds the same values (full float precision), so the model is the file's; a
    failure is one line, as from the file."""
    from afmctl.data.datafiles import read_csv
    csv = _recording(tmp_path / "rec.csv")
    cols = read_csv(csv, ("t", "u", "y"))
    with IdentifyWorker() as worker:
        worker.submit("x", "auto", csv, {"candidates": ["pi", "preisach"], "jobs": 2},
                      columns={k: np.asarray(v) for k, v in cols.items()})
        there = worker.result("x")
        worker.submit("bad", "pi", csv, {"burn_in": "100"}, columns={k: np.asarray(v) for k, v in cols.items()})
        with pytest.raises(AfmctlError) as err:
            worker.result("bad")
    here = identify("auto", csv, candidates=["pi", "preisach"])
    assert there.model.model_dump_json() == here.model.model_dump_json()
    assert "--burn-in: 100 s is outside" in str(err.value) and "\n" not in str(err.value)


def test_a_failed_fit_comes_back_as_one_line_and_the_worker_goes_on(tmp_path):
    csv = _recording(tmp_path / "rec.csv")
    with IdentifyWorker() as worker:
        worker.submit("bad", "pi", tmp_path / "missing.csv", {})
        worker.submit("good", "pi", csv, {"n_operators": 4})
        with pytest.raises(AfmctlError) as err:
            worker.result("bad")
        assert "missing.csv" in str(err.value) and "\n" not in str(err.value)
        assert worker.result("good").model.kind == "pi"


def test_a_stop_ends_the_wait_and_close_ends_a_fit_still_running_at_once(tmp_path):
    csv = _recording(tmp_path / "long.csv", seconds=20.0, rate_Hz=5000.0)
    worker = IdentifyWorker()
    worker.submit("x", "auto", csv, {})
    time.sleep(2.0)                                          # the worker is fitting (auto: seconds)
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):                   # a stop from another thread (zenoh)
        worker.result("x", stop=lambda: time.monotonic() - t0 > 0.3)
    worker.close()
    assert time.monotonic() - t0 < 3.0
    assert not worker._proc.is_alive()


def test_calibrates_worker_count_comes_from_the_environment_or_is_refused_in_one_line(monkeypatch):
    from afmctl.api.calibrate import FIT_JOBS, FIT_JOBS_ENV, fit_jobs

    monkeypatch.delenv(FIT_JOBS_ENV, raising=False)
    assert fit_jobs() == FIT_JOBS == 2
    monkeypatch.setenv(FIT_JOBS_ENV, "1")
    assert fit_jobs() == 1
    for bad in ("0", "two", "99"):
        monkeypatch.setenv(FIT_JOBS_ENV, bad)
        with pytest.raises(AfmctlError, match=f"{FIT_JOBS_ENV}: '{bad}'; allowed a whole number 1 … 16"):
            fit_jobs()
