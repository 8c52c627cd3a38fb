"""The package as a user installs it: the built wheel holds one top-level package, ``afmctl``
(every source file and the DBC in it), and installed into a fresh environment ``import drivers``
fails while ``import afmctl.drivers`` works."""
from __future__ import annotations

import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from test_architecture import FOLDERS, ROOT, find_modules

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel built from a copy of the sources (no build/ or egg-info left in the checkout)."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for folder in FOLDERS:
        shutil.copytree(ROOT / folder, src / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(src)],
                   check=True, timeout=300)
    (whl,) = out.glob("afmctl-*.whl")
    return whl


def test_wheel_holds_one_top_level_package_with_every_module(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"afmctl"}
    assert "afmctl/drivers/afm_amplifier.dbc" in names
    assert {f"afmctl/view/static/{f}" for f in ("index.html", "view.js", "plot.js", "view.css")} <= set(names)
    # every source module is in it (a subpackage missing from pyproject's `packages` would not be)
    expected = {str(Path(*m.split(".")) / "__init__.py") if p.name == "__init__.py"
                else str(Path(*m.split(".")).with_suffix(".py"))
                for m, p in find_modules(ROOT, FOLDERS).items()}
    assert sorted(expected - set(names)) == []


def test_installed_wheel_has_no_top_level_drivers(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
                    str(wheel)], check=True, timeout=300)
    # Dependencies come from this test environment's site-packages (its .pth files, and with them
    # the editable afmctl, are not read from PYTHONPATH); cwd is empty, so no checkout is visible.
    env = {"PYTHONPATH": sysconfig.get_paths()["purelib"], "PATH": "/usr/bin:/bin"}
    probe = ("import importlib.util as u, importlib.resources as r, afmctl\n"
             "print(afmctl.__file__)\n"
             "print(u.find_spec('drivers'), u.find_spec('compensators'), u.find_spec('sim_backend'))\n"
             "print((r.files('afmctl.drivers') / 'afm_amplifier.dbc').is_file())\n")
    out = subprocess.run([str(py), "-c", probe], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    where, specs, dbc = out.stdout.splitlines()
    assert where.startswith(str(venv))
    assert specs == "None None None"
    assert dbc == "True"
    failed = subprocess.run([str(py), "-c", "import drivers"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=60)
    assert failed.returncode == 1 and "No module named 'drivers'" in failed.stderr
