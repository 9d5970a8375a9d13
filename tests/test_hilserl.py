"""HIL-SERL / RLPD learner (baselines.hilserl): acting, losses, targets, checkpoints, batches.

Networks are shrunk (32x32, batch 32) to keep the file fast; the algorithm is the same at
every size. One scripted demonstration on WindowInstall-A-v0 (flat observations) serves as
real data.
"""

import dataclasses
import io

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from baselines.hilserl import (BATCH_KEYS, ENGAGE, HILSERL_OWN, RELEASE, RLPD_CONFIG, STAY,
                               VACUUM_COMMANDS, VACUUM_OBS_INDEX, VACUUM_OFF, VACUUM_ON,
                               HILSERLAgent, HILSERLConfig, grasp_command_labels,
                               hilserl_buffers_for, obs_normalizer, symmetric_sampler,
                               vacuum_values)
from window_bench.data.chunks import chunk_transitions
from window_bench.harness.agent import takeover_segments
from window_bench.installer.scripted import ScriptedInstaller
from window_bench.data.steplog import EpisodeLog

torch.set_num_threads(1)
OBS_DIM = 52
GAMMA = 0.99
SMALL = HILSERLConfig(hidden=(32, 32), batch_size=32)


def rollout(env, act, seed, provenance, max_steps=None, episode_id=0):
    """Run ``act(obs) -> (7,)`` for one episode and log it as an EpisodeLog."""
    obs, _ = env.reset(seed=seed)
    O, A, R = [obs], [], []
    terminated = truncated = False
    while not (terminated or truncated):
        a = np.asarray(act(obs), np.float32).reshape(7)
        obs, r, terminated, truncated, _ = env.step(a)
        O.append(obs), A.append(a), R.append(r)
        if max_steps is not None and len(A) >= max_steps:
            truncated = truncated or not terminated
    T = len(A)
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    (term if terminated else trunc)[-1] = True
    return EpisodeLog(observations=np.array(O), actions=np.array(A),
                      rewards=np.array(R, np.float32), terminated=term, truncated=trunc,
                      provenance=[provenance] * T,
                      takeover_kind=[""] * T, episode_id=episode_id,
                      env_id="WindowInstall-A-v0", seed=seed)


@pytest.fixture(scope="module")
def env():
    e = gym.make("WindowInstall-A-v0", obs_mode="flat", max_episode_steps=40)
    yield e
    e.close()


@pytest.fixture(scope="module")
def demo():
    """One complete scripted episode (about 105 steps, terminated by acceptance)."""
    e = gym.make("WindowInstall-A-v0", obs_mode="flat")
    inst = ScriptedInstaller(e.unwrapped, seed=0)
    inst.reset(seed=0)
    ep = rollout(e, inst.act, seed=0, provenance="demo", episode_id=1)
    e.close()
    assert ep.terminated[-1] and ep.T >= 100
    return ep


def to_td(chunks, keys=(*BATCH_KEYS, "valid")):
    n = len(chunks["obs"])
    return TensorDict({k: torch.as_tensor(np.asarray(chunks[k])) for k in keys},
                      batch_size=[n])


@pytest.fixture(scope="module")
def demo_td(demo):
    return to_td(chunk_transitions(demo, 1, GAMMA))


def params(module):
    return [p.detach().clone() for p in module.parameters()]


# --------------------------------------------------------------------------- config
@pytest.mark.parametrize("kwargs, match", [
    ({"num_critics": 0}, "num_critics"),
    ({"num_min": 3}, "num_min"),
    ({"batch_size": 33}, "batch_size"),
    ({"critic_actor_ratio": 0}, "critic_actor_ratio"),
    ({"activation": "gelu"}, "activation"),
    ({"hidden": ()}, "hidden"),
    ({"tau": 0.0}, "tau"),
    ({"gamma": 1.5}, "gamma"),
    ({"init_temperature": 0.0}, "init_temperature"),
    ({"log_std_min": 2.0}, "log_std_min"),
    ({"vacuum_head": "bernoulli"}, "vacuum_head"),
    ({"vacuum_epsilon": 1.5}, "vacuum_epsilon"),
    ({"grasp_penalty": 0.02}, "grasp_penalty"),
    ({"grasp_penalty": float("nan")}, "grasp_penalty"),
    ({"obs_clip": 0.0}, "obs_clip"),
    ({"offline_steps": -1}, "offline_steps"),
    ({"offline_steps": 1.5}, "offline_steps"),
    ({"offline_steps": True}, "offline_steps"),
    ({"suction_loss_terminal": 1}, "suction_loss_terminal"),
    ({"target_range": [1.0, 0.0]}, "target_range"),
    ({"target_range": [0.0]}, "target_range"),
    ({"target_range": [0.0, float("inf")]}, "target_range"),
    ({"target_range": 1.0}, "target_range"),
    ({"fine_pose_mm": -1.0}, r"HILSERLConfig.fine_pose_mm = -1.0 .* \[0.0, 1000.0\]"),
    ({"fine_pose_deg": 0.0}, r"HILSERLConfig.fine_pose_deg = 0.0 .* \(0.0, 90.0\]"),
])
def test_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HILSERLConfig(**kwargs)


def test_defaults_are_hilserl_and_rlpd_preset():
    c = HILSERLConfig()
    assert (c.hidden, c.num_critics, c.num_min, c.init_temperature, c.backup_entropy,
            c.critic_actor_ratio, c.batch_size, c.activation) == (
        (256, 256), 2, 2, 0.01, False, 2, 256, "tanh")
    assert HILSERLAgent(OBS_DIM, config=SMALL).target_entropy == -3.5
    assert (RLPD_CONFIG.num_critics, RLPD_CONFIG.num_min, RLPD_CONFIG.backup_entropy) == (
        10, 2, True)


# --------------------------------------------------------------------------- acting
def test_act_shapes_range_and_determinism(demo):
    mean, std = obs_normalizer([demo])
    agent = HILSERLAgent(OBS_DIM, config=SMALL, seed=3, obs_mean=mean, obs_std=std)
    one, batch = demo.observations[0], demo.observations[:5]
    a1 = agent.act(one)
    assert a1.shape == (1, 7) and a1.dtype == np.float32
    ab = agent.act(batch)
    assert ab.shape == (5, 1, 7)
    assert np.all(np.abs(ab) <= 1.0) and np.all(np.abs(a1) <= 1.0)
    d1, d2 = agent.act(batch, deterministic=True), agent.act(batch, deterministic=True)
    np.testing.assert_array_equal(d1, d2)
    s1, s2 = agent.act(batch), agent.act(batch)
    assert not np.allclose(s1, s2)  # fresh noise on every call
    assert not np.allclose(s1, d1)
    # Same seed, same sequence of samples.
    twin = HILSERLAgent(OBS_DIM, config=SMALL, seed=3, obs_mean=mean, obs_std=std)
    np.testing.assert_array_equal(twin.act(one), a1)
    with pytest.raises(ValueError, match="obs has shape"):
        agent.act(np.zeros(OBS_DIM + 1))


def test_fine_pose_features_reach_actor_and_critics(demo, demo_td):
    from window_bench.installer.supervisor import FLAT_SLICES
    mean, std = obs_normalizer([demo])
    cfg = dataclasses.replace(SMALL, fine_pose_mm=10.0, fine_pose_deg=2.0)
    agent = HILSERLAgent(OBS_DIM, config=cfg, seed=0, obs_mean=mean, obs_std=std)
    obs = np.repeat(demo.observations[-1:].astype(np.float32), 2, axis=0)
    obs[1, FLAT_SLICES["window_pos_rel"].start] += 0.002        # 2 mm sideways
    x = agent._normalize(torch.from_numpy(obs))
    assert x.shape == (2, OBS_DIM + 6)
    assert float((x[1, OBS_DIM] - x[0, OBS_DIM]).abs()) > 0.1   # tanh(0.2)-scale step
    assert not np.array_equal(agent.act(obs, deterministic=True)[0],
                              agent.act(obs, deterministic=True)[1])
    agent.update(demo_td[:8])                                  # trains on the widened input
    twin = HILSERLAgent.from_state_dict(agent.state_dict())
    np.testing.assert_array_equal(twin.act(obs, deterministic=True),
                                  agent.act(obs, deterministic=True))
    with pytest.raises(ValueError, match="fine_pose_mm = 10.0 needs the flat state"):
        HILSERLAgent(20, config=cfg)


def test_agent_rejects_bad_normalization():
    with pytest.raises(ValueError, match="obs_std"):
        HILSERLAgent(OBS_DIM, config=SMALL, obs_mean=np.zeros(OBS_DIM),
                     obs_std=-np.ones(OBS_DIM))
    with pytest.raises(ValueError, match="together"):
        HILSERLAgent(OBS_DIM, config=SMALL, obs_mean=np.zeros(OBS_DIM))
    with pytest.raises(ValueError, match="shape"):
        HILSERLAgent(OBS_DIM, config=SMALL, obs_mean=np.zeros(3), obs_std=np.ones(3))


# --------------------------------------------------------------------------- losses
def test_update_reduces_critic_loss(demo, demo_td):
    mean, std = obs_normalizer([demo])
    cfg = HILSERLConfig(hidden=(32, 32), batch_size=32, critic_actor_ratio=1)
    agent = HILSERLAgent(OBS_DIM, config=cfg, seed=0, obs_mean=mean, obs_std=std)
    batch = demo_td[:64]
    losses = [agent.update(batch)["critic_loss"] for _ in range(60)]
    assert np.all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])
    assert agent.critic_steps == 60 and agent.actor_steps == 60


def test_update_counts_critic_actor_ratio(demo_td):
    agent = HILSERLAgent(OBS_DIM, config=SMALL)  # ratio 2
    drawn = []

    def sample():
        drawn.append(1)
        return demo_td[:32]

    info = agent.update(sample)
    assert len(drawn) == 2 and agent.critic_steps == 2 and agent.actor_steps == 1
    assert set(info) >= {"critic_loss", "actor_loss", "entropy", "temperature"}
    agent.update(demo_td[:64])  # one TensorDict, split in two minibatches
    assert agent.critic_steps == 4 and agent.actor_steps == 2
    with pytest.raises(ValueError, match="cannot be split"):
        agent.update(demo_td[:33])


def test_update_rejects_bad_batches(demo_td):
    agent = HILSERLAgent(OBS_DIM, config=SMALL)
    bad = demo_td[:32].clone()
    bad["discount"] = torch.full((32,), 0.9)
    with pytest.raises(ValueError, match="discount"):
        agent.update(torch.cat([bad, bad]))
    wide = TensorDict({**{k: demo_td[:32][k] for k in BATCH_KEYS},
                       "actions": torch.zeros(32, 2, 7)}, batch_size=[32])
    with pytest.raises(ValueError, match="h = 1"):
        agent.update(torch.cat([wide, wide]))
    with pytest.raises(ValueError, match="lacks keys"):
        agent.update(torch.cat([demo_td[:32], demo_td[:32]]).exclude("reward"))


@pytest.mark.parametrize("target, direction", [(-50.0, -1), (50.0, +1)])
def test_temperature_moves_toward_target_entropy(demo_td, target, direction):
    """Entropy above the target lowers alpha; below it raises alpha (the entropy of a
    7-D action in [-1, 1]^7 lies below 7 ln 2 ~ 4.9, far from both targets)."""
    cfg = HILSERLConfig(hidden=(32, 32), batch_size=32, target_entropy=target)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    alphas = [agent.temperature]
    for _ in range(5):
        alphas.append(agent.update(demo_td[:64])["temperature"])
    steps = np.sign(np.diff(alphas))
    assert np.all(steps == direction), alphas


def _constant_target_critics(agent, values, grasp=None):
    """Make every target member (and, with ``grasp``, the target grasp critic) output a
    constant: zero last-layer weights, bias = value."""
    nets = list(zip(agent.target_critic.members, values))
    if grasp is not None:
        nets.append((agent.target_grasp_critic, grasp))
    with torch.no_grad():
        for net, v in nets:
            last = [m for m in net.modules() if isinstance(m, torch.nn.Linear)][-1]
            last.weight.zero_()
            last.bias.fill_(v)


def _two_rows(reward, terminal):
    return TensorDict({"obs": torch.zeros(2, OBS_DIM), "next_obs": torch.ones(2, OBS_DIM),
                       "actions": torch.zeros(2, 1, 7), "reward": torch.tensor(reward),
                       "discount": torch.full((2,), GAMMA),
                       "terminal": torch.tensor(terminal), "valid": torch.ones(2, dtype=bool)},
                      batch_size=[2])


def test_td_target_terminal_masks_bootstrap():
    cfg = HILSERLConfig(hidden=(8,), batch_size=2, num_critics=3, num_min=3)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    _constant_target_critics(agent, [2.0, -1.0, 0.5])
    y = agent.td_target(_two_rows([0.5, 1.0], [False, True]))
    # min over the members = -1; no entropy backup (HIL-SERL)
    torch.testing.assert_close(y, torch.tensor([0.5 + GAMMA * -1.0, 1.0]))


def test_td_target_entropy_backup_uses_next_action_log_prob():
    cfg = HILSERLConfig(hidden=(8,), batch_size=2, num_critics=2, num_min=2,
                        backup_entropy=True, init_temperature=0.3)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    _constant_target_critics(agent, [2.0, 1.5])
    state = agent._update_rng.get_state()
    replay_rng = torch.Generator()
    replay_rng.set_state(state)
    with torch.no_grad():
        _, log_prob = agent.actor.sample(torch.ones(2, OBS_DIM), replay_rng)
    y = agent.td_target(_two_rows([0.0, 1.0], [False, True]))
    expected = torch.tensor([GAMMA * (1.5 - 0.3 * float(log_prob[0])), 1.0])
    torch.testing.assert_close(y, expected)


def test_td_target_of_real_demo_chunks_never_exceeds_one(demo_td):
    """The sparse acceptance reward (1 once, on the terminating step) through the harness's
    chunking: with target critics valued at their ceiling 1, every target is <= 1, exactly
    1 on the accepted step and gamma elsewhere (no reward scaling, no double reward, the
    bootstrap masked at termination). Q above 1 after training is therefore the critics'
    extrapolation, not the target's arithmetic (docs/baselines.md, issue 15)."""
    agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(8,), batch_size=2))
    _constant_target_critics(agent, [1.0, 1.0])
    y = agent.td_target(demo_td)
    terminal = demo_td["terminal"].reshape(-1)
    assert int(terminal.sum()) == 1 and bool(terminal[-1])
    assert float(y.max()) <= 1.0 + 1e-6
    torch.testing.assert_close(y[terminal], torch.ones(1))
    torch.testing.assert_close(y[~terminal], torch.full((int((~terminal).sum()),), GAMMA))


def test_suction_loss_terminal_ends_the_targets_where_the_panel_is_lost(env):
    """Row 0 loses the panel (vacuum flag 1 -> 0), row 1 keeps it: with the option the lost
    row's critic and grasp targets are the reward alone, without it both bootstrap."""
    obs, _ = env.reset(seed=0)       # setting A starts with the panel held
    assert obs.shape == (OBS_DIM,) and obs[VACUUM_OBS_INDEX] == 1.0
    batch = _two_rows([0.0, 0.0], [False, False])
    batch["obs"][:, VACUUM_OBS_INDEX] = 1.0
    batch["actions"][:, 0, 6] = VACUUM_ON      # kept on by command (stay), lost by the grip
    batch["next_obs"][:, VACUUM_OBS_INDEX] = torch.tensor([0.0, 1.0])
    targets = {}
    for flag in (False, True):
        agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(8,), batch_size=2,
                                                           suction_loss_terminal=flag))
        _constant_target_critics(agent, [2.0, 2.0], grasp=3.0)
        targets[flag] = (agent.td_target(batch), agent.grasp_td_target(batch))
    torch.testing.assert_close(targets[False][0], torch.full((2,), GAMMA * 2.0))
    torch.testing.assert_close(targets[True][0], torch.tensor([0.0, GAMMA * 2.0]))
    torch.testing.assert_close(targets[False][1], torch.full((2,), GAMMA * 3.0))
    torch.testing.assert_close(targets[True][1], torch.tensor([0.0, GAMMA * 3.0]))
    with pytest.raises(ValueError, match="suction_loss_terminal"):
        HILSERLAgent(OBS_DIM + 1, config=HILSERLConfig(suction_loss_terminal=True))


def test_target_range_clips_both_targets_and_survives_a_resume():
    """Targets of r + 0.99 * 2 (critics) and r + 0.99 * 3 (grasp critic) lie above the
    achievable return 1: with ``target_range=[0, 1]`` both are 1, a target of -0.99 is 0,
    and a saved agent comes back with the same range."""
    batch = _two_rows([0.5, 0.0], [False, False])
    targets = {}
    for bounds in (None, [0, 1]):
        agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(8,), batch_size=2,
                                                           num_critics=2, num_min=1,
                                                           target_range=bounds))
        _constant_target_critics(agent, [2.0, 2.0], grasp=3.0)
        targets[bounds is not None] = (agent.td_target(batch), agent.grasp_td_target(batch))
        _constant_target_critics(agent, [-1.0, -1.0])
        low = agent.td_target(_two_rows([0.0, 0.0], [False, False]))
    torch.testing.assert_close(targets[False][0], torch.tensor([0.5 + GAMMA * 2, GAMMA * 2]))
    torch.testing.assert_close(targets[True][0], torch.ones(2))
    torch.testing.assert_close(targets[False][1], torch.tensor([0.5 + GAMMA * 3, GAMMA * 3]))
    torch.testing.assert_close(targets[True][1], torch.ones(2))
    torch.testing.assert_close(low, torch.zeros(2))
    assert agent.config.target_range == (0.0, 1.0)
    restored = HILSERLAgent.from_state_dict(agent.state_dict())
    assert restored.config == agent.config
    restored.load_state_dict(agent.state_dict())


def test_td_target_min_over_random_subset():
    """RLPD: min over 2 of 4 members drawn without replacement: the largest member can
    never be the min, every other member sometimes is."""
    cfg = HILSERLConfig(hidden=(8,), batch_size=2, num_critics=4, num_min=2)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    _constant_target_critics(agent, [1.0, 2.0, 3.0, 4.0])
    batch = _two_rows([0.0, 0.0], [False, False])
    seen = {round(float(agent.td_target(batch)[0]) / GAMMA, 4) for _ in range(200)}
    assert seen == {1.0, 2.0, 3.0}


def test_polyak_target_update(demo_td):
    cfg = HILSERLConfig(hidden=(32, 32), batch_size=32, critic_actor_ratio=1, tau=0.05)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    agent.update(demo_td[:32])  # online and target critics now differ
    before = params(agent.target_critic)
    agent.update(demo_td[32:64])
    after, online = params(agent.target_critic), params(agent.critic)
    assert any(not torch.equal(a, b) for a, b in zip(after, before))
    for b, a, o in zip(before, after, online):
        torch.testing.assert_close(a, 0.95 * b + 0.05 * o, rtol=1e-5, atol=1e-6)


def test_invalid_rows_do_not_train_the_critic(demo_td):
    """Rows with valid False (truncated windows for h > 1) are out of the TD loss."""
    cfg = HILSERLConfig(hidden=(16,), batch_size=32, critic_actor_ratio=1)
    batch = demo_td[:32].clone()
    batch["valid"] = torch.zeros(32, dtype=torch.bool)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    before = params(agent.critic)
    info = agent.update(batch)
    assert info["critic_loss"] == 0.0
    assert all(torch.equal(a, b) for a, b in zip(before, params(agent.critic)))


# --------------------------------------------------------------------------- vacuum head
def _constant_outputs(net, values):
    """Make a network output ``values`` for every input: zero last-layer weights, bias."""
    with torch.no_grad():
        last = [m for m in net.modules() if isinstance(m, torch.nn.Linear)][-1]
        last.weight.zero_()
        last.bias.copy_(torch.as_tensor(values, dtype=torch.float32))


def test_discrete_head_is_the_default_and_splits_the_action():
    """HIL-SERL's hybrid agent: Gaussian actor and critic ensemble over the 6 pose
    dimensions, a grasp critic over {release, stay, engage}; 'gaussian' keeps all 7 in the
    actor."""
    agent = HILSERLAgent(OBS_DIM, config=SMALL)
    assert SMALL.vacuum_head == "discrete" and SMALL.obs_clip == 10.0
    first = lambda net: [m for m in net.modules() if isinstance(m, torch.nn.Linear)][0]  # noqa: E731
    assert first(agent.critic.members[0]).in_features == OBS_DIM + 6
    assert [m for m in agent.actor.modules() if isinstance(m, torch.nn.Linear)][-1].out_features == 12
    assert agent.grasp_critic(torch.zeros(3, OBS_DIM)).shape == (3, len(VACUUM_COMMANDS))
    assert agent.target_entropy == -3.5   # -|A|/2 over the full 7-d action, as HIL-SERL
    g = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(32, 32), batch_size=32,
                                                   vacuum_head="gaussian"))
    assert first(g.critic.members[0]).in_features == OBS_DIM + 7
    assert g.grasp_critic is None and "grasp_critic" not in g.state_dict()
    with pytest.raises(ValueError, match="vacuum_head"):
        g.vacuum_command(np.zeros(OBS_DIM))


def test_held_vacuum_is_hilserl_fixed_gripper(demo, demo_td):
    """vacuum_head='held' (HIL-SERL's fixed-gripper setup): the actor and the critics cover
    the 6 pose dimensions, nothing learns the vacuum, every action commands hold, and the
    acting weights alone reproduce the actions."""
    cfg = HILSERLConfig(hidden=(16,), batch_size=32, vacuum_head="held")
    agent = HILSERLAgent(OBS_DIM, config=cfg, seed=3)
    first = lambda net: [m for m in net.modules() if isinstance(m, torch.nn.Linear)][0]  # noqa: E731
    assert first(agent.critic.members[0]).in_features == OBS_DIM + 6
    assert agent.grasp_critic is None and "grasp_critic" not in agent.state_dict()
    obs = demo.observations[:50]
    for deterministic in (True, False):
        a = agent.act(obs, deterministic=deterministic)
        assert a.shape == (50, 1, 7) and np.all(a[:, 0, 6] == VACUUM_ON)
        assert np.all(np.abs(a[:, 0, :6]) < 1.0) and len(np.unique(a[:, 0, 0])) > 1
    info = agent.update(demo_td[:64])
    assert "grasp_critic_loss" not in info and np.isfinite(info["critic_loss"])
    # A release in the stored actions (e.g. a takeover's) is not an input to the critics.
    b = demo_td[:32].clone()
    b["actions"][:, 0, 6] = -1.0
    torch.testing.assert_close(agent._prepare(b)["actions"], agent._prepare(demo_td[:32])["actions"])
    twin = HILSERLAgent.from_policy_state_dict(agent.policy_state_dict())
    np.testing.assert_array_equal(twin.act(obs, deterministic=True), agent.act(obs, deterministic=True))
    with pytest.raises(ValueError, match="vacuum_head"):
        agent.vacuum_command(obs[0])
    with pytest.raises(ValueError, match="held"):
        HILSERLAgent(OBS_DIM, action_dim=1, config=cfg)


def test_action_scale_is_hilserl_per_task_action_scale(demo, demo_td):
    """action_scale (HIL-SERL's ACTION_SCALE): the policy's unit action moves the TCP by the
    scale times the env's unit; stored env-unit actions learn in the policy's units."""
    base = HILSERLConfig(hidden=(16,), batch_size=32, vacuum_head="held")
    scaled = dataclasses.replace(base, action_scale=(0.4, 0.5))
    a1, a2 = HILSERLAgent(OBS_DIM, config=base, seed=3), HILSERLAgent(OBS_DIM, config=scaled, seed=3)
    obs = demo.observations[:20]
    u1, u2 = a1.act(obs, deterministic=True), a2.act(obs, deterministic=True)
    np.testing.assert_allclose(u2[:, 0, :3], 0.4 * u1[:, 0, :3], rtol=1e-6)
    np.testing.assert_allclose(u2[:, 0, 3:6], 0.5 * u1[:, 0, 3:6], rtol=1e-6)
    assert np.all(u2[:, 0, 6] == VACUUM_ON)
    b = demo_td[:32]
    env_units = b["actions"][:, 0, :6].to(torch.float32)
    learnt = a2._prepare(b)["actions"]
    scale = torch.tensor([0.4] * 3 + [0.5] * 3)
    torch.testing.assert_close(learnt, (env_units / scale).clamp(-1, 1))
    for bad in ((0.0, 1.0), (0.5,), (1.5, 0.5)):
        with pytest.raises(ValueError, match="action_scale"):
            HILSERLConfig(action_scale=bad)


def test_grasp_td_target_is_double_dqn():
    """y_g = r + gamma (1 - terminal) Qbar_g(s', argmax_c Q_g(s', c)): the online grasp
    critic chooses the command, the target grasp critic values it."""
    agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(8,), batch_size=2))
    batch = _two_rows([0.5, 1.0], [False, True])     # vacuum off and kept off: no toggle
    _constant_outputs(agent.target_grasp_critic, [5.0, 2.0, 4.0])
    for online, value in (([0.0, 1.0, 0.0], 2.0), ([1.0, 0.0, 0.0], 5.0),
                          ([0.0, 0.0, 1.0], 4.0)):   # online argmax: stay, release, engage
        _constant_outputs(agent.grasp_critic, online)
        torch.testing.assert_close(agent.grasp_td_target(batch),
                                   torch.tensor([0.5 + GAMMA * value, 1.0]))


def test_toggle_penalty_enters_the_grasp_target_only_where_the_state_changes():
    """Rows: held + on (stay), held + off (release), free + on (engage), free + off (stay).
    The grasp critic's reward carries grasp_penalty on the two changes only; the critics'
    targets keep the task reward; grasp_penalty = 0 removes it."""
    batch = TensorDict({"obs": torch.zeros(4, OBS_DIM), "next_obs": torch.ones(4, OBS_DIM),
                        "actions": torch.zeros(4, 1, 7), "reward": torch.full((4,), 0.5),
                        "discount": torch.full((4,), GAMMA),
                        "terminal": torch.zeros(4, dtype=bool)}, batch_size=[4])
    batch["obs"][:, VACUUM_OBS_INDEX] = torch.tensor([1.0, 1.0, 0.0, 0.0])
    batch["actions"][:, 0, 6] = torch.tensor([VACUUM_ON, VACUUM_OFF, VACUUM_ON, VACUUM_OFF])
    assert HILSERLConfig().grasp_penalty == -0.02     # HIL-SERL's single-arm learnt gripper
    for penalty in (-0.02, 0.0):
        agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(8,), batch_size=2,
                                                           grasp_penalty=penalty))
        _constant_target_critics(agent, [2.0, 2.0], grasp=3.0)
        toggled = torch.tensor([0.0, 1.0, 1.0, 0.0])
        torch.testing.assert_close(agent.grasp_td_target(batch),
                                   0.5 + penalty * toggled + GAMMA * 3.0)
        torch.testing.assert_close(agent.td_target(batch), torch.full((4,), 0.5 + GAMMA * 2.0))
        np.testing.assert_array_equal(agent._prepare(batch)["vacuum_cmd"],
                                      [STAY, RELEASE, ENGAGE, STAY])


def test_executed_vacuum_values_map_to_the_grasp_commands():
    """A demonstration's or a takeover's continuous vacuum value is labelled by what it did:
    a change of state is release / engage, no change is stay; and each command executes a
    value that the same labelling gives back where it changes or keeps the state."""
    vacuum = torch.tensor([1.0, -1.0, 1.0, -1.0, 0.6, 0.4, 0.5, 0.95])
    held = torch.tensor([True, True, False, False, False, True, True, True])
    np.testing.assert_array_equal(grasp_command_labels(vacuum, held),
                                  [STAY, RELEASE, ENGAGE, STAY, ENGAGE, RELEASE, RELEASE, STAY])
    commands = torch.tensor([RELEASE, STAY, ENGAGE] * 2)
    state = torch.tensor([True] * 3 + [False] * 3)
    executed = vacuum_values(commands, state)
    np.testing.assert_array_equal(executed, [VACUUM_OFF, VACUUM_ON, VACUUM_ON,
                                             VACUUM_OFF, VACUUM_OFF, VACUUM_ON])
    np.testing.assert_array_equal(grasp_command_labels(executed, state),
                                  [RELEASE, STAY, STAY, STAY, STAY, ENGAGE])


def test_stay_keeps_the_vacuum_state_in_the_environment(env):
    """Setting A starts held: "stay" executes vacuum on and the panel stays held; after a
    release, "stay" executes vacuum off and it stays free."""
    agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(8,), batch_size=2))
    obs, _ = env.reset(seed=0)
    assert obs[VACUUM_OBS_INDEX] == 1.0
    for command, executed, flag in ((STAY, VACUUM_ON, 1.0), (RELEASE, VACUUM_OFF, 0.0),
                                    (STAY, VACUUM_OFF, 0.0)):
        _constant_outputs(agent.grasp_critic, np.eye(3)[command])
        assert agent.vacuum_command(obs) == command
        a = agent.act(obs, deterministic=True)[0]
        assert a[6] == executed
        a[:6] = 0.0
        obs, *_ = env.step(a)
        assert obs[VACUUM_OBS_INDEX] == flag
    # Where the observation is not the flat state, the flag is passed along.
    free = np.array(obs)
    free[VACUUM_OBS_INDEX] = 1.0
    assert agent.act(free, deterministic=True, vacuum_flag=[0.0])[0, 6] == VACUUM_OFF


def test_pixel_track_stay_reads_the_raw_vacuum_flag():
    """On the pixel track the learner sees embeddings: "stay" reads the raw observation's
    vacuum flag (the last proprioceptive value)."""
    from window_bench.pixels.agent import VACUUM_INDEX, PixelHILSERL
    from window_bench.pixels.encoder import OBS_DIM as PIXEL_OBS_DIM

    agent = PixelHILSERL(HILSERLConfig(hidden=(8,), batch_size=2))
    _constant_outputs(agent.agent.grasp_critic, np.eye(3)[STAY])
    obs = np.zeros((2, PIXEL_OBS_DIM), np.float32)
    obs[:, VACUUM_INDEX] = [1.0, 0.0]
    np.testing.assert_array_equal(agent.act(obs, deterministic=True)[:, 0, 6],
                                  [VACUUM_ON, VACUUM_OFF])


def test_grasp_critic_trains_the_executed_command_only(demo_td):
    """The grasp loss regresses Q_g(s, c) of the executed command c (the demo holds the
    panel it holds: stay) to its target; release and engage get no gradient from it."""
    cfg = HILSERLConfig(hidden=(16,), batch_size=32, critic_actor_ratio=1, tau=1.0)
    agent = HILSERLAgent(OBS_DIM, config=cfg)
    batch = demo_td[:32]
    assert torch.all(batch["actions"][:, 0, 6] > 0.5)
    b = agent._prepare(batch)
    assert torch.all(b["vacuum_cmd"] == STAY)
    y = agent._grasp_td_target(b)
    with torch.no_grad():
        q = agent.grasp_critic(b["obs"])
    expected = float(((q[:, STAY] - y) ** 2).mean())
    info = agent.update(batch)
    assert info["grasp_critic_loss"] == pytest.approx(expected, rel=1e-5)
    last = [m for m in agent.grasp_critic.modules() if isinstance(m, torch.nn.Linear)][-1]
    before = HILSERLAgent(OBS_DIM, config=cfg)   # same seed: the initial weights
    last0 = [m for m in before.grasp_critic.modules() if isinstance(m, torch.nn.Linear)][-1]
    for c in (RELEASE, ENGAGE):
        assert torch.equal(last.weight[c], last0.weight[c])
        assert torch.equal(last.bias[c], last0.bias[c])
    assert not torch.equal(last.weight[STAY], last0.weight[STAY])
    # tau = 1: the target grasp critic is a copy after the step (Polyak after every step)
    for p_, t_ in zip(agent.grasp_critic.parameters(), agent.target_grasp_critic.parameters()):
        torch.testing.assert_close(p_, t_)


def test_vacuum_action_is_argmax_and_epsilon_greedy_when_sampling(demo):
    obs = np.repeat(demo.observations[:1], 2000, axis=0)      # the panel held
    agent = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(16,), batch_size=32,
                                                       vacuum_epsilon=0.3), seed=1)
    _constant_outputs(agent.grasp_critic, [1.0, 0.0, 0.0])
    assert np.all(agent.act(obs, deterministic=True)[:, 0, 6] == VACUUM_OFF)    # release
    _constant_outputs(agent.grasp_critic, [0.0, 1.0, 0.0])
    assert np.all(agent.act(obs, deterministic=True)[:, 0, 6] == VACUUM_ON)     # stay
    np.testing.assert_array_equal(agent.vacuum_command(obs[:3]), [STAY] * 3)
    sampled = agent.act(obs)[:, 0, 6]
    assert set(np.unique(sampled)) == {VACUUM_OFF, VACUUM_ON}
    # epsilon 0.3 of uniform commands over 3: release with probability 0.1
    assert 0.07 < np.mean(sampled == VACUUM_OFF) < 0.13
    greedy = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(16,), batch_size=32), seed=1)
    _constant_outputs(greedy.grasp_critic, [0.0, 1.0, 0.0])
    assert np.all(greedy.act(obs)[:, 0, 6] == VACUUM_ON)   # HIL-SERL's default: no epsilon


def test_policies_saved_with_the_two_way_grasp_critic_still_act(demo):
    """A policy saved before the three-way head (config without grasp_penalty, vacuum_head
    'discrete', two grasp-critic outputs) loads as vacuum_head='binary' and acts as before:
    its argmax over {release, hold}, executed as off / on, whatever the vacuum state."""
    old = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(16,), batch_size=32,
                                                     vacuum_head="binary"), seed=2)
    _constant_outputs(old.grasp_critic, [1.0, 0.0])
    policy = old.policy_state_dict()
    del policy["config"]["grasp_penalty"]
    policy["config"]["vacuum_head"] = "discrete"
    restored = HILSERLAgent.from_policy_state_dict(policy)
    assert restored.config.vacuum_head == "binary" and restored.config.grasp_penalty == 0.0
    obs = demo.observations[:20]
    np.testing.assert_array_equal(restored.act(obs, deterministic=True),
                                  old.act(obs, deterministic=True))
    assert np.all(restored.act(obs, deterministic=True)[:, 0, 6] == VACUUM_OFF)
    state = old.state_dict()
    del state["config"]["grasp_penalty"]
    state["config"]["vacuum_head"] = "discrete"
    resumed = HILSERLAgent.from_state_dict(state)
    assert resumed.grasp_critic(torch.zeros(1, OBS_DIM)).shape == (1, 2)
    assert "grasp_critic_loss" in resumed.update(to_td(chunk_transitions(demo, 1, GAMMA))[:32])


def test_hilserl_own_preset_loads_and_validates():
    """The preset ``hilserl-own``: HIL-SERL's own protocol and settings as --agent-config
    overrides, valid for the agent on every profile, the rest of the config unchanged."""
    import json

    import window_bench  # noqa: F401  (fills the registries)
    from window_bench.harness.agent import check_agent_config, parse_overrides
    from window_bench.harness.methods import PROFILES, get_preset

    preset = get_preset("hilserl-own")
    assert preset is HILSERL_OWN
    # As a command line would give them: --agent-config KEY=VALUE with JSON values.
    typed = parse_overrides([f"{k}={json.dumps(v)}" for k, v in preset.items()])
    for profile in PROFILES.values():
        check_agent_config(HILSERLAgent, 1, profile, typed)
        cfg = HILSERLAgent.make_config(1, profile, typed)
        assert (cfg.offline_steps, cfg.gamma, cfg.hidden) == (0, 0.98, (256, 256))
        np.testing.assert_allclose(np.exp([cfg.log_std_min, cfg.log_std_max]), [1e-5, 5.0])
        default = HILSERLAgent.make_config(1, profile, {})
        changed = {k for k in vars(default) if getattr(cfg, k) != getattr(default, k)}
        assert changed <= set(preset), changed
    agent = HILSERLAgent(OBS_DIM, config=HILSERLAgent.make_config(1, PROFILES["cpu"], typed))
    assert agent.offline_steps == 0 and agent.config.vacuum_head == "discrete"
    with pytest.raises(ValueError, match="unknown agent config field"):
        HILSERLAgent.make_config(1, PROFILES["cpu"], {**typed, "discount": 0.98})


def test_normalised_observations_are_clipped():
    agent = HILSERLAgent(OBS_DIM, config=SMALL, obs_mean=np.zeros(OBS_DIM),
                         obs_std=np.ones(OBS_DIM))
    far, edge = np.full(OBS_DIM, 1e6, np.float32), np.full(OBS_DIM, 10.0, np.float32)
    np.testing.assert_array_equal(agent.act(far, deterministic=True),
                                  agent.act(edge, deterministic=True))
    free = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(32, 32), batch_size=32,
                                                      obs_clip=None),
                        obs_mean=np.zeros(OBS_DIM), obs_std=np.ones(OBS_DIM))
    assert not np.array_equal(free.act(far, deterministic=True),
                              free.act(edge, deterministic=True))


def test_states_saved_before_the_grasp_critic_load_as_gaussian():
    old = HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(16,), batch_size=32,
                                                     vacuum_head="gaussian", obs_clip=None))
    state = old.state_dict()
    for key in ("vacuum_head", "obs_clip", "vacuum_epsilon", "offline_steps",
                "suction_loss_terminal", "target_range", "grasp_penalty"):
        del state["config"][key]
    restored = HILSERLAgent.from_state_dict(state)
    assert restored.config.vacuum_head == "gaussian" and restored.config.obs_clip is None
    assert restored.offline_steps is None   # those runs had the profile's Stage I
    x = np.ones((3, OBS_DIM), np.float32)
    np.testing.assert_array_equal(restored.act(x, deterministic=True),
                                  old.act(x, deterministic=True))


# --------------------------------------------------------------------------- checkpoints
def test_state_dict_round_trip_is_an_exact_resume(demo, demo_td):
    mean, std = obs_normalizer([demo])
    a = HILSERLAgent(OBS_DIM, config=SMALL, seed=0, obs_mean=mean, obs_std=std)
    for i in range(3):
        a.update(demo_td[:64])
        a.act(demo.observations[0])
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = HILSERLAgent(OBS_DIM, config=SMALL, seed=7)  # different seed and no normalization
    b.load_state_dict(torch.load(buf))
    for agent in (a, b):  # identical futures
        agent.info = agent.update(demo_td[40:104])
    assert a.info == b.info
    nets = ("actor", "critic", "target_critic", "grasp_critic", "target_grasp_critic")
    for pa, pb in zip(sum((params(getattr(a, n)) for n in nets), []),
                      sum((params(getattr(b, n)) for n in nets), [])):
        assert torch.equal(pa, pb)
    assert a.temperature == b.temperature and a.critic_steps == b.critic_steps == 8
    np.testing.assert_array_equal(a.act(demo.observations[:4]), b.act(demo.observations[:4]))
    c = HILSERLAgent.from_state_dict(a.state_dict())
    assert c.config == a.config and c.config.h == 1
    np.testing.assert_array_equal(c.act(demo.observations[:4], deterministic=True),
                                  a.act(demo.observations[:4], deterministic=True))
    with pytest.raises(ValueError, match="config differs"):
        HILSERLAgent(OBS_DIM, config=HILSERLConfig(hidden=(16,), batch_size=32)
                     ).load_state_dict(a.state_dict())


# --------------------------------------------------------------------------- buffers
def test_buffer_routing_rule():
    assert hilserl_buffers_for("policy") == ("online",)
    assert hilserl_buffers_for("takeover") == ("online", "demo")
    assert hilserl_buffers_for("demo") == ("demo",)
    with pytest.raises(ValueError, match="step_provenance"):
        hilserl_buffers_for("operator")


def test_takeover_segments_become_h1_demo_logs():
    T = 6
    prov = ["policy", "takeover", "takeover", "policy", "takeover", "takeover"]
    obs = np.arange(T + 1, dtype=np.float32)[:, None].repeat(3, axis=1)
    rewards = np.zeros(T, np.float32)
    rewards[-1] = 1.0
    term = np.zeros(T, bool)
    term[-1] = True
    ep = EpisodeLog(observations=obs, actions=np.arange(T * 7, dtype=np.float32).reshape(T, 7),
                    rewards=rewards, terminated=term, truncated=np.zeros(T, bool),
                    provenance=prov, takeover_kind=["" if p == "policy" else "safety"
                                                    for p in prov],
                    episode_id=4, chunk_horizon=3)
    first, second = takeover_segments(ep)
    np.testing.assert_array_equal(first.observations[:, 0], [1, 2, 3])
    np.testing.assert_array_equal(first.actions, ep.actions[1:3])
    assert first.truncated[-1] and not first.terminated.any()
    np.testing.assert_array_equal(second.observations[:, 0], [4, 5, 6])
    assert second.terminated[-1] and second.rewards[-1] == 1.0
    for seg in (first, second):
        assert seg.episode_id == 4 and seg.chunk_horizon == 1
        assert set(seg.provenance) == {"takeover"}
        ch = chunk_transitions(seg, 1, GAMMA)
        assert ch["valid"].all()  # each step bootstraps from its own next state
    np.testing.assert_array_equal(chunk_transitions(first, 1, GAMMA)["next_obs"][:, 0], [2, 3])
    np.testing.assert_array_equal(chunk_transitions(second, 1, GAMMA)["terminal"],
                                  [False, True])
    no_takeover = EpisodeLog(observations=obs, actions=ep.actions, rewards=rewards,
                             terminated=term, truncated=np.zeros(T, bool),
                             provenance=["policy"] * T, takeover_kind=[""] * T)
    assert takeover_segments(no_takeover) == []


def test_symmetric_sampler_is_exactly_half_demo(demo_td):
    online_td = demo_td.clone()
    online_td["obs"] = online_td["obs"] + 1000.0  # tell the rows apart
    gen = torch.Generator().manual_seed(0)

    def draw(td):
        return lambda n: td[torch.randint(len(td), (n,), generator=gen)]

    sample = symmetric_sampler(draw(demo_td), draw(online_td), 32)
    for _ in range(5):
        batch = sample()
        assert batch.batch_size == torch.Size([32])
        assert int(batch["from_demo"].sum()) == 16
        from_online = batch["obs"][:, 0] > 500.0
        assert torch.equal(from_online, ~batch["from_demo"])
    with pytest.raises(ValueError, match="even"):
        symmetric_sampler(draw(demo_td), draw(online_td), 31)


def test_rlpd_batches_from_chunk_replay_are_half_demo(env, demo):
    """The harness's 1:1 batch (window_bench.data.replay.mixed_batch) feeds every critic step."""
    from window_bench.data.replay import PROVENANCE_CODES, ChunkReplay, mixed_batch

    demo_buf, online_buf = ChunkReplay(1000, 1, GAMMA, seed=0), ChunkReplay(1000, 1, GAMMA, 1)
    demo_buf.add_episode(demo)
    agent = HILSERLAgent(OBS_DIM, config=SMALL)
    policy_ep = rollout(env, lambda o: agent.act(o)[0], seed=5, provenance="policy",
                        max_steps=20, episode_id=2)
    online_buf.add_episode(policy_ep)
    batches = []

    def sample():
        batches.append(mixed_batch(demo_buf, online_buf, SMALL.batch_size))
        return batches[-1]

    agent.update(sample)
    assert len(batches) == SMALL.critic_actor_ratio
    for batch in batches:
        codes = batch["provenance_code"][:, 0]
        assert int((codes == PROVENANCE_CODES["demo"]).sum()) == SMALL.batch_size // 2
        assert int((codes == PROVENANCE_CODES["policy"]).sum()) == SMALL.batch_size // 2


# --------------------------------------------------------------------------- smoke
def test_pretrain_collect_update_evaluate(env, demo):
    """Offline pretraining on demos, a warm-start episode without updates, online updates on
    half/half batches, then a deterministic evaluation episode: the agent runs end to end."""
    from window_bench.data.replay import ChunkReplay, mixed_batch

    mean, std = obs_normalizer([demo])
    agent = HILSERLAgent(OBS_DIM, config=SMALL, seed=1, obs_mean=mean, obs_std=std)
    demo_buf, online_buf = ChunkReplay(1000, 1, GAMMA, seed=0), ChunkReplay(1000, 1, GAMMA, 1)
    demo_buf.add_episode(demo)
    for _ in range(3):  # offline: the online buffer is empty, batches are all demo
        agent.update(lambda: mixed_batch(demo_buf, online_buf, SMALL.batch_size))
    frozen = params(agent.actor)
    warm = rollout(env, lambda o: agent.act(o)[0], seed=11, provenance="policy",
                   max_steps=15, episode_id=3)
    assert all(torch.equal(a, b) for a, b in zip(frozen, params(agent.actor)))
    for buffer in hilserl_buffers_for("policy"):
        {"online": online_buf, "demo": demo_buf}[buffer].add_episode(warm)
    for _ in range(3):
        info = agent.update(lambda: mixed_batch(demo_buf, online_buf, SMALL.batch_size))
    assert all(np.isfinite(v) for v in info.values())
    evaluation = rollout(env, lambda o: agent.act(o, deterministic=True)[0], seed=100,
                         provenance="policy", max_steps=15)
    assert evaluation.T == 15 and np.all(np.abs(evaluation.actions) <= 1.0)


def test_offline_steps_zero_skips_stage_i_in_the_harness(tmp_path, demos_root):
    """``--agent-config offline_steps=0`` (HIL-SERL's and RLPD's own protocol): no Stage I
    gradient step, checkpoint 0 evaluates the initial policy, online learning then runs on
    1:1 batches (the default, the profile's Stage I, runs in tests/test_harness.py)."""
    from window_bench.harness.run import Run

    run = Run("hil-serl", "WindowInstall-A-v0", "smoke", 0, tmp_path / "run", demos=demos_root,
              progress=False, agent_config={"offline_steps": 0}, eval_workers=1)
    assert run.agent_cls.make_config(1, run.profile, run.agent_config).offline_steps == 0
    r = run.train()
    assert r["hyperparameters"]["offline_steps"] == 0
    assert [c["env_steps"] for c in r["checkpoints"]] == [0, 200, 400]
    assert r["checkpoints"][0]["grad_steps"] == 0 and r["checkpoints"][0]["episodes"] == 2
    # Smoke: UTD 0.05 over the 300 online steps = 15 credits, 2 critic steps per call.
    assert r["final"]["grad_steps"] == 2 * 8


@pytest.mark.parametrize("h", [1, 10])
def test_propagation_check_targets_are_the_true_returns(demo, h):
    """experiments/sanity/hilserl_propagation.py: its h-step targets, bootstrapped from the
    true return-to-go, give back the true return-to-go at every step of a real episode (the
    check it makes on the critics would otherwise measure its own arithmetic)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "hilserl_propagation",
        Path(__file__).parents[1] / "experiments/sanity/hilserl_propagation.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    d = script.transitions([demo], GAMMA, h)
    T = demo.T
    assert len(d["obs"]) == T and d["start"].sum() == 1 and d["start"][0]
    np.testing.assert_allclose(d["rtg"][0], GAMMA ** (T - 1), rtol=1e-5)
    nxt = np.minimum(np.arange(T) + h, T - 1)
    np.testing.assert_array_equal(d["done"], (np.arange(T) + h >= T).astype(np.float32))
    rebuilt = d["ret"] + d["disc"] * (1 - d["done"]) * d["rtg"][nxt]
    np.testing.assert_allclose(rebuilt, d["rtg"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(d["disc"][:T - h], GAMMA ** h, rtol=1e-6)


def test_safety_box_clips_commanded_poses_into_the_demonstrations_envelope(demo):
    """safety_box (HIL-SERL's clip_safety_box): the box is D_demo's TCP envelope widened by
    the margins; an action commanding a pose outside it is replaced by the one commanding
    the nearest pose inside, in the env's own step arithmetic; the box travels with the
    policy file and the resume state; without demos or on pixels it refuses."""
    from baselines.hilserl import _tcp_pose
    from window_bench.envs.env import POS_SCALE, ROT_SCALE, mat_to_rotvec, rotvec_to_mat
    from window_bench.harness.files import dump_state, parse_state

    cfg = HILSERLConfig(hidden=(16,), batch_size=32, vacuum_head="held",
                        safety_box=(0.01, 2.0))
    agent = HILSERLAgent(OBS_DIM, config=cfg, seed=1)
    with pytest.raises(RuntimeError, match="fit_safety_box"):
        agent.act(demo.observations[0])
    agent.fit_safety_box([demo])
    box = agent.box
    pos = np.array([_tcp_pose(o)[0] for o in demo.observations])
    np.testing.assert_allclose(box.pos_low, pos.min(0) - 0.01)
    np.testing.assert_allclose(box.pos_high, pos.max(0) + 0.01)
    # Inside the box (the demonstration's own actions): unchanged up to float32.
    for t in (0, 40, 80):
        a = demo.actions[t]
        np.testing.assert_allclose(box.clip(demo.observations[t], a), a, atol=1e-5)
    # Full speed away from the envelope along every axis: the commanded pose lands on the
    # box's face (position) or inside its rotation bounds, never beyond.
    o = demo.observations[0]
    p, mat = _tcp_pose(o)
    for a in np.vstack([np.eye(7)[:6], -np.eye(7)[:6]]):
        a = a.astype(np.float32) + np.float32([0, 0, 0, 0, 0, 0, 1])
        c = box.clip(o, a).astype(np.float64)
        target = p + mat @ (c[:3] * POS_SCALE)
        assert np.all(target >= box.pos_low - 1e-9) and np.all(target <= box.pos_high + 1e-9)
        v = mat_to_rotvec(box.rot_ref.T @ mat @ rotvec_to_mat(c[3:6] * ROT_SCALE))
        assert np.all(v >= box.rot_low - 1e-6) and np.all(v <= box.rot_high + 1e-6)
        assert c[6] == 1 and np.all(np.abs(c[:6]) <= 1)
    # act() is the same weights' unboxed action, clipped.
    unboxed = HILSERLAgent(OBS_DIM, config=dataclasses.replace(cfg, safety_box=None), seed=1)
    obs = demo.observations[:5]
    expected = [box.clip(o, a[0]) for o, a in zip(obs, unboxed.act(obs, deterministic=True))]
    np.testing.assert_allclose(agent.act(obs, deterministic=True)[:, 0], expected, atol=1e-6)
    # The policy file and the resume state carry the box; a state without one is refused.
    state, _ = parse_state(dump_state(agent.policy_state_dict(), "policy"), "x", "policy")
    again = HILSERLAgent.from_policy_state_dict(state)
    np.testing.assert_array_equal(again.act(demo.observations[:5], deterministic=True),
                                  agent.act(demo.observations[:5], deterministic=True))
    resumed = HILSERLAgent.from_state_dict(agent.state_dict())
    np.testing.assert_array_equal(resumed.box.pos_high, box.pos_high)
    bare = {k: v for k, v in agent.policy_state_dict().items() if k != "safety_box"}
    with pytest.raises(ValueError, match="safety box"):
        HILSERLAgent.from_policy_state_dict(bare)
    with pytest.raises(ValueError, match="flat state"):
        HILSERLAgent(20, config=cfg)
    for bad in ((0.01,), (-0.01, 2.0), (0.01, 200.0), (float("nan"), 1.0)):
        with pytest.raises(ValueError, match="safety_box"):
            HILSERLConfig(safety_box=bad)
