"""SB3 SAC baseline (baselines.sac): demo pre-fill, episode ends, SB3's own train() driven
from outside, plain resume state and the acting policy.

One agent (TimeLimit 30 so that its online episodes get truncated, 3 episodes of 30 steps
from the harness's Rollout, a learner call after each step) on WindowInstall-A-v0 with
flat observations is shared by the tests of this file.
"""

import gymnasium as gym
import numpy as np
import pytest
import torch

from baselines.sac import SACAgent, SACPolicy, demo_transitions, make_sac, spaces_env
from window_bench.data.steplog import EpisodeLog
from window_bench.harness.agent import check_plain
from window_bench.harness.run import AgentPolicy
from window_bench.installer.rollout import Rollout
from window_bench.installer.scripted import ScriptedInstaller

torch.set_num_threads(1)
EPISODES, LIMIT = 3, 30
STEPS = EPISODES * LIMIT

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
    """An agent pre-filled with the demos that collected EPISODES episodes through the
    harness's Rollout and took one SB3 gradient step after each environment step."""
    env = make_env()
    agent = SACAgent(make_sac(spaces_env(env.observation_space.shape[0]), demos, seed=0,
                              total_steps=STEPS, batch_size=32))
    rollout = Rollout(env, AgentPolicy(agent, deterministic=False))
    metrics = []
    for ep in range(EPISODES):
        rollout.reset(seed=ep, episode_id=ep)
        while not rollout.done:
            rollout.step()
            metrics.append(agent.learn(None))
        agent.add_episode(rollout.episode_log())
    yield agent, metrics
    env.close()


def test_buffer_holds_every_demo_transition_after_the_budget(demos, trained):
    agent, _ = trained
    rb = agent.model.replay_buffer
    n = demo_transitions(demos)
    assert n == sum(ep.T for ep in demos) and agent.model.n_demo_transitions == n
    assert rb.buffer_size == n + STEPS and rb.size() == n + STEPS  # full, never wrapped
    assert agent.model.num_timesteps == STEPS
    obs = np.concatenate([ep.observations[:-1] for ep in demos])
    nxt = np.concatenate([ep.observations[1:] for ep in demos])
    np.testing.assert_array_equal(rb.observations[:n, 0], obs)
    np.testing.assert_array_equal(rb.next_observations[:n, 0], nxt)
    np.testing.assert_array_equal(rb.actions[:n, 0], np.concatenate([ep.actions for ep in demos]))
    np.testing.assert_array_equal(rb.rewards[:n, 0], np.concatenate([ep.rewards for ep in demos]))


def test_timeouts_are_not_terminal(demos, trained):
    agent, _ = trained
    rb = agent.model.replay_buffer
    n = demo_transitions(demos)
    term = np.concatenate([ep.terminated for ep in demos])
    trunc = np.concatenate([ep.truncated for ep in demos])
    np.testing.assert_array_equal(rb.dones[:n, 0], term | trunc)
    np.testing.assert_array_equal(rb.timeouts[:n, 0], trunc)
    # Online: TimeLimit 30, three episodes = 3 truncations, no acceptance by a fresh policy.
    online_dones, online_timeouts = rb.dones[n:, 0], rb.timeouts[n:, 0]
    assert online_dones.sum() == EPISODES
    np.testing.assert_array_equal(online_dones, online_timeouts)
    np.testing.assert_array_equal(np.flatnonzero(online_dones) + 1,
                                  np.arange(LIMIT, STEPS + 1, LIMIT))
    # What SB3 trains on: done * (1 - timeout) - only the accepted demo step is terminal.
    samples = rb._get_samples(np.arange(rb.size()))
    assert np.flatnonzero(samples.dones.numpy()[:, 0]).tolist() == [demos[0].T - 1]


def test_each_learner_call_is_one_sb3_gradient_step(trained):
    agent, metrics = trained
    assert agent.model._n_updates == STEPS
    assert all(n == 1 for _, n in metrics)
    first, last = metrics[0][0], metrics[-1][0]
    assert {"actor_loss", "critic_loss", "ent_coef", "ent_coef_loss"} <= set(first)
    assert first["n_updates"] == 1 and last["n_updates"] == STEPS
    assert last["ent_coef"] < first["ent_coef"] <= 1.0   # SB3's entropy tuning is running


def test_sac_policy_acts_and_evaluates(trained):
    agent, _ = trained
    policy = SACPolicy(agent.model)
    env = make_env()
    obs, _ = env.reset(seed=123)
    policy.reset(seed=123)
    a = policy.act(obs)
    assert policy.h == 1 and a.shape == (1, 7) and a.dtype == np.float32
    np.testing.assert_array_equal(a, policy.act(obs))  # deterministic by default
    assert policy.act(np.stack([obs, obs, obs])).shape == (3, 1, 7)
    with pytest.raises(ValueError, match="obs has shape"):
        policy.act(obs[:10])
    state = agent.policy_state_dict()
    check_plain(state)
    assert set(state) == {"obs_dim", "action_low", "action_high", "architecture",
                          "activation", "actor"}   # no critics, optimisers or buffer
    copy = SACAgent.from_policy_state_dict(state)
    batch = np.stack([obs, 2 * obs])
    np.testing.assert_array_equal(copy.act(batch), policy.act(batch))
    steps, done = 0, False
    while not done:  # one autonomous evaluation episode
        obs, _, terminated, truncated, _ = env.step(policy.act(obs)[0])
        done, steps = terminated or truncated, steps + 1
    env.close()
    assert steps == LIMIT


def test_state_round_trip_resumes_training_exactly(demos, trained):
    agent, _ = trained
    state = agent.state_dict()
    check_plain(state)
    assert state["replay"]["observations"].shape[0] == demo_transitions(demos) + STEPS
    resumed = SACAgent.from_state_dict(state)
    assert resumed.model.num_timesteps == STEPS and resumed.model._n_updates == STEPS
    for key, value in agent.model.policy.state_dict().items():
        assert torch.equal(value, resumed.model.policy.state_dict()[key]), key
    for field in ("observations", "next_observations", "actions", "rewards", "dones",
                  "timeouts"):
        np.testing.assert_array_equal(getattr(agent.model.replay_buffer, field),
                                      getattr(resumed.model.replay_buffer, field))
    # SB3 samples with the global RNGs (the harness saves them): same seeds, same step.
    after = []
    for a in (agent, resumed):
        torch.manual_seed(3)
        np.random.seed(3)
        after.append(a.learn(None)[0])
    assert after[0] == after[1]
    for key, value in agent.model.policy.state_dict().items():
        assert torch.equal(value, resumed.model.policy.state_dict()[key]), key


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
    assert model.batch_size == 256 and model.gamma == 0.99  # SB3 defaults kept
    assert model.replay_buffer.buffer_size == n + 100 and model.replay_buffer.pos == n
    env.close()
