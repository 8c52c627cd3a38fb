"""The install as pyproject.toml declares it: `packages` names every folder that ships (a
folder left out is dropped from the wheel, and setuptools warns about an importable one), and
the runtime dependencies — what `make demo` installs — hold none of the test tools."""
from __future__ import annotations

import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
#: what the `test` extra brings and a demo environment must not hold
TEST_TOOLS = {"pytest", "hypothesis", "playwright", "pipython", "mdt69x", "nv200", "igorwriter",
              "gwyddionpy", "pytest-timeout", "pytest-xdist", "mypy"}


def _package_folders() -> set[str]:
    """Every folder below the package-dir roots that holds a file (dotted package names)."""
    setuptools = PYPROJECT["tool"]["setuptools"]
    roots = setuptools["package-dir"]
    names = set()
    for package, folder in roots.items():
        base = ROOT / folder
        for path in [base, *(p for p in base.rglob("*") if p.is_dir())]:
            rel = path.relative_to(base).parts
            if "__pycache__" in rel or not any(f.is_file() for f in path.iterdir()):
                continue
            dotted = ".".join((package, *rel))
            names.add(dotted)
    return names


def test_pyproject_packages_name_every_package_folder():
    declared = set(PYPROJECT["tool"]["setuptools"]["packages"])
    found = _package_folders()
    assert sorted(found - declared) == [], "add these to [tool.setuptools] packages in pyproject.toml"
    assert sorted(declared - found) == []


def _closure(name: str, extras: tuple[str, ...] = ()) -> set[str]:
    """The distribution names ``name[extras]`` pulls in, from the installed metadata, markers
    evaluated for this interpreter and platform."""
    seen: set[tuple[str, tuple[str, ...]]] = set()
    todo = [(canonicalize_name(name), extras)]
    while todo:
        item = todo.pop()
        if item in seen:
            continue
        seen.add(item)
        try:
            requires = metadata.distribution(item[0]).requires or []
        except metadata.PackageNotFoundError:
            continue
        envs = [{"extra": e} for e in item[1]] or [{"extra": ""}]
        for text in requires:
            req = Requirement(text)
            if req.marker is None or any(req.marker.evaluate(env) for env in envs):
                todo.append((canonicalize_name(req.name), tuple(sorted(req.extras))))
    return {n for n, _ in seen}


def test_the_runtime_install_holds_no_test_tools():
    runtime = _closure("afmctl")
    assert {"numpy", "scipy", "numba", "pyserial", "eclipse-zenoh"} <= runtime
    assert sorted(runtime & TEST_TOOLS) == []
    # the check can fail: the test extra does bring them
    with_test = _closure("afmctl", ("test",))
    assert {"pytest", "hypothesis", "playwright", "pipython", "mdt69x", "igorwriter", "mypy"} <= with_test
