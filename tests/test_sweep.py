"""bench sweep: grid files, cell identity and state, scheduling, and a tiny real grid on Ray."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from window_bench.harness.results import DEFAULTS_REVISION

from window_bench.harness.sweep import Cell, GridError, cell_command, cell_status, load_grid, \
    schedule

REPO = Path(__file__).resolve().parents[1]


def _grid(tmp_path, text: str):
    p = tmp_path / "g.toml"
    p.write_text(text)
    return load_grid(p)


GRID = """
profile = "smoke"
M = 2
[[train]]
methods = ["qcfql-offline", "qcfql"]
envs = ["WindowInstall-A-v0"]
seeds = [0, 1]
"""


@pytest.mark.parametrize("text, message", [
    ('M = 0\n[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]', "M = 0"),
    ('seed_set = "val"\n[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]',
     "seed_set = 'val'; allowed: dev, test"),
    ('[[train]]\nmethods=["qcfl"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]', "unknown method 'qcfl'"),
    ('[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-C-v0"]\nseeds=[0]', "unknown env"),
    ('[[train]]\nmethods=["sac"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]\nh=[5]',
     "QC-FQL methods only"),
    ('[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseeds=[-1]', "seed -1"),
    ('[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseed=[0]', "unknown key(s) seed"),
    ('profile = "smoke"', "declares no cells"),
    ('profile = [', "not valid TOML"),
    ('track = "rgb"\n[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]',
     "track = 'rgb'; allowed: state, pixels"),
    ('eval_workers = 0\n[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]',
     "eval_workers = 0; allowed: an integer in 1..64"),
    ('final_checkpoint = "best"\n[[train]]\nmethods=["sac"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]',
     "final_checkpoint = 'best'; allowed: last, best-dev"),
])
def test_bad_grid_is_one_line_error(tmp_path, text, message):
    with pytest.raises(GridError, match=None) as e:
        _grid(tmp_path, text)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_repository_grids_load():
    names = {p.stem: load_grid(p) for p in (REPO / "experiments").glob("*.toml")}
    assert {"table2", "table3", "table5", "table6", "table7"} <= set(names)
    t2 = names["table2"]
    assert (t2.profile, t2.M, t2.seed_set) == ("cpu", 100, "test")
    assert len(t2.cells) == 33                  # ten methods + the paper's QC-FQL, seeds 0-2
    t5 = names["table5"]
    assert {c.h for c in t5.cells} == {5, 20}   # h = 10 is Table 2's cell
    assert all(c.on for c in names["table7"].cells) and len(names["table7"].cells) == 18


def test_cell_names_h_and_overrides(tmp_path):
    g = _grid(tmp_path, GRID + 'h = [10, 5]\nagent_config = { alpha = 30 }\n')
    names = sorted(c.name for c in g.cells)
    assert "WindowInstall-A-v0/qcfql-alpha30-smoke-s0" in names      # h = 10 is qcfql's own h
    assert "WindowInstall-A-v0/qcfql-h5-alpha30-smoke-s1" in names
    c = next(c for c in g.cells if c.h == 5)
    argv = cell_command(c, g, tmp_path, resume=False)
    assert argv[argv.index("--h") + 1] == "5" and "--resume" not in argv
    assert argv[argv.index("--agent-config") + 1] == "alpha=30"
    assert argv[argv.index("--final-episodes") + 1] == "2"
    assert argv[argv.index("--final-seed-set") + 1] == "test"


def test_list_overrides_name_cells_as_the_leaderboard_names_runs(tmp_path):
    from window_bench.harness.leaderboard import run_dest

    g = _grid(tmp_path, GRID + 'agent_config = { student_hidden = [64, 32] }\n')
    c = next(c for c in g.cells if c.method == "qcfql" and c.seed == 0)
    assert c.name.endswith("/qcfql-student_hidden64x32-smoke-s0")
    argv = cell_command(c, g, tmp_path, resume=False)
    assert argv[argv.index("--agent-config") + 1] == "student_hidden=[64, 32]"
    results = {"env_id": c.env_id, "method": {"name": c.method}, "profile": {"name": c.profile},
               "seed": c.seed, "track": "state",
               "agent_config_overrides": {"student_hidden": [64, 32]}}
    assert run_dest(results, tmp_path) == c.path(tmp_path)
    grid = load_grid(REPO / "experiments" / "student_size.toml")
    assert {c.name for c in grid.cells} >= {
        "WindowInstall-B-v0/qcfql-offline-student_hidden512x512x512x512-cpu-s0",
        "WindowInstall-B-v0/qcfql-student_hidden512x512x512x512-cpu-s2"}


def test_operator_cells_are_named_apart_as_the_leaderboard_names_runs(tmp_path):
    """A grid of another operator profile must not land on the default operator's cells."""
    from window_bench.harness.leaderboard import run_dest

    g = _grid(tmp_path, 'operator = "attentive"\n' + GRID)
    c = next(c for c in g.cells if c.method == "qcfql" and c.seed == 0)
    assert c.name == "WindowInstall-A-v0/qcfql-attentive-smoke-s0"
    argv = cell_command(c, g, tmp_path, resume=False)
    assert argv[argv.index("--operator") + 1] == "attentive"
    default = next(c for c in _grid(tmp_path, GRID).cells if c.method == "qcfql" and c.seed == 0)
    assert default.name == "WindowInstall-A-v0/qcfql-smoke-s0"
    results = {"env_id": c.env_id, "method": {"name": c.method}, "profile": {"name": c.profile},
               "seed": c.seed, "track": "state", "operator": "attentive"}
    assert run_dest(results, tmp_path) == c.path(tmp_path)


def test_eval_workers_reach_every_cell_command(tmp_path):
    g = _grid(tmp_path, "eval_workers = 1\n" + GRID)
    assert g.eval_workers == 1
    argv = cell_command(g.cells[0], g, tmp_path, resume=True)
    assert argv[argv.index("--eval-workers") + 1] == "1"
    assert "--eval-workers" not in cell_command(g.cells[0], _grid(tmp_path, GRID), tmp_path,
                                                resume=True)


def test_a_best_dev_grid_asks_for_it_and_a_last_checkpoint_result_is_not_done(tmp_path):
    from window_bench.harness.leaderboard import run_dest

    g = _grid(tmp_path, 'final_checkpoint = "best-dev"\n' + GRID)
    c, last = g.cells[0], _grid(tmp_path, GRID).cells[0]
    argv = cell_command(c, g, tmp_path, resume=False)
    assert argv[argv.index("--final-checkpoint") + 1] == "best-dev"
    assert "--final-checkpoint" not in cell_command(last, _grid(tmp_path, GRID), tmp_path, False)
    # named apart from the last-checkpoint cell, as the leaderboard names the run
    assert c.name == "WindowInstall-A-v0/qcfql-offline-best-dev-smoke-s0" != last.name
    results = {"env_id": c.env_id, "method": {"name": c.method}, "profile": {"name": c.profile},
               "seed": c.seed, "track": "state", "final_eval": {"checkpoint": "best-dev"}}
    assert run_dest(results, tmp_path) == c.path(tmp_path)
    d = c.path(tmp_path)
    d.mkdir(parents=True)
    (d / "state.safetensors").write_bytes(b"x")
    fe = {"episodes": 2, "seed_set": "test"}
    (d / "results.json").write_text(json.dumps({"defaults": DEFAULTS_REVISION, "final_eval": fe}))    # the last checkpoint's
    assert cell_status(c, g, tmp_path) == "partial"
    (d / "results.json").write_text(json.dumps({"defaults": DEFAULTS_REVISION,
                                                "final_eval": {**fe, "checkpoint": "best-dev"}}))
    assert cell_status(c, g, tmp_path) == "done"


def test_pixel_track_cells_are_named_apart_and_run_with_track_pixels(tmp_path):
    g = _grid(tmp_path, 'track = "pixels"\n' + GRID)
    c = next(c for c in g.cells if c.method == "qcfql" and c.seed == 0)
    assert c.name == "WindowInstall-A-v0/qcfql-pixels-smoke-s0"
    argv = cell_command(c, g, tmp_path, resume=False)
    assert argv[argv.index("--track") + 1] == "pixels"
    state = next(c for c in _grid(tmp_path, GRID).cells if c.method == "qcfql" and c.seed == 0)
    assert "--track" not in cell_command(state, g, tmp_path, resume=False)
    assert c.stage1_group != state.stage1_group          # a pixel Stage I is its own


def test_only_selects_cells_by_name_and_rejects_a_pattern_matching_none(tmp_path):
    from window_bench.harness.sweep import Sweep

    g = _grid(tmp_path, GRID)
    s = Sweep(g, tmp_path, only=["*/qcfql-smoke-s*"], progress=False)
    assert sorted(c.name for c in s.grid.cells) == ["WindowInstall-A-v0/qcfql-smoke-s0",
                                                    "WindowInstall-A-v0/qcfql-smoke-s1"]
    with pytest.raises(GridError, match="--only \\*/sac\\* matches none of its 4 cells"):
        Sweep(g, tmp_path, only=["*/sac*"])


def test_schedule_starts_one_cell_per_stage1_group_first(tmp_path):
    g = _grid(tmp_path, GRID.replace('["qcfql-offline", "qcfql"]',
                                     '["qcfql-offline", "qcfql", "qcfql-no-warmstart", "act"]'))
    order = schedule(g.cells)
    first = order[:4]                  # act s0 and s1 are groups of their own; QC-FQL s0, s1
    assert {c.stage1_group for c in first} == {c.stage1_group for c in g.cells}
    assert Cell("sac", "WindowInstall-A-v0", 0, "smoke").stage1_group is None   # no Stage I


def test_stage1_key_covers_every_agent_with_a_stage_i_on_both_tracks():
    """Every method with offline pretraining has a Stage I cache key on the state and the
    pixel track (a pixel sweep once died here with KeyError 'qcfql-pixels' after re-observing
    its demos); a state kind hashes only its own module, so the grid's cached entries stay
    valid, and a pixel kind also hashes the pixel front end."""
    from window_bench.harness.methods import METHODS
    from window_bench.harness.stage1 import _source_sha256, key_material
    from window_bench.harness.tracks import get_track

    kinds = {m.agent for m in METHODS.values() if m.offline_pretrain}
    assert kinds == {"qcfql", "hilserl", "act"}
    code = lambda kind, track: key_material(kind, track, {}, 1, 1, "d", 0)["code_sha256"]  # noqa: E731
    for kind in kinds:
        pixel = get_track("pixels").agent_kind(kind)
        assert code(kind, "state") == _source_sha256(f"baselines.{kind}",
                                                     "window_bench.data.replay",
                                                     "window_bench.data.chunks")
        assert code(pixel, "pixels") == _source_sha256(
            f"baselines.{kind}", "window_bench.pixels.agent", "window_bench.pixels.encoder",
            "window_bench.data.replay", "window_bench.data.chunks")
    for kind, track in (("sac", "state"), ("sac-pixels", "pixels")):
        with pytest.raises(ValueError, match=f"'{kind}' has no Stage I"):
            key_material(kind, track, {}, 1, 1, "d", 0)


def test_cell_status_done_partial_new_conflict(tmp_path):
    g = _grid(tmp_path, GRID)
    c = g.cells[0]
    d = c.path(tmp_path)
    assert cell_status(c, g, tmp_path) == "new"
    d.mkdir(parents=True)
    (d / "state.safetensors").write_bytes(b"x")
    assert cell_status(c, g, tmp_path) == "partial"
    (d / "results.json").write_text(json.dumps({"defaults": DEFAULTS_REVISION, "final_eval": {"episodes": 2, "seed_set": "test"}}))
    assert cell_status(c, g, tmp_path) == "done"
    (d / "state.safetensors").unlink()
    (d / "results.json").write_text(json.dumps({"defaults": DEFAULTS_REVISION, "final_eval": {"episodes": 20, "seed_set": "dev"}}))
    assert cell_status(c, g, tmp_path).startswith("conflict")
    # a finished run of earlier defaults is never taken for the grid's cell, nor overwritten
    (d / "results.json").write_text(json.dumps({"final_eval": {"episodes": 2, "seed_set": "test"}}))
    assert cell_status(c, g, tmp_path).startswith(
        f"conflict: {d} holds a run made under revision 1 of the defaults")


def test_status_reports_each_cell_from_its_files_without_starting_anything(tmp_path):
    import fcntl
    import os

    import torch

    from window_bench.harness.files import LOCK, dump_state
    from window_bench.harness.sweep import LOGS

    p = tmp_path / "g.toml"
    p.write_text(GRID)
    out = tmp_path / "runs"
    g = load_grid(p)
    done, offline, online, failed = (c.path(out) for c in g.cells)
    for d in (done, online, offline):
        d.mkdir(parents=True)
    (done / "results.json").write_text(json.dumps({
        "defaults": DEFAULTS_REVISION, "final_eval": {"episodes": 2, "seed_set": "test", "successes": 1},
        "final": {"wall_clock_s": 600.0},
        "provenance": {"git_commit": "48c79d63c1c5986b0a41a2121ddf2a1f63514538"}}))
    counters = {"stage": "online", "offline_done": 40, "env_steps": 150, "wall_clock_s": 120.0,
                "episodes": [{"steps": 100}, {"steps": 50}]}
    (online / "state.safetensors").write_bytes(dump_state(
        {"counters": counters, "w": torch.zeros(3)}, "state"))
    (offline / "state.safetensors").write_bytes(dump_state(
        {"counters": dict(counters, stage="offline", env_steps=0, episodes=[])}, "state"))
    (out / LOGS / g.cells[3].env_id).mkdir(parents=True)
    (out / LOGS / f"{g.cells[3].name}.json").write_text(json.dumps(
        {"status": "failed", "rc": 1, "error": ""}))
    # the online cell is held by a "running" process
    fd = os.open(online / LOCK, os.O_RDWR | os.O_CREAT)
    os.write(fd, b"pid 4242: bench run ... (since 2026-12-01T00:00:00Z)")
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        r = subprocess.run([sys.executable, "-m", "window_bench.cli", "sweep", str(p), "--out",
                            str(out), "--status"], capture_output=True, text=True, timeout=120)
    finally:
        os.close(fd)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 5
    status = {line.split()[1]: line for line in lines[:4]}
    assert status[g.cells[0].name].startswith("done") and "1/2 on the test seeds" in \
        status[g.cells[0].name] and "10 min" in status[g.cells[0].name]
    assert "code 48c79d6" in status[g.cells[0].name]
    # the other seed of the done cell's row names the row's code; other rows do not
    assert g.cells[1].method == g.cells[0].method and g.cells[1].seed != g.cells[0].seed
    assert status[g.cells[1].name].endswith("its row ran at 48c79d6")
    assert "row ran at" not in status[g.cells[2].name] + status[g.cells[3].name]
    assert status[g.cells[2].name].startswith("running")
    assert "pid 4242" in status[g.cells[2].name]
    assert "Stage III, 150/400 env steps, 2 episodes, 2 min so far" in status[g.cells[2].name]
    assert status[g.cells[1].name].startswith("partial") and "Stage I, 40 updates" in \
        status[g.cells[1].name]
    assert status[g.cells[3].name].startswith("failed") and "exit code 1" in \
        status[g.cells[3].name]
    assert lines[4].endswith("4 cells; done 1, running 1, partial 1, failed 1")
    assert not (out / "sweep-g.json").exists()       # nothing was run or recorded
    # the lock is free again: the same cell now reads as partial
    r = subprocess.run([sys.executable, "-m", "window_bench.cli", "sweep", str(p), "--out",
                        str(out), "--status", "--only", g.cells[2].name],
                       capture_output=True, text=True, timeout=120)
    assert r.stdout.splitlines()[0].startswith("partial")


def test_code_notes_name_cells_whose_row_ran_at_other_code(tmp_path):
    """Starting a seed of a row whose finished seeds ran at another commit gets a note (the
    row would mix code); the same commit, a row with no finished seed, or an unknown or
    dirty-marked commit are handled as such."""
    from window_bench.harness.sweep import code_notes, row_commits, short_commit

    g = _grid(tmp_path, GRID)
    out = tmp_path / "runs"
    assert short_commit("48c79d63c1c5986b0a41a2121ddf2a1f63514538-dirty") == "48c79d6-dirty"
    assert short_commit("unknown") is None and short_commit(None) is None
    d = g.cells[0].path(out)
    d.mkdir(parents=True)
    (d / "results.json").write_text(json.dumps({
        "defaults": DEFAULTS_REVISION, "final_eval": {"episodes": 2, "seed_set": "test", "successes": 0},
        "provenance": {"git_commit": "48c79d63c1c5986b0a41a2121ddf2a1f63514538"}}))
    assert list(row_commits(g, out).values()) == [{"48c79d6"}]
    todo = list(g.cells[1:])
    notes = code_notes(todo, g, out, here="f67ee2d")
    assert len(notes) == 1 and notes[0].startswith(g.cells[1].name)
    assert "ran at 48c79d6, this checkout is f67ee2d" in notes[0]
    assert code_notes(todo, g, out, here="48c79d6") == []


def test_cli_bad_grid_exit_2(tmp_path):
    p = tmp_path / "g.toml"
    p.write_text("M = -3\n")
    r = subprocess.run([sys.executable, "-m", "window_bench.cli", "sweep", str(p)],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "M = -3" in r.stderr


def test_tiny_grid_on_ray_resumes_shares_stage1_and_makes_its_tables(tmp_path):
    """2 methods x 2 seeds (smoke) through Ray: every cell finished with its final evaluation
    on the test seeds; the two methods of a seed share one Stage I (the second loads it, and
    its checkpoint 0 equals the first's); a second sweep skips everything; bench tables
    makes Table 2 from the raw files."""
    from window_bench.harness.sweep import Sweep
    from window_bench.harness.tables import build

    grid = _grid(tmp_path, GRID.replace('["qcfql-offline", "qcfql"]',
                                        '["qcfql-offline", "qcfql-offline-warmstart"]'))
    out = tmp_path / "runs"
    summary = Sweep(grid, out, workers=2, progress=False).run()
    assert {c["status"] for c in summary["cells"].values()} == {"done"}, summary
    for seed in (0, 1):
        a, b = (json.loads((out / "WindowInstall-A-v0" / f"{m}-smoke-s{seed}" / "results.json")
                           .read_text()) for m in ("qcfql-offline", "qcfql-offline-warmstart"))
        for r in (a, b):
            assert (r["final_eval"]["seed_set"], r["final_eval"]["episodes"]) == ("test", 2)
            assert r["final_eval"]["seeds"] == [500000, 500001]
            assert len(r["final_eval"]["policy_sha256"]) == 64
            lost = r["final_eval"]["suction_lost_by"]     # why suction was lost, per episode
            assert set(lost) == {"grip_break", "commanded"}
            assert sum(lost.values()) <= r["final_eval"]["failure_modes"].get("suction_lost", 0)
        assert a["stage1"]["key"] == b["stage1"]["key"]
        assert sorted([a["stage1"]["cache_hit"], b["stage1"]["cache_hit"]]) == [False, True]
        strip = lambda c: {k: v for k, v in c.items() if k != "wall_clock_s"}  # noqa: E731
        assert strip(a["checkpoints"][0]) == strip(b["checkpoints"][0])
    again = Sweep(grid, out, workers=2, progress=False).run()
    assert all("rc" not in c for c in again["cells"].values())     # nothing ran again
    t2 = build(out, tmp_path / "docs", figures=False)["table2.md"]
    rows = [ln for ln in t2.splitlines() if ln.startswith("| Ours (offline")]
    assert len(rows) == 2 and all("| 2 |" in r for r in rows)          # n = 2 seeds
    assert "`smoke` profile, final evaluation with M = 2 on the" in t2  # the rows' protocol


# ---------------------------------------------------------------------------- hostile grids
ONE = '[[train]]\nmethods=["qcfql"]\nenvs=["WindowInstall-A-v0"]\nseeds=[0]\n'


@pytest.mark.parametrize("line, message", [
    ('agent_config = { q_agg = "x/../../../../escape" }',
     "agent_config.q_agg = 'x/../../../../escape'; allowed: a word"),
    ("agent_config = { lr = nan }", "agent_config.lr = nan; allowed: finite numbers"),
    ("agent_config = { alpha = -inf }", "agent_config.alpha = -inf; allowed: finite numbers"),
    ("agent_config = { hidden = -5 }", "agent_config.hidden = -5; allowed: a list, like"),
    ("agent_config = { hidden = [-5] }", "QCFQLConfig.hidden = (-5,) is not allowed"),
    ('agent_config = { hidden = [256, "a"] }', "allowed: a number, true/false, a word, or a list"),
    ("agent_config = { alpha = [1, 2] }", "agent_config.alpha = (1, 2); allowed: one value"),
    ("agent_config = { lr = 2.0 }", "QCFQLConfig.lr = 2.0 is not allowed"),
    ('agent_config = { q_agg = "max" }', "QCFQLConfig.q_agg = 'max' is not allowed"),
    ("agent_config = { __class__ = 1 }", "agent_config.__class__: not a config field name"),
    ("agent_config = { nope = 1 }", "unknown agent config field 'nope'"),
    ("agent_config = { h = 5 }", "set the chunk horizon with the block's h"),
    ("agent_config = { alpha = { a = 1 } }", "allowed: a number, true/false, a word"),
])
def test_agent_config_values_are_checked_when_the_grid_is_loaded(tmp_path, line, message):
    with pytest.raises(GridError) as e:
        _grid(tmp_path, ONE + line + "\n")
    assert message in str(e.value) and "\n" not in str(e.value), str(e.value)


@pytest.mark.parametrize("head, message", [
    ('name = "../../x"\n', "name = '../../x'; allowed: one file name"),
    ('operator = "../../x"\n', "operator = '../../x'; allowed: attentive, attentive-flush, average, by-eye, expert, flush, novice"),
    ("table = 9\n", "table = 9; allowed: an integer in 2..7"),
])
def test_names_that_become_paths_are_checked(tmp_path, head, message):
    with pytest.raises(GridError) as e:
        _grid(tmp_path, head + ONE)
    assert message in str(e.value)


def test_a_sweep_writes_nothing_outside_out(tmp_path, capsys, monkeypatch):
    """A bad grid stops with one line and exit 2 before any file; a cell path that a symlink
    leads outside --out is refused before Ray starts; --out a file is refused too."""
    from window_bench.cli import main
    from window_bench.harness.sweep import Sweep

    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text('profile = "smoke"\n' + ONE + 'agent_config = { q_agg = "x/../../../../e" }\n')
    (tmp_path / "afile").write_text("x")
    before = sorted(tmp_path.rglob("*"))
    for argv in (["sweep", str(bad), "--out", "runs/o"],
                 ["sweep", str(bad), "--out", "runs/o", "--status"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "q_agg = 'x/../../../../e'" in err
    good = tmp_path / "good.toml"
    good.write_text('profile = "smoke"\n' + ONE)
    before.append(good)
    for argv in (["sweep", str(good), "--out", "afile"],
                 ["sweep", str(good), "--out", "afile", "--status"]):
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2
        assert "argument --out: afile is a file, not a directory" in capsys.readouterr().err
    assert sorted(tmp_path.rglob("*")) == sorted(before)
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    (out / "WindowInstall-A-v0").symlink_to(elsewhere)
    with pytest.raises(GridError, match="outside --out"):
        Sweep(load_grid(good), out)


def test_a_binary_or_oversize_grid_file_is_one_line(tmp_path):
    from window_bench.harness.sweep import MAX_GRID_BYTES

    p = tmp_path / "g.toml"
    p.write_bytes(b"\x80\x04garbage" * 10)
    with pytest.raises(GridError, match="not valid TOML .*utf-8"):
        load_grid(p)
    with open(p, "wb") as f:
        f.truncate(MAX_GRID_BYTES + 1)
    with pytest.raises(GridError, match="over the 1,048,576-byte limit"):
        load_grid(p)


def test_status_reads_hand_edited_results_without_traceback(tmp_path):
    """A finished cell whose results.json has ``final_eval`` or ``final`` of the wrong type
    (hand-edited) is reported as a status line, never as a traceback."""
    from window_bench.harness.sweep import _progress_detail, cell_report

    grid_file = tmp_path / "g.toml"
    grid_file.write_text('name = "g"\ntable = 2\nprofile = "smoke"\nM = 4\nseed_set = "dev"\n'
                         '[[train]]\nmethods = ["qcfql"]\nenvs = ["WindowInstall-A-v0"]\n'
                         'seeds = [0]\n')
    grid = load_grid(grid_file)
    cell = grid.cells[0]
    run = cell.path(tmp_path / "runs")
    run.mkdir(parents=True)
    for bad in ({"final_eval": 7}, {"final_eval": {"episodes": 4, "seed_set": "dev"},
                                     "final": "x"}, {"final_eval": [1, 2]}):
        (run / "results.json").write_text(json.dumps(bad))
        report = cell_report(cell, grid, tmp_path / "runs")
        assert isinstance(report["status"], str)
    detail = _progress_detail(cell, {"stage": "offline", "offline_done": "many",
                                     "wall_clock_s": None})
    assert detail.startswith("Stage I, 0 updates")


def test_a_grid_block_may_name_a_preset_whose_overrides_its_own_entries_win(tmp_path):
    from window_bench.harness.methods import get_preset

    g = _grid(tmp_path, GRID + 'preset = "qcfql-as-published"\nagent_config = { policy_ema = 0.5 }\n')
    c = next(c for c in g.cells if c.method == "qcfql")
    assert dict(c.agent_config) == {**get_preset("qcfql-as-published"), "policy_ema": 0.5}
    with pytest.raises(GridError, match=r"train\[0\]\.preset = 'nope': unknown agent preset"):
        _grid(tmp_path, GRID + 'preset = "nope"\n')
