"""Why suction was lost: the env's ``suction_loss`` info ("commanded" / "grip_break") and the
evaluation rows and summaries that count commanded releases vs grip breaks."""

import numpy as np
import pytest
import torch

import window_bench.envs.env as E
from baselines.hilserl import HILSERLAgent, HILSERLConfig
from window_bench.harness.run import Evaluator, summarize_eval

A = "WindowInstall-A-v0"
HOLD = np.array([0, 0, 0, 0, 0, 0, 1.0], np.float32)   # zero motion, vacuum on
OFF = np.zeros(7, np.float32)                           # zero motion, vacuum off


def test_commanded_release_is_reported(make_env):
    env = make_env(A, info_strings=True)
    _, info = env.reset(seed=0)             # A: latched at reset
    assert info["suction_loss"] == "" and info["suction_releases"] == 0
    _, _, _, _, info = env.step(HOLD)
    assert info["suction_loss"] == "" and info["suction_engaged"]
    _, _, _, _, info = env.step(OFF)
    assert info["suction_loss"] == "commanded" and not info["suction_engaged"]
    assert info["suction_releases"] == 1 and info["suction_failures"] == 0
    _, _, _, _, info = env.step(OFF)        # nothing held, nothing lost
    assert info["suction_loss"] == "" and info["suction_releases"] == 1


def test_grip_break_is_reported(make_env, monkeypatch):
    env = make_env(A, info_strings=True)
    env.reset(seed=0)
    monkeypatch.setattr(E, "VACUUM_HOLD_FORCE", 1.0)     # below the panel's weight
    monkeypatch.setattr(E, "VACUUM_HOLD_MOMENT", 0.01)
    _, _, _, _, info = env.step(HOLD)
    assert info["suction_loss"] == "grip_break" and info["suction_failed"]
    assert info["suction_failures"] == 1 and info["suction_releases"] == 0


def _row(mode, releases=0, breaks=0, success=False):
    return {"seed": 0, "success": success, "cycle_time_s": 10.0, "suction_acquired": True,
            "insertion_entered": success, "failure_mode": mode,
            "commanded_releases": releases, "grip_breaks": breaks}


def test_summary_counts_releases_and_breaks():
    rows = [_row("suction_lost", releases=1), _row("suction_lost", releases=2),
            _row("suction_lost", breaks=1), _row("suction_lost", releases=1, breaks=1),
            _row("approach_failed", releases=1), _row("", success=True)]
    s = summarize_eval(rows)
    assert s["episodes_with_commanded_release"] == 4
    assert s["episodes_with_grip_break"] == 2
    assert s["suction_lost_by"] == {"grip_break": 2, "commanded": 2}
    old = summarize_eval([{k: v for k, v in _row("suction_lost").items()
                           if k not in ("commanded_releases", "grip_breaks")}])
    assert old["suction_lost_by"] == {"grip_break": 0, "commanded": 0}


def _vacuum_policy(prefer: str) -> dict:
    """A small HIL-SERL policy whose grasp critic always prefers ``prefer`` (release/hold:
    the commands release and engage of its three, release, stay, engage)."""
    agent = HILSERLAgent(52, config=HILSERLConfig(hidden=(16,), batch_size=32))
    with torch.no_grad():
        last = [m for m in agent.grasp_critic.modules() if isinstance(m, torch.nn.Linear)][-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([1.0, 0.0, 0.0] if prefer == "release" else [0.0, 0.0, 1.0]))
    return agent.policy_state_dict()


def test_evaluation_rows_record_commanded_releases():
    """A policy whose grasp critic prefers 'release' drops the panel on its first step:
    the harness's evaluation row records a commanded release and no grip break."""
    rows = Evaluator(A, 1, 1, 5)(HILSERLAgent, _vacuum_policy("release"))   # dev seed 100,000
    assert rows[0]["commanded_releases"] == 1 and rows[0]["grip_breaks"] == 0
    assert rows[0]["failure_mode"] == "suction_lost"
    assert summarize_eval(rows)["suction_lost_by"] == {"grip_break": 0, "commanded": 1}


def test_pooled_evaluation_equals_in_process_and_shows_progress(capsys):
    """Worker processes take one episode at a time (a progress bar over the episodes); the
    rows equal the in-process evaluation's, and a second policy through the same pool is
    evaluated as itself, not as the policy its workers built for the first call."""
    release, hold = _vacuum_policy("release"), _vacuum_policy("hold")
    alone = {p: Evaluator(A, 4, 1, 6)(HILSERLAgent, policy)
             for p, policy in (("release", release), ("hold", hold))}
    assert [r["commanded_releases"] for r in alone["release"]] == [1, 1, 1, 1]
    assert [r["commanded_releases"] for r in alone["hold"]] == [0, 0, 0, 0]
    pooled = Evaluator(A, 4, 2, 6, progress=True)
    try:
        assert pooled(HILSERLAgent, release) == alone["release"]
        assert pooled(HILSERLAgent, hold) == alone["hold"]
    finally:
        pooled.close()
    # A bar over the 4 episodes was shown. Which counts it printed depends on timing (tqdm
    # redraws at most every 0.1 s and a leave=False bar is erased on close), so not "4/4".
    err = capsys.readouterr().err
    assert "evaluate (dev seeds)" in err and "/4 [" in err
