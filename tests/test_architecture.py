"""The harness knows no agent and no track: it imports neither the learners (``baselines``)
nor the pixel track (``window_bench.pixels``), names no agent kind in its logic, and finds
them only in the registries that ``window_bench.catalog`` fills."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

from window_bench.harness.methods import AGENTS, agent_class
from window_bench.harness.tracks import DEFAULT_TRACK, TRACKS

ROOT = Path(__file__).resolve().parents[1]
HARNESS = sorted((ROOT / "window_bench" / "harness").glob("*.py"))
ABOVE = re.compile(r"^(baselines|window_bench\.pixels|window_bench\.catalog)\b")
#: The registries' own tables name kinds (METHODS); pages render track names (tables).
NAMES_KINDS = {"methods.py", "tables.py"}


def _code_strings(tree: ast.Module) -> list[ast.Constant]:
    """String constants that are not docstrings."""
    docs = {id(node.body[0].value) for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef))
            and node.body and isinstance(node.body[0], ast.Expr)
            and isinstance(node.body[0].value, ast.Constant)}
    return [n for n in ast.walk(tree) if isinstance(n, ast.Constant)
            and isinstance(n.value, str) and id(n) not in docs]


@pytest.mark.parametrize("path", HARNESS, ids=lambda p: p.name)
def test_the_harness_imports_nothing_above_it(path):
    """No import of the learners, the pixel track or the catalog, static or lazy, and no
    module path of theirs in a string (an ``importlib`` import or a ``"module:Class"``)."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                 [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        above = [n for n in names if ABOVE.match(n)]
        assert not above, f"{path.name}:{node.lineno} imports {above}"
    for s in _code_strings(tree):
        assert not ABOVE.match(s.value), f"{path.name}:{s.lineno} names {s.value!r}"


@pytest.mark.parametrize("path", [p for p in HARNESS if p.name not in NAMES_KINDS],
                         ids=lambda p: p.name)
def test_the_harness_has_no_agent_or_track_branch(path):
    """Capabilities, not kinds: no agent kind and no track other than the default named in
    the harness's code, and no comparison of a method's agent."""
    src = path.read_text()
    assert not re.search(r"\.agent\s*(==|!=|in\b)|agent_kind\s*(==|!=)", src), path.name
    named = {s.value for s in _code_strings(ast.parse(src))}
    assert not named & ((set(AGENTS) | set(TRACKS)) - {DEFAULT_TRACK}), path.name


def test_run_py_stays_short():
    """The run's loop, with evaluation, the Stage I cache, the results files and the tracks'
    differences in their own modules."""
    n = len((ROOT / "window_bench" / "harness" / "run.py").read_text().splitlines())
    assert n <= 600, f"window_bench/harness/run.py has {n} lines"


def test_no_import_circle_between_the_cli_and_the_pixel_cli():
    tree = ast.parse((ROOT / "window_bench" / "pixels" / "cli.py").read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert "window_bench.cli" not in imported


def test_registries_name_the_choices_and_load_no_learner_on_import():
    """``import window_bench`` registers every agent and track without importing a learner
    (or torch); an unknown name is one line listing the registered ones."""
    code = ("import sys, window_bench; from window_bench.harness.methods import AGENTS; "
            "from window_bench.harness.tracks import TRACKS; "
            "print((sorted(AGENTS), sorted(TRACKS), "
            "[m for m in sys.modules if m.split('.')[0] in ('torch', 'baselines')]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == str((sorted(AGENTS), sorted(TRACKS), []))
    assert {"qcfql", "qcfql-pixels", "sac-pixels"} <= set(AGENTS)
    with pytest.raises(ValueError,
                       match=r"^unknown agent kind 'bc'; registered: qcfql, .*act-pixels$"):
        agent_class("bc")
    with pytest.raises(ValueError, match=r"^track='rgb'; allowed: state, pixels, pixels-seat$"):
        TRACKS.lookup("rgb")
