"""ACT baseline: masked loss, CVAE prior/bypass, temporal ensembling, checkpoints, learning."""

import io
import math
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from baselines.act import (ACT_PROFILES, FLAT_ROBOT_DIM, ACTAgent, ACTConfig, _collect_demos,
                           act_loss, kl_to_prior, temporal_ensemble)
from window_bench.envs.env import STATE_KEYS
from window_bench.envs.task import STAGES
from window_bench.data.steplog import EpisodeLog, without_noops

torch.set_num_threads(1)
SMOKE = ACT_PROFILES["smoke"]
OBS_DIM = 52


def synthetic_episode(T=23, seed=0, obs_dim=OBS_DIM):
    rng = np.random.default_rng(seed)
    return EpisodeLog(observations=rng.normal(size=(T + 1, obs_dim)),
                      actions=rng.uniform(-1, 1, (T, 7)), rewards=np.zeros(T),
                      terminated=np.arange(T) == T - 1, truncated=np.zeros(T, bool),
                      provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=seed)


@pytest.fixture(scope="module")
def demos():
    """Three real scripted-installer episodes on WindowInstall-A-v0 (about 105 steps each)."""
    return _collect_demos("WindowInstall-A-v0", [0, 1, 2])


@pytest.fixture
def trained():
    """A smoke-size agent after a few updates on synthetic episodes, acting in open-loop
    chunks (the option; ensembling, the default, is tested on its own)."""
    eps = [synthetic_episode(23, 0), synthetic_episode(17, 1)]
    agent = ACTAgent(OBS_DIM, config=replace(SMOKE, temporal_ensembling=False), seed=3)
    agent.train_offline(eps, 5)
    return agent, eps


# ----------------------------------------------------------------------------- loss
def random_loss_inputs(B=4, k=10, A=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    pred = torch.randn(B, k, A, generator=g)
    target = torch.randn(B, k, A, generator=g)
    # Real lengths 10, 6, 1, 3: each row is padded past its episode end.
    is_pad = torch.arange(k)[None, :] >= torch.tensor([10, 6, 1, 3])[:, None]
    mu, logvar = torch.randn(B, 5, generator=g), torch.randn(B, 5, generator=g)
    return pred, target, is_pad, mu, logvar


def test_loss_ignores_anything_at_padded_steps():
    pred, target, is_pad, mu, logvar = random_loss_inputs()
    loss, l1, kl = act_loss(pred, target, is_pad, mu, logvar, 10.0)
    pad = is_pad[..., None].expand_as(pred)
    for junk in (1e6, float("nan"), -3.0):
        p2 = pred.masked_fill(pad, junk)
        t2 = target.masked_fill(pad, -junk)
        loss2, l12, _ = act_loss(p2, t2, is_pad, mu, logvar, 10.0)
        assert torch.equal(loss2, loss) and torch.equal(l12, l1)
    # ... while a real step does count.
    p3 = pred.clone()
    p3[1, 5, 0] += 1.0  # step 5 of row 1 is its last real step
    assert act_loss(p3, target, is_pad, mu, logvar, 10.0)[1] > l1
    # The L1 term is the mean over real entries only.
    real = ~pad
    assert torch.isclose(l1, (pred - target).abs()[real].mean(), rtol=1e-6)
    assert torch.isclose(loss, l1 + 10.0 * kl)


def test_l2_loss_is_the_masked_squared_error_and_still_reports_l1():
    pred, target, is_pad, mu, logvar = random_loss_inputs()
    loss, l1, kl = act_loss(pred, target, is_pad, mu, logvar, 10.0, loss="l2")
    real = ~is_pad[..., None].expand_as(pred)
    assert torch.isclose(loss, (pred - target).square()[real].mean() + 10.0 * kl, rtol=1e-6)
    assert torch.equal(l1, act_loss(pred, target, is_pad, mu, logvar, 10.0)[1])
    p2 = pred.masked_fill(is_pad[..., None], float("nan"))   # padding still has no effect
    assert torch.equal(act_loss(p2, target, is_pad, mu, logvar, 10.0, loss="l2")[0], loss)
    with pytest.raises(ValueError, match=r"ACTConfig.loss = 'huber'"):
        ACTConfig(loss="huber")
    with pytest.raises(ValueError, match=r"ACTConfig.obs_clip = -1"):
        ACTConfig(obs_clip=-1)


def test_obs_clip_bounds_the_policy_input_and_batches_match_single_chunks():
    eps = [synthetic_episode(23, 0)]
    agent = ACTAgent(OBS_DIM, config=replace(SMOKE, obs_clip=3.0), seed=0)
    agent.fit_normalizer(eps)
    far = eps[0].observations[0].astype(np.float32).copy()
    far[0] = agent.norm["obs_mean"][0] + 1e4 * agent.norm["obs_std"][0]
    at_clip = far.copy()
    at_clip[0] = agent.norm["obs_mean"][0] + 3.0 * agent.norm["obs_std"][0]
    assert np.allclose(agent.predict_chunk(far), agent.predict_chunk(at_clip), atol=1e-6)
    unclipped = ACTAgent(OBS_DIM, config=SMOKE, seed=0)
    unclipped.norm = agent.norm
    assert not np.allclose(unclipped.predict_chunk(far), unclipped.predict_chunk(at_clip))
    obs = eps[0].observations[:4].astype(np.float32)
    batch = agent.predict_chunks(obs)
    assert batch.shape == (4, SMOKE.chunk, 7)
    assert np.allclose(batch, np.stack([agent.predict_chunk(o) for o in obs]), atol=1e-6)


def test_fine_pose_features_join_the_object_token_and_resolve_millimetres():
    from window_bench.installer.supervisor import FLAT_SLICES
    eps = [synthetic_episode(23, 0)]
    agent = ACTAgent(OBS_DIM, config=replace(SMOKE, fine_pose_mm=10.0, fine_pose_deg=2.0), seed=0)
    agent.fit_normalizer(eps)
    assert agent.model.robot_dim == FLAT_ROBOT_DIM and agent.model.env_dim == OBS_DIM - 40 + 6
    obs = eps[0].observations[:2].astype(np.float32).copy()
    pos = FLAT_SLICES["window_pos_rel"]
    obs[:, pos] = 0.0
    obs[1, pos.start] = 0.003                      # 3 mm sideways
    x = agent.normalize_obs(torch.from_numpy(obs))
    assert x.shape == (2, OBS_DIM + 6)
    # the z-score barely moves (std ~1 m here); the fine feature moves by tanh(0.3)
    assert abs(float(x[1, pos.start] - x[0, pos.start])) < 0.01
    assert float(x[1, OBS_DIM] - x[0, OBS_DIM]) == pytest.approx(math.tanh(0.3), abs=1e-6)
    assert not np.allclose(agent.predict_chunk(obs[0]), agent.predict_chunk(obs[1]))
    # acting weights alone rebuild the same policy
    rebuilt = ACTAgent.from_policy_state_dict(agent.policy_state_dict())
    assert np.array_equal(rebuilt.predict_chunk(obs[1]), agent.predict_chunk(obs[1]))
    agent.train_offline(eps, 2)                    # trains on the widened token
    with pytest.raises(ValueError, match=r"fine_pose_mm = 10.0 needs the flat state"):
        ACTAgent(20, config=replace(SMOKE, robot_dim=0, fine_pose_mm=10.0))
    with pytest.raises(ValueError, match=r"fine_pose_deg = 0 .* \(0.0, 90.0\]"):
        ACTConfig(fine_pose_deg=0)
    with pytest.raises(ValueError, match=r"fine_pose_mm = -1 .* \[0.0, 1000.0\]"):
        ACTConfig(fine_pose_mm=-1)


def test_without_the_cvae_training_never_runs_the_encoder_and_has_no_kl():
    eps = [synthetic_episode(23, 0), synthetic_episode(17, 1)]
    agent = ACTAgent(OBS_DIM, config=replace(SMOKE, cvae=False), seed=0)
    with torch.no_grad():
        for name, p in agent.model.named_parameters():
            if name.startswith(("cls_embed", "vae_", "latent_proj.")):
                p.fill_(float("nan"))
    logs = agent.train_offline(eps, 20)
    assert all(g["kl"] == 0.0 and math.isfinite(g["loss"]) for g in logs)
    assert logs[-1]["loss"] == logs[-1]["l1"]
    assert np.isfinite(agent.predict_chunk(eps[0].observations[0])).all()
    with pytest.raises(ValueError, match=r"ACTConfig.cvae = 1"):
        ACTConfig(cvae=1)


def test_all_pad_tail_equals_shorter_chunk():
    pred, target, _, mu, logvar = random_loss_inputs()
    is_pad = torch.zeros(4, 10, dtype=torch.bool)
    is_pad[:, 6:] = True
    full = act_loss(pred, target, is_pad, mu, logvar, 10.0)
    short = act_loss(pred[:, :6], target[:, :6], torch.zeros(4, 6, dtype=torch.bool),
                     mu, logvar, 10.0)
    for a, b in zip(full, short):
        assert torch.allclose(a, b, rtol=1e-6, atol=0)


def test_update_ignores_padded_targets(trained):
    agent, _ = trained
    twin = ACTAgent(OBS_DIM, config=SMOKE, seed=9)
    twin.load_state_dict(agent.state_dict())
    rng = np.random.default_rng(0)
    is_pad = np.arange(SMOKE.chunk)[None, :] >= np.array([10, 4, 1, 7])[:, None]
    batch = {"obs": rng.normal(size=(4, OBS_DIM)),
             "actions": rng.uniform(-1, 1, (4, SMOKE.chunk, 7)), "is_pad": is_pad}
    junk = dict(batch, actions=np.where(is_pad[..., None], 123.0, batch["actions"]))
    out_a, out_b = agent.update(batch), twin.update(junk)
    assert out_a == out_b
    for pa, pb in zip(agent.model.parameters(), twin.model.parameters()):
        assert torch.equal(pa, pb)


# ----------------------------------------------------------------------------- CVAE
def test_kl_is_zero_exactly_at_the_prior():
    z = torch.zeros(8, 32)
    assert kl_to_prior(z, z).item() == 0.0
    mu = torch.zeros(2, 3)
    mu[:, 0] = 1.0  # KL(N(1, 1) || N(0, 1)) = 1/2 per sample
    assert kl_to_prior(mu, torch.zeros(2, 3)).item() == pytest.approx(0.5)
    logvar = torch.full((1, 1), math.log(4.0))  # KL(N(0, 4) || N(0, 1)) = (4 - 1 - ln 4) / 2
    assert kl_to_prior(torch.zeros(1, 1), logvar).item() == pytest.approx((3 - math.log(4)) / 2)


def test_update_reports_zero_kl_when_the_encoder_outputs_the_prior(trained):
    agent, eps = trained
    with torch.no_grad():
        agent.model.latent_proj.weight.zero_()
        agent.model.latent_proj.bias.zero_()
    out = agent.update(agent.sample_batch(eps, 8, np.random.default_rng(0)))
    assert out["kl"] == 0.0
    assert out["loss"] == pytest.approx(out["l1"])


def test_inference_uses_z_zero_and_bypasses_the_encoder(trained):
    agent, eps = trained
    obs = eps[0].observations[4]
    first = agent.act(obs)
    assert np.array_equal(agent.act(obs), first)  # deterministic: no dropout, no sampling
    with torch.no_grad():  # a broken CVAE encoder cannot matter at inference ...
        for p in list(agent.model.vae_encoder.parameters()) + [agent.model.cls_embed]:
            p.fill_(float("nan"))
    assert np.array_equal(agent.act(obs), first)
    # ... and z = 0 is what the policy sees: the same as feeding mu = 0, logvar -> -inf.
    norm = agent.norm
    obs_n = ((torch.as_tensor(obs) - norm["obs_mean"]) / norm["obs_std"])[None]
    pred, mu, logvar = agent.model(obs_n)
    assert mu is None and logvar is None
    # Training-mode forward does use the encoder (now NaN): the bypass is real.
    agent.model.train()
    act_n = torch.zeros(1, SMOKE.chunk, 7)
    assert torch.isnan(agent.model(obs_n, act_n, torch.zeros(1, SMOKE.chunk, dtype=bool))[0]).all()


# ----------------------------------------------------------------------------- ensembling
def test_temporal_ensemble_on_a_hand_built_sequence():
    k = 4
    # Chunk predicted at step j has row r = (10 * j + r, -(10 * j + r)).
    chunks = [np.stack([[10 * j + r, -(10 * j + r)] for r in range(k)]).astype(float)
              for j in range(3)]
    # Now = step 2: chunk 0 predicts row 2 (=2), chunk 1 row 1 (=11), chunk 2 row 0 (=20).
    w = np.exp(-0.01 * np.arange(3))
    expected = (w * np.array([2.0, 11.0, 20.0])).sum() / w.sum()
    got = temporal_ensemble(chunks, 0.01)
    assert got == pytest.approx([expected, -expected])
    assert expected < 11.0  # the oldest prediction weighs most
    assert temporal_ensemble(chunks[:1], 0.01) == pytest.approx(chunks[0][0])
    assert temporal_ensemble(chunks, 0.0) == pytest.approx([11.0, -11.0])  # plain mean
    with pytest.raises(ValueError, match="at most k"):
        temporal_ensemble(chunks * 2, 0.01)


def test_agent_with_ensembling_averages_its_own_predictions(trained):
    agent, eps = trained
    te = ACTAgent(OBS_DIM, config=SMOKE, seed=0)   # ensembling: the default
    te.load_state_dict(agent.state_dict())  # inference-only settings may differ
    assert te.h == 1 and agent.h == SMOKE.chunk
    obs_seq = eps[0].observations[:14]
    chunks = [agent.predict_chunk(o) for o in obs_seq]
    te.reset()
    for t, o in enumerate(obs_seq):
        a = te.act(o)
        assert a.shape == (1, 7) and a.dtype == np.float32
        window = chunks[max(0, t - SMOKE.chunk + 1): t + 1]  # only chunks that cover step t
        assert np.allclose(a[0], temporal_ensemble(window, 0.01), atol=1e-6)
    te.reset()  # a new episode forgets the old chunks
    assert np.allclose(te.act(obs_seq[5])[0], chunks[5][0], atol=1e-7)


def test_ensembling_weights_are_exp_minus_001_i_oldest_first():
    """ACT's weights w_i = exp(-0.01 i) / sum_j exp(-0.01 j), i = 0 the oldest prediction:
    k one-hot chunks (chunk j predicts e_j for now) return the weights themselves."""
    k = 10
    chunks = []
    for j in range(k):
        c = np.zeros((k, k))
        c[k - 1 - j, j] = 1.0        # chunk j, predicted k-1-j steps ago: its row for now
        chunks.append(c)
    w = np.exp(-0.01 * np.arange(k))
    np.testing.assert_allclose(temporal_ensemble(chunks, 0.01), w / w.sum(), rtol=1e-12)
    assert ACTConfig().ensemble_coeff == 0.01
    assert all(c.temporal_ensembling for c in ACT_PROFILES.values())
    # m < 0 weighs the newest most: the same weights reversed, finite even for a long chunk.
    w_new = np.exp(0.5 * np.arange(k))
    np.testing.assert_allclose(temporal_ensemble(chunks, -0.5), w_new / w_new.sum(), rtol=1e-12)
    long = [np.tile(np.eye(300)[j], (300, 1)) for j in range(300)]   # chunk j says e_j
    assert np.isfinite(temporal_ensemble(long, -5.0)).all()
    assert temporal_ensemble(long, -5.0)[299] == pytest.approx(1 / np.exp(-5.0 * np.arange(300)).sum())
    for bad in (-5.1, 6.0, float("nan")):
        with pytest.raises(ValueError, match=r"ensemble_coeff.*\[-5.0, 5.0\]"):
            ACTConfig(ensemble_coeff=bad)


def test_harness_evaluates_act_with_a_query_every_step(monkeypatch):
    """The harness's ACT (make_agent with the profile's config) has h = 1, and its
    evaluation worker re-queries the policy at every environment step."""
    from window_bench.harness.methods import get_method, get_profile
    from window_bench.harness.run import AgentPolicy, Evaluator, make_agent

    agent = make_agent(get_method("act"), get_profile("smoke"), [synthetic_episode(23, 0)],
                       seed=0)
    assert agent.h == 1 and AgentPolicy(agent, deterministic=True).h == 1
    calls = []
    real = ACTAgent.predict_chunk
    monkeypatch.setattr(ACTAgent, "predict_chunk",
                        lambda self, obs: calls.append(1) or real(self, obs))
    rows = Evaluator("WindowInstall-A-v0", 1, 1, 12)(ACTAgent, agent.policy_state_dict())
    assert len(rows) == 1 and not rows[0]["success"]
    assert len(calls) == 12        # one query per step of the 12-step episode


# ----------------------------------------------------------------------------- act / I/O
def test_act_shape_range_and_errors(trained):
    agent, eps = trained
    a = agent.act(eps[1].observations[0])
    assert a.shape == (SMOKE.chunk, 7) and a.dtype == np.float32
    assert np.all(np.abs(a) <= 1.0)
    with torch.no_grad():  # a huge output is clipped to the action box
        agent.model.action_head.bias.fill_(1e3)
    assert np.all(agent.act(eps[1].observations[0]) == 1.0)
    with pytest.raises(ValueError, match=r"shape \(52,\)"):
        agent.act(np.zeros(51))
    with pytest.raises(RuntimeError, match="fit_normalizer"):
        ACTAgent(OBS_DIM, config=SMOKE).act(np.zeros(OBS_DIM))


def test_sample_batch_pads_past_the_episode_end():
    eps = [synthetic_episode(23, 0), synthetic_episode(3, 1)]  # the second is shorter than k
    agent = ACTAgent(OBS_DIM, config=SMOKE)
    b = agent.sample_batch(eps, 500, np.random.default_rng(1))
    k = SMOKE.chunk
    assert b["obs"].shape == (500, OBS_DIM) and b["actions"].shape == (500, k, 7)
    assert b["is_pad"].shape == (500, k) and b["is_pad"].dtype == bool
    assert set(b["episode"]) == {0, 1}
    for i in range(500):
        ep, t = eps[b["episode"][i]], b["start"][i]
        assert 0 <= t < ep.T
        n_real = min(k, ep.T - t)
        assert np.array_equal(b["obs"][i], ep.observations[t])
        assert np.array_equal(b["actions"][i, :n_real], ep.actions[t:t + n_real])
        assert np.all(b["actions"][i, n_real:] == 0)
        assert np.array_equal(b["is_pad"][i], np.arange(k) >= n_real)
    # Start steps are uniform over all 26 steps: the short episode gets about 3/26.
    assert 0.06 < np.mean(b["episode"] == 1) < 0.18
    with pytest.raises(ValueError, match="obs_dim"):
        agent.sample_batch([synthetic_episode(5, 0, obs_dim=10)], 4, np.random.default_rng(0))


def episode_with_pauses():
    """23 steps; steps 4-6 and 15 are hesitation pauses (no motion, vacuum held), step 9 only
    switches the vacuum on, the last step is a pause too."""
    ep = synthetic_episode(23, 0)
    ep.actions[:, 6] = -1.0
    ep.actions[9:, 6] = 1.0
    for t in (4, 5, 6, 9, 15, 22):
        ep.actions[t, :6] = 0.0
    return ep


def test_without_noops_drops_the_pauses_only_and_keeps_the_log_complete():
    ep = episode_with_pauses()
    out = without_noops(ep)
    out.validate()
    kept = [t for t in range(23) if t not in (4, 5, 6, 15)]   # 9 switches the vacuum; 22 ends
    assert out.T == len(kept)
    assert np.array_equal(out.actions, ep.actions[kept])
    assert np.array_equal(out.observations[:-1], ep.observations[kept])
    assert np.array_equal(out.observations[-1], ep.observations[-1])
    assert out.terminated[-1] and not out.terminated[:-1].any()
    assert without_noops(synthetic_episode(23, 1)).T == 23      # nothing to drop
    ep.stage_flags[12:, 1] = True                               # entered the opening at 12
    inside = without_noops(ep, before="insertion_entered")
    assert np.array_equal(inside.actions, ep.actions[[t for t in range(23) if t not in (4, 5, 6)]])
    assert without_noops(ep, before="seated").T == out.T
    with pytest.raises(ValueError, match="before='entered'"):
        without_noops(ep, before="entered")


def test_drop_noops_trains_and_normalises_on_the_moving_steps_only():
    ep = episode_with_pauses()
    pauses = ep.observations[[4, 5, 6, 15]]
    agent = ACTAgent(OBS_DIM, config=replace(SMOKE, drop_noops=True))
    b = agent.sample_batch([ep], 400, np.random.default_rng(0))
    assert not any((b["obs"] == p).all(1).any() for p in pauses)
    pause_action = np.array([0, 0, 0, 0, 0, 0, -1], np.float32)   # steps 4-6, vacuum off
    assert not (b["actions"][~b["is_pad"]] == pause_action).all(1).any()
    agent.fit_normalizer([ep])
    kept = without_noops(ep)
    assert np.allclose(agent.norm["obs_mean"].numpy(), kept.observations[:-1].mean(0), atol=1e-6)
    plain = ACTAgent(OBS_DIM, config=SMOKE)
    b = plain.sample_batch([ep], 400, np.random.default_rng(0))
    assert any((b["obs"] == p).all(1).any() for p in pauses)
    assert (b["actions"][~b["is_pad"]] == pause_action).all(1).any()
    with pytest.raises(ValueError, match="drop_noops"):
        ACTConfig(drop_noops="yes")


def test_grasp_features_follow_the_fine_pose_and_read_the_cups_offset():
    from window_bench.installer.supervisor import grasp_features
    eps = [synthetic_episode(23, 0)]
    agent = ACTAgent(OBS_DIM, config=replace(SMOKE, fine_pose_mm=10.0, grasp_mm=10.0), seed=0)
    agent.fit_normalizer(eps)
    assert agent.model.env_dim == OBS_DIM - 40 + 6 + 2
    obs = torch.from_numpy(eps[0].observations[:3].astype(np.float32))
    x = agent.normalize_obs(obs)
    assert x.shape == (3, OBS_DIM + 8)
    assert torch.equal(x[:, -2:], grasp_features(obs, 10.0))
    rebuilt = ACTAgent.from_policy_state_dict(agent.policy_state_dict())
    assert np.array_equal(rebuilt.predict_chunk(obs[1].numpy()),
                          agent.predict_chunk(obs[1].numpy()))
    agent.train_offline(eps, 2)
    with pytest.raises(ValueError, match=r"grasp_mm = 10.0 needs the flat state"):
        ACTAgent(20, config=replace(SMOKE, robot_dim=0, grasp_mm=10.0))
    with pytest.raises(ValueError, match=r"grasp_mm = -1 .* \[0.0, 1000.0\]"):
        ACTConfig(grasp_mm=-1)


def test_action_power_learns_and_acts_in_companded_units():
    """With ``action_power = 2`` the normaliser and the targets are ``sign(a) |a|^(1/2)`` on
    the arm's entries (the vacuum as is), and acting maps the model's output back."""
    ep = synthetic_episode(40, 0)
    ep.actions[:, :6] = 0.04                      # a 1 mm step: 0.2 companded units
    plain = ACTAgent(OBS_DIM, config=SMOKE, seed=0)
    comp = ACTAgent(OBS_DIM, config=replace(SMOKE, action_power=2.0), seed=0)
    for agent in (plain, comp):
        agent.fit_normalizer([ep])
    assert plain.norm["act_mean"][:6].numpy() == pytest.approx(0.04, abs=1e-6)
    assert comp.norm["act_mean"][:6].numpy() == pytest.approx(0.2, abs=1e-6)
    assert comp.norm["act_mean"][6].item() == pytest.approx(ep.actions[:, 6].mean(), abs=1e-6)
    # an untrained model predicts ~0 normalised units -> the mean -> 0.2 ** 2 = 0.04 in the env
    with torch.no_grad():
        for p in comp.model.parameters():
            p.zero_()
    chunk = comp.predict_chunk(ep.observations[0].astype(np.float32))
    assert chunk[:, :6] == pytest.approx(0.04, abs=1e-6)
    comp.train_offline([ep], 2)
    with pytest.raises(ValueError, match=r"action_power = 0.5 .* \[1.0, 4.0\]"):
        ACTConfig(action_power=0.5)


def test_normalizer_floors_constant_dims():
    ep = synthetic_episode(40, 0)
    ep.actions[:, 6] = 1.0  # setting A: the vacuum is always on
    agent = ACTAgent(OBS_DIM, config=SMOKE)
    agent.fit_normalizer([ep])
    assert agent.norm["act_std"][6].item() == pytest.approx(1e-2)
    assert agent.norm["act_mean"][6].item() == pytest.approx(1.0)
    assert np.allclose(agent.norm["obs_mean"].numpy(), ep.observations[:-1].mean(0), atol=1e-6)
    assert np.allclose(agent.norm["act_std"][:6].numpy(), ep.actions[:, :6].std(0), atol=1e-6)


def test_state_dict_round_trip_is_exact(trained):
    agent, eps = trained
    buf = io.BytesIO()
    torch.save(agent.state_dict(), buf)
    buf.seek(0)
    sd = torch.load(buf, weights_only=True)
    other = ACTAgent(OBS_DIM, config=agent.config, seed=99)
    other.load_state_dict(sd)
    obs = eps[0].observations[7]
    assert np.array_equal(other.act(obs), agent.act(obs))
    logs_a, logs_b = agent.train_offline(eps, 3), other.train_offline(eps, 3)
    assert logs_a == logs_b  # same batches (sampling RNG), same noise, same optimizer state
    for pa, pb in zip(agent.model.parameters(), other.model.parameters()):
        assert torch.equal(pa, pb)
    # The state dict is a snapshot, not a view of live tensors.
    assert not torch.equal(sd["model"]["action_head.weight"], agent.model.action_head.weight)
    with pytest.raises(ValueError, match="d_model"):
        ACTAgent(OBS_DIM, config=replace(SMOKE, d_model=64)).load_state_dict(sd)
    # An evaluation worker rebuilds the agent from the state alone.
    rebuilt = ACTAgent.from_state_dict(agent.state_dict())
    assert rebuilt.config == agent.config
    assert np.array_equal(rebuilt.act(obs, deterministic=True), agent.act(obs))
    with pytest.raises(ValueError, match="deterministic=False"):
        rebuilt.act(obs, deterministic=False)


def test_config_and_constructor_errors():
    with pytest.raises(ValueError, match=r"n_heads = 3 must divide d_model = 32"):
        replace(SMOKE, n_heads=3)
    with pytest.raises(ValueError, match=r"ACTConfig.chunk = 0"):
        ACTConfig(chunk=0)
    with pytest.raises(ValueError, match=r"dropout = 1.0"):
        ACTConfig(dropout=1.0)
    with pytest.raises(ValueError, match=r"lr = -1"):
        ACTConfig(lr=-1)
    with pytest.raises(ValueError, match=r"robot_dim = 40 .* obs_dim = 20"):
        ACTAgent(20, config=SMOKE)
    with pytest.raises(ValueError, match="unknown"):
        ACTAgent(OBS_DIM, config="huge")
    one_token = ACTAgent(20, config=replace(SMOKE, robot_dim=0))
    assert one_token.model.env_proj is None and one_token.model.robot_dim == 20


def test_flat_robot_dim_matches_the_environment():
    env = gym.make("WindowInstall-A-v0", obs_mode="state")
    try:
        sizes = [env.observation_space[key].shape[0] for key in STATE_KEYS]
    finally:
        env.close()
    robot = [key.startswith("robot0_") for key in STATE_KEYS]
    n_robot = sum(robot)
    assert all(robot[:n_robot]) and not any(robot[n_robot:])  # robot keys come first
    assert sum(sizes[:n_robot]) == FLAT_ROBOT_DIM and sum(sizes) == OBS_DIM


# ----------------------------------------------------------------------------- learning
def test_smoke_model_learns_from_scripted_demos(demos):
    assert all(ep.terminated[-1] for ep in demos) and all(ep.T > 50 for ep in demos)
    agent = ACTAgent(OBS_DIM, config=SMOKE, seed=0)
    agent.fit_normalizer(demos)
    before = agent.chunk_l1(demos)
    logs = agent.train_offline(demos, 150)
    first = np.mean([g["loss"] for g in logs[:20]])
    last = np.mean([g["loss"] for g in logs[-20:]])
    assert last < 0.5 * first, (first, last)
    assert agent.chunk_l1(demos) < 0.6 * before
    assert agent.grad_steps == 150


def test_script_trains_evaluates_and_resumes(tmp_path):
    from baselines.act import main
    from window_bench.harness.files import load_state

    out, ckpt, pol = tmp_path / "act.json", tmp_path / "act.pt", tmp_path / "policies"
    common = ["--profile", "smoke", "--demos", "2", "--heldout", "1", "--eval-every", "10",
              "--out", str(out), "--save", str(ckpt), "--policies", str(pol),
              "--agent-config", "latent_dim=3"]
    main(common + ["--steps", "10", "--episodes", "0"])
    result = main(common + ["--steps", "20", "--episodes", "1", "--resume"])
    rows = result["checkpoints"]
    assert [r["grad_steps"] for r in rows] == [10, 20]
    assert rows[1]["chunked"]["episodes"] == 1 and rows[1]["temporal_ensembling"]["episodes"] == 1
    ep = rows[1]["chunked"]["rows"][0]   # the diagnostics of an evaluation episode
    assert ep["stage"] in STAGES and 0 <= ep["vacuum_off_steps"] <= ep["steps"]
    assert len(ep["abs_action_mean"]) == 7 and ep["grip_breaks"] >= 0
    assert result["demo_successes"] == 2 and result["provenance"]["git_commit"]
    assert result["config"]["latent_dim"] == 3
    assert ACTAgent.from_state_dict(torch.load(ckpt, weights_only=True)).grad_steps == 20
    # each checkpoint's acting weights, as the harness writes them, with their size recorded
    f = pol / "step_0000020.safetensors"
    assert f.stat().st_size == rows[1]["policy_bytes"]
    policy = ACTAgent.from_policy_state_dict(load_state(f, "policy")[0])
    assert policy.config.latent_dim == 3
    with pytest.raises(SystemExit):
        main(common + ["--agent-config", "nope=1"])


def test_cpu_policy_file_is_under_1_mb_without_the_cvae_encoder():
    """The `cpu` profile's acting weights, as the harness writes them (safetensors), stay
    under 1 MB (a reported policy is committed as this file), and leave out the CVAE
    encoder, which only training runs."""
    from window_bench.harness.files import dump_state

    agent = ACTAgent(OBS_DIM, config=ACT_PROFILES["cpu"], seed=0)
    agent.fit_normalizer([synthetic_episode(23, 0)])
    sd = agent.policy_state_dict()
    size = len(dump_state(sd, "policy", {"agent_kind": "act", "env_id": "WindowInstall-A-v0"}))
    assert size <= 1_000_000, size
    assert not [k for k in sd["model"] if k.startswith(("cls_embed", "vae_", "latent_proj."))]
    cvae = sum(p.numel() for n, p in agent.model.named_parameters()
               if n.startswith(("cls_embed", "vae_", "latent_proj.")))
    acting = sum(v.numel() for v in sd["model"].values())
    assert cvae > 0 and acting + cvae == sum(p.numel() for p in agent.model.parameters())
    # the paper-size policy is far larger: the bound is a property of the cpu sizes
    big = ACTAgent(OBS_DIM, config=replace(ACT_PROFILES["cpu"], d_model=256, ff=1024), seed=0)
    big.norm = agent.norm
    assert len(dump_state(big.policy_state_dict(), "policy")) > 4 * size


def test_trainset_script_replays_a_policy_file_in_both_modes(tmp_path):
    import importlib.util

    from window_bench.harness.files import RunFileError, dump_state

    spec = importlib.util.spec_from_file_location(
        "act_trainset", Path(__file__).parents[1] / "experiments/sanity/act_trainset.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    eps = _collect_demos("WindowInstall-A-v0", [0])
    agent = ACTAgent(OBS_DIM, config=SMOKE, seed=0)
    agent.train_offline(eps, 5)
    f = tmp_path / "step_0000005.safetensors"
    f.write_bytes(dump_state(agent.policy_state_dict(), "policy"))
    result = script.main(["--policy", str(f), "--demos", "1", "--stall", "1",
                          "--max-steps", "40", "--out", str(tmp_path)])
    for mode in script.MODES:
        s = result[f"train_starts/{mode}"]
        assert s["episodes"] == 1 and s["rows"][0]["seed"] == 0 and len(s["wilson95"]) == 2
        row = s["rows"][0]
        assert 0 <= row["progress_end_step"] <= row["steps"] <= 40 and row["closest_mm"] >= 0
        # lateral offsets from the seat axis (x, z), in mm, at the closest approach and the end
        assert len(row["lateral_at_closest_mm"]) == 2 and min(row["lateral_end_mm"]) >= 0
        assert s["pr_s"] in (0.0, 1.0)
    assert result["policy_bytes"] == f.stat().st_size and result["demo_seeds"] == [0]
    (stall,) = result["stall"]
    assert stall["seed"] == 0 and stall["stalled_steps"] >= 1
    assert stall["nearest_demo_distance_median"] >= 0 and stall["demo_abs_pose_action_all"] > 0


def test_feedback_gain_of_a_policy_that_cancels_the_offset_is_minus_the_shift():
    """The feedback-gain probe (experiments/sanity/act_feedback_gain.py) on hand-built
    policies: one that commands, in the TCP frame, the world motion cancelling the observed
    lateral offset within its chunk has gain -delta; one that ignores the offset has 0."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "act_feedback_gain", Path(__file__).parents[1] / "experiments/sanity/act_feedback_gain.py")
    probe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(probe)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(300, OBS_DIM)).astype(np.float32)
    q = rng.normal(size=(300, 4))
    obs[:, probe.EEF_QUAT] = q / np.linalg.norm(q, axis=1, keepdims=True)
    rel = rng.uniform(-0.01, 0.01, (300, 3))
    rel[:, 1] = np.repeat([0.11, 0.2, 0.5], 100)  # 100 states in each distance band
    obs[:, FLAT_ROBOT_DIM:FLAT_ROBOT_DIM + 3] = rel
    rot = probe.tcp_rotations(obs.astype(np.float64))
    assert np.allclose(np.einsum("nij,nkj->nik", rot, rot), np.eye(3), atol=1e-6)

    def cancelling(o):
        world = -o[:, FLAT_ROBOT_DIM:FLAT_ROBOT_DIM + 3].astype(np.float64)
        world[:, 1] = 0.0
        tcp = np.einsum("nji,nj->ni", probe.tcp_rotations(o.astype(np.float64)), world)
        chunk = np.zeros((len(o), 10, 7))
        chunk[:, :, :3] = tcp[:, None] / (10 * probe.M_PER_UNIT)
        return chunk

    for name, g in probe.gains(cancelling, obs, 0.005).items():
        assert g["states"] > 0 and abs(g["median_mm"] + 5.0) < 1e-3, (name, g)
    for g in probe.gains(lambda o: np.zeros((len(o), 10, 7)), obs, 0.005).values():
        assert g["median_mm"] == 0.0


def test_bc_flow_eval_reads_a_stage1_entry_and_evaluates_teacher_and_student(tmp_path, capsys):
    """experiments/sanity/bc_flow_eval.py: a Stage I entry (the harness's format, here a
    tiny untrained QC-FQL) is only read; both policies act in open-loop chunks of h."""
    import importlib.util
    import sys

    from baselines.qcfql import QCFQLAgent, QCFQLConfig
    from window_bench.harness.files import RunFileError, dump_state

    path = Path(__file__).parents[1] / "experiments/sanity/bc_flow_eval.py"
    sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location("bc_flow_eval", path)
        script = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(script)
    finally:
        sys.path.remove(str(path.parent))
    agent = QCFQLAgent(OBS_DIM, 7, QCFQLConfig(h=5, hidden=(16,)), seed=0)
    entry = tmp_path / "cache" / "abcdef0123.safetensors"
    entry.parent.mkdir()
    entry.write_bytes(dump_state({"agent": agent.state_dict()}, "stage1"))
    before = entry.read_bytes()
    result = script.main([str(entry), "--dev", "1", "--train-starts", "0", "--max-steps", "12",
                          "--out", str(tmp_path)])
    assert entry.read_bytes() == before and (tmp_path / "bc_flow_abcdef01.json").is_file()
    for policy in script.POLICIES:
        s = result["sets"][f"dev/{policy}"]
        assert s["episodes"] == 1 and s["rows"][0]["seed"] == 100000
        assert s["rows"][0]["steps"] == 12 and s["pr_s"] in (0.0, 1.0)
    # a finished run's state file holds the same agent; a cache entry is not read as one
    run_state = tmp_path / "RUN" / "state.safetensors"
    run_state.parent.mkdir()
    run_state.write_bytes(dump_state({"agent": agent.state_dict(), "counters": {}}, "state"))
    again = script.main([str(run_state), "--dev", "1", "--train-starts", "0", "--max-steps",
                         "12", "--out", str(tmp_path)])
    assert (tmp_path / "bc_flow_RUN.json").is_file()
    assert again["sets"]["dev/teacher"]["rows"] == result["sets"]["dev/teacher"]["rows"]
    (tmp_path / "X").mkdir()
    (tmp_path / "X" / "state.safetensors").write_bytes(before)
    with pytest.raises(SystemExit) as refused:   # one line, exit 2, no traceback
        script.main([str(tmp_path / "X" / "state.safetensors"), "--train-starts", "0"])
    assert refused.value.code == 2
    assert "not a state file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.main([str(tmp_path / "missing.safetensors"), "--train-starts", "0"])
    with pytest.raises(SystemExit):   # training starts need the demos' directory
        script.main([str(entry), "--dev", "0"])
