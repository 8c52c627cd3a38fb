"""The CLI shell: help, version, and one-line errors."""
import subprocess
import sys

from afmctl.cli import main


def test_help_lists_verbs(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    assert "afmctl demo" in out


def test_version_runs_as_module():
    r = subprocess.run([sys.executable, "-m", "afmctl", "--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0
    assert r.stdout.startswith("afmctl ")


def test_no_logging_handlers_at_import():
    code = ("import logging, afmctl, afmctl.cli, compensators, drivers, sim_backend;"
            "import compensators.base, compensators.models, drivers.base;"
            "assert not logging.getLogger().handlers, logging.getLogger().handlers")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
