"""Run mypy over the whole ``afmctl`` package as it installs: drivers/, compensators/ and
sim_backend/ are ``afmctl.drivers``, ``afmctl.compensators`` and ``afmctl.sim_backend``
(pyproject.toml, [tool.setuptools.package-dir]).

mypy cannot follow setuptools' package-dir mapping (nor the import hook of an editable
install), so this builds the installed layout as a tree of symbolic links under
``build/typecheck/`` — ``afmctl/<entry>`` -> ``afmctl/<entry>`` for every entry of the
service folder, ``afmctl/drivers`` -> ``drivers/`` and so on — and runs ``mypy -p afmctl``
on it with that tree as its only search path. The configuration is ``[tool.mypy]`` in
pyproject.toml. Exit status: mypy's (0 = no errors).

    python tools/typecheck.py            # what `make test` runs first
    python tools/typecheck.py --verbose  # any extra arguments go to mypy
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREE = ROOT / "build" / "typecheck"


def build_tree(root: Path = ROOT, tree: Path = TREE) -> Path:
    """The installed package layout as symbolic links under ``tree``; returns ``tree``."""
    setuptools = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    mapping: dict[str, str] = setuptools["package-dir"]
    if tree.exists():
        shutil.rmtree(tree)
    top = tree / "afmctl"
    top.mkdir(parents=True)
    for entry in (root / mapping["afmctl"]).iterdir():
        if entry.name != "__pycache__":
            os.symlink(entry, top / entry.name)
    for package, folder in mapping.items():
        if package != "afmctl":
            os.symlink(root / folder, tree.joinpath(*package.split(".")))
    return tree


def main(argv: list[str]) -> int:
    tree = build_tree()
    env = dict(os.environ, MYPYPATH=str(tree))
    cmd = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"), "-p", "afmctl", *argv]
    return subprocess.run(cmd, cwd=tree, env=env).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
