"""``bench sweep GRID``: a grid of runs declared in a TOML file, executed on Ray.

A grid file (``experiments/table2.toml`` ...) names a profile, the final evaluation's M and
seed set, and blocks of cells::

    name = "table5"
    profile = "cpu"
    M = 100                      # final-checkpoint evaluation rollouts
    seed_set = "test"            # window_bench.harness.seeds
    # final_checkpoint = "best-dev"  # default "last" (window_bench.harness.results)

    [[train]]                    # methods x envs x seeds x h (h: QC-FQL methods only)
    methods = ["qcfql-no-intervention"]
    envs = ["WindowInstall-A-v0"]
    seeds = [0, 1, 2]
    h = [5, 20]
    # agent_config = { alpha = 100 }

    [[evaluate]]                 # Table 7: evaluation-only cells on a trained cell's policy
    method = "qcfql"
    env = "WindowInstall-A-v0"
    seeds = [0, 1, 2]
    on = ["WindowInstall-A-Panel40x40-v0"]

:func:`load_grid` checks everything before any work: ids against the registries, every
``agent_config`` value against the config of each agent it goes to (as ``bench run
--agent-config`` does: known field, type, finite and in range, one of the allowed words), and
every name that becomes part of a path (grid name, cell names) as one safe file name; a sweep
writes nothing outside OUT (:func:`check_inside`).

Every cell is one ``bench run`` (or ``bench eval``) in its own process, started by a Ray task
that asks for one CPU: a crash or an out-of-memory kill stays inside its cell and is recorded
in ``OUT/sweep-logs/<cell>.json`` beside its log. A cell's directory is its identity
(``<out>/<env>/<method>[-h<h>][-<overrides>]-<profile>-s<seed>``, the leaderboard's naming), so
grids that share a cell (Table 5's h = 10 row is Table 2's) share its files. Before starting a
cell the sweep reads its directory: finished (``results.json`` with the grid's final
evaluation) is skipped, partial (a saved training state) is resumed with ``--resume``,
anything else starts fresh. ``bench run`` writes its state atomically at episode boundaries,
so Ctrl-C or SIGKILL at any moment leaves every cell resumable: rerun the same command.

Cells that share Stage I (same agent, config, h, demonstrations, seed) share one cached
result (:mod:`window_bench.harness.stage1`): the sweep starts one cell of each such group
first and holds the others back until its Stage I is cached, so no worker waits on another's
pretraining while other work is ready. Demonstrations are collected once per (env, operator,
n, seed) into ``<out>/demos/`` under a file lock.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import fnmatch
import itertools
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from window_bench.harness.evaluation import atomic_write_text
from window_bench.harness.leaderboard import override_tag
from window_bench.harness.methods import agent_class, get_method, get_preset, get_profile
from window_bench.harness.results import DEFAULTS_REVISION, FINAL_CHECKPOINTS, revision_of
from window_bench.harness.schemas import FIELD_NAME, POLICY_FILE, SAFE_NAME, read_json
from window_bench.harness.seeds import SEED_SETS
from window_bench.harness.tracks import DEFAULT_TRACK, TRACKS, get_track
from window_bench.installer.operators import DEFAULT_OPERATOR, OPERATORS
from window_bench.data.steplog import DEFAULT_DEMO_ACTIONS, DEMO_ACTIONS

GRID_KEYS = {"name", "table", "title", "profile", "M", "seed_set", "operator", "eval_workers",
             "final_checkpoint", "track", "demo_actions", "train", "evaluate"}
TRAIN_KEYS = {"methods", "envs", "seeds", "h", "agent_config", "preset"}
EVALUATE_KEYS = {"method", "env", "seeds", "on", "h", "agent_config", "preset"}
MAX_GRID_BYTES = 1 << 20
LOGS = "sweep-logs"      # OUT/sweep-logs/<cell>.log and .json: nothing of ours in a run directory


class GridError(ValueError):
    """A grid file that cannot be run; the message is one line naming the file and value."""


# ---------------------------------------------------------------------------- cells
@dataclass(frozen=True)
class Cell:
    """One ``bench run`` (``on`` is None) or one evaluation of a trained cell's final policy
    on the env ``on``."""

    method: str
    env_id: str
    seed: int
    profile: str
    h: int | None = None                       # None: the method's own h
    agent_config: tuple = ()                   # sorted (key, value) pairs
    on: str | None = None
    track: str = DEFAULT_TRACK                 # observation track (harness/tracks.py)
    operator: str = DEFAULT_OPERATOR           # the grid's operator profile
    final_checkpoint: str = "last"             # the grid's (harness/results.py)
    demo_actions: str = DEFAULT_DEMO_ACTIONS   # the grid's (bench run --demo-actions)

    @property
    def train_cell(self) -> "Cell":
        return dataclasses.replace(self, on=None)

    @property
    def name(self) -> str:
        """``<env>/<run>`` for a training cell, ``<evaluated env>/<run>`` for an evaluation."""
        tag = f"-h{self.h}" if self.h is not None else ""
        tag += override_tag(self.agent_config)
        tag += "" if self.track == DEFAULT_TRACK else f"-{self.track}"   # as bench leaderboard does
        tag += "" if self.operator == DEFAULT_OPERATOR else f"-{self.operator}"
        tag += "" if self.final_checkpoint == "last" else f"-{self.final_checkpoint}"
        tag += "" if self.demo_actions == DEFAULT_DEMO_ACTIONS else f"-{self.demo_actions}"
        return f"{self.on or self.env_id}/{self.method}{tag}-{self.profile}-s{self.seed}"

    def path(self, out: Path) -> Path:
        """The run directory (training cell) or the evaluation's JSON file (evaluation cell:
        ``OUT/<evaluated env>/<run>.json``, beside, never inside, the run directory)."""
        return out / (self.name if self.on is None else self.name + ".json")

    @property
    def stage1_group(self) -> tuple | None:
        """Cells with the same group compute the same Stage I (None: no Stage I to share): the
        same agent of the same track, env, seed, profile, h and config."""
        m, track = get_method(self.method), get_track(self.track)
        if self.on is not None or not m.offline_pretrain or \
                not track.stage1_modules(track.agent_kind(m.agent)):
            return None
        return (m.agent, self.env_id, self.seed, self.profile, self.h or m.h, self.agent_config,
                self.track)


@dataclass(frozen=True)
class Grid:
    name: str
    path: Path
    profile: str
    M: int
    seed_set: str
    operator: str
    cells: tuple[Cell, ...]
    table: int | None = None
    eval_workers: int | None = None      # None: the profile's (1: a cell uses one core)


def _fail(path, msg: str):
    raise GridError(f"{path}: {msg}")


def _list(path, block: str, value, what: str, check) -> list:
    if not isinstance(value, list) or not value:
        _fail(path, f"{block}.{what} must be a non-empty list, got {value!r}")
    for v in value:
        check(v)
    return value


def load_grid(path: str | os.PathLike) -> Grid:
    """Parse and check a grid file; every problem is a one-line :class:`GridError`."""
    import window_bench

    path = Path(path)
    if not path.is_file():
        raise GridError(f"{path}: no such grid file")
    if path.stat().st_size > MAX_GRID_BYTES:     # a grid is a page of TOML, never megabytes
        raise GridError(f"{path}: {path.stat().st_size:,} bytes, over the {MAX_GRID_BYTES:,}-"
                        f"byte limit for a grid file; not read")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError, OSError) as e:
        raise GridError(f"{path}: not valid TOML ({str(e).splitlines()[0]})") from None
    unknown = set(doc) - GRID_KEYS
    if unknown:
        _fail(path, f"unknown key(s) {', '.join(sorted(unknown))}; allowed: "
                    f"{', '.join(sorted(GRID_KEYS))}")
    try:
        profile = get_profile(doc.get("profile", "smoke")).name
    except ValueError as e:
        _fail(path, str(e))
    M = doc.get("M", 100)
    if isinstance(M, bool) or not isinstance(M, int) or not 1 <= M <= 10_000:
        _fail(path, f"M = {M!r}; allowed: an integer in 1..10000")
    seed_set = doc.get("seed_set", "test")
    if seed_set not in SEED_SETS:
        _fail(path, f"seed_set = {seed_set!r}; allowed: {', '.join(SEED_SETS)}")
    name = doc.get("name", path.stem)
    if not isinstance(name, str) or not SAFE_NAME.match(name):
        _fail(path, f"name = {name!r}; allowed: one file name of letters, digits and _.+=- "
                    f"(it names OUT/sweep-<name>.json)")
    table = doc.get("table")
    if table is not None and (isinstance(table, bool) or table not in range(2, 8)):
        _fail(path, f"table = {table!r}; allowed: an integer in 2..7")
    if not isinstance(doc.get("title", ""), str):
        _fail(path, f"title = {doc['title']!r}; allowed: a string")
    operator = doc.get("operator", DEFAULT_OPERATOR)
    if operator not in OPERATORS:
        _fail(path, f"operator = {operator!r}; allowed: {', '.join(sorted(OPERATORS))}")
    demo_actions = doc.get("demo_actions", DEFAULT_DEMO_ACTIONS)
    if demo_actions not in DEMO_ACTIONS:
        _fail(path, f"demo_actions = {demo_actions!r}; allowed: {', '.join(DEMO_ACTIONS)}")
    track = doc.get("track", DEFAULT_TRACK)
    if track not in TRACKS:
        _fail(path, f"track = {track!r}; allowed: {', '.join(TRACKS)}")
    eval_workers = doc.get("eval_workers")
    if eval_workers is not None and (isinstance(eval_workers, bool) or
                                     not isinstance(eval_workers, int) or
                                     not 1 <= eval_workers <= 64):
        _fail(path, f"eval_workers = {eval_workers!r}; allowed: an integer in 1..64")
    final_checkpoint = doc.get("final_checkpoint", "last")
    if final_checkpoint not in FINAL_CHECKPOINTS:
        _fail(path, f"final_checkpoint = {final_checkpoint!r}; allowed: "
                    f"{', '.join(FINAL_CHECKPOINTS)}")

    def env_ok(block):
        def check(e):
            if e not in window_bench.ENV_IDS:
                _fail(path, f"{block}: unknown env {e!r}; registered: "
                            f"{', '.join(window_bench.ENV_IDS)}")
        return check

    def seed_ok(block):
        def check(s):
            if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < 1000:
                _fail(path, f"{block}: seed {s!r}; allowed: an integer in 0..999")
        return check

    def method_ok(block):
        def check(m):
            try:
                get_method(m)
            except ValueError as e:
                _fail(path, f"{block}: {e}")
        return check

    def h_list(block, spec, methods):
        hs = spec.get("h")
        if hs is None:
            return [None]
        def check(h):
            if isinstance(h, bool) or not isinstance(h, int) or not 1 <= h <= 100:
                _fail(path, f"{block}.h: {h!r}; allowed: integers in 1..100")
        _list(path, block, hs, "h", check)
        for m in methods:
            if not agent_class(get_method(m).agent).follows_method_h:
                _fail(path, f"{block}.h: h is a run parameter of the QC-FQL methods only, "
                            f"not of {m!r}")
        return hs

    def overrides(block, spec, methods, hs):
        """The block's agent_config as sorted pairs, each value checked against the config
        of every agent it goes to (as ``bench run --agent-config`` checks it), and each one
        a part of a cell's directory name."""
        cfg = spec.get("agent_config", {})
        if not isinstance(cfg, dict):
            _fail(path, f"{block}.agent_config must be a table, got {cfg!r}")
        preset = spec.get("preset")     # a published agent config (bench run --preset)
        if preset is not None:
            try:
                cfg = {**get_preset(preset), **cfg}
            except (ValueError, TypeError) as e:
                _fail(path, f"{block}.preset = {preset!r}: {str(e).splitlines()[0]}")
        for k, v in cfg.items():
            where = f"{block}.agent_config.{k}"
            if not re.match(FIELD_NAME, k):
                _fail(path, f"{where}: not a config field name (letters, digits, _; no "
                            f"leading _)")
            if k == "h":
                _fail(path, f"{where}: set the chunk horizon with the block's h = [...]")
            items = v if isinstance(v, list) else [v]
            for x in items:
                if x is None and not isinstance(v, list):   # a preset's "off" (TOML has no null)
                    continue
                if isinstance(x, float) and not math.isfinite(x):
                    _fail(path, f"{where} = {v!r}; allowed: finite numbers")
                if isinstance(x, str) and not SAFE_NAME.match(x):
                    _fail(path, f"{where} = {v!r}; allowed: a word of letters, digits and "
                                f"_.+=- (it becomes part of a directory name)")
                if not isinstance(x, (bool, int, float, str)) or \
                        (isinstance(v, list) and isinstance(x, (bool, str))):
                    _fail(path, f"{where} = {v!r}; allowed: a number, true/false, a word, or "
                                f"a list of numbers")
        pairs = tuple(sorted((k, tuple(v) if isinstance(v, list) else v)
                             for k, v in cfg.items()))
        for m, h in itertools.product(methods, hs):
            method = get_method(m)
            try:
                cls = agent_class(get_track(track).agent_kind(method.agent))
                base = cls.make_config(h or method.h, get_profile(profile), {}) if pairs else None
                for k, v in pairs:     # a list where the config holds a tuple, and only there
                    d = getattr(base, k, None)
                    if d is not None and isinstance(d, tuple) != isinstance(v, tuple):
                        _fail(path, f"{block}.agent_config.{k} = {v!r}; allowed: "
                                    + (f"a list, like {list(d)}" if isinstance(d, tuple)
                                       else f"one value, like {d!r}"))
                cls.make_config(h or method.h, get_profile(profile), dict(pairs))
            except (ValueError, TypeError) as e:
                if isinstance(e, GridError):
                    raise
                msg = str(e).splitlines()[0] if str(e) else type(e).__name__
                _fail(path, f"{block}.agent_config for {m}: {msg}")
        return pairs

    cells: list[Cell] = []
    for i, spec in enumerate(doc.get("train", [])):
        block = f"train[{i}]"
        if set(spec) - TRAIN_KEYS:
            _fail(path, f"{block}: unknown key(s) {', '.join(sorted(set(spec) - TRAIN_KEYS))}; "
                        f"allowed: {', '.join(sorted(TRAIN_KEYS))}")
        methods = _list(path, block, spec.get("methods"), "methods", method_ok(block))
        envs = _list(path, block, spec.get("envs"), "envs", env_ok(block))
        seeds = _list(path, block, spec.get("seeds"), "seeds", seed_ok(block))
        hs = h_list(block, spec, methods)
        cfg = overrides(block, spec, methods, hs)
        for m, h, e, s in itertools.product(methods, hs, envs, seeds):
            cells.append(Cell(m, e, s, profile, h if h != get_method(m).h else None, cfg,
                              track=track, operator=operator,
                              final_checkpoint=final_checkpoint, demo_actions=demo_actions))
    for i, spec in enumerate(doc.get("evaluate", [])):
        block = f"evaluate[{i}]"
        if set(spec) - EVALUATE_KEYS:
            _fail(path, f"{block}: unknown key(s) "
                        f"{', '.join(sorted(set(spec) - EVALUATE_KEYS))}; allowed: "
                        f"{', '.join(sorted(EVALUATE_KEYS))}")
        method = spec.get("method")
        method_ok(block)(method)
        env_ok(block)(spec.get("env"))
        seeds = _list(path, block, spec.get("seeds"), "seeds", seed_ok(block))
        on = _list(path, block, spec.get("on"), "on", env_ok(block))
        hs = h_list(block, spec, [method])
        cfg = overrides(block, spec, [method], hs)
        for h, s, target in itertools.product(hs, seeds, on):
            cells.append(Cell(method, spec["env"], s, profile,
                              h if h != get_method(method).h else None, cfg, on=target,
                              track=track, operator=operator,
                              final_checkpoint=final_checkpoint, demo_actions=demo_actions))
    if not cells:
        _fail(path, "declares no cells (add a [[train]] or [[evaluate]] block)")
    unique = tuple(dict.fromkeys(cells))
    for c in unique:
        run = c.name.split("/", 1)[1]
        if not SAFE_NAME.match(run):
            _fail(path, f"cell name {run!r} is not one safe directory name")
    return Grid(name, path, profile, M, seed_set, operator, unique, table, eval_workers)


# ---------------------------------------------------------------------------- cell state
def _read_json(path: Path) -> dict | None:
    """A cell's JSON file, or None where it is missing, oversize or not strict JSON."""
    try:
        doc = read_json(path)
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


def _obj(value) -> dict:
    """A field that should hold a JSON object, or an empty one (a hand-edited file's
    ``"final_eval": 7`` reads as no evaluation, never as a traceback)."""
    return value if isinstance(value, dict) else {}


def cell_status(cell: Cell, grid: Grid, out: Path) -> str:
    """``done``, ``partial`` (resume it), ``new``, or ``conflict: ...`` (the directory holds
    a different run's results; never overwritten)."""
    p = cell.path(out)
    if cell.on is not None:
        r = _read_json(p)
        if r is None:
            return "new"
        if (r.get("episodes"), r.get("seed_set")) == (grid.M, grid.seed_set):
            return "done"
        return (f"conflict: {p} holds M = {r.get('episodes')} on {r.get('seed_set')!r} seeds, "
                f"the grid asks for M = {grid.M} on {grid.seed_set!r}")
    r = _read_json(p / "results.json")
    if r is not None:
        if revision_of(r) != DEFAULTS_REVISION:
            return (f"conflict: {p} holds a run made under revision {revision_of(r)} of the "
                    f"defaults (now {DEFAULTS_REVISION}); move it away to rerun it")
        fe = _obj(r.get("final_eval"))
        if (fe.get("episodes"), fe.get("seed_set"), fe.get("checkpoint", "last")) == \
                (grid.M, grid.seed_set, cell.final_checkpoint):
            return "done"
        if not _has_state(p):
            return (f"conflict: {p} holds a finished run without a final M = {grid.M} "
                    f"evaluation on {grid.seed_set!r} seeds of the {cell.final_checkpoint!r} "
                    f"checkpoint; move it away to rerun it")
    return "partial" if _has_state(p) else "new"


def _has_state(run_dir: Path) -> bool:
    return any((run_dir / n).exists() for n in ("state.safetensors", "state.pt"))


def final_policy(run_dir: Path) -> Path:
    """The final policy file a finished run recorded in its results."""
    r = _read_json(run_dir / "results.json") or {}
    rel = _obj(r.get("final_eval")).get("policy")
    if rel is None:
        raise FileNotFoundError(f"{run_dir}/results.json names no final policy")
    if not isinstance(rel, str) or not re.match(POLICY_FILE, rel):
        raise FileNotFoundError(f"{run_dir}/results.json: final policy {rel!r} is not a file "
                                f"of the run's policies/")
    return run_dir / rel


def _progress_detail(cell: Cell, counters: dict) -> str:
    """How far a partial run is, from the counters of its last saved state."""
    def num(key) -> float:   # a hand-edited state reads as 0, never as a traceback
        v = counters.get(key)
        return v if isinstance(v, (int, float)) and not isinstance(v, bool) else 0

    stage = counters.get("stage")
    episodes = counters.get("episodes")
    if stage == "offline":
        where = f"Stage I, {num('offline_done'):,.0f} updates"
    elif stage in ("warm", "online"):
        m, prof = get_method(cell.method), get_profile(cell.profile)
        budget = prof.budget_steps if m.online_updates else prof.warm_steps
        where = (f"Stage {'II' if stage == 'warm' else 'III'}, "
                 f"{num('env_steps'):,.0f}/{budget:,} env steps, "
                 f"{len(episodes) if isinstance(episodes, list) else 0} episodes")
    else:
        where = {"evaluate0": "Stage I done, checkpoint-0 evaluation",
                 "done": "training done, final evaluation"}.get(
                     stage, f"stage {str(stage)[:40]!r}")
    return f"{where}, {num('wall_clock_s') / 60:.0f} min so far"


def short_commit(commit: str | None) -> str | None:
    """``abcdef1`` (or ``abcdef1-dirty``) of a provenance's ``git_commit``; None if unknown."""
    if not commit or commit == "unknown":
        return None
    sha, _, dirty = commit.partition("-")
    return sha[:7] + (f"-{dirty}" if dirty else "")


def cell_commit(cell: Cell, out: Path) -> str | None:
    """The code commit a finished training cell ran at (its results' provenance), short."""
    if cell.on is not None:
        return None
    r = _read_json(cell.path(out) / "results.json") or {}
    return short_commit((r.get("provenance") or {}).get("git_commit"))


def row_of(cell: Cell) -> Cell:
    """A table row: the cells that differ only in their seed share it."""
    return dataclasses.replace(cell, seed=0)


def row_commits(grid: Grid, out: Path) -> dict[Cell, set[str]]:
    """Per row of ``grid``, the code commits its finished training cells ran at. A row whose
    seeds ran at different commits mixes code; a new seed of a row is comparable with the
    others when it runs from a checkout of the row's commit."""
    rows: dict[Cell, set[str]] = {}
    for c in grid.cells:
        if c.on is None and cell_status(c, grid, out) == "done":
            commit = cell_commit(c, out)
            if commit is not None:
                rows.setdefault(row_of(c), set()).add(commit)
    return rows


def cell_report(cell: Cell, grid: Grid, out: Path) -> dict:
    """Where one cell stands, read from its files alone (nothing is started or locked):
    ``status`` as :func:`cell_status`, with ``running`` for a partial or new cell whose run
    directory another process holds, and ``failed`` for a cell whose last sweep attempt ended
    with an error and left no state; ``detail`` says how far it is (a finished cell's final
    success, a partial one's stage and counters, as its last saved state records them)."""
    from window_bench.harness.files import lock_holder, state_counters

    status = cell_status(cell, grid, out)
    p = cell.path(out)
    detail = ""
    if status == "done":
        r = _read_json(p) if cell.on is not None else (_read_json(p / "results.json") or {})
        fe = r if cell.on is not None else _obj(r.get("final_eval"))
        k, n = fe.get("successes"), fe.get("episodes")
        wall = _obj(r.get("final")).get("wall_clock_s")
        wall = wall if isinstance(wall, (int, float)) and not isinstance(wall, bool) else None
        detail = f"{k}/{n} on the {fe.get('seed_set')} seeds" if k is not None else ""
        detail += f", {wall / 60:.0f} min wall clock in bench run" if wall else ""
        commit = cell_commit(cell, out)
        detail += f", code {commit}" if commit else ""
    elif status.startswith("conflict"):
        status, detail = "conflict", status.removeprefix("conflict: ")
    else:
        if cell.on is None:
            holder = lock_holder(p)     # "pid N: <command> (since <time>)", as RunDir writes it
            if holder is not None:
                status = "running"
                pid = holder.split(":", 1)[0]
                since = holder.rsplit("(since ", 1)[-1].rstrip(")") if "(since " in holder else ""
                detail = f"{pid}, since {since}; " if since else f"{pid}; "
            counters = state_counters(p / "state.safetensors")
            if counters is not None:
                detail += _progress_detail(cell, counters)
        last = _read_json(out / LOGS / f"{cell.name}.json") or {}
        if status == "new" and last.get("status") == "failed":
            status = "failed"
            detail = (f"exit code {last.get('rc')} {last.get('error', '')}".strip()
                      + f"; log {out / LOGS / (cell.name + '.log')}")
    return {"cell": cell.name, "status": status, "detail": detail.rstrip("; ")}


def code_notes(cells, grid: Grid, out: Path, here: str | None = None) -> list[str]:
    """One line per cell about to run whose row's finished seeds ran at other code than
    this checkout (``here``: this checkout's commit, read from git when None): the row
    would mix code. A note, not an error: rerunning a row at new code is legitimate."""
    if here is None:
        from window_bench.harness.evaluation import git_commit
        here = short_commit(git_commit())
    rows = row_commits(grid, out)
    notes = []
    for c in cells:
        commits = rows.get(row_of(c)) if c.on is None else None
        if commits and here not in commits:
            notes.append(f"{c.name}: its row's finished seeds ran at {', '.join(sorted(commits))}"
                         f", this checkout is {here}; the row will mix code (run it from a "
                         f"checkout of the row's commit to keep it)")
    return notes


def grid_report(grid: Grid, out: str | os.PathLike) -> list[dict]:
    """:func:`cell_report` of every cell of ``grid`` under ``out``, in the grid's order. A
    training cell that is not done, in a row with finished seeds, also names the commit(s)
    those ran at (``its row ran at ...``): run it from a checkout of that commit to keep
    the row's code."""
    out = Path(out)
    rows = row_commits(grid, out)
    reports = []
    for c in grid.cells:
        r = cell_report(c, grid, out)
        commits = rows.get(row_of(c)) if c.on is None else None
        if commits and r["status"] != "done":
            r["detail"] = "; ".join(x for x in (r["detail"], "its row ran at "
                                                + ", ".join(sorted(commits))) if x)
        reports.append(r)
    return reports


def demos_dir(cell: Cell, grid: Grid, out: Path) -> Path:
    n = get_profile(cell.profile).n_demos
    return out / "demos" / f"{cell.env_id}-{grid.operator}-n{n}-s{cell.seed}"


def cell_command(cell: Cell, grid: Grid, out: Path, resume: bool,
                 stage1_cache: bool = True) -> list[str]:
    bench = [sys.executable, "-m", "window_bench.cli"]
    if cell.on is not None:
        return bench + ["eval", str(final_policy(cell.train_cell.path(out))), "--env", cell.on,
                        "--episodes", str(grid.M), "--seed-set", grid.seed_set,
                        "--out", str(cell.path(out))] + _eval_workers(grid)
    argv = bench + ["run", "--method", cell.method, "--env", cell.env_id,
                    "--profile", cell.profile, "--seed", str(cell.seed),
                    "--out", str(cell.path(out)), "--operator", grid.operator,
                    "--demos", str(demos_dir(cell, grid, out)),
                    "--final-episodes", str(grid.M), "--final-seed-set", grid.seed_set]
    argv += _eval_workers(grid)
    argv += ["--demo-actions", cell.demo_actions]
    if cell.final_checkpoint != "last":
        argv += ["--final-checkpoint", cell.final_checkpoint]
    if stage1_cache:
        argv += ["--stage1-cache", str(out / "stage1_cache")]
    if cell.h is not None:
        argv += ["--h", str(cell.h)]
    if cell.track != DEFAULT_TRACK:
        argv += ["--track", cell.track]
    if cell.agent_config:
        argv += ["--agent-config", *(f"{k}={json.dumps(list(v) if isinstance(v, tuple) else v)}"
                                     for k, v in cell.agent_config)]
    return argv + (["--resume"] if resume else [])


def _eval_workers(grid: Grid) -> list[str]:
    return [] if grid.eval_workers is None else ["--eval-workers", str(grid.eval_workers)]


def demos_command(cell: Cell, grid: Grid, out: Path) -> list[str]:
    """Run._demos collects with seed 1_000_000 + run seed; the same demos, collected once."""
    return [sys.executable, "-m", "window_bench.cli", "demos", "--env", cell.env_id,
            "--n", str(get_profile(cell.profile).n_demos), "--out",
            str(demos_dir(cell, grid, out)), "--operator", grid.operator,
            "--seed", str(1_000_000 + cell.seed)]


# ---------------------------------------------------------------------------- the Ray task
def _die_with_parent() -> None:
    """In the child, before exec: SIGKILL when the Ray worker that started it dies, so a
    killed sweep leaves no orphan run writing into a cell directory."""
    import ctypes

    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    os.setpgrp()


@contextlib.contextmanager
def _file_lock(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def run_cell(argv: list[str], log: str, demos: list[str] | None = None,
             demos_root: str | None = None) -> dict:
    """Body of the Ray task: (collect the demonstrations once, then) run ``argv`` with its
    output appended to ``log``; returns the exit code and the wall clock."""
    t0 = time.time()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as f:
        f.write(f"\n== {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())} "
                f"{' '.join(argv)}\n".encode())
        f.flush()
        if demos is not None:
            done = Path(demos_root) / ".complete"
            with _file_lock(Path(demos_root + ".lock")):
                if not done.exists():
                    rc = subprocess.call(demos, stdout=f, stderr=subprocess.STDOUT, env=env,
                                         preexec_fn=_die_with_parent)
                    if rc != 0:
                        return {"rc": rc, "wall_s": time.time() - t0, "what": "demos"}
                    done.write_text("")
        rc = subprocess.call(argv, stdout=f, stderr=subprocess.STDOUT, env=env,
                             preexec_fn=_die_with_parent)
    return {"rc": rc, "wall_s": time.time() - t0, "what": argv[3]}


# ---------------------------------------------------------------------------- scheduling
def schedule(cells) -> list[Cell]:
    """Training cells round-robin over their Stage I groups (one cell of every group first,
    so the shared pretrainings start early), then the evaluation-only cells."""
    groups: dict = {}
    for c in cells:
        if c.on is None:
            groups.setdefault(c.stage1_group or ("solo", c), []).append(c)
    order = [c for batch in itertools.zip_longest(*groups.values()) for c in batch if c]
    return order + [c for c in cells if c.on is not None]


def select(grid: Grid, only: list[str] | None) -> Grid:
    """The grid cut to the cells whose name matches one of the shell patterns ``only``
    (None or empty: all of them); :class:`GridError` when no cell matches."""
    if not only:
        return grid
    cells = tuple(c for c in grid.cells if any(fnmatch.fnmatchcase(c.name, pattern)
                                               for pattern in only))
    if not cells:
        raise GridError(f"{grid.path}: --only {' '.join(only)} matches none of its "
                        f"{len(grid.cells)} cells (e.g. {grid.cells[0].name})")
    return dataclasses.replace(grid, cells=cells)


def check_inside(grid: Grid, out: str | os.PathLike) -> None:
    """Every path a sweep of ``grid`` writes resolves inside ``out``: a cell name or a
    symlink that leads elsewhere is a :class:`GridError` before anything runs."""
    out = Path(out)
    root = out.resolve()
    paths = [out / f"sweep-{grid.name}.json", out / "stage1_cache"]
    for c in grid.cells:
        paths += [c.path(out), out / LOGS / f"{c.name}.log", out / LOGS / f"{c.name}.json"]
        if c.on is None:
            paths.append(demos_dir(c, grid, out))
    for p in paths:
        if not p.resolve().is_relative_to(root):
            raise GridError(f"{grid.path}: {p} resolves to {p.resolve()}, outside --out {out}")


class Sweep:
    """Runs a grid's cells on Ray (see the module docstring)."""

    def __init__(self, grid: Grid, out: str | os.PathLike, workers: int | None = None,
                 address: str | None = None, progress: bool = True, stage1_cache: bool = True,
                 only: list[str] | None = None):
        self.grid, self.out = select(grid, only), Path(out)
        check_inside(self.grid, self.out)
        self.stage1_cache = stage1_cache
        self.address = address
        self.workers = workers
        self.progress = progress
        if workers is not None and workers < 1:
            raise ValueError(f"--workers {workers}; allowed: >= 1")

    def _init_ray(self):
        import ray

        os.environ.setdefault("RAY_DEDUP_LOGS", "0")
        kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        if self.address:
            ray.init(address=self.address, **kw)
        else:
            # "local": always a new cluster of our own, never one a `ray start` left behind
            ray.init(address="local", num_cpus=self.workers or os.cpu_count(), **kw)
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.slots = min(self.workers or cpus, cpus)
        return ray

    def run(self) -> dict:
        """Run every unfinished cell; returns the summary also written to
        ``<out>/sweep-<grid>.json``."""
        g, out = self.grid, self.out
        out.mkdir(parents=True, exist_ok=True)
        status = {c: cell_status(c, g, out) for c in g.cells}
        conflicts = {c: s for c, s in status.items() if s.startswith("conflict")}
        todo = [c for c in schedule(g.cells) if status[c] in ("new", "partial")]
        skipped = sum(s == "done" for s in status.values())
        ray = self._init_ray()
        task = ray.remote(num_cpus=1, max_retries=0)(run_cell)
        results: dict[Cell, dict] = {}
        running: dict = {}                     # ObjectRef -> (cell, start time)
        t_start = time.time()
        view = _ProgressView(len(g.cells), skipped, len(conflicts), self.slots, self.progress)
        for c, s in conflicts.items():
            view.log(f"[red]skipped[/] {c.name}: {s}")
            results[c] = {"status": "conflict", "message": s}
        for line in code_notes(todo, g, out):
            view.log(f"[yellow]note[/] {line}")
        interrupted = False
        try:
            with view:
                while todo or running:
                    before = set(results)
                    ready = self._ready(todo, running, results)
                    for c in set(results) - before:      # evaluation cells whose source failed
                        view.finished(c, results[c])
                    if not ready and not running:
                        for c in todo:
                            results[c] = {"status": "failed", "rc": None, "wall_s": 0.0,
                                          "message": "could not be scheduled"}
                            view.finished(c, results[c])
                        break
                    for c in ready:
                        resume = cell_status(c, g, out) == "partial"
                        argv = cell_command(c, g, out, resume, self.stage1_cache)
                        log = str(out / LOGS / f"{c.name}.log")
                        demos = None if c.on is not None else demos_command(c, g, out)
                        droot = None if demos is None else str(demos_dir(c, g, out))
                        running[task.remote(argv, log, demos, droot)] = (c, time.time(), resume)
                        todo.remove(c)
                    view.update(running=len(running))
                    done, _ = ray.wait(list(running), num_returns=1, timeout=0.5)
                    for ref in done:
                        c, t0, resume = running.pop(ref)
                        try:
                            r = ray.get(ref)
                        except Exception as e:   # the worker itself died (OOM kill, ...)
                            r = {"rc": -1, "wall_s": time.time() - t0, "error": str(e)[:300]}
                        r["status"] = "done" if r["rc"] == 0 else "failed"
                        r["resumed"] = resume
                        results[c] = r
                        self._record(c, r)
                        view.finished(c, r)
                    view.update(running=len(running))
        except KeyboardInterrupt:
            interrupted = True
            for ref in running:
                ray.cancel(ref, force=True)
        finally:
            ray.shutdown()
        summary = self._summary(results, time.time() - t_start, interrupted)
        atomic_write_text(out / f"sweep-{g.name}.json", json.dumps(summary, indent=1))
        if interrupted:
            raise KeyboardInterrupt
        return summary

    def _ready(self, todo: list, running: dict, results: dict) -> list:
        """Cells to start now: free slots, their source cell trained (evaluation cells), and
        not waiting for a Stage I that another running cell is computing."""
        def computing(c: Cell) -> bool:
            return bool(c.stage1_group) and not (c.path(self.out) / "stage1.json").exists()

        busy = {c.stage1_group for c, _, _ in running.values() if computing(c)
                and self.stage1_cache}
        picked = []
        for c in list(todo):
            if len(picked) >= self.slots - len(running):
                break
            if c.on is not None and cell_status(c.train_cell, self.grid, self.out) != "done":
                src = c.train_cell
                if src not in self.grid.cells or results.get(src, {}).get("status") in (
                        "failed", "conflict"):
                    results[c] = {"status": "failed", "rc": None, "wall_s": 0.0,
                                  "message": f"the trained cell {src.name} is not finished"}
                    todo.remove(c)
                continue
            if c.stage1_group in busy:
                continue
            if computing(c) and self.stage1_cache:
                busy.add(c.stage1_group)
            picked.append(c)
        return picked

    def _record(self, c: Cell, r: dict) -> None:
        atomic_write_text(self.out / LOGS / f"{c.name}.json",
                          json.dumps({"cell": c.name, **r}, indent=1))

    def _summary(self, results: dict, wall: float, interrupted: bool) -> dict:
        return {"grid": self.grid.name, "grid_file": str(self.grid.path),
                "out": str(self.out), "workers": self.slots, "address": self.address,
                "stage1_cache": self.stage1_cache,
                "wall_clock_s": round(wall, 1), "interrupted": interrupted,
                "cells": {c.name: results.get(c, {"status": cell_status(c, self.grid, self.out)})
                          for c in self.grid.cells}}


class _ProgressView:
    """A rich view across the grid: cells done / running / failed and an ETA from the
    median wall clock of the cells finished so far."""

    def __init__(self, total: int, skipped: int, conflicts: int, slots: int, enabled: bool):
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, \
            TimeElapsedColumn

        self.console = Console(stderr=True)
        self.slots, self.walls = slots, []
        self.n = {"done": skipped, "failed": conflicts, "running": 0}
        self.total = total
        self.bar = Progress(TextColumn("[bold]grid"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("{task.fields[state]}"), TimeElapsedColumn(),
                            TextColumn("ETA {task.fields[eta]}"), console=self.console,
                            disable=not enabled)
        self.task = self.bar.add_task("grid", total=total, completed=skipped + conflicts,
                                      state=self._state(), eta="-")
        if skipped:
            self.log(f"{skipped} finished cell(s) skipped")

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def _state(self) -> str:
        return (f"done {self.n['done']} · running {self.n['running']} · "
                f"failed {self.n['failed']}")

    def log(self, text: str) -> None:
        self.console.log(text)

    def update(self, running: int) -> None:
        import statistics

        self.n["running"] = running
        left = self.total - self.n["done"] - self.n["failed"]
        eta = "-"
        if self.walls and left:
            s = statistics.median(self.walls) * -(-left // self.slots)
            eta = time.strftime("%H:%M:%S", time.gmtime(s))
        self.bar.update(self.task, state=self._state(), eta=eta)

    def finished(self, cell: Cell, r: dict) -> None:
        self.n["done" if r["status"] == "done" else "failed"] += 1
        if r.get("rc") is not None:
            self.walls.append(r["wall_s"])
        self.bar.advance(self.task)
        colour = "green" if r["status"] == "done" else "red"
        why = "" if r["status"] == "done" else f", exit code {r['rc']} {r.get('message', '')}"
        self.log(f"[{colour}]{r['status']}[/] {cell.name} ({r['wall_s']:.0f} s"
                 f"{', resumed' if r.get('resumed') else ''}{why.rstrip()})")
