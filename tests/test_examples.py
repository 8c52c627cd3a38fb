"""Every example configuration runs: in-process simulation, MDT693B over a pty, CAN on
the virtual bus (each with a shortened trajectory through AFMCTL_ overrides)."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from afmctl.cli import main
from afmctl.control.runlog import RunLogReader

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
pytestmark = pytest.mark.timeout(120)


def _run(args, capsys):
    rc = main(["run", "--config", *args, "--json", "--quiet"])
    out = capsys.readouterr().out
    return rc, json.loads(out) if out.strip() else {}


def test_sim_inprocess_example(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AFMCTL_RUNLOG__DIR", str(tmp_path))
    monkeypatch.setenv("AFMCTL_TRAJECTORY__LINES", "2")
    monkeypatch.setenv("AFMCTL_TRAJECTORY__LINE_RATE_HZ", "8")
    monkeypatch.setenv("AFMCTL_AMPLIFIER__PORT", f"virtual:afmctl-ex-{os.getpid()}")
    rc, s = _run([str(EXAMPLES / "sim_inprocess.toml")], capsys)
    assert rc == 0 and s["state"] == "stopped" and s["errors"] == 0
    assert s["samples"] > 2 * 125
    # simulated: the summary reports the tip's tracking error
    assert len(s["tracking"]["max_abs_nm"]) == 3
    log = RunLogReader(s["runlog"])
    assert log.summary()["seq_gaps"] == 0 and log.meta()["scanner"] == "sim0"


def test_mdt693b_serial_example_on_a_pty(tmp_path, monkeypatch, capsys):
    from afmctl.sim_backend.testing import serve_pty
    monkeypatch.setenv("AFMCTL_RUNLOG__DIR", str(tmp_path))
    monkeypatch.setenv("AFMCTL_TRAJECTORY__NX", "2")
    monkeypatch.setenv("AFMCTL_TRAJECTORY__NY", "1")
    with serve_pty("mdt693b") as server:
        rc, s = _run([str(EXAMPLES / "mdt693b_serial.toml"), "--port", server.port], capsys)
        assert server.sink.count > 0
    assert rc == 0 and s["state"] == "stopped" and s["errors"] == 0
    sp = RunLogReader(s["runlog"]).setpoints()
    assert sp["u_V"][:, 2].max() <= 100.0            # the example's z limit


def test_can_example_on_the_virtual_bus(tmp_path, monkeypatch, capsys):
    from afmctl.sim_backend.testing import serve_can
    channel = f"afmctl-canex-{os.getpid()}"
    monkeypatch.setenv("AFMCTL_RUNLOG__DIR", str(tmp_path))
    monkeypatch.setenv("AFMCTL_TRAJECTORY__TEXT", "N")
    monkeypatch.setenv("AFMCTL_TRAJECTORY__HEIGHT_NM", "600")
    monkeypatch.setenv("AFMCTL_AMPLIFIER__PORT", f"virtual:{channel}")
    with serve_can(channel) as amp:
        rc, s = _run([str(EXAMPLES / "can.toml")], capsys)
    assert rc == 0 and s["state"] == "stopped" and s["errors"] == 0
    assert amp.sink.count > 0 if hasattr(amp, "sink") else True


def test_run_reports_bad_config_in_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[loop]\nrate_Hz = -1\n[simulation]\nenabled = true\n")
    assert main(["run", "--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "field loop.rate_Hz" in err


def test_run_starts_and_closes_the_zenoh_bridge(tmp_path, monkeypatch, capsys, caplog):
    """`afmctl run` starts the zenoh bridge when [zenoh] enabled = true (interface item 8)
    and closes it at the end (the publishing itself: tests/test_zenoh_e2e.py)."""
    import zenoh  # noqa: F401  (a hard dependency: fail, never skip)
    import logging
    import threading

    from afmctl.zenoh_api.settings import loopback_pair
    srv, _ = loopback_pair()
    monkeypatch.setenv("AFMCTL_RUNLOG__DIR", str(tmp_path))
    monkeypatch.setenv("AFMCTL_TRAJECTORY__LINES", "2")
    monkeypatch.setenv("AFMCTL_TRAJECTORY__LINE_RATE_HZ", "8")
    monkeypatch.setenv("AFMCTL_AMPLIFIER__PORT", f"virtual:afmctl-exz-{os.getpid()}")
    monkeypatch.setenv("AFMCTL_ZENOH__ENABLED", "true")
    monkeypatch.setenv("AFMCTL_ZENOH__LISTEN", json.dumps(srv.listen))
    caplog.set_level(logging.INFO, logger="afmctl.zenoh_api.bridge")
    rc, s = _run([str(EXAMPLES / "sim_inprocess.toml")], capsys)
    assert rc == 0 and s["state"] == "stopped" and s["samples"] > 0
    assert any("zenoh API up" in r.getMessage() and srv.listen[0] in r.getMessage() for r in caplog.records)
    time.sleep(0.2)
    assert not [t for t in threading.enumerate() if t.name.startswith("afmctl-zenoh")]


@pytest.mark.parametrize("extra, msg", [
    ('[amplifier]\ndriver = "mdt693b"\nport = "/dev/afmctl-no-such-tty"\n[amplifier.options]\nbogus = 1\n',
     "amplifier.options"),
    ('[amplifier]\ndriver = "mdt693b"\nport = "/dev/afmctl-no-such-tty"\n', "afmctl-no-such-tty"),
    ('[simulation]\nenabled = true\n[compensation.x]\nmodel = "missing.json"\n', "missing.json"),
])
def test_run_errors_are_one_line(tmp_path, capsys, extra, msg):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[runlog]\ndir = "{tmp_path}"\n' + extra)
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("afmctl: error:") and msg in err[-1]


def test_link_ceiling_warning():
    from afmctl.commands.run import link_warning
    from afmctl.config import load_config
    fast = load_config(text='[amplifier]\ndriver = "mdt693b"\nport = "/dev/x"\n[loop]\nrate_Hz = 1000\n')
    assert "about 380 setpoints/s" in link_warning(fast)
    assert link_warning(load_config(EXAMPLES / "mdt693b_serial.toml")) is None
    assert link_warning(load_config(EXAMPLES / "can.toml")) is None


def test_nk_imprint_example_script(tmp_path, capsys):
    """examples/nk_imprint.py: the PI compensator imprints 'NK' far closer to the target."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("nk_imprint", EXAMPLES / "nk_imprint.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "nk.png"
    assert mod.main(["--out", str(out), "--height-nm", "4000"]) == 0
    assert out.stat().st_size > 10_000
    lines = {ln.split(":")[0]: float(ln.split("rms ")[1].split(" nm")[0])
             for ln in capsys.readouterr().out.splitlines() if "rms" in ln}
    assert lines["PI inverse models"] < 0.6 * lines["linear calibration (no model)"]


def test_sim_wave_gcs_example(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("AFMCTL_RUNLOG__DIR", str(tmp_path))
    rc, s = _run([str(EXAMPLES / "sim_wave_gcs.toml")], capsys)
    assert rc == 0 and s["state"] == "stopped" and s["errors"] == 0, s
    assert s["output"] == "wave" and s["wave"]["played"] == s["wave"]["samples"] >= 10 / 50.0 * 20000
    assert "wave generator" in s["wave"]["player"] and s["slew_limited"] == 0
    # the device's recorder measured the play: per axis, over the lines' central part, in nm and %
    rec = s["tracking"]["recorded"]
    assert rec["part"] == ("the central 80 % of lines 2..10 of 10 (every line but the first, which starts from rest); "
                           "x is the fast axis"), s["tracking"]
    x, y = rec["axes"]["x"], rec["axes"]["y"]
    assert (x["reference"], y["reference"]) == ("line", "step") and "z" not in rec["axes"]     # z holds
    assert 5.0 < x["max_pct"] < 60.0 and x["max_nm"] == pytest.approx(x["max_pct"] * 40.0)    # no model: ~23 %
    # the summary as printed: device-timed, so no missed deadlines; per-axis figures named
    from afmctl.commands.run import _print_summary
    _print_summary(s)
    out = capsys.readouterr().out
    assert "device-timed" in out and "missed deadlines" not in out
    assert "measured by the device's recorder" in out and "of its 4000 nm line" in out


def _example_loaders():
    """Every shipped .toml and the loader of the command that reads it."""
    from afmctl.commands.view import zenoh_settings
    from afmctl.config import load_config
    from afmctl.simulation.service import load_settings
    from afmctl.zenoh_api.lab_acl import load_acl
    from afmctl.zenoh_api.router import load_router_settings
    special = {"acl.toml": load_acl, "router.toml": load_router_settings,
               "view.toml": lambda p: zenoh_settings(p, ["tcp/127.0.0.1:7447"])}  # as its comment runs it
    for path in sorted(EXAMPLES.rglob("*.toml")):
        if path.name in special:
            yield path, special[path.name]
        elif path.parent.name == "lab" and path.name.startswith("sim"):
            yield path, load_settings
        else:
            yield path, load_config


def test_every_example_configuration_loads():
    """Each example passes the loader of the command it is written for (afmctl run's unless
    it is a lab's router, access list, viewer or simulator file)."""
    loaded = [(path.name, loader(path)) for path, loader in _example_loaders()]
    names = [n for n, _ in loaded]
    assert {"e727_tcp.toml", "nv200_serial.toml", "nv200_tcp.toml", "mdt693b_serial.toml"} <= set(names)
    for path in EXAMPLES.glob("*.toml"):   # each instrument's example says what to check on the real unit
        text = path.read_text()
        if "sim" not in path.name and "tour" not in path.name and "can" not in path.name:
            assert "check before the first run" in text and "limits" in text, path.name


@pytest.fixture
def instrument(request):
    """The simulator an instrument example speaks to: (name, port URL, its sink)."""
    from afmctl.sim_backend.amplifiers import RecordingSink, make_device
    from afmctl.sim_backend.amplifiers.tcp_server import TcpServer
    from afmctl.sim_backend.testing import serve_pty
    example, protocol, link = request.param
    if link == "tcp":
        sink = RecordingSink()
        with TcpServer(make_device(protocol, sink)) as server:
            yield example, server.port, sink
    else:
        with serve_pty(protocol) as server:
            yield example, server.port, server.sink


@pytest.mark.parametrize("instrument", [("e727_tcp.toml", "gcs", "tcp"), ("nv200_serial.toml", "nv200", "pty"),
                                        ("nv200_tcp.toml", "nv200", "tcp")], indirect=True,
                         ids=["e727-tcp", "nv200-serial", "nv200-tcp"])
def test_instrument_example_runs_a_short_session_on_its_simulator(instrument, tmp_path, monkeypatch, capsys):
    example, port, sink = instrument
    monkeypatch.setenv("AFMCTL_RUNLOG__DIR", str(tmp_path))
    if example.startswith("e727"):
        monkeypatch.setenv("AFMCTL_TRAJECTORY__LINES", "1")
        monkeypatch.setenv("AFMCTL_TRAJECTORY__LINE_RATE_HZ", "8")
    else:
        monkeypatch.setenv("AFMCTL_TRAJECTORY__POINTS", '[{"x_nm": 1500.0, "y_nm": 0.0}]')
    rc, s = _run([str(EXAMPLES / example), "--port", port], capsys)
    assert rc == 0 and s["state"] == "stopped" and s["errors"] == 0, s
    u = RunLogReader(s["runlog"]).setpoints()["u_V"]
    assert s["samples"] > 50 and u.max() <= 100.0 and u.min() >= 0.0   # the example's limits
    assert max(max(v.values()) for _, v in sink.history) > 10.0       # the device was driven
