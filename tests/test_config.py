"""Configuration: TOML, environment overrides, rejection of unknown keys, clear errors."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from afmctl.cli import main
from afmctl.config import Config, load_config
from afmctl.errors import AfmctlError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SIM = "[simulation]\nenabled = true\n"


def test_defaults_and_sections():
    cfg = load_config(text=SIM)
    assert cfg.loop.rate_Hz == 1000.0 and cfg.dt_s == pytest.approx(1e-3)
    assert cfg.scanner.axes == ["x", "y", "z"]
    assert cfg.trajectory.kind == "raster"
    assert cfg.zenoh.enabled is False
    assert cfg.runlog.flush_interval_s <= 0.1
    assert cfg.limits("x") == (0.0, 150.0)


def test_limits_and_slew_combine_amplifier_and_safety():
    cfg = load_config(text=SIM + """
[amplifier]
slew_V_per_s = 300
[amplifier.limits_V.x]
min_V = -10
max_V = 120
[safety]
slew_V_per_s = 800
[safety.limits_V.x]
min_V = 0
max_V = 130
""")
    assert cfg.limits("x") == (0.0, 120.0)
    assert cfg.slew_V_per_s() == 300.0


@pytest.mark.parametrize("text, field", [
    ("[loop]\nrate_Hz = 1e6\n", "loop.rate_Hz"),
    ("[loop]\nrate_hz = 100\n", "loop.rate_hz"),
    ("[bogus]\nx = 1\n", "bogus"),
    ("[runlog]\nflush_interval_s = 0.5\n", "runlog.flush_interval_s"),
    ("[amplifier.limits_V.x]\nmin_V = 10\nmax_V = 5\n", "amplifier.limits_V.x"),
    ("[amplifier]\ndriver = \"telepathy\"\n", "amplifier.driver"),
    ("[trajectory]\nkind = \"raster\"\nlines = 0\n", "trajectory.raster.lines"),
    ("[trajectory]\nkind = \"warp\"\n", "trajectory"),
    ("[scanner]\naxes = [\"x\", \"x\"]\n", "scanner.axes"),
    ("[zenoh]\nmode = \"broker\"\n", "zenoh.mode"),
])
def test_errors_name_the_field_and_range(text, field):
    with pytest.raises(AfmctlError) as err:
        load_config(text=SIM + text)
    msg = str(err.value)
    assert f"field {field}" in msg
    assert "\n" not in msg


def test_range_is_in_the_message():
    with pytest.raises(AfmctlError, match="less than or equal to 20000"):
        load_config(text=SIM + "[loop]\nrate_Hz = 30000\n")


def test_port_required_without_simulation():
    with pytest.raises(AfmctlError, match="amplifier.port is required"):
        load_config(text="[amplifier]\ndriver = \"mdt693b\"\n")


def test_environment_overrides_file(monkeypatch):
    monkeypatch.setenv("AFMCTL_LOOP__RATE_HZ", "500")
    monkeypatch.setenv("AFMCTL_AMPLIFIER__PORT", "/dev/ttyUSB7")
    monkeypatch.setenv("AFMCTL_TRAJECTORY__LINES", "3")
    cfg = load_config(text=SIM + "[loop]\nrate_Hz = 100\nspin_s = 0.0001\n[trajectory]\nkind = \"raster\"\nlines = 9\n")
    assert cfg.loop.rate_Hz == 500.0
    assert cfg.loop.spin_s == 0.0001          # nested keys merge, not replace
    assert cfg.amplifier.port == "/dev/ttyUSB7"
    assert cfg.trajectory.lines == 3
    monkeypatch.setenv("AFMCTL_LOOP__RATE_HZ", "0")
    with pytest.raises(AfmctlError, match="field loop.rate_Hz"):
        load_config(text=SIM)


def test_relative_paths_resolve_next_to_the_file(tmp_path):
    (tmp_path / "cfg.toml").write_text(SIM + "[compensation.x]\nmodel = \"m/x.json\"\n"
                                       "[trajectory]\nkind = \"file\"\npath = \"t.csv\"\n")
    cfg = load_config(tmp_path / "cfg.toml")
    assert cfg.compensation.x.model == tmp_path / "m" / "x.json"
    assert cfg.trajectory.path == tmp_path / "t.csv"


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(AfmctlError, match="not valid TOML"):
        load_config(text="[loop\n")
    with pytest.raises(AfmctlError, match="cannot read"):
        load_config(tmp_path / "nope.toml")


@settings(max_examples=60, deadline=None)
@given(rate=st.one_of(st.floats(allow_nan=True), st.integers(-10, 10**6), st.text(max_size=4)),
       slew=st.one_of(st.floats(allow_nan=True), st.integers(-10, 10**8)))
def test_fuzzed_numbers_validate_or_fail_cleanly(rate, slew):
    data = {"simulation": {"enabled": True}, "loop": {"rate_Hz": rate}, "safety": {"slew_V_per_s": slew}}
    from afmctl.config import config_from_dict
    try:
        cfg = config_from_dict(data)
    except AfmctlError as err:
        assert "field " in str(err)
        return
    assert 1.0 <= cfg.loop.rate_Hz <= 20000.0
    assert 0 < cfg.slew_V_per_s() <= 1e7


def test_schema_command(capsys, tmp_path):
    assert main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert set(schema["properties"]) >= {"scanner", "amplifier", "loop", "compensation", "safety", "trajectory",
                                         "runlog", "zenoh"}
    assert schema["additionalProperties"] is False
    out = tmp_path / "s.json"
    assert main(["schema", "--out", str(out)]) == 0
    assert json.loads(out.read_text()) == Config.model_json_schema()


@pytest.mark.parametrize("name", ["sim_inprocess.toml", "mdt693b_serial.toml", "can.toml"])
def test_examples_validate(name):
    cfg = load_config(EXAMPLES / name)
    assert cfg.zenoh.enabled is False
    assert cfg.runlog.flush_interval_s <= 0.1


def test_environment_keys_match_without_case(monkeypatch):
    monkeypatch.setenv("AFMCTL_SAFETY__LIMITS_V__X__MAX_V", "90")
    monkeypatch.setenv("AFMCTL_SAFETY__LIMITS_V__X__MIN_V", "5")
    monkeypatch.setenv("AFMCTL_TRAJECTORY__LINE_RATE_HZ", "3")
    cfg = load_config(text=SIM)
    assert cfg.limits("x") == (5.0, 90.0)
    assert cfg.trajectory.line_rate_Hz == 3.0
    # file keys stay exact
    with pytest.raises(AfmctlError, match="field trajectory.raster.line_rate_hz"):
        load_config(text=SIM + "[trajectory]\nkind = \"raster\"\nline_rate_hz = 2\n")


def test_command_line_overrides_beat_file_and_environment(tmp_path, monkeypatch):
    f = tmp_path / "c.toml"
    f.write_text('[amplifier]\ndriver = "mdt693b"\n[compensation.x]\nmodel = "m.json"\n')
    with pytest.raises(AfmctlError, match="amplifier.port is required"):
        load_config(f)
    monkeypatch.setenv("AFMCTL_AMPLIFIER__PORT", "/dev/from-env")
    assert load_config(f).amplifier.port == "/dev/from-env"
    cfg = load_config(f, overrides={"amplifier": {"port": "/dev/from-cli"}})
    assert cfg.amplifier.port == "/dev/from-cli"
    assert cfg.compensation.x.model == tmp_path / "m.json"


def _numeric_fields():
    """(section, field) of every int/float field of every config section."""
    import typing

    from pydantic import BaseModel
    out = []
    for sec, info in Config.model_fields.items():
        tp = info.annotation
        if not (isinstance(tp, type) and issubclass(tp, BaseModel)):
            continue
        for name, f in tp.model_fields.items():
            args = set(typing.get_args(f.annotation)) | {f.annotation}
            if args & {float, int} and not args & {str, bool}:
                out.append((sec, name))
    return out


NUMERIC = _numeric_fields()


def test_numeric_fields_found():
    assert ("loop", "rate_Hz") in NUMERIC and ("safety", "slew_V_per_s") in NUMERIC and len(NUMERIC) > 15


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf", "1e300", "-1e300"])
def test_no_numeric_field_takes_nonfinite_or_absurd_values(bad):
    """Every number of the configuration is range-checked: NaN, ±inf and ±1e300 are refused
    with an error naming the field (a NaN slew limit would disable the safety layer)."""
    accepted = []
    for sec, name in NUMERIC:
        try:
            load_config(text=f"{SIM}[{sec}]\n{name} = {bad}\n" if sec != "simulation"
                        else f"[simulation]\nenabled = true\n{name} = {bad}\n")
        except AfmctlError as err:
            assert f"{sec}.{name}" in str(err), str(err)
            continue
        accepted.append(f"{sec}.{name}")
    assert accepted == []


def test_error_names_value_range_and_environment_variable(monkeypatch):
    with pytest.raises(AfmctlError) as e:
        load_config(text=SIM + "[safety]\nslew_V_per_s = nan\n")
    assert "safety.slew_V_per_s = nan" in str(e.value) and "0 < value <= 1e+07" in str(e.value)
    monkeypatch.setenv("AFMCTL_LOOP__RATE_HZ", "fast")
    with pytest.raises(AfmctlError) as e:
        load_config(text=SIM)
    assert str(e.value).startswith("environment AFMCTL_LOOP__RATE_HZ: field loop.rate_Hz = 'fast'")
    assert "allowed:" in str(e.value)


def test_help_example_configuration_validates(capsys):
    """The configuration shown by `afmctl run --help` / `afmctl schema --help` is valid."""
    from afmctl.commands.schema import EXAMPLE_TOML
    cfg = load_config(text=EXAMPLE_TOML)
    assert cfg.amplifier.driver == "mdt693b" and cfg.trajectory.kind == "raster"
    for verb in ("run", "schema"):
        with pytest.raises(SystemExit):
            main([verb, "--help"])
        assert 'kind = "raster"' in capsys.readouterr().out
