"""tools/typecheck.py (what `make test` runs before pytest): mypy sees the package as it
installs — afmctl.drivers, afmctl.compensators, afmctl.sim_backend resolve to their folders —
and a type error makes it fail."""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("typecheck", ROOT / "tools" / "typecheck.py")
assert spec is not None and spec.loader is not None
typecheck = importlib.util.module_from_spec(spec)
spec.loader.exec_module(typecheck)


def typecheck_cache_dir() -> str:
    """``[tool.mypy] cache_dir`` of pyproject.toml (relative to the tree mypy runs in)."""
    import tomllib
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["mypy"]["cache_dir"]


def test_the_tree_maps_every_package_dir_folder(tmp_path):
    tree = typecheck.build_tree(ROOT, tmp_path / "tree")
    assert (tree / "afmctl" / "drivers").resolve() == (ROOT / "drivers").resolve()
    assert (tree / "afmctl" / "compensators").resolve() == (ROOT / "compensators").resolve()
    assert (tree / "afmctl" / "sim_backend" / "amplifiers").resolve() == (ROOT / "sim_backend" / "amplifiers").resolve()
    assert (tree / "afmctl" / "control").resolve() == (ROOT / "afmctl" / "control").resolve()
    assert not (tree / "drivers").exists()          # no top-level `drivers` for mypy either


@pytest.mark.slow
def test_mypy_resolves_the_mapped_packages_and_fails_on_an_error(tmp_path):
    tree = typecheck.build_tree(ROOT, tmp_path / "tree")
    # `make test` runs tools/typecheck.py first: starting from its cache, mypy rechecks only what
    # the snippet adds (2 s instead of over a minute); without one it checks everything
    cache = tmp_path / "cache"
    project_cache = (typecheck.TREE / typecheck_cache_dir()).resolve()
    if project_cache.is_dir():
        shutil.copytree(project_cache, cache)
    bad = "from afmctl.drivers.base import VoltageLimits\nlimits: int = VoltageLimits(0.0, 1.0)\n"
    out = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"),
                          "--cache-dir", str(cache), "-c", bad], cwd=tree, capture_output=True,
                         text=True, timeout=600, env=dict(os.environ, MYPYPATH=str(tree)))
    assert out.returncode == 1
    assert 'Incompatible types in assignment (expression has type "VoltageLimits"' in out.stdout, out.stdout
    assert "import-not-found" not in out.stdout
