"""The user's workflow on a scanner afmctl was not tuned on: ``afmctl excite --kind all`` →
the plant → ``afmctl identify --model auto`` → ``afmctl compensate`` → the plant.

The plant differs from the default simulated scanner in every part: a narrower, stiffer
loop, 6 % creep with other time constants, a 3 kHz amplifier and a 1.6 kHz mode with Q 30.
Raster lines of 4 µm; error over the central 80 % of every trace and retrace."""
from __future__ import annotations

import json

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.data.datafiles import read_csv, write_csv
from afmctl.sim_backend.config import AmplifierConfig, CreepConfig, DynamicsConfig
from afmctl.sim_backend.scanner import default_scanner_config
from plants import play_x as play_plant_x
from plants import stiff_hysteresis, user_style_record

#: the module fixture identifies a 20 kHz recording (``auto`` with its dynamics stage): about
#: 2 minutes on a quiet 2-core machine, over 4 when the machine is loaded
pytestmark = pytest.mark.timeout(600)

RATE_HZ = 20_000.0          # recording rate: resolves the 1.6 kHz mode
DT_S = 1e-5                 # raster sample period
SLEW = 2.0e4                # the plant amplifier's slew limit [V/s]


def plant():
    cfg = default_scanner_config()
    cfg.x.hysteresis = stiff_hysteresis()
    cfg.x.creep = CreepConfig(fraction=0.06, tau_min_s=0.02, tau_max_s=50.0, n_lags=4)
    cfg.x.amplifier = AmplifierConfig(bandwidth_Hz=3000.0, slew_V_per_s=SLEW)
    cfg.x.dynamics = DynamicsConfig(resonance_Hz=1600.0, quality_factor=30.0)
    return cfg


def play_x(u_V: np.ndarray, dt_s: float) -> np.ndarray:
    return play_plant_x(plant(), u_V, dt_s)


def raster(rate: float, lines: int, x0: float = 5000.0, width: float = 4000.0):
    n = int(round(0.5 / rate / DT_S))
    r = np.arange(n) / n
    na = int(0.2 / DT_S)
    approach = x0 * (0.5 - 0.5 * np.cos(np.pi * np.arange(na) / na))
    rest = np.full(int(0.3 / DT_S), x0)
    line = np.concatenate([x0 + width * r, x0 + width * (1 - r)])
    tgt = np.concatenate([approach, rest, np.tile(line, lines), np.full(int(0.05 / DT_S), x0)])
    keep = np.zeros(tgt.size, bool)
    for a in approach.size + rest.size + n * np.arange(2 * lines):
        keep[a + n // 10: a + n - n // 10] = True
    return tgt, keep


def compensated_raster_error(d, model_path, rate: float, lines: int) -> tuple[float, float]:
    """Max and RMS error [% of the 4 µm line] of the raster compensated through ``afmctl
    compensate`` with ``model_path`` and played through the plant (files in ``d``)."""
    tgt, keep = raster(rate, lines)
    write_csv(d / "target.csv", {"t": np.arange(tgt.size) * DT_S, "y": tgt})
    assert main(["compensate", "--model", str(model_path), "--target", str(d / "target.csv"),
                 "--out", str(d / "volts.csv"), "--limits", "0", "150", "--slew-V-per-s", f"{SLEW:g}", "--clip"]) == 0
    e = 100.0 * (play_x(read_csv(d / "volts.csv", ("t", "u"))["u"], DT_S) - tgt)[keep] / 4000.0
    return float(np.max(np.abs(e))), float(np.sqrt(np.mean(e * e)))


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    d = tmp_path_factory.mktemp("unseen")
    assert main(["excite", "--kind", "all", "--u-min-V", "0", "--u-max-V", "150", "--rate-Hz", f"{RATE_HZ:g}",
                 "--slew-V-per-s", f"{SLEW:g}", "--out", str(d / "exc.csv")]) == 0
    e = read_csv(d / "exc.csv", ("t", "u"))
    write_csv(d / "data.csv", {"t": e["t"], "u": e["u"], "y": play_x(e["u"], 1.0 / RATE_HZ)})
    # one candidate: what is tested is the chain auto builds on it (the +dynamics variant, the
    # refit), not the choice between kinds (tests/test_selection*.py); two cost over 5 minutes
    assert main(["identify", "--model", "auto", "--data", str(d / "data.csv"), "--out", str(d / "auto.json"),
                 "--param", 'candidates=["preisach+creep"]']) == 0
    return d


@pytest.mark.slow
@pytest.mark.parametrize("rate, lines, limit_pct", [(10.0, 6, 1.0), (50.0, 10, 2.0)])
def test_auto_chain_compensates_an_unseen_plant(model, rate, lines, limit_pct):
    d = model
    assert json.loads((d / "auto.json").read_text())["dynamics"] is not None   # the mode and the amplifier show
    peak, rms = compensated_raster_error(d, d / "auto.json", rate, lines)
    print(f"unseen plant, {rate:g} lines/s: {peak:.2f} % max / {rms:.2f} % RMS of the line")
    assert peak <= limit_pct and rms <= 0.5 * limit_pct


@pytest.fixture(scope="module")
def user_model(tmp_path_factory):
    """The same plant recorded as a lab records it without afmctl's excitation (nested 1 Hz
    triangles, 10 and 40 Hz triangles, a chirp; the waveforms pieced together with jumps),
    identified as preisach+creep+dynamics through the CLI."""
    d = tmp_path_factory.mktemp("unseen-user")
    u = user_style_record(SLEW, fs=RATE_HZ)
    write_csv(d / "data.csv", {"t": np.arange(u.size) / RATE_HZ, "u": u, "y": play_x(u, 1.0 / RATE_HZ)})
    assert main(["identify", "--model", "preisach+creep+dynamics", "--data", str(d / "data.csv"),
                 "--out", str(d / "chain.json")]) == 0
    return d


@pytest.mark.slow
@pytest.mark.parametrize("rate, lines", [(1.0, 3), (10.0, 6)])
def test_a_user_style_recording_compensates_an_unseen_plant(user_model, rate, lines):
    """#24's acceptance from a user-style recording: within 1 % of the line at 1 and 10
    lines/s (measured 0.57 / 0.64 % from this 20 kHz record; the same plant from a 50 kHz one
    through `identify --model auto` gave 1.33 / 1.56 % before the static stages were fitted
    at the record's own rate, without the jumps' transients, and again through the dynamics'
    inverse)."""
    d = user_model
    chain = json.loads((d / "chain.json").read_text())
    assert 0.03 <= sum(chain["creep"]["creep_weights"]) <= 0.09          # the plant's 0.06
    peak, rms = compensated_raster_error(d, d / "chain.json", rate, lines)
    print(f"unseen plant, user-style recording, {rate:g} lines/s: {peak:.2f} % max / {rms:.2f} % RMS of the line")
    assert peak <= 1.0 and rms <= 0.5
