"""Every third-party module that the package, the agents or the tests import is declared in
pyproject.toml, core or an extra, under its own distribution name. A module that arrives only
through another package's requirements is missing on a fresh install the day that package
drops it, and an undeclared one (scipy once) fails only on a machine that lacks it."""

import ast
import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("window_bench", "baselines", "tests")
# Our own packages, and the test modules that import each other (conftest, test_harness).
LOCAL = {"window_bench", "baselines", *(p.stem for p in (ROOT / "tests").glob("*.py"))}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def imported_modules(source: str) -> set[str]:
    """Top-level names of the absolute imports in ``source``, including the string forms
    ``pytest.importorskip("x")`` and ``importlib.import_module("x")``."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
        elif (isinstance(node, ast.Call) and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
              and getattr(node.func, "attr", getattr(node.func, "id", None))
              in ("importorskip", "import_module")):
            names.add(node.args[0].value)
    return {n.split(".")[0] for n in names}


def declared_distributions(pyproject: dict) -> set[str]:
    """Normalized distribution names required by the core dependencies or any extra."""
    project = pyproject["project"]
    reqs = list(project.get("dependencies", []))
    for extra in project.get("optional-dependencies", {}).values():
        reqs += extra
    return {_norm(re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", r.strip()).group()) for r in reqs}


def undeclared_imports(files, declared: set[str]) -> dict[str, list[str]]:
    """``{module: [files]}`` for third-party modules whose distribution is not declared.
    A module that no installed distribution provides (an extra's, such as pynput, that is
    not installed here) is taken to be distributed under its own name."""
    providers = importlib.metadata.packages_distributions()
    missing: dict[str, list[str]] = {}
    for path in files:
        for mod in imported_modules(Path(path).read_text()):
            if mod in sys.stdlib_module_names or mod in LOCAL:
                continue
            dists = {_norm(d) for d in providers.get(mod, [mod])}
            if not dists & declared:
                missing.setdefault(mod, []).append(str(path))
    return missing


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_third_party_import_is_declared():
    files = sorted(p for d in SOURCES for p in (ROOT / d).rglob("*.py"))
    assert len(files) > 50, "the walk found the sources"
    missing = undeclared_imports(files, declared_distributions(_pyproject()))
    assert not missing, "imported but not declared in pyproject.toml: " + "; ".join(
        f"{m} ({', '.join(sorted(set(fs))[:3])})" for m, fs in sorted(missing.items()))


def test_optional_imports_are_declared_in_an_extra():
    """Teleoperation's device libraries are imported lazily and are not installed here; they
    still have to be in an extra, or `pip install -e ".[teleop]"` would not bring them."""
    extras = _pyproject()["project"]["optional-dependencies"]
    teleop = declared_distributions({"project": {"optional-dependencies": {"t": extras["teleop"]}}})
    assert {"pynput", "pyspacemouse"} <= teleop
    assert {"pynput", "pyspacemouse"} <= imported_modules(
        (ROOT / "window_bench/installer/teleop.py").read_text())


def test_checker_reports_an_undeclared_import(tmp_path):
    src = tmp_path / "mod.py"
    src.write_text("import os, json\nfrom . import sibling\nimport window_bench.envs\n"
                   "from scipy.stats import bootstrap\nimport numpy as np\n"
                   "import pytest\nmp = pytest.importorskip('moviepy')\n")
    assert imported_modules(src.read_text()) == {"os", "json", "window_bench", "scipy",
                                                 "numpy", "pytest", "moviepy"}
    declared = declared_distributions({"project": {
        "dependencies": ["numpy>=1.26", "window-bench[video]"],
        "optional-dependencies": {"test": ["pytest ; python_version>='3'"]}}})
    assert declared == {"numpy", "window-bench", "pytest"}
    missing = undeclared_imports([src], declared)
    assert set(missing) == {"scipy", "moviepy"} and missing["scipy"] == [str(src)]
    # Declared under its distribution name, however the name is spelt.
    assert "scipy" not in undeclared_imports([src], declared | {_norm("SciPy")})
