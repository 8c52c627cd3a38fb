"""Learned wave tables (``.afmwave``): written and read back exactly, played by the controller
as they are (``[trajectory] kind = "learned"``), and refused with one line when the
trajectory, the amplifier's limits or a model file no longer match what they were learned for."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from afmctl.config import LearnedSpec, RasterSpec
from afmctl.control.controller import Controller, State
from afmctl.control.hardware import open_driver
from afmctl.control.learned_table import (LearnedSource, load_learned, make_learned, save_learned)
from afmctl.control.pipeline import build_pipeline
from afmctl.control.runlog import RunLogReader
from afmctl.control.wave_plan import plan_table
from afmctl.errors import AfmctlError
from afmctl.inputs.trajectories import build, collect
from afmctl.sim_backend.testing import serve_pty
from afmctl.testing import assert_no_threads_left, make_config

RATE_HZ = 2000.0
NM_PER_V = 50.0
SPEC = RasterSpec(x0_nm=1000.0, y0_nm=1500.0, z_nm=1000.0, width_nm=3000.0, height_nm=0.0, lines=2,
                  line_rate_Hz=20.0)


@pytest.fixture(autouse=True)
def no_leaked_threads():
    yield
    assert_no_threads_left("afmctl-")


def cfg_for(tmp_path, port: str, max_V: float = 120.0, rate_Hz: float = RATE_HZ, **extra):
    cal = {a: {"nm_per_V": NM_PER_V} for a in "xyz"}
    return make_config(tmp_path, loop={"rate_Hz": rate_Hz}, scanner={"calibration": cal},
                       amplifier={"driver": "gcs", "port": port, "output": "wave", "slew_V_per_s": 4000.0,
                                  "limits_V": {a: {"min_V": 0.0, "max_V": max_V} for a in "xyz"}},
                       safety={"slew_V_per_s": 4000.0, "ramp_V_per_s": 1000.0, "watchdog_s": 0.2}, **extra)


def learned_file(tmp_path, cfg, name: str = "t.afmwave"):
    """A planned table with a small smooth change (as a learning step would make), saved."""
    targets = collect(build(SPEC, cfg.dt_s))
    table = plan_table(cfg, build_pipeline(cfg), targets, 22.0, {a: cfg.limits(a) for a in "xyz"}, 1.0)
    n = len(table)
    table.u_V[:, 0] += 0.4 * np.sin(np.linspace(0.0, 2.0 * np.pi, n))    # ≤ 0.0013 V per row
    path = save_learned(tmp_path / name, make_learned(cfg, table, SPEC.model_dump(mode="json"),
                                                      [{"iteration": 1, "max_pct": 1.0}]))
    return path, table


def test_a_learned_table_reads_back_exactly(tmp_path):
    cfg = cfg_for(tmp_path, "unused")
    path, table = learned_file(tmp_path, cfg)
    back = load_learned(path)
    for name in ("target_nm", "corrected_nm", "drift_nm", "u_V", "T_C"):
        np.testing.assert_array_equal(getattr(back.table, name), getattr(table, name))
    assert back.table.pad == table.pad and back.history == [{"iteration": 1, "max_pct": 1.0}]
    LearnedSource(back, path).table_for(cfg)          # learned for this configuration: accepted


@pytest.mark.parametrize("damage", ["garbage", "missing", "shape"])
def test_a_damaged_file_is_one_line_naming_it(tmp_path, damage):
    cfg = cfg_for(tmp_path, "unused")
    path, table = learned_file(tmp_path, cfg)
    if damage == "garbage":
        path.write_bytes(b"not a zip at all")
    elif damage == "missing":
        path.unlink()
    else:
        with np.load(path) as z:
            arrays = dict(z)
        arrays["u_V"] = arrays["u_V"][:-1]
        np.savez(path.open("wb"), **arrays)
    with pytest.raises(AfmctlError) as err:
        load_learned(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("change, message", [
    ({"max_V": 100.0}, "the voltage limits [V] was"),
    ({"rate_Hz": 1000.0}, "loop.rate_Hz was"),
    ({"settle_s": 1.0}, "amplifier.settle_s [s] was 0.2"),
])
def test_a_table_learned_under_other_conditions_is_refused(tmp_path, change, message):
    path, _ = learned_file(tmp_path, cfg_for(tmp_path, "unused"))
    settle_s = change.pop("settle_s", None)
    other = cfg_for(tmp_path, "unused", **change)
    if settle_s is not None:
        other.amplifier.settle_s = settle_s
    with pytest.raises(AfmctlError) as err:
        LearnedSource.from_file(path).table_for(other)
    assert str(path) in str(err.value) and message in str(err.value) and "relearn" in str(err.value)


def test_an_unset_settle_hold_plays_the_one_the_table_was_learned_with(tmp_path):
    learning = cfg_for(tmp_path, "unused")
    learning.amplifier.settle_s = 2.0                    # as afmctl learn holds by default
    path, _ = learned_file(tmp_path, learning)
    source = LearnedSource.from_file(path)
    unset = cfg_for(tmp_path, "unused")
    assert unset.amplifier.settle_s is None
    source.table_for(unset)                              # accepted ...
    assert source.settle_s(unset) == 2.0                 # ... and played after the learning's hold
    source.table_for(learning)
    assert source.settle_s(learning) == 2.0
    shorter = cfg_for(tmp_path, "unused")
    shorter.amplifier.settle_s = 0.2
    with pytest.raises(AfmctlError, match=r"amplifier.settle_s \[s\] was 2.0 .* now has 0.2"):
        source.table_for(shorter)


def test_a_changed_model_file_is_refused(tmp_path, chain_file):
    cfg = cfg_for(tmp_path, "unused", compensation={"x": {"model": str(chain_file)}})
    path, _ = learned_file(tmp_path, cfg)
    LearnedSource.from_file(path).table_for(cfg)
    chain_file.write_text(chain_file.read_text().replace("}", " }", 1))
    with pytest.raises(AfmctlError, match="the x model file was changed"):
        LearnedSource.from_file(path).table_for(cfg)


@pytest.mark.slow
def test_the_controller_plays_the_learned_table_as_it_is(tmp_path):
    """... after the settle hold it was learned with (the configuration leaves it unset)."""
    with serve_pty("gcs", baud=921600) as srv:
        cfg = cfg_for(tmp_path, srv.port)
        learning = cfg.model_copy(deep=True)
        learning.amplifier.settle_s = 0.5
        path, table = learned_file(tmp_path, learning)
        amp = open_driver(cfg, srv.port)
        try:
            with Controller(cfg, amp) as ctl:
                ctl.start(LearnedSpec(file=path), runlog_path=tmp_path / "l.afmlog")
                assert ctl.wait(60)
                stats = ctl.stats()
        finally:
            amp.close()
    assert ctl.state is State.STOPPED and stats["wave"]["played"] == len(table), stats
    reader = RunLogReader(tmp_path / "l.afmlog")
    events = reader.events()
    sp, ev = reader.setpoints(), {e["event"]: e["seq"] for e in events}
    rows = sp[(sp["seq"] >= ev["ramp-done"]) & (sp["seq"] < ev["end"])]
    np.testing.assert_allclose(rows["u_V"][:, 0], table.u_V[:len(rows), 0])
    held = {e["event"]: e["wall_time"] for e in events}
    assert "holding it 0.5 s" in next(e["detail"] for e in events if e["event"] == "settle")
    assert held["ramp-done"] - held["settle"] >= 0.5


RUN_TOML = """
[amplifier]
driver = "{driver}"
output = "{output}"
[loop]
rate_Hz = 2000
[simulation]
enabled = true
[runlog]
dir = "{dir}"
fsync = false
[trajectory]
kind = "learned"
file = "{file}"
"""


@pytest.mark.slow
@pytest.mark.parametrize("driver, output, message", [
    ("gcs", "setpoints", "trajectory.kind = 'learned' plays a learned table on the amplifier's clock"),
    ("can", "wave", "amplifier.driver was gcs when the table was learned"),
])
def test_afmctl_run_refuses_a_learned_table_it_cannot_play(tmp_path, driver, output, message):
    path, _ = learned_file(tmp_path, cfg_for(tmp_path, "unused"))
    (tmp_path / "run.toml").write_text(RUN_TOML.format(driver=driver, output=output, dir=tmp_path, file=path))
    res = subprocess.run([sys.executable, "-m", "afmctl", "run", "--config", str(tmp_path / "run.toml")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    errors = [ln for ln in res.stderr.strip().splitlines() if ln.startswith("afmctl: error:")]
    assert len(errors) == 1 and message in errors[0], res.stderr


def test_what_the_learnings_plays_leave_is_kept_and_taken_out_for_the_time_passed(tmp_path, chain_file):
    from afmctl.compensators.learning_laws import static_ops
    from afmctl.compensators.models import load_model
    from afmctl.control.learned_after import HistoryAfter, corrected_for_history

    cfg = cfg_for(tmp_path, "unused", compensation={"x": {"model": str(chain_file)}})
    _, table = learned_file(tmp_path, cfg)
    n = len(table)
    term = np.zeros((3, n, 3))
    term[:, :, 0] = np.array([12.0, 6.0, 2.0])[:, None]          # x: 12 nm right after, 6 nm 10 s later, 2 at 30 s
    after = HistoryAfter((0.0, 10.0, 30.0), term, 1000.0)
    np.testing.assert_allclose(after.at(5.0)[:, 0], 9.0)          # between the kept delays: linear
    np.testing.assert_allclose(after.at(30.0)[:, 0], 2.0)
    assert not np.any(after.at(31.0))                             # after the last: rested
    path = save_learned(tmp_path / "a.afmwave", make_learned(cfg, table, SPEC.model_dump(mode="json"), [], after))
    back = load_learned(path).after
    assert back is not None and back.delays_s == after.delays_s and back.ended_unix_s == 1000.0
    np.testing.assert_array_equal(back.term_nm, term)

    cfg.simulation.enabled = False                                # a device that kept its state
    played = corrected_for_history(table, after, cfg, now_unix_s=1005.0)
    forward = static_ops(load_model(chain_file), cfg.dt_s)[0]
    moved = forward().block(played.u_V[:, 0].copy()) - forward().block(table.u_V[:, 0].copy())
    assert np.max(np.abs(moved + 9.0)) < 0.5, moved                # the static part lands 9 nm lower
    np.testing.assert_array_equal(played.u_V[:, 1:], table.u_V[:, 1:])
    assert "ended 5 s ago" in played.report[-1] and "taken out" in played.report[-1]
    # an in-process simulator starts at rest with every command: nothing to take out
    cfg.simulation.enabled = True
    assert corrected_for_history(table, after, cfg, now_unix_s=1005.0) is table


def test_a_table_learned_as_recorded_says_so_when_played_late(tmp_path):
    """Axes learned on a device without a creep stage were learned for the play right after
    the learning's: the file keeps which and when, and a run later than the fresh window
    says in one line that the creep has moved on (nothing to take out); soon after, or on an
    in-process simulator, it says nothing. A malformed entry is one line naming the file."""
    import time

    from afmctl.control.learned_after import AS_RECORDED_FRESH_S, AsRecorded
    cfg = cfg_for(tmp_path, "unused")
    _, table = learned_file(tmp_path, cfg)
    now = time.time()
    late = AsRecorded(("x",), now - 3 * AS_RECORDED_FRESH_S)
    path = save_learned(tmp_path / "r.afmwave", make_learned(cfg, table, SPEC.model_dump(mode="json"), [], None, late))
    back = load_learned(path)
    assert back.as_recorded == late
    cfg.simulation.enabled = False
    played = LearnedSource(back, path).table_for(cfg)
    np.testing.assert_array_equal(played.u_V, table.u_V)
    assert played.report[-1].startswith("x: learned without a creep stage 30 s ago")
    assert AsRecorded(("x",), now).note(now + 1.0) is None             # right after: nothing to say
    cfg.simulation.enabled = True
    assert LearnedSource(back, path).table_for(cfg).report == table.report
    with np.load(path) as z:
        arrays = dict(z)
    meta = json.loads(str(arrays["meta_json"]))
    meta["as_recorded"] = {"axes": ["q"], "ended_unix_s": 1.0}
    arrays["meta_json"] = np.array(json.dumps(meta))
    np.savez(path.open("wb"), **arrays)
    with pytest.raises(AfmctlError) as err:
        load_learned(path)
    assert str(path) in str(err.value) and "as_recorded" in str(err.value) and "\n" not in str(err.value)


def test_a_table_learned_as_recorded_keeps_its_rest_and_reads_it_back(tmp_path):
    """Every play of a table learned as recorded starts ``rest_s`` after the play before it
    ended: the wait is what is left of that rest, none once it has passed or for a table
    from before the rest (0 s). The file keeps it; one out of range is one line naming the
    file and the range."""
    from afmctl.control.learned_after import AS_RECORDED_FRESH_S, AsRecorded
    spaced = AsRecorded(("x", "y"), 1000.0, 4.0)
    assert spaced.wait_s(1001.5) == pytest.approx(2.5)
    assert spaced.wait_s(1004.5) == 0.0 and spaced.wait_s(990.0) == 4.0     # a clock stepped back: the rest at most
    assert AsRecorded(("x",), 1000.0).wait_s(1000.0) == 0.0                  # written before the rest: none
    assert AsRecorded((), 1000.0, 4.0).wait_s(1000.0) == 0.0
    assert "holding the present output 2.5 s" in spaced.waiting(2.5)
    cfg = cfg_for(tmp_path, "unused")
    _, table = learned_file(tmp_path, cfg)
    path = save_learned(tmp_path / "s.afmwave", make_learned(cfg, table, SPEC.model_dump(mode="json"), [], None, spaced))
    assert load_learned(path).as_recorded == spaced
    with np.load(path) as z:
        arrays = dict(z)
    meta = json.loads(str(arrays["meta_json"]))
    meta["as_recorded"]["rest_s"] = 3 * AS_RECORDED_FRESH_S
    arrays["meta_json"] = np.array(json.dumps(meta))
    np.savez(path.open("wb"), **arrays)
    with pytest.raises(AfmctlError) as err:
        load_learned(path)
    assert str(path) in str(err.value) and "rest_s must be 0 to 10 s" in str(err.value), err.value


@pytest.mark.parametrize("stop", [False, True])
def test_a_table_learned_as_recorded_starts_after_its_rest(tmp_path, stop):
    """The run holds the present output until the rest after the learning's last play has
    passed, then approaches and plays, as every play of the learning did; a stop during
    that hold ends the run at once, nothing of the table played."""
    import time

    from afmctl.control.learned_after import AsRecorded
    with serve_pty("gcs", baud=921600) as srv:
        cfg = cfg_for(tmp_path, srv.port)
        _, table = learned_file(tmp_path, cfg)
        amp = open_driver(cfg, srv.port)
        ended = time.time()
        path = save_learned(tmp_path / "s.afmwave", make_learned(cfg, table, SPEC.model_dump(mode="json"), [], None,
                                                                 AsRecorded(("x",), ended, 1.5)))
        try:
            with Controller(cfg, amp) as ctl:
                ctl.start(LearnedSpec(file=path), runlog_path=tmp_path / "l.afmlog")
                if stop:
                    time.sleep(0.5)
                    ctl.stop()
                assert ctl.wait(60)
                stats = ctl.stats()
        finally:
            amp.close()
    events = RunLogReader(tmp_path / "l.afmlog").events()
    at = {e["event"]: e["wall_time"] for e in events}
    assert "rest" in at and "learned without a creep stage" in next(e["detail"] for e in events if e["event"] == "rest")
    assert ctl.state is State.STOPPED, stats
    if stop:
        assert "ramp" not in at and stats["wave"]["played"] == 0, (at, stats)
    else:
        assert at["ramp"] >= ended + 1.5 - 0.01 and at["ramp"] < at["rest"] + 1.5 + 1.0, at
        assert stats["wave"]["played"] == len(table)


@pytest.mark.slow
def test_on_a_device_the_replay_starts_no_sooner_than_a_run_could(tmp_path, monkeypatch):
    """On a device (the simulated E-727 over a pty, kept between plays) the learned table's
    replay starts AS_RECORDED_REST_S after the last play, as ``afmctl run`` right after
    learning would: the model's history term then meets the same age of creep in both. The
    axis has a creep stage, so the learning's own plays do not rest. (The rest is 1.5 s
    here, for the suite's time.)"""
    from afmctl.compensators.creep import LinearCreepModel
    from afmctl.compensators.models import save_model
    from afmctl.control import learn_run
    from afmctl.control.learn_run import LearnOptions, LearnRun
    monkeypatch.setattr(learn_run, "AS_RECORDED_REST_S", 1.5)
    AS_RECORDED_REST_S = 1.5
    creep = LinearCreepModel(time_constants_s=[0.01, 0.1, 1.0, 10.0, 100.0], creep_weights=[0.008] * 5,
                             gain_nm_per_V=NM_PER_V, offset_nm=0.0, initial_V=0.0)
    save_model(creep, tmp_path / "x_creep.json")
    with serve_pty("gcs", baud=921600) as srv:
        cfg = cfg_for(tmp_path, srv.port, simulation={"enabled": False}, trajectory=SPEC.model_dump(mode="json"),
                      compensation={"x": {"model": str(tmp_path / "x_creep.json")}})
        cfg.amplifier.settle_s = 0.2
        amp = open_driver(cfg, srv.port)
        try:
            run = LearnRun(cfg, amp, LearnOptions(iterations=0))
            times: list[dict[str, float]] = []
            played = run.player.on_played
            run.player.on_played = lambda table, rows, t: (times.append(t), played(table, rows, t))
            run.run()
        finally:
            amp.close()
    assert run.player.spaced_axes == () and run.replayed is not None
    assert len(times) == 2 and times[1]["approach"] - times[0]["finished"] >= AS_RECORDED_REST_S - 0.05, times
