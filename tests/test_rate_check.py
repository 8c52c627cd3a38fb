"""``afmctl run`` warns when the loop holds each voltage too long for the scanner's first
mode (afmctl/control/rate_check.py): below twice the mode of the axis model's dynamics
stage, else of the simulated scanner; never for a wave run or a real stage whose model has
no dynamics."""
from __future__ import annotations

from pathlib import Path

from afmctl.compensators.chain import ChainModel
from afmctl.compensators.dynamics import LinearDynamicsModel
from afmctl.compensators.pi import PIModel
from afmctl.config import load_config
from afmctl.control.rate_check import mode_warnings
from afmctl.sim_backend.scanner import default_scanner_config

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "sim_inprocess.toml"


def _config(rate_Hz: float, output: str = "setpoints"):
    return load_config(EXAMPLE, overrides={"loop": {"rate_Hz": rate_Hz}, "amplifier": {"output": output}})


def _chain(with_dynamics: bool) -> ChainModel:
    pi = PIModel(thresholds=[0.0, 50.0], weights=[80.0, 5.0])
    dyn = LinearDynamicsModel.from_modes([(1000.0, 0.025)]) if with_dynamics else None
    return ChainModel(hysteresis=pi, dynamics=dyn)


def test_a_loop_at_the_mode_rate_warns_per_lateral_axis_and_names_the_fix():
    lines = mode_warnings(_config(1000), [None, None, None], default_scanner_config())
    assert [ln.split("axis ")[1][0] for ln in lines] == ["x", "y"]      # z's mode is 5 kHz: not lateral
    assert all("(1000 Hz, the simulated scanner's)" in ln and "loop.rate_Hz to 5000 or more" in ln for ln in lines)


def test_the_model_s_mode_counts_first_and_for_a_real_stage():
    dyn = _chain(True)                      # a 1 kHz mode
    lines = mode_warnings(_config(1500), [dyn, None, None], None)
    assert len(lines) == 1 and "axis x (1000 Hz, the model's)" in lines[0]
    assert mode_warnings(_config(1500), [_chain(False), None, None], None) == []      # no mode known


def test_no_warning_from_twice_the_mode_on_or_for_wave():
    scanner = default_scanner_config()
    assert mode_warnings(_config(2000), [None, None, None], scanner) == []      # the shipped rate
    assert len(mode_warnings(_config(1900), [None, None, None], scanner)) == 2
    # an identified mode is an estimate: the demo's model puts the 1000 Hz mode at 1001-1002 Hz
    dyn = _chain(True)
    mode = float(mode_warnings(_config(1000), [dyn, None, None], None)[0].split("(")[1].split(" Hz")[0])
    assert mode_warnings(_config(2.0 * mode * 0.995), [dyn, None, None], None) == []
    assert len(mode_warnings(_config(2.0 * mode * 0.985), [dyn, None, None], None)) == 1
    assert len(mode_warnings(_config(1000), [_chain(True), _chain(False), None], scanner)) == 2
    assert mode_warnings(_config(1000, "wave"), [None, None, None], scanner) == []
