"""Dynamics identification on the simulated scanner, ``afmctl excite``, and the dynamics
inverse through ``afmctl compensate`` within the amplifier's limits."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.compensators.dynamics import LinearDynamicsModel
from afmctl.compensators.dynamics_limits import invert_within_limits, rate_limit
from afmctl.compensators.models import load_model
from afmctl.data.datafiles import read_csv, write_csv
from afmctl.data.excitation import ExcitationSpec, excitation
from afmctl.sim_backend.scanner import Scanner, default_scanner_config


def run_cli(args, capsys):
    rc = main([str(a) for a in args])
    out = capsys.readouterr()
    return rc, out.out, out.err


def play_x(u_V: np.ndarray, dt_s: float) -> np.ndarray:
    s = Scanner(default_scanner_config())
    U = np.zeros((u_V.size, 3))
    U[:, 0] = u_V
    return s.run(U, dt_s)[:, 0]


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory):
    """``afmctl excite --kind dynamics`` at 50 kHz played through the default scanner."""
    d = tmp_path_factory.mktemp("dyn")
    assert main(["excite", "--kind", "dynamics", "--u-min-V", "0", "--u-max-V", "150", "--rate-Hz", "50000",
                 "--slew-V-per-s", "10000", "--periods", "6", "--out", str(d / "exc.csv")]) == 0
    e = read_csv(d / "exc.csv", ("t", "u"))
    write_csv(d / "data.csv", {"t": e["t"], "u": e["u"], "y": play_x(e["u"], 2e-5)})
    return d


def test_identified_frf_matches_the_simulators_true_one(sim_recording, capsys, tmp_path):
    rc, out, err = run_cli(["identify", "--model", "dynamics", "--data", sim_recording / "data.csv",
                            "--out", tmp_path / "dyn.json"], capsys)
    assert rc == 0, err
    # the printed residual covers the small-signal part it was fitted on
    rms, span = re.search(r"fit residual\s*: rms ([0-9.e+-]+) nm, .* of the ([0-9.e+-]+) nm span", out).groups()
    assert float(rms) < 0.15 * float(span) and float(span) < 500
    m = load_model(tmp_path / "dyn.json", expect=("dynamics",))
    dt = 2e-5
    f = np.geomspace(20, 5000, 60)
    true = Scanner(default_scanner_config()).axes["x"].linear_response(f, dt)
    fit = m.discrete(dt).frequency_response(f)
    ratio = fit / true
    # magnitude within 10 % and phase within 15° up to 5 kHz (mode at 1 kHz, Q 20: the peak
    # itself is 20× the static gain); the simulator answers in the same sample, a lead the
    # causal model cannot hold (≈ 1.5 samples: 11° at 1 kHz)
    assert np.max(np.abs(np.abs(ratio) - 1)) < 0.10
    assert np.max(np.abs(np.degrees(np.angle(ratio)))) < 15 + np.max(f) * dt * 1.5 * 360
    mode = [p for p in m.poles() if p.imag > 0][0]
    assert abs(abs(mode) / (2 * math.pi) - 1000.0) < 10.0
    assert 0.02 < -mode.real / abs(mode) < 0.035
    assert 45 < m.fit_info["static_gain_y_per_u"] < 55  # the Preisach plant's small-signal slope


@pytest.mark.parametrize("kind", ["static", "creep", "dynamics", "all"])
def test_excite_writes_playable_voltages_within_range_and_slew(kind, capsys, tmp_path):
    out = tmp_path / "e.csv"
    rc, text, err = run_cli(["excite", "--kind", kind, "--u-min-V", "10", "--u-max-V", "90", "--rate-Hz", "20000",
                             "--slew-V-per-s", "5000", "--dwell-s", "0.5", "--out", out], capsys)
    assert rc == 0, err
    d = read_csv(out, ("t", "u"))
    assert d["u"][0] == 10.0 and d["u"].min() >= 10.0 and d["u"].max() <= 90.0
    assert np.max(np.abs(np.diff(d["u"]))) * 20000 <= 2500 * (1 + 1e-9)
    assert np.allclose(np.diff(d["t"]), 1 / 20000)
    assert "written" in text


def test_excite_static_has_reversal_curves_and_creep_has_dwells():
    spec = ExcitationSpec(0.0, 100.0, 1000.0, dwell_s=1.0)
    u = excitation("static", spec)
    turning = u[1:-1][(np.diff(u)[:-1] * np.diff(u)[1:]) < 0]
    assert np.unique(np.round(turning, 6)).size >= 14  # 12 interior reversal levels besides 0/100
    assert np.count_nonzero(np.isclose(turning, 100.0)) >= 12  # ascending curves from each level
    c = excitation("creep", spec)
    still = np.diff(c) == 0
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], still.astype(int), [0]]))))[::2]
    assert np.count_nonzero(runs >= 999) >= 8


@pytest.mark.parametrize("args, needle", [
    (["--u-min-V", "5", "--u-max-V", "1", "--rate-Hz", "100"], "--u-min-V"),
    (["--u-min-V", "0", "--u-max-V", "1", "--rate-Hz", "0"], "--rate-Hz"),
    (["--u-min-V", "0", "--u-max-V", "1", "--rate-Hz", "100", "--f-max-Hz", "80"], "--f-max-Hz"),
    (["--u-min-V", "0", "--u-max-V", "1", "--rate-Hz", "100", "--amplitude-pct", "90"], "--amplitude-pct"),
    (["--u-min-V", "0", "--u-max-V", "nan", "--rate-Hz", "100"], "--u-max-V"),
])
def test_excite_bad_options_are_one_line_errors(args, needle, capsys, tmp_path):
    rc, out, err = run_cli(["excite", "--kind", "all", *args, "--out", tmp_path / "e.csv"], capsys)
    assert rc == 2 and needle in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def _target(rate_Hz: float, dt: float) -> np.ndarray:
    """Two 3 µm trace/retrace lines at rest before and after."""
    n = int(0.5 / rate_Hz / dt)
    r = np.arange(n) / n
    line = np.concatenate([1000 + 3000 * r, 1000 + 3000 * (1 - r)])
    rest = np.full(int(0.02 / dt), 1000.0)
    return np.concatenate([rest, line, line, rest])


def test_limited_inverse_never_exceeds_range_or_slew_and_reports():
    dyn = LinearDynamicsModel.from_modes([(1000.0, 0.025)], [5000.0], bandwidth_Hz=8000.0)
    lin = linear_80()
    dt = 1e-5

    def static():
        return lin.inverse(dt)

    tgt = _target(50.0, dt)
    res = invert_within_limits(dyn, tgt, dt, static, 0.0, 150.0, slew_V_per_s=1e4)
    # the turnarounds are rounded at the model's band limit
    assert res.bandwidth_Hz == res.model_bandwidth_Hz and res.rounded_s > 0 and "rounded" in res.report()
    assert res.u_V.min() >= 0 and res.u_V.max() <= 150
    assert np.max(np.abs(np.diff(res.u_V))) <= 1e4 * dt
    # 3 µm in 10 ms at 80 nm/V is 3750 V/s for the static inverse: within 1e4 V/s, so only
    # the dynamics asked for too much and the report does not call the target too fast
    assert 3000.0 < res.static_slew_V_per_s < 4500.0 and not res.too_fast_for_the_amplifier()
    assert "too fast for the amplifier" not in res.report()
    # without rounding, the band limit of the whole inverse is lowered instead
    low = invert_within_limits(dyn, tgt, dt, static, 0.0, 150.0, slew_V_per_s=1e4, round_first=False)
    assert low.bandwidth_Hz < low.model_bandwidth_Hz and "lowered" in low.report() and low.rounded_s == 0
    assert np.max(np.abs(np.diff(low.u_V))) <= 1e4 * dt
    # an impossible slew: clipped to the limit and said so
    hard = invert_within_limits(dyn, tgt, dt, static, 0.0, 150.0, slew_V_per_s=100.0)
    assert hard.slew_limited > 0 and "still beyond them, so clipped and rate-limited" in hard.report()
    assert np.max(np.abs(np.diff(hard.u_V))) <= 100.0 * dt
    # ... and it says the target itself is too fast, with the speed share that would fit (100 / ~3750 V/s)
    assert hard.too_fast_for_the_amplifier() and "the target itself is too fast for the amplifier" in hard.report()
    share = float(hard.report().split("(at ")[-1].split(" %")[0])
    assert share == pytest.approx(100.0 * 100.0 / hard.static_slew_V_per_s, rel=1e-2) and 2.0 < share < 3.5


def _central_error_pct(y: np.ndarray, tgt: np.ndarray, rate_Hz: float, dt: float) -> float:
    """Max error over the central 80 % of the four half lines of :func:`_target`, % of 3 µm."""
    n, a0 = int(0.5 / rate_Hz / dt), int(0.02 / dt)
    e = np.concatenate([(y - tgt)[a + n // 10: a + n - n // 10] for a in a0 + n * np.arange(4)])
    return float(100 * np.max(np.abs(e)) / 3000.0)


def test_rounding_turnarounds_keeps_the_resonance_cancelled_along_the_lines():
    """At 50 lines/s the exact inverse needs more than 10 kV/s at the turnarounds only:
    rounding them keeps the lines far more accurate than lowering the band limit of the
    whole inverse (which leaves the 1 kHz mode ringing into the lines). Plant: the model
    itself behind a slew-limited amplifier."""
    from afmctl.compensators.dynamics_limits import rate_limit as limit

    dyn = LinearDynamicsModel.from_modes([(1000.0, 0.025)], [5000.0], bandwidth_Hz=3000.0)
    lin = linear_80()
    dt, rate = 1e-5, 50.0
    tgt = _target(rate, dt)
    err = {}
    for first in (True, False):
        res = invert_within_limits(dyn, tgt, dt, lambda: lin.inverse(dt), 0.0, 150.0, 5e3, round_first=first)
        u = limit(res.u_V, 0.0, 150.0, 5e3 * dt)[0]    # the amplifier
        plant = dyn.model_copy(update={"initial_nm": float(tgt[0])})   # at rest at the start
        err[first] = _central_error_pct(plant.forward(dt).block(lin.forward(dt).block(u)), tgt, rate, dt)
    assert err[True] < 0.5 * err[False], err


def linear_80():
    """A pure 80 nm/V gain as a model file (creep model with no creep)."""
    from afmctl.compensators.creep import LinearCreepModel

    return LinearCreepModel(gain_nm_per_V=80.0, time_constants_s=[1.0], creep_weights=[0.0])


def test_rate_limit_clips_and_counts():
    u, c, s = rate_limit(np.array([0.0, 5.0, 200.0, 200.0, -10.0]), 0.0, 150.0, 50.0)
    assert np.allclose(u, [0.0, 5.0, 55.0, 105.0, 55.0], rtol=1e-8) and c == 3 and s == 3
    assert np.max(np.abs(np.diff(u))) <= 50.0


def test_compensate_with_dynamics_beats_static_alone_at_speed(capsys, tmp_path):
    """A linear 80 nm/V plant with a 1 kHz mode and a 5 kHz amplifier, through the CLI:
    the offline dynamics inverse cuts the central-80 % error of 30 lines/s lines."""
    from afmctl.compensators.models import save_model

    dt = 1e-5
    dyn = LinearDynamicsModel.from_modes([(1000.0, 0.025)], [5000.0], delay_s=20e-6)
    lin = linear_80()
    save_model(dyn, tmp_path / "dyn.json")
    save_model(lin, tmp_path / "lin.json")
    tgt = _target(30.0, dt)
    write_csv(tmp_path / "tgt.csv", {"t": np.arange(tgt.size) * dt, "y": tgt})
    errs = {}
    for name, extra in (("static", []), ("dynamics", ["--dynamics", tmp_path / "dyn.json", "--limits", "0", "150",
                                                      "--slew-V-per-s", "10000"])):
        rc, out, err = run_cli(["compensate", "--model", tmp_path / "lin.json", "--target", tmp_path / "tgt.csv",
                                "--out", tmp_path / "v.csv", *extra], capsys)
        assert rc == 0, err
        u = read_csv(tmp_path / "v.csv", ("t", "u"))["u"]
        y = dyn.forward(dt, initial_nm=1000.0).block(lin.forward(dt).block(u))
        n = int(0.5 / 30.0 / dt)
        start = int(0.02 / dt)
        e = np.concatenate([(y - tgt)[a + n // 10:a + n - n // 10] for a in start + n * np.arange(4)])
        errs[name] = 100 * np.max(np.abs(e)) / 3000
        if name == "dynamics":
            assert "band limit" in out
    assert errs["dynamics"] < 0.2 < errs["static"]
    assert errs["dynamics"] < errs["static"] / 5


def test_compensate_dynamics_option_errors(capsys, tmp_path):
    from afmctl.compensators.models import save_model

    save_model(LinearDynamicsModel.from_modes([(1000.0, 0.05)]), tmp_path / "dyn.json")
    save_model(linear_80(), tmp_path / "lin.json")
    write_csv(tmp_path / "tgt.csv", {"t": np.array([0.0, 1e-5, 3e-5]), "y": np.zeros(3)})
    rc, out, err = run_cli(["compensate", "--model", tmp_path / "lin.json", "--dynamics", tmp_path / "dyn.json",
                            "--target", tmp_path / "tgt.csv", "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "uniformly" in err
    rc, out, err = run_cli(["compensate", "--model", tmp_path / "lin.json", "--slew-V-per-s", "5",
                            "--target", tmp_path / "tgt.csv", "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "uniformly" in err          # a slew limit needs the sample period
    rc, out, err = run_cli(["compensate", "--model", tmp_path / "lin.json", "--slew-V-per-s", "-5",
                            "--target", tmp_path / "tgt.csv", "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "--slew-V-per-s" in err
    write_csv(tmp_path / "tgt.csv", {"t": np.array([0.0, 1e-5, 2e-5]), "y": np.zeros(3)})
    rc, out, err = run_cli(["compensate", "--model", tmp_path / "dyn.json", "--target", tmp_path / "tgt.csv",
                            "--out", tmp_path / "v.csv"], capsys)
    assert rc == 2 and "--dynamics" in err and "dyn.json" in err


def test_compensate_slew_limit_holds_for_a_model_without_dynamics(capsys, tmp_path):
    """#36: --slew-V-per-s with any model: the voltages are rate-limited, the report says how
    many samples and that the target itself is too fast, and the largest step is printed."""
    from afmctl.compensators.models import save_model

    save_model(linear_80(), tmp_path / "lin.json")
    t = np.arange(2000) * 1e-4
    y = 4000.0 * (1 - np.abs(2 * ((t * 20.0) % 1.0) - 1))           # 50 V at 2 kV/s, turnarounds every 25 ms
    write_csv(tmp_path / "tgt.csv", {"t": t, "y": y})
    rc, out, err = run_cli(["compensate", "--model", tmp_path / "lin.json", "--slew-V-per-s", "1000",
                            "--target", tmp_path / "tgt.csv", "--out", tmp_path / "v.csv"], capsys)
    assert rc == 0, err
    u = read_csv(tmp_path / "v.csv", ("t", "u"))["u"]
    assert np.max(np.abs(np.diff(u))) <= 1000.0 * 1e-4 * (1 + 1e-9)
    assert "slew-limited" in out and "too fast for the amplifier" in out and "at 50 % of this speed" in out
    assert "largest step     : " in out and "V per sample" in out
