"""Meant actions: the demonstrator's command before its hand's noise, logged beside the
executed action, stored with the demonstrations, and trained on with ``--demo-actions meant``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import window_bench  # noqa: F401
from window_bench.data.steplog import demo_actions
from window_bench.harness.results import DEFAULTS_REVISION
from window_bench.installer.demos import collect_demos, load_demos
from window_bench.installer.operators import HumanlikeInstaller, OperatorProfile
from window_bench.installer.rollout import Rollout

REPO = Path(__file__).resolve().parents[1]
ENV = "WindowInstall-A-v0"


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    root = tmp_path_factory.mktemp("demos")
    collect_demos(ENV, 2, root, seed=1_000_000, progress=False)     # the default operator's
    return root, load_demos(root, ENV)


def test_meant_actions_are_the_command_without_the_hands_noise(demos):
    _, eps = demos
    for ep in eps:
        assert ep.meant_actions is not None and ep.meant_actions.shape == ep.actions.shape
        d = np.abs(ep.actions[:, :6] - ep.meant_actions[:, :6])
        assert d.mean() > 1e-3                      # the hand's noise is not in the label
        np.testing.assert_array_equal(ep.actions[:, 6], ep.meant_actions[:, 6])  # vacuum
        still = np.all(ep.meant_actions[:, :6] == 0, axis=1)
        np.testing.assert_array_equal(ep.actions[still], ep.meant_actions[still])  # pauses


def test_without_noise_meant_is_executed():
    env = gym.make(ENV, obs_mode="flat")
    quiet = OperatorProfile("quiet", motion_noise=0.0)
    log = Rollout(env, HumanlikeInstaller(env, quiet), provenance="demo").run(seed=3)
    env.close()
    np.testing.assert_array_equal(log.actions, log.meant_actions)


def test_policy_steps_mean_what_they_execute():
    env = gym.make(ENV, obs_mode="flat")
    rng = np.random.default_rng(0)

    class Chunker:
        h = 5

        def act(self, obs):
            return rng.uniform(-1, 1, (5, 7)).astype(np.float32)

        meant_action = np.ones(7, np.float32)    # a chunk's steps never take this
    rollout = Rollout(env, Chunker())
    rollout.reset(seed=0)
    for _ in range(12):
        rollout.step()
    rollout.done, rollout.truncated = True, True
    log = rollout.episode_log()
    env.close()
    np.testing.assert_array_equal(log.actions, log.meant_actions)


def test_demo_actions_swaps_the_labels_only(demos):
    _, eps = demos
    meant = demo_actions(eps, "meant")
    for a, b in zip(eps, meant):
        np.testing.assert_array_equal(b.actions, a.meant_actions)
        np.testing.assert_array_equal(b.observations, a.observations)
        np.testing.assert_array_equal(b.rewards, a.rewards)
        assert not np.array_equal(a.actions, b.actions)
    assert demo_actions(eps, "executed") == eps
    with pytest.raises(ValueError, match="--demo-actions 'clean'; allowed: executed, meant"):
        demo_actions(eps, "clean")
    old = [eps[0]]
    old[0] = type(eps[0])(**{**eps[0].__dict__, "meant_actions": None})
    with pytest.raises(ValueError, match="records no meant actions: collect the demonstrations"):
        demo_actions(old, "meant")


def test_bad_meant_actions_are_refused(demos):
    _, eps = demos
    ep = eps[0]
    for bad in (ep.meant_actions[:-1], ep.meant_actions * 3):
        broken = type(ep)(**{**ep.__dict__, "meant_actions": bad})
        with pytest.raises(ValueError, match="EpisodeLog.meant_actions"):
            broken.validate()


def test_run_refuses_meant_on_demos_that_lack_them_before_any_file(tmp_path, demos):
    """Demonstrations recorded before meant actions were logged: one line, nothing written."""
    from window_bench.data.dataset import save_episodes
    from window_bench.installer.demos import demo_dataset_id
    from window_bench.installer.operators import DEFAULT_OPERATOR

    _, eps = demos
    old = [type(e)(**{**e.__dict__, "meant_actions": None}) for e in eps]
    save_episodes(old, demo_dataset_id(ENV, DEFAULT_OPERATOR), env_id=ENV,
                  obs_dim=old[0].observations.shape[1], data_path=tmp_path / "old")
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "window_bench.cli", "run", "--method", "act",
                        "--env", ENV, "--profile", "smoke", "--demos", str(tmp_path / "old"),
                        "--demo-actions", "meant", "--out", str(out)],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "records no meant actions" in r.stderr
    assert not out.exists()
    r = subprocess.run([sys.executable, "-m", "window_bench.cli", "run", "--method", "act",
                        "--demo-actions", "clean", "--out", str(out)],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 2 and "invalid choice: 'clean'" in r.stderr and not out.exists()


def test_a_run_trains_on_what_it_is_told_and_says_so(tmp_path, demos):
    """The learner's D_demo carries the meant labels, the results say so, and the Stage I
    cache keeps the two apart."""
    from window_bench.harness.run import Run

    root, eps = demos
    runs = {}
    for which in ("executed", "meant"):
        run = Run("qcfql-offline", ENV, "smoke", 0, tmp_path / which, demos=root,
                  demo_actions=which, progress=False)
        got = run._demos()[:2]
        want = eps if which == "executed" else demo_actions(eps, "meant")
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a.actions, b.actions)
        runs[which] = run
        run.files.close()
    from window_bench.harness.stage1 import demos_sha256

    assert demos_sha256(runs["executed"]._demos()) != demos_sha256(runs["meant"]._demos())


def test_an_executed_grid_names_its_cells_apart_and_asks_for_it(tmp_path):
    """The default labels are the meant ones; a grid of the executed record (the paper's)
    names its cells apart, as the leaderboard names such a run."""
    from window_bench.harness.leaderboard import run_dest
    from window_bench.harness.sweep import GridError, cell_command, load_grid

    grid = tmp_path / "g.toml"
    grid.write_text('demo_actions = "executed"\nprofile = "smoke"\nM = 2\n[[train]]\n'
                    'methods = ["act"]\nenvs = ["WindowInstall-A-v0"]\nseeds = [0]\n')
    g = load_grid(grid)
    c = g.cells[0]
    assert c.name == "WindowInstall-A-v0/act-executed-smoke-s0"
    argv = cell_command(c, g, tmp_path, resume=False)
    assert argv[argv.index("--demo-actions") + 1] == "executed"
    results = {"env_id": c.env_id, "method": {"name": c.method}, "profile": {"name": c.profile},
               "seed": c.seed, "track": "state", "demo_actions": "executed",
               "defaults": DEFAULTS_REVISION}
    assert run_dest(results, tmp_path) == c.path(tmp_path)
    grid.write_text(grid.read_text().replace('"executed"', '"meant"', 1))
    assert load_grid(grid).cells[0].name == "WindowInstall-A-v0/act-smoke-s0"
    grid.write_text(grid.read_text().replace('"meant"', '"clean"', 1))
    with pytest.raises(GridError, match="demo_actions = 'clean'; allowed: executed, meant"):
        load_grid(grid)


def test_labels_other_than_the_revisions_are_their_own_rows_in_the_tables():
    from window_bench.harness.tables import _overrides

    assert _overrides({"demo_actions": "meant"}) == (("demo_actions", '"meant"'),)   # rev. 1
    assert _overrides({"demo_actions": "executed"}) == _overrides({}) == ()
    now = {"defaults": DEFAULTS_REVISION}
    assert _overrides({**now, "demo_actions": "executed"}) == (("demo_actions", '"executed"'),)
    assert _overrides({**now, "demo_actions": "meant"}) == _overrides(now) == ()


def test_meant_actions_survive_the_dataset_and_old_datasets_load_without(tmp_path, demos):
    from window_bench.data.dataset import load_episodes, save_episodes

    _, eps = demos
    old = type(eps[0])(**{**eps[0].__dict__, "meant_actions": None})
    for name, logs in (("wb/new-v0", eps), ("wb/old-v0", [old])):
        save_episodes(logs, name, env_id=ENV, obs_dim=old.observations.shape[1],
                      data_path=tmp_path)
        back = load_episodes(name, data_path=tmp_path)
        for a, b in zip(logs, back):
            if a.meant_actions is None:
                assert b.meant_actions is None
            else:
                np.testing.assert_array_equal(a.meant_actions, b.meant_actions)


def test_a_dataset_mixing_logs_with_and_without_meant_actions_stores_none(tmp_path, demos):
    """A collection resumed across the field's introduction: one set of info keys."""
    from window_bench.data.dataset import load_episodes, save_episodes

    _, eps = demos
    mixed = [eps[0], type(eps[1])(**{**eps[1].__dict__, "meant_actions": None})]
    save_episodes(mixed, "wb/mixed-v0", env_id=ENV, obs_dim=eps[0].observations.shape[1],
                  data_path=tmp_path)
    back = load_episodes("wb/mixed-v0", data_path=tmp_path)
    assert [b.meant_actions for b in back] == [None, None]
    np.testing.assert_array_equal(back[0].actions, eps[0].actions)
