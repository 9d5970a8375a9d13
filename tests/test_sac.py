"""SB3 SAC baseline (baselines.sac): demo pre-fill, episode ends, checkpoints, resume.

One short ``learn`` (90 steps, TimeLimit 30 so that online episodes get truncated,
learning_starts 20 and batch 32 to keep it fast) on WindowInstall-A-v0 with flat
observations is shared by the tests of this file.
"""

import json
import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch

from baselines.sac import (CHECKPOINT_FILE, SACPolicy, demo_transitions, load_sac, make_sac,
                           save_sac, train_sac)
from window_bench.installer.scripted import ScriptedInstaller
from window_bench.data.steplog import EpisodeLog

torch.set_num_threads(1)
STEPS, EVERY, LEARNING_STARTS, LIMIT = 90, 30, 20, 30


def make_env():
    return gym.make("WindowInstall-A-v0", obs_mode="flat", max_episode_steps=LIMIT)


def scripted_demo(seed, max_steps=None):
    """A scripted episode as a demo log; cut at ``max_steps`` it ends truncated."""
    env = gym.make("WindowInstall-A-v0", obs_mode="flat")
    inst = ScriptedInstaller(env.unwrapped, seed=seed)
    obs, _ = env.reset(seed=seed)
    inst.reset(seed=seed)
    O, A, R = [obs], [], []
    terminated = truncated = False
    while not (terminated or truncated):
        a = inst.act(obs)
        obs, r, terminated, truncated, _ = env.step(a)
        O.append(obs), A.append(a), R.append(r)
        if max_steps is not None and len(A) >= max_steps and not terminated:
            truncated = True
    env.close()
    T = len(A)
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    (term if terminated else trunc)[-1] = True
    return EpisodeLog(observations=np.array(O), actions=np.array(A),
                      rewards=np.array(R, np.float32), terminated=term, truncated=trunc,
                      provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=seed,
                      env_id="WindowInstall-A-v0", seed=seed)


@pytest.fixture(scope="module")
def demos():
    eps = [scripted_demo(0), scripted_demo(1, max_steps=25)]
    assert eps[0].terminated[-1] and eps[1].truncated[-1]
    return eps


@pytest.fixture(scope="module")
def trained(demos):
    """A model pre-filled with the demos and trained for STEPS steps, with the callback's
    observations at every checkpoint."""
    env = make_env()
    model = make_sac(env, demos, seed=0, total_steps=STEPS, learning_starts=LEARNING_STARTS,
                     batch_size=32)
    seen = []

    def on_checkpoint(k):
        seen.append({"k": k, "num_timesteps": model.num_timesteps,
                     "stored": model.replay_buffer.size(), "updates": model._n_updates})

    train_sac(model, STEPS, EVERY, on_checkpoint)
    yield model, seen
    env.close()


def test_buffer_holds_every_demo_transition_after_the_budget(demos, trained):
    model, _ = trained
    rb = model.replay_buffer
    n = demo_transitions(demos)
    assert n == sum(ep.T for ep in demos) and model.n_demo_transitions == n
    assert rb.buffer_size == n + STEPS and rb.size() == n + STEPS  # full, never wrapped
    obs = np.concatenate([ep.observations[:-1] for ep in demos])
    nxt = np.concatenate([ep.observations[1:] for ep in demos])
    np.testing.assert_array_equal(rb.observations[:n, 0], obs)
    np.testing.assert_array_equal(rb.next_observations[:n, 0], nxt)
    np.testing.assert_array_equal(rb.actions[:n, 0], np.concatenate([ep.actions for ep in demos]))
    np.testing.assert_array_equal(rb.rewards[:n, 0], np.concatenate([ep.rewards for ep in demos]))


def test_timeouts_are_not_terminal(demos, trained):
    model, _ = trained
    rb = model.replay_buffer
    n = demo_transitions(demos)
    term = np.concatenate([ep.terminated for ep in demos])
    trunc = np.concatenate([ep.truncated for ep in demos])
    np.testing.assert_array_equal(rb.dones[:n, 0], term | trunc)
    np.testing.assert_array_equal(rb.timeouts[:n, 0], trunc)
    # Online: TimeLimit 30 over 90 steps = 3 truncations, no acceptance with a fresh policy.
    online_dones, online_timeouts = rb.dones[n:, 0], rb.timeouts[n:, 0]
    assert online_dones.sum() == STEPS // LIMIT
    np.testing.assert_array_equal(online_dones, online_timeouts)
    np.testing.assert_array_equal(np.flatnonzero(online_dones) + 1,
                                  np.arange(LIMIT, STEPS + 1, LIMIT))
    # What SB3 trains on: done * (1 - timeout) - only the accepted demo step is terminal.
    samples = rb._get_samples(np.arange(rb.size()))
    assert np.flatnonzero(samples.dones.numpy()[:, 0]).tolist() == [demos[0].T - 1]


def test_checkpoint_callback_fires_after_each_steps_update(demos, trained):
    _, seen = trained
    n = demo_transitions(demos)
    assert [s["k"] for s in seen] == [30, 60, 90]
    for s in seen:
        assert s["num_timesteps"] == s["k"]
        assert s["stored"] == n + s["k"]  # step k's transition is stored
        assert s["updates"] == s["k"] - LEARNING_STARTS  # and step k's gradient step done


def test_sac_policy_acts_and_evaluates(trained):
    model, _ = trained
    policy = SACPolicy(model)
    env = make_env()
    obs, _ = env.reset(seed=123)
    policy.reset(seed=123)
    a = policy.act(obs)
    assert policy.h == 1 and a.shape == (1, 7) and a.dtype == np.float32
    np.testing.assert_array_equal(a, policy.act(obs))  # deterministic by default
    assert policy.act(np.stack([obs, obs, obs])).shape == (3, 1, 7)
    with pytest.raises(ValueError, match="obs has shape"):
        policy.act(obs[:10])
    copy = SACPolicy.from_state_dict(pickle.loads(pickle.dumps(policy.state_dict())))
    batch = np.stack([obs, 2 * obs])
    np.testing.assert_array_equal(copy.act(batch), policy.act(batch))
    steps, done = 0, False
    while not done:  # one autonomous evaluation episode
        obs, _, terminated, truncated, _ = env.step(policy.act(obs)[0])
        done, steps = terminated or truncated, steps + 1
    env.close()
    assert steps == LIMIT


def test_save_load_round_trip_and_resume(demos, trained, tmp_path):
    model, _ = trained
    save_sac(model, tmp_path)
    meta = json.loads((tmp_path / CHECKPOINT_FILE).read_text())
    assert meta["num_timesteps"] == STEPS and meta["provenance"]["git_commit"]
    env = make_env()
    loaded = load_sac(tmp_path, env)
    assert loaded.num_timesteps == STEPS and loaded.n_demo_transitions == model.n_demo_transitions
    for key, value in model.policy.state_dict().items():
        assert torch.equal(value, loaded.policy.state_dict()[key]), key
    for field in ("observations", "next_observations", "actions", "rewards", "dones",
                  "timeouts"):
        np.testing.assert_array_equal(getattr(model.replay_buffer, field),
                                      getattr(loaded.replay_buffer, field))
    obs = demos[0].observations[:5]
    np.testing.assert_array_equal(SACPolicy(model).act(obs), SACPolicy(loaded).act(obs))

    # The budget is spent: a resumed train_sac has nothing left to do.
    seen = []
    train_sac(loaded, STEPS, EVERY, seen.append)
    assert seen == [] and loaded.num_timesteps == STEPS
    env.close()


def test_resume_mid_budget_continues_the_checkpoints(demos, tmp_path):
    env = make_env()
    model = make_sac(env, demos, seed=1, total_steps=60, learning_starts=10, batch_size=32)
    saved = []

    def on_checkpoint(k):
        saved.append(k)
        save_sac(model, tmp_path)

    train_sac(model, 30, 15, on_checkpoint)  # the run is "killed" after step 30
    assert saved == [15, 30]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([
        CHECKPOINT_FILE, "model_30.zip", "replay_30.pkl"])  # older pair removed
    resumed = load_sac(tmp_path, env)
    seen = []
    train_sac(resumed, 60, 15, lambda k: seen.append((k, resumed.replay_buffer.size())))
    n = demo_transitions(demos)
    assert seen == [(45, n + 45), (60, n + 60)]
    np.testing.assert_array_equal(resumed.replay_buffer.observations[:n, 0],
                                  np.concatenate([ep.observations[:-1] for ep in demos]))
    env.close()


def test_make_sac_refuses_settings_that_lose_demos_or_timeouts(demos):
    env = make_env()
    n = demo_transitions(demos)
    with pytest.raises(ValueError, match="buffer_size"):
        make_sac(env, demos, seed=0, total_steps=100, buffer_size=n + 99)
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        make_sac(env, demos, seed=0, total_steps=100, optimize_memory_usage=True)
    with pytest.raises(ValueError, match="handle_timeout_termination"):
        make_sac(env, demos, seed=0, total_steps=100,
                 replay_buffer_kwargs={"handle_timeout_termination": False})
    with pytest.raises(ValueError, match="no demos"):
        make_sac(env, [], seed=0, total_steps=100)
    with pytest.raises(ValueError, match="total_steps"):
        make_sac(env, demos, seed=0, total_steps=0)
    model = make_sac(env, demos, seed=0, total_steps=100)
    assert model.learning_starts == 100 and model.batch_size == 256  # SB3 defaults kept
    assert model.replay_buffer.buffer_size == n + 100 and model.replay_buffer.pos == n
    env.close()
