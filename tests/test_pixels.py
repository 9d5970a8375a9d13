"""The pixel observation track: encoder shapes, the frozen backbone, weight files, cached
features and determinism (window_bench.pixels)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from window_bench.pixels import weights as W
from window_bench.pixels.encoder import (EMBED_DIM, OBS_DIM, PROPRIO_DIM, VIEW_FEATURES,
                                         PixelObsEncoder, ResNet10, frozen, split_observation)
from window_bench.pixels.features import PixelFeatures, encode_views, make_pixel_env

ENV = "WindowInstall-A-v0"


@pytest.fixture(scope="module")
def backbone():
    """A seeded random backbone: these tests check plumbing, not what the features mean."""
    with torch.random.fork_rng():
        torch.manual_seed(0)
        return frozen(ResNet10())


def _random_obs(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, OBS_DIM, generator=g)


def test_shapes(backbone):
    images = torch.randint(0, 256, (3, 128, 128, 3), dtype=torch.uint8)
    with torch.no_grad():
        fmap = backbone(images)
    assert fmap.shape == (3, 512, 4, 4)
    maps, proprio = split_observation(_random_obs(5))
    assert [m.shape for m in maps] == [(5, 512, 4, 4)] * 2 and proprio.shape == (5, PROPRIO_DIM)
    assert OBS_DIM == 2 * VIEW_FEATURES + PROPRIO_DIM
    enc = PixelObsEncoder(seed=0)
    out = enc(_random_obs(5))
    assert out.shape == (5, 2 * EMBED_DIM + PROPRIO_DIM) == (5, PixelObsEncoder.out_dim)
    assert out[:, :2 * EMBED_DIM].abs().max() < 1.0          # tanh embeddings
    with pytest.raises(ValueError, match="expected"):
        enc(torch.zeros(5, OBS_DIM - 1))
    maps, _ = split_observation(_random_obs(5))
    view = enc.views[0]
    torch.testing.assert_close(view(maps[0]), view.unfolded(maps[0]), atol=1e-5, rtol=1e-4)
    with pytest.raises(ValueError, match=r"\(B, H, W, 3\)"):
        backbone(torch.zeros(1, 3, 128, 128, dtype=torch.uint8))


def test_backbone_frozen_through_a_training_step(backbone):
    """Gradients of a loss through the whole encoder reach the aggregation, never the
    backbone; the backbone (weights and BatchNorm statistics) is bit-identical after it."""
    before = {k: v.clone() for k, v in backbone.state_dict().items()}
    enc = PixelObsEncoder(seed=1)
    opt = torch.optim.Adam([*enc.parameters(), *backbone.parameters()], lr=1e-2)
    images = torch.randint(0, 256, (4, 128, 128, 3), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(0))
    fmaps = backbone(images).reshape(2, -1)                   # 2 observations x 2 views
    obs = torch.cat([fmaps, torch.zeros(2, PROPRIO_DIM)], dim=1)
    loss = enc(obs).square().sum()
    opt.zero_grad()
    loss.backward()
    opt.step()
    assert all(p.grad is None for p in backbone.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in enc.views.parameters())
    after = backbone.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_pixel_agent_update_keeps_backbone_and_trains_aggregation(backbone):
    from baselines.qcfql import QCFQLConfig
    from window_bench.pixels.agent import PixelQCFQL

    before = {k: v.clone() for k, v in backbone.state_dict().items()}
    agent = PixelQCFQL(QCFQLConfig(h=2, hidden=(32, 32), batch_size=8), seed=0)
    agg0 = agent.encoder.views[0].spatial.kernel.detach().clone()
    batch = _batch(8, h=2)
    metrics = agent.update(batch)
    assert np.isfinite(metrics["loss"]) and agent.num_updates == 1
    assert not torch.equal(agg0, agent.encoder.views[0].spatial.kernel)
    assert all(torch.equal(before[k], v) for k, v in backbone.state_dict().items())
    chunk = agent.act(batch["obs"][0].numpy(), deterministic=True)
    assert chunk.shape == (2, 7)
    from window_bench.harness.agent import check_plain

    obs3 = batch["obs"][:3].numpy()
    for state, restore in ((agent.state_dict(), PixelQCFQL.from_state_dict),
                           (agent.policy_state_dict(), PixelQCFQL.from_policy_state_dict)):
        check_plain(state)                                    # writable without pickle
        np.testing.assert_array_equal(restore(state).act(obs3, deterministic=True),
                                      agent.act(obs3, deterministic=True))


def test_flow_trains_encoder_sends_the_teachers_gradient_into_the_aggregation():
    """``flow_trains_encoder``: the aggregation's gradient is the critic's plus the flow
    teacher's (without it, the critic's alone); the student never trains it."""
    from baselines.qcfql import QCFQLConfig
    from window_bench.pixels.agent import PixelQCFQL

    def grad(**kw):
        agent = PixelQCFQL(QCFQLConfig(h=2, hidden=(32, 32), batch_size=8, **kw), seed=0)
        b = _batch(8, h=2)
        emb, next_emb = agent.encoder.encode_pair(b["obs"], b["next_obs"])
        parts = agent.agent.prepare({**b, "obs": emb, "next_obs": next_emb})
        torch.manual_seed(0)
        critic, _ = agent.agent.critic_loss(parts)
        (g_critic,) = torch.autograd.grad(critic, agent.encoder.views[0].spatial.kernel,
                                          retain_graph=True)
        agent.encoder_optimizer.zero_grad(set_to_none=True)
        torch.manual_seed(1)
        agent.update(b)
        return g_critic, agent.encoder.views[0].spatial.kernel.grad

    g_critic, g_off = grad()
    _, g_on = grad(flow_trains_encoder=True)
    torch.testing.assert_close(g_off, g_critic)
    assert not torch.allclose(g_on, g_off)
    with pytest.raises(ValueError, match="flow_trains_encoder = 1 is not allowed"):
        QCFQLConfig(flow_trains_encoder=1)


def test_pixel_agent_from_the_harness_spec():
    from window_bench.harness.agent import AgentSpec
    from window_bench.harness.methods import PROFILES
    from window_bench.pixels.agent import PixelQCFQL

    mean, std = np.zeros(OBS_DIM), np.ones(OBS_DIM)
    mean[-PROPRIO_DIM:], std[-PROPRIO_DIM:] = 0.5, 2.0
    spec = AgentSpec(obs_dim=OBS_DIM, action_dim=7, h=10, seed=0, profile=PROFILES["smoke"],
                     demos=[], obs_mean=mean, obs_std=std, overrides={"alpha": 30.0})
    agent = PixelQCFQL.create(spec)
    assert agent.h == 10 and agent.config.alpha == 30.0
    assert agent.config.hidden == tuple(PROFILES["smoke"].hidden)
    assert torch.equal(agent.encoder.proprio_mean, torch.full((PROPRIO_DIM,), 0.5))
    with pytest.raises(ValueError, match="obs_dim = 52"):
        PixelQCFQL.create(dataclasses.replace(spec, obs_dim=52))


def _batch(n: int, h: int) -> dict:
    g = torch.Generator().manual_seed(n)
    return {"obs": _random_obs(n, 1), "next_obs": _random_obs(n, 2),
            "actions": torch.rand(n, h, 7, generator=g) * 2 - 1,
            "action_mask": torch.ones(n, h, dtype=torch.bool), "reward": torch.zeros(n),
            "discount": torch.full((n,), 0.98), "terminal": torch.zeros(n, dtype=torch.bool),
            "valid": torch.ones(n, dtype=torch.bool),
            "episode_accepted": torch.ones(n, dtype=torch.bool),
            "provenance_code": torch.ones(n, h, dtype=torch.uint8)}


# ---------------------------------------------------------------- weight files
def test_weights_round_trip_and_timm_layout(tmp_path):
    with torch.random.fork_rng():
        torch.manual_seed(3)
        model = ResNet10()
    path = tmp_path / "w.safetensors"
    size = W.save_backbone(model, path, {"note": "test"})
    assert size < 10_000_000                                  # float16: ships in the package
    loaded = W.load_backbone(path)
    assert not loaded.training and not any(p.requires_grad for p in loaded.parameters())
    for k, v in model.state_dict().items():
        expect = v.to(torch.float16).float() if v.is_floating_point() else v
        assert torch.equal(loaded.state_dict()[k], expect), k
    assert W.weights_record(path) == {"note": "test"}
    # a timm file: float32, with the ImageNet classifier and no num_batches_tracked
    from safetensors.torch import save_file

    sd = {k: v.contiguous() for k, v in model.state_dict().items()
          if not k.endswith("num_batches_tracked")}
    sd.update({"fc.weight": torch.zeros(1000, 512), "fc.bias": torch.zeros(1000)})
    save_file(sd, str(tmp_path / "timm.safetensors"))
    timm = W.load_backbone(tmp_path / "timm.safetensors")
    assert torch.equal(timm.layer4[0].conv2.weight, model.layer4[0].conv2.weight)


def test_wrong_weight_files_are_refused(tmp_path):
    from safetensors.torch import save_file

    sd = ResNet10().state_dict()
    cases = {
        "not_safetensors": ("pickle", "not a safetensors weights file"),
        "missing": ({k: v for k, v in sd.items() if k != "layer2.0.conv1.weight"},
                    "1 missing keys"),
        "unexpected": ({**sd, "head.weight": torch.zeros(3)}, "1 unexpected keys"),
        "shape": ({**sd, "layer1.0.conv1.weight": torch.zeros(64, 64, 1, 1)}, "wrong shape"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / f"{name}.safetensors"
        if content == "pickle":
            torch.save(sd, path)                              # a pickle is never loaded
        else:
            save_file({k: v.contiguous() for k, v in content.items()}, str(path))
        with pytest.raises(W.WeightsError, match=message):
            W.load_backbone(path)
    with pytest.raises(W.WeightsError, match="no such file"):
        W.load_backbone(tmp_path / "absent.safetensors")


def test_no_silent_random_encoder(monkeypatch, tmp_path):
    monkeypatch.setattr(W, "DEFAULT_WEIGHTS", tmp_path / "absent.safetensors")
    with pytest.raises(W.WeightsError, match="bench encoder train"):
        W.resolve_backbone(None)
    model, label = W.resolve_backbone(None, allow_random=True)
    assert label.startswith("random")


def test_cli_encoder_info_rejects_a_wrong_file(tmp_path, capsys):
    from window_bench.cli import main

    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"\x00" * 64)
    assert main(["encoder", "info", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "not a safetensors weights file" in err
    assert len(err.splitlines()) == 1


# ---------------------------------------------------------------- features in the env
def _run(env, seed: int, steps: int) -> list:
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        a = rng.uniform(-0.3, 0.3, 7).astype(np.float32)
        a[6] = 1.0
        obs, *_ = env.step(a)
        out.append(obs)
    return out


def test_feature_wrapper_is_deterministic_and_matches_on_the_fly(backbone):
    import gymnasium as gym

    env = make_pixel_env(ENV, backbone)
    assert env.observation_space.shape == (OBS_DIM,)
    first = _run(env, seed=5, steps=3)
    second = _run(env, seed=5, steps=3)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)                   # same seed, same features
    fmap = np.stack(first)[:, :2 * VIEW_FEATURES]
    assert np.array_equal(fmap, fmap.astype(np.float16).astype(np.float32))  # lossless fp16
    env.close()

    # On the fly: the raw views of the same episode, the backbone run on all of them in one
    # batch, then the trainable encoder; it matches the encoder on the cached features.
    raw_env = gym.make(ENV, obs_mode="pixels")
    raw = _run(raw_env, seed=5, steps=3)
    raw_env.close()
    for cached, obs in zip(first, raw):
        np.testing.assert_array_equal(cached, encode_views(backbone, obs))
    images = torch.from_numpy(np.stack([o[v] for o in raw for v in ("wrist_rgb", "side_rgb")]))
    with torch.no_grad():
        fly = backbone(images).to(torch.float16).float().reshape(len(raw), -1)
    proprio = torch.from_numpy(np.stack([o["robot0_proprio"] for o in raw]))
    enc = PixelObsEncoder(seed=0)
    with torch.no_grad():
        from_cache = enc(torch.from_numpy(np.stack(first)))
        on_the_fly = enc(torch.cat([fly, proprio], dim=1))
    torch.testing.assert_close(from_cache, on_the_fly, atol=2e-3, rtol=0)


def test_wrapper_refuses_state_envs_and_trainable_backbones(backbone):
    import gymnasium as gym

    with pytest.raises(ValueError, match="obs_mode='pixels'"):
        PixelFeatures(gym.make(ENV, obs_mode="flat"), backbone)
    with pytest.raises(ValueError, match="frozen"):
        PixelFeatures(gym.make(ENV, obs_mode="pixels"), ResNet10())


def test_pixel_smoke_pipeline_is_deterministic(backbone):
    """Rollout -> chunk replay -> updates on the pixel track, twice with one seed: the
    same logged features, the same batches, the same parameters."""
    from baselines.qcfql import QCFQLConfig
    from window_bench.data.replay import ChunkReplay
    from window_bench.installer.rollout import Rollout
    from window_bench.pixels.agent import PixelQCFQL

    class Policy:
        h = 2

        def __init__(self, agent):
            self.agent = agent

        def act(self, obs):
            return self.agent.act(obs)

    def once():
        agent = PixelQCFQL(QCFQLConfig(h=2, hidden=(32, 32), batch_size=4), seed=0)
        env = make_pixel_env(ENV, backbone, max_episode_steps=4)
        log = Rollout(env, Policy(agent)).run(seed=11)
        env.close()
        replay = ChunkReplay(capacity=16, h=2, gamma=0.99, seed=0)
        replay.add_episode(log)
        for _ in range(2):
            agent.update(replay.sample(4))
        return log.observations, agent.encoder.state_dict(), agent.agent.critic.state_dict()

    a, b = once(), once()
    np.testing.assert_array_equal(a[0], b[0])
    for sa, sb in zip(a[1:], b[1:]):
        assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_heldout_quality_reports_against_the_mean_predictor():
    from window_bench.pixels.pretrain import GROUPS, TARGETS, heldout_quality

    rng = np.random.default_rng(0)
    truth = rng.standard_normal((50, len(TARGETS)))
    mean = truth.mean(0)
    perfect = heldout_quality(truth, truth, mean)
    blind = heldout_quality(np.tile(mean, (50, 1)), truth, mean)
    assert set(perfect) == set(GROUPS)
    for name in GROUPS:
        assert perfect[name]["rmse"] == 0.0 and perfect[name]["r2"] == pytest.approx(1.0)
        assert blind[name]["rmse"] == pytest.approx(blind[name]["rmse_mean_predictor"])
        assert blind[name]["r2"] == pytest.approx(0.0, abs=1e-9)


def test_cli_encoder_train_rejects_bad_arguments_before_work(capsys):
    from window_bench.cli import main

    for argv in (["--episodes", "0"], ["--lr", "2"], ["--seed", "-1"], ["--env", "Nope-v0"]):
        with pytest.raises(SystemExit) as exc:
            main(["encoder", "train", "--out", "x.safetensors", *argv])
        assert exc.value.code == 2
    assert "error" in capsys.readouterr().err


def test_pixel_demos_replay_the_state_demos_exactly(backbone):
    """A state-track episode re-observed on the pixel track: same steps, the proprioception
    equals the flat state's robot0_proprio, and a log that does not replay is refused."""
    import gymnasium as gym

    from window_bench.envs.env import STATE_KEYS
    from window_bench.installer.rollout import Rollout
    from window_bench.installer.scripted import RandomPolicy
    from window_bench.harness.tracks import get_track
    from window_bench.pixels.track import make_track_env, pixel_demos, proprio_normalizer

    env = make_track_env(ENV, "state", max_episode_steps=4)
    log = Rollout(env, RandomPolicy(env, seed=0), provenance="demo").run(seed=21)
    env.close()
    [pix] = pixel_demos([log], ENV, backbone)
    assert pix.observations.shape == (log.T + 1, OBS_DIM)
    np.testing.assert_array_equal(pix.actions, log.actions)
    sizes = dict(zip(STATE_KEYS, (7, 7, 3, 4, 1, 18, 3, 3, 6)))
    start = sum(sizes[k] for k in STATE_KEYS[:STATE_KEYS.index("robot0_proprio")])
    np.testing.assert_allclose(pix.observations[:, -PROPRIO_DIM:],
                               log.observations[:, start:start + PROPRIO_DIM], rtol=0, atol=1e-6)
    mean, std = proprio_normalizer(pix.observations)
    assert mean.shape == std.shape == (PROPRIO_DIM,)
    tampered = dataclasses.replace(log, rewards=log.rewards + 1.0)
    with pytest.raises(RuntimeError, match="diverges on replay at step 0"):
        pixel_demos([tampered], ENV, backbone)
    with pytest.raises(ValueError, match="allowed: state, pixels"):
        get_track("rgb")
    pixels = get_track("pixels")
    assert pixels.agent_kind("qcfql") == "qcfql-pixels"
    assert get_track("state").agent_kind("hilserl") == "hilserl"
    assert pixels.agent_kind("hilserl") == "hilserl-pixels"
    assert pixels.agent_kind("sac") == "sac-pixels"
    assert pixels.agent_kind("act") == "act-pixels"
    with pytest.raises(ValueError, match="not available for the 'bc' agent"):
        pixels.agent_kind("bc")
    assert isinstance(make_track_env(ENV, "state").observation_space, gym.spaces.Box)


def test_the_shipped_default_encoder_loads_with_its_record():
    """The package's default backbone is a real weights file (not a pointer or a stub) with
    its training command and held-out quality."""
    assert W.DEFAULT_WEIGHTS.is_file() and W.DEFAULT_WEIGHTS.stat().st_size < 10_000_000
    model, label = W.resolve_backbone(None)
    assert label == f"default:{W.DEFAULT_WEIGHTS.name}" and not model.training
    record = W.weights_record(W.DEFAULT_WEIGHTS)
    assert record["command"].startswith("bench encoder train")
    assert record["heldout_quality"]["panel position rel. seat (mm)"]["r2"] > 0.5


def test_bench_run_on_the_pixel_track(tmp_path):
    """``Run(track="pixels")``: the pixel agent kind, demos re-observed, evaluation workers
    on the pixel env, the track and the encoder in results.json; an unknown track and a
    missing weights file are refused before any work."""
    import json

    from window_bench.harness.run import Run

    out = tmp_path / "run"
    run = Run("qcfql-offline", ENV, "smoke", 0, out, track="pixels", progress=False)
    assert run.method.agent == "qcfql-pixels" and run.encoder["weights"].startswith("default:")
    r = run.train()
    saved = json.loads((out / "results.json").read_text())
    assert r["track"] == saved["track"] == "pixels"
    assert saved["method"]["agent"] == "qcfql-pixels"
    assert saved["encoder"]["sha256"] and saved["encoder"]["command"].startswith("bench encoder")
    assert len(saved["checkpoints"]) == 1 and saved["checkpoints"][0]["episodes"] == 2
    # Determinism: the same seed again (on the same demonstrations) gives the same policy
    # tensors and the same evaluation, also through the Stage I cache `bench sweep` passes.
    again = Run("qcfql-offline", ENV, "smoke", 0, tmp_path / "again", track="pixels",
                demos=out / "demos", stage1_cache=tmp_path / "stage1_cache",
                progress=False).train()
    assert again["stage1"]["cache_hit"] is False and len(list(
        (tmp_path / "stage1_cache").glob("*.safetensors"))) == 1
    drop = lambda cp: {k: v for k, v in cp.items() if k != "wall_clock_s"}  # noqa: E731
    assert [drop(c) for c in again["checkpoints"]] == [drop(c) for c in r["checkpoints"]]
    from safetensors.torch import load_file

    a, b = (load_file(str(d / "policies" / "step_0000000.safetensors"))
            for d in (out, tmp_path / "again"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="track='rgb'"):
        Run("act", ENV, "smoke", 0, tmp_path / "h", track="rgb")
    with pytest.raises(W.WeightsError, match="no such file"):
        Run("qcfql", ENV, "smoke", 0, tmp_path / "w", track="pixels",
            encoder_weights=tmp_path / "absent.safetensors")


# ---------------------------------------------------------------- float16 feature storage
def test_replay_stores_features_as_float16_and_acts_as_on_the_fly(backbone):
    """The pixel replay keeps the feature maps as float16 (half the bytes) and returns the
    same float32 batches as a float32 replay; the policy acts on cached float16 features as
    on the backbone's unrounded float32 output, within 1e-2 per action value (embeddings
    within 2e-2): float16 rounding of a map is below 5e-4 relative."""
    import gymnasium as gym

    from baselines.qcfql import QCFQLConfig
    from window_bench.data.replay import ChunkReplay
    from window_bench.installer.rollout import Rollout
    from window_bench.pixels.agent import PixelQCFQL
    from window_bench.pixels.encoder import FEATURE_VALUES

    agent = PixelQCFQL(QCFQLConfig(h=2, hidden=(32, 32), batch_size=4), seed=0)

    class Policy:
        h = 2

        def act(self, obs):
            return agent.act(obs, deterministic=True)

    env = make_pixel_env(ENV, backbone, max_episode_steps=6)
    log = Rollout(env, Policy()).run(seed=3)
    env.close()
    half, full = (ChunkReplay(8, 2, 0.99, seed=0, half_obs=n) for n in (FEATURE_VALUES, 0))
    for rb in (half, full):
        rb.add_episode(log)
    stored = half._buffer.storage._storage
    assert stored["obs_half"].dtype == torch.float16 and stored["obs"].shape[1:] == (PROPRIO_DIM,)
    a, b = half.sample(5), full.sample(5)
    assert set(a.keys()) == set(b.keys())
    assert all(torch.equal(a[k], b[k]) for k in b.keys())   # same draws, same float32 values
    restored = ChunkReplay(8, 2, 0.99, seed=0, half_obs=FEATURE_VALUES)
    restored.load_state_dict(half.state_dict())
    assert torch.equal(restored.sample(3)["next_obs"], half.sample(3)["next_obs"])
    with pytest.raises(ValueError, match="half_obs"):
        full.load_state_dict(half.state_dict())
    bad = dataclasses.replace(log, observations=log.observations + np.float32(1e-4))
    with pytest.raises(ValueError, match="not float16-exact"):
        half.add_episode(bad)

    # On the fly: the same episode's raw views through the backbone, no float16 rounding.
    raw_env = gym.make(ENV, obs_mode="pixels", max_episode_steps=6)
    obs, _ = raw_env.reset(seed=3)
    fly = []
    for t in range(log.T + 1):
        images = torch.from_numpy(np.stack([obs[v] for v in ("wrist_rgb", "side_rgb")]))
        with torch.no_grad():
            fmap = backbone(images).reshape(-1).numpy()
        fly.append(np.concatenate([fmap, obs["robot0_proprio"]]))
        if t < log.T:
            obs, *_ = raw_env.step(log.actions[t])
    raw_env.close()
    fly = np.stack(fly).astype(np.float32)
    assert not np.array_equal(fly, log.observations)         # the cache did round
    np.testing.assert_allclose(agent.embed(log.observations), agent.embed(fly), atol=2e-2, rtol=0)
    np.testing.assert_allclose(agent.act(log.observations, deterministic=True),
                               agent.act(fly, deterministic=True), atol=1e-2, rtol=0)


# ---------------------------------------------------------------- HIL-SERL and SAC on pixels
def _pixel_episode(T: int, seed: int, episode_id: int = 0):
    """A random pixel-track episode (feature maps float16-exact, as PixelFeatures makes them)."""
    from window_bench.data.steplog import EpisodeLog
    from window_bench.pixels.encoder import FEATURE_VALUES

    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((T + 1, OBS_DIM)).astype(np.float32)
    obs[:, :FEATURE_VALUES] = np.abs(obs[:, :FEATURE_VALUES]).astype(np.float16)
    actions = rng.uniform(-1, 1, (T, 7)).astype(np.float32)
    actions[:, 6] = np.sign(actions[:, 6])
    return EpisodeLog(observations=obs, actions=actions, rewards=rng.uniform(-1, 0, T),
                      terminated=np.r_[np.zeros(T - 1, bool), True], truncated=np.zeros(T, bool),
                      provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=episode_id,
                      seed=seed)


def test_replay_draws_are_the_same_rows_as_torchrl_indexing():
    """The pixel replay's fast reads change no batch: its row gather returns what TorchRL's
    own storage read returns for the same seeded draws, and ``mixed_batch``, which joins the
    two draws as stored and widens them once, returns the concatenation of the two samples."""
    from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer, RoundRobinWriter

    from window_bench.data.replay import ChunkReplay, mixed_batch
    from window_bench.pixels.encoder import FEATURE_VALUES

    def replay(seed, episodes, half=FEATURE_VALUES):
        rb = ChunkReplay(40, 1, 0.99, seed=seed, half_obs=half)
        for i in episodes:
            rb.add_episode(_pixel_episode(7, i, i))
        return rb

    rb = replay(3, (1, 2, 3))
    stored = rb._buffer.storage._storage[:len(rb)]
    torchrl = ReplayBuffer(storage=LazyTensorStorage(40), sampler=RandomSampler(),
                           writer=RoundRobinWriter(),
                           generator=torch.Generator().manual_seed(3))
    torchrl.extend(stored.clone())
    for n in (1, 5, 64):
        ours, theirs = rb._buffer.sample(n), torchrl.sample(n)
        assert set(ours.keys()) == set(theirs.keys()) and "obs_half" in ours.keys()
        assert all(torch.equal(ours[k], theirs[k]) for k in theirs.keys())
    for half in (FEATURE_VALUES, 0):
        demo, online = replay(0, (1, 2), half), replay(1, (3, 4, 5), half)
        twins = replay(0, (1, 2), half), replay(1, (3, 4, 5), half)
        for n in (2, 9):
            joined = mixed_batch(demo, online, n)
            k = round(n * 0.5)
            parts = torch.cat([twins[0].sample(k), twins[1].sample(n - k)])
            assert set(joined.keys()) == set(parts.keys()) and joined["obs"].dtype == torch.float32
            assert all(torch.equal(joined[k], parts[k]) for k in parts.keys())


def test_sac_pixel_replay_stores_float16_maps_and_samples_as_sb3():
    """SB3 SAC's pixel buffer keeps the feature maps as float16 and returns, for the same
    draws of SB3's global RNG, the batches of SB3's own float32 ``ReplayBuffer``; the agent's
    state round trip restores it exactly, also from a state saved with float32 rows."""
    from gymnasium import spaces
    from stable_baselines3.common.buffers import ReplayBuffer

    from window_bench.harness.methods import agent_class
    from window_bench.pixels.sac import PixelReplayBuffer

    obs_space = spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
    act_space = spaces.Box(-1.0, 1.0, (7,), np.float32)
    ours, sb3 = (cls(30, obs_space, act_space, "cpu") for cls in (PixelReplayBuffer, ReplayBuffer))
    assert ours.observation_maps.dtype == np.float16 and ours.observations.shape[-1] == PROPRIO_DIM
    for ep in (_pixel_episode(9, 1), _pixel_episode(8, 2)):
        for t in range(ep.T):
            args = (ep.observations[t][None], ep.observations[t + 1][None], ep.actions[t][None],
                    np.array([ep.rewards[t]], np.float32), np.array([ep.terminated[t]]),
                    [{"TimeLimit.truncated": t == 3}])
            for rb in (ours, sb3):
                rb.add(*args)
    for n in (1, 12):
        np.random.seed(n)
        a = [ours.sample(n) for _ in range(2)]         # the second draw: the same RNG stream
        np.random.seed(n)
        b = [sb3.sample(n) for _ in range(2)]
        for field in ("observations", "actions", "next_observations", "dones", "rewards"):
            for x, y in ((getattr(a[i], field), getattr(b[i], field)) for i in range(2)):
                assert x.dtype == y.dtype and torch.equal(x, y), field
    bad = _pixel_episode(2, 3).observations + np.float32(1e-4)
    with pytest.raises(ValueError, match="not float16-exact"):
        ours.add(bad[0][None], bad[1][None], np.zeros((1, 7)), np.zeros(1), np.zeros(1), [{}])

    demos = [_pixel_episode(6, s, s) for s in (1, 2)]
    agent = agent_class("sac-pixels").create(_pixel_spec(demos))
    state = agent.state_dict()
    again = agent_class("sac-pixels").from_state_dict(state)
    old = {**state, "replay": {**state["replay"], **{     # SB3's float32 rows
        k: np.concatenate([state["replay"][f].astype(np.float32), state["replay"][k]], axis=-1)
        for k, f in (("observations", "observation_maps"),
                     ("next_observations", "next_observation_maps"))}}}
    for restored in (again, agent_class("sac-pixels").from_state_dict(old)):
        rb, rb0 = restored.model.replay_buffer, agent.model.replay_buffer
        for f in ("observations", "next_observations", *rb.map_fields, "actions", "rewards"):
            np.testing.assert_array_equal(getattr(rb, f), getattr(rb0, f))
        assert rb.pos == rb0.pos == 12


def _pixel_spec(demos, seed: int = 0):
    from window_bench.harness.agent import AgentSpec
    from window_bench.harness.methods import PROFILES
    from window_bench.harness.run import obs_normalizer

    mean, std = obs_normalizer(np.concatenate([ep.observations for ep in demos]))
    return AgentSpec(obs_dim=OBS_DIM, action_dim=7, h=1, seed=seed, profile=PROFILES["smoke"],
                     demos=demos, obs_mean=mean, obs_std=std)


def _same_actions(a, b, obs) -> None:
    np.testing.assert_array_equal(a.act(obs, deterministic=True), b.act(obs, deterministic=True))


@pytest.mark.parametrize("kind", ["hilserl-pixels", "sac-pixels"])
def test_hilserl_and_sac_pixel_agents(kind):
    """The pixel front end behind HIL-SERL and SB3 SAC: built from the harness's spec (the
    proprioception normaliser from the demos), learning moves the aggregation, actions of
    shape (1, 7), plain state and policy state round trips, and one seed, one result."""
    from window_bench.data.replay import ChunkReplay
    from window_bench.harness.agent import check_plain
    from window_bench.harness.methods import agent_class
    from window_bench.pixels.encoder import FEATURE_VALUES

    cls = agent_class(kind)
    assert cls.track == "pixels"
    demos = [_pixel_episode(12, s, s) for s in (1, 2)]

    def trained(seed=0):
        torch.manual_seed(123)
        agent = cls.create(_pixel_spec(demos, seed))
        rb = ChunkReplay(24, 1, agent.gamma, seed=0, half_obs=FEATURE_VALUES)
        for ep in demos:
            rb.add_episode(ep)
        first = {k: v.clone() for k, v in _encoders(agent)[0].state_dict().items()}
        for _ in range(3):
            metrics, steps = agent.learn(lambda: rb.sample(8))
            assert steps >= 1 and all(np.isfinite(v) for v in metrics.values())
        return agent, first

    agent, first = trained()
    encoders = _encoders(agent)
    assert encoders and all(torch.equal(e.proprio_mean, encoders[0].proprio_mean) for e in encoders)
    np.testing.assert_allclose(encoders[0].proprio_mean.numpy(),
                               np.concatenate([ep.observations for ep in demos])[:, -18:].mean(0),
                               rtol=1e-5, atol=1e-6)
    assert not torch.equal(first["views.0.spatial.kernel"],
                           encoders[0].state_dict()["views.0.spatial.kernel"])
    obs = demos[0].observations[:3]
    assert agent.act(obs[0], deterministic=True).shape == (1, 7)
    assert agent.act(obs, deterministic=True).shape == (3, 1, 7)
    agent.encoder_weights = "/x/w.safetensors"
    for state, restore in ((agent.state_dict(), cls.from_state_dict),
                           (agent.policy_state_dict(), cls.from_policy_state_dict)):
        check_plain(state)
        again = restore(state)
        _same_actions(again, agent, obs)
        assert again.encoder_weights == "/x/w.safetensors"
    _same_actions(trained()[0], agent, obs)                  # one seed, one result
    with pytest.raises(ValueError, match="obs_dim = 52"):
        cls.create(dataclasses.replace(_pixel_spec(demos), obs_dim=52))


def _encoders(agent) -> list:
    if hasattr(agent, "model"):     # SB3: an extractor each for the actor, critics, targets
        return [m for m in agent.model.policy.modules() if isinstance(m, PixelObsEncoder)]
    return [agent.encoder]


def test_the_supervisor_of_a_pixel_policy_reads_the_privileged_state(backbone):
    """Takeovers on the pixel track: the installer watches the scene, so the supervisor gets
    the flat state of the pixel env's current step, equal to a flat env's on the same episode."""
    import gymnasium as gym

    from window_bench.pixels.track import StateSupervisor, privileged_state

    seen = []

    class Recorder:
        events = ["kept"]

        def reset(self, env, seed=None):
            seen.append(("reset", seed))

        def intervene(self, obs, info):
            seen.append(obs)
            return None

    pix, flat = make_pixel_env(ENV, backbone), gym.make(ENV, obs_mode="flat")
    sup = StateSupervisor(Recorder())
    pix.reset(seed=4)
    sup.reset(pix, seed=4)
    expected, _ = flat.reset(seed=4)
    for t in range(3):
        assert sup.intervene(None, {}) is None
        np.testing.assert_array_equal(seen[-1], expected)
        a = np.full(7, 0.2, np.float32)
        pix.step(a)
        expected, *_ = flat.step(a)
    assert seen[0] == ("reset", 4) and sup.events == ["kept"]
    assert privileged_state(pix).shape == (52,) and pix.unwrapped.obs_mode == "pixels"
    pix.close()
    flat.close()


def _observe_demos_once(monkeypatch) -> None:
    """Runs of one test re-observe the same demonstrations (``pixel_demos`` is deterministic,
    tested above): the first re-observation serves them all."""
    from window_bench.pixels import track

    real, cache = track.pixel_demos, {}

    def once(eps, *args, **kwargs):
        if "demos" not in cache:
            cache["demos"] = real(eps, *args, **kwargs)
        return cache["demos"]

    monkeypatch.setattr(track, "pixel_demos", once)


@pytest.mark.parametrize("method,kind", [("hil-serl", "hilserl-pixels"), ("sac", "sac-pixels")])
def test_bench_run_hilserl_and_sac_on_the_pixel_track(tmp_path, monkeypatch, demos_root,
                                                      method, kind):
    """HIL-SERL and SB3 SAC through ``Run(track="pixels")`` end to end, at the smoke
    profile cut to 120 env steps and one evaluation episode per checkpoint (the full smoke
    profile is measured in docs/pixels.md): the pixel agent kind, Stage I, warm start,
    online updates (HIL-SERL with takeovers), evaluation workers on the pixel env, and the
    same seed twice gives the same checkpoints and bit-identical policy tensors."""
    import json

    from safetensors.torch import load_file

    from window_bench.harness import methods
    from window_bench.harness.run import Run

    monkeypatch.setitem(methods.PROFILES, "smoke", dataclasses.replace(
        methods.PROFILES["smoke"], budget_steps=120, warm_steps=20, checkpoint_every=120,
        eval_episodes=1, max_episode_steps=60, utd=0.1))
    _observe_demos_once(monkeypatch)

    def run(name):
        r = Run(method, ENV, "smoke", 0, tmp_path / name, track="pixels", demos=demos_root,
                progress=False, eval_workers=1).train()
        return r, json.loads((tmp_path / name / "results.json").read_text())

    (r, saved), (again, _) = run("a"), run("b")
    assert saved["track"] == "pixels" and saved["method"]["agent"] == kind
    assert [c["env_steps"] for c in r["checkpoints"]] == [0, 120]
    assert r["final"]["grad_steps"] >= 10                      # online updates happened
    drop = lambda cp: {k: v for k, v in cp.items() if k != "wall_clock_s"}  # noqa: E731
    assert [drop(c) for c in again["checkpoints"]] == [drop(c) for c in r["checkpoints"]]
    a, b = (load_file(str(tmp_path / d / "policies" / "step_0000120.safetensors"))
            for d in ("a", "b"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------- ACT on pixels
def test_act_pixel_agent_trains_its_front_end_on_cached_demo_features():
    """``act-pixels``: ACT's tokens are (proprioception, both view embeddings); its loss trains
    the aggregation; the demos' feature maps are kept once as float16 and an update reads
    exactly them; exact state and policy round trips; wrong demos are refused in one line."""
    from window_bench.harness.agent import check_plain
    from window_bench.harness.methods import agent_class
    from window_bench.pixels.encoder import FEATURE_VALUES

    cls = agent_class("act-pixels")
    demos = [_pixel_episode(15, s, s) for s in (1, 2)]
    agent = cls.create(_pixel_spec(demos))
    agent.attach_demos(demos)
    assert agent.config.robot_dim == PROPRIO_DIM and agent.offline_steps == 100
    assert agent._demo_maps.dtype == torch.float16 and agent._demo_maps.shape == (2, 30, VIEW_FEATURES)
    np.testing.assert_array_equal(agent._demo_maps[1, 15].float().numpy(),
                                  demos[1].observations[0, VIEW_FEATURES:FEATURE_VALUES])
    emb = torch.arange(2 * EMBED_DIM + PROPRIO_DIM, dtype=torch.float32)[None]
    assert cls.tokens(emb)[0, :PROPRIO_DIM].tolist() == list(range(2 * EMBED_DIM, emb.shape[1]))
    first = agent.encoder.views[1].spatial.kernel.clone()
    for _ in range(3):
        metrics, steps = agent.learn(None)
        assert steps == 1 and np.isfinite(metrics["loss"])
    assert not torch.equal(first, agent.encoder.views[1].spatial.kernel)
    obs = demos[0].observations[4]
    agent.reset()
    assert agent.act(obs).shape == (1, 7)
    for state, restore in ((agent.state_dict(), cls.from_state_dict),
                           (agent.policy_state_dict(), cls.from_policy_state_dict)):
        check_plain(state)
        again = restore(state)
        agent.reset(), again.reset()
        _same_actions(again, agent, obs)
    resumed = cls.from_state_dict(agent.state_dict())
    resumed.attach_demos(demos)
    assert resumed.learn(None)[0] == agent.learn(None)[0]           # an exact resume
    with pytest.raises(ValueError, match="one observation"):
        agent.act(demos[0].observations[:2])
    with pytest.raises(ValueError, match=r"expected \(T\+1, 16402\)"):
        agent.attach_demos([dataclasses.replace(demos[0], observations=np.zeros((16, 52)))])
    bad = dataclasses.replace(demos[0], observations=demos[0].observations + np.float32(1e-4))
    with pytest.raises(ValueError, match="not float16-exact"):
        agent.attach_demos([bad])


def test_bench_run_act_on_the_pixel_track(tmp_path, monkeypatch, demos_root):
    """``bench run --method act --track pixels`` end to end at the smoke profile (ACT's 100
    offline steps; one evaluation episode of at most 60 steps): the ``act-pixels`` agent,
    the frozen backbone bit-identical after training, and the same seed twice gives the
    same checkpoint and bit-identical policy tensors."""
    import json

    from safetensors.torch import load_file

    from window_bench.harness import methods
    from window_bench.harness.run import Run

    monkeypatch.setitem(methods.PROFILES, "smoke", dataclasses.replace(
        methods.PROFILES["smoke"], eval_episodes=1, max_episode_steps=60))
    _observe_demos_once(monkeypatch)

    def run(name):
        r = Run("act", ENV, "smoke", 0, tmp_path / name, track="pixels", demos=demos_root,
                progress=False, eval_workers=1)
        backbone = r.observation.backbone     # the pixel track's, for this run
        before = {k: v.clone() for k, v in backbone.state_dict().items()}
        out = r.train()
        after = backbone.state_dict()
        assert not any(p.requires_grad for p in backbone.parameters())
        assert all(torch.equal(before[k], after[k]) for k in before)     # frozen
        return out, json.loads((tmp_path / name / "results.json").read_text())

    (r, saved), (again, _) = run("a"), run("b")
    assert saved["track"] == "pixels" and saved["method"]["agent"] == "act-pixels"
    assert [c["env_steps"] for c in r["checkpoints"]] == [0]
    assert r["final"]["grad_steps"] == 100
    drop = lambda cp: {k: v for k, v in cp.items() if k != "wall_clock_s"}  # noqa: E731
    assert [drop(c) for c in again["checkpoints"]] == [drop(c) for c in r["checkpoints"]]
    a, b = (load_file(str(tmp_path / d / "policies" / "step_0000000.safetensors"))
            for d in ("a", "b"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    from window_bench.harness.files import load_state

    policy, _ = load_state(tmp_path / "a" / "policies" / "step_0000000.safetensors", "policy")
    assert "views.0.spatial.kernel" in policy["encoder"]          # the trained aggregation
    assert policy["agent"]["config"]["robot_dim"] == PROPRIO_DIM


# ---------------------------------------------------------------- run-level resume on pixels
def test_pixel_run_resumes_after_a_kill_as_if_never_killed(tmp_path, monkeypatch, demos_root):
    """The complete pipeline (``qcfql``: Stage I, warm start, online updates, takeovers by the
    installer watching the scene) on the pixel track, killed mid-episode in Stage III with no
    state written after the last episode end (what SIGKILL leaves; the real SIGKILL at the
    full smoke profile is benchmarks/pixel_kill_resume.sh) and resumed: the same checkpoints,
    training episodes, final agent state and replays, bit for bit, as a run never killed.
    Smoke profile cut to 120 env steps, checkpoints at 0, 60 and 120 (one episode each)."""
    from test_harness import _assert_same   # tensors and arrays bit for bit

    from window_bench.harness import methods
    from window_bench.harness.files import load_state
    from window_bench.harness.run import Run

    monkeypatch.setitem(methods.PROFILES, "smoke", dataclasses.replace(
        methods.PROFILES["smoke"], budget_steps=120, warm_steps=20, checkpoint_every=60,
        eval_episodes=1, max_episode_steps=40, utd=0.1))
    _observe_demos_once(monkeypatch)

    def run(out, resume=False):
        return Run("qcfql", ENV, "smoke", 0, out, resume=resume, track="pixels",
                   demos=demos_root, progress=False, save_every_s=0.0, eval_workers=1)

    whole = run(tmp_path / "whole").train()
    killed = run(tmp_path / "killed")
    killed._stop_after_env_steps = 75
    with pytest.raises(KeyboardInterrupt):
        killed.train()
    saved, _ = load_state(tmp_path / "killed" / "state.safetensors", "state")
    assert 75 - 40 <= saved["counters"]["env_steps"] < 75      # the last episode end
    resumed = run(tmp_path / "killed", resume=True).train()
    drop = lambda cps: [{k: v for k, v in c.items() if k != "wall_clock_s"} for c in cps]  # noqa: E731
    assert [c["env_steps"] for c in whole["checkpoints"]] == [0, 60, 120]
    assert drop(resumed["checkpoints"]) == drop(whole["checkpoints"])
    assert resumed["train_episodes"] == whole["train_episodes"]
    assert whole["final"]["grad_steps"] > 0
    a, _ = load_state(tmp_path / "whole" / "state.safetensors", "state")
    b, _ = load_state(tmp_path / "killed" / "state.safetensors", "state")
    for key in ("agent", "demo_rb", "online_rb"):
        _assert_same(a[key], b[key], key)

    # The harness observes the pixel track on the policy's chunk grid (h = 10 here): the same
    # run observing every step (training env and evaluation) is the same run, bit for bit,
    # with fewer renders and encoder passes.
    from window_bench.pixels import features

    real_init = features.PixelFeatures.__init__

    def every_step(self, env, backbone, observe_every=1, cameras="paper"):
        assert observe_every == 10              # what the harness asks for, h of `qcfql`
        real_init(self, env, backbone, observe_every=1, cameras=cameras)

    monkeypatch.setattr(features.PixelFeatures, "__init__", every_step)
    eager = run(tmp_path / "eager").train()
    assert drop(eager["checkpoints"]) == drop(whole["checkpoints"])
    assert eager["train_episodes"] == whole["train_episodes"]
    c, _ = load_state(tmp_path / "eager" / "state.safetensors", "state")
    for key in ("agent", "demo_rb", "online_rb"):
        _assert_same(a[key], c[key], key)


class _ObsPolicy:
    """A deterministic chunked policy whose actions depend on the whole observation (feature
    maps and proprioception), so an observation that differed would change the episode."""

    def __init__(self, h: int):
        self.h = h
        self.w = np.random.default_rng(0).standard_normal((OBS_DIM, 6)).astype(np.float32)

    def act(self, obs):
        a = np.tanh(obs @ self.w / 300.0)
        chunk = np.repeat(np.concatenate([0.3 * a, [1.0]])[None].astype(np.float32), self.h, 0)
        return chunk


def test_observing_on_the_chunk_grid_changes_nothing_but_the_work(backbone, monkeypatch):
    """``PixelFeatures(observe_every=h)``: the same episode as observing every step (actions,
    rewards, the observations on the grid and the last one), the rows in between all NaN,
    and only grid steps rendered; a policy or a chunking on another grid is refused."""
    from window_bench.data.chunks import chunk_transitions
    from window_bench.envs.env import WindowInstallEnv
    from window_bench.installer.rollout import Rollout

    h, T = 3, 8                                  # truncated at 8: s_T off the grid
    renders, real = [], WindowInstallEnv._render_views

    def counted(self):
        renders.append(1)
        return real(self)

    monkeypatch.setattr(WindowInstallEnv, "_render_views", counted)
    logs = {}
    for every in (1, h):
        renders.clear()
        env = make_pixel_env(ENV, backbone, observe_every=every, max_episode_steps=T)
        logs[every] = Rollout(env, _ObsPolicy(h)).run(seed=3)
        logs[every, "renders"] = len(renders)
        env.close()
    eager, lazy = logs[1], logs[h]
    assert eager.T == lazy.T == T and eager.observed.all()
    np.testing.assert_array_equal(eager.actions, lazy.actions)
    np.testing.assert_array_equal(eager.rewards, lazy.rewards)
    grid = (np.arange(T + 1) % h == 0) | (np.arange(T + 1) == T)
    np.testing.assert_array_equal(lazy.observed, grid)
    np.testing.assert_array_equal(lazy.observations[grid], eager.observations[grid])
    assert np.isnan(lazy.observations[~grid]).all()
    assert (logs[1, "renders"], logs[h, "renders"]) == (T + 1, int(grid.sum()))   # 9 vs 5
    a, b = chunk_transitions(eager, h, 0.99), chunk_transitions(lazy, h, 0.99)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # Chunks on another grid would read unobserved rows; a policy off the grid would act on one.
    with pytest.raises(ValueError, match="s_2 was not observed"):
        chunk_transitions(lazy, 2, 0.99)
    env = make_pixel_env(ENV, backbone, observe_every=h, max_episode_steps=T)
    with pytest.raises(RuntimeError, match="unobserved step"):
        Rollout(env, _ObsPolicy(1)).run(seed=3)
    env.close()
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="observe_every"):
            make_pixel_env(ENV, backbone, observe_every=bad)


def test_episode_log_marks_unobserved_rows_and_still_refuses_corrupt_ones():
    from window_bench.data.steplog import EpisodeLog

    def log(obs):
        return EpisodeLog(observations=obs, actions=np.zeros((3, 7)), rewards=np.zeros(3),
                          terminated=[False, False, True], truncated=[False] * 3,
                          provenance=["policy"] * 3, takeover_kind=[""] * 3)

    obs = np.ones((4, 5), np.float32)
    obs[1] = np.nan
    log(obs).validate()                                   # an all-NaN row: unobserved
    np.testing.assert_array_equal(log(obs).observed, [True, False, True, True])
    part = obs.copy()
    part[2, 0] = np.nan                                   # one NaN in an observed row
    with pytest.raises(ValueError, match="non-finite value nan at index \\(2, 0\\)"):
        log(part).validate()
    for end in (0, 3):
        cut = obs.copy()
        cut[end] = np.nan
        with pytest.raises(ValueError, match="s_0 and s_T must be observed"):
            log(cut).validate()



# ---------------------------------------------------------------- the seat-camera track
def test_bench_run_on_the_seat_camera_track(tmp_path, monkeypatch, demos_root):
    """``Run(track="pixels-seat")``: the pixel agents on the two seat cameras. The demos are
    re-observed through the seat cameras (their own cache entry), the policy files name the
    camera set, evaluation renders those cameras, and results.json records the track and
    the cameras; a policy state naming an unknown camera set is refused in one line."""
    import json

    from window_bench.harness import methods
    from window_bench.harness.files import load_state
    from window_bench.harness.run import Run
    from window_bench.harness.tracks import get_track
    from window_bench.pixels import track as T

    monkeypatch.setitem(methods.PROFILES, "smoke", dataclasses.replace(
        methods.PROFILES["smoke"], eval_episodes=1, max_episode_steps=30))
    seen = []
    real = T.pixel_demos

    def observed(eps, env_id, backbone, progress=False, cameras="paper"):
        seen.append(cameras)
        return real(eps, env_id, backbone, progress, cameras=cameras)

    monkeypatch.setattr(T, "pixel_demos", observed)
    out = tmp_path / "seat"
    r = Run("qcfql-offline", ENV, "smoke", 0, out, track="pixels-seat", demos=demos_root,
            progress=False, eval_workers=1)
    assert r.method.agent == "qcfql-pixels"
    res = r.train()
    saved = json.loads((out / "results.json").read_text())
    assert res["track"] == saved["track"] == "pixels-seat" and seen == ["seat"]
    assert saved["encoder"]["cameras"] == "seat"
    policy, _ = load_state(out / "policies" / "step_0000000.safetensors", "policy")
    assert policy["cameras"] == "seat"
    # the track's fixed pose read-out: recorded, in the policy file, read back from there
    assert saved["encoder"]["pose_readout"]["file"] == "pose_readout_seat.safetensors"
    assert saved["hyperparameters"]["pose_readout_sha256"]
    assert policy["encoder"]["pose_readout.weight"].shape == (6, OBS_DIM)  # 12 features
    from window_bench.harness.methods import agent_class
    assert agent_class("qcfql-pixels").from_policy_state_dict(policy).encoder.out_dim == 94
    env = get_track("pixels").eval_env(ENV, policy, observe_every=10)
    assert env.cameras == "seat"
    env.close()
    old = {k: v for k, v in policy.items() if k != "cameras"}   # saved before camera sets
    env = get_track("pixels").eval_env(ENV, old)
    assert env.cameras == "paper"
    env.close()
    with pytest.raises(ValueError, match=r"camera set '\.\./x'; allowed: paper, seat"):
        get_track("pixels").eval_env(ENV, {**policy, "cameras": "../x"})


@pytest.mark.parametrize("method, field, value, shown, off", [
    ("qcfql-offline", "fine_pose_mm", "10", "10", "0"), ("qcfql", "grasp_mm", "10", "10", "0"),
    ("act", "fine_pose_mm", "10", "10", "0"), ("hil-serl", "fine_pose_mm", "10", "10", "0"),
    ("hil-serl", "safety_box", "[0.03,10]", "(0.03, 10.0)", "none")])
def test_state_only_features_are_refused_on_pixels_before_any_file(tmp_path, capsys, method,
                                                                   field, value, shown, off):
    """Features computed from the flat state have no place on a camera observation: one
    line naming the field, exit 2, and no run directory."""
    from window_bench.cli import main

    out = tmp_path / "run"
    assert main(["run", "--method", method, "--track", "pixels", "--out", str(out),
                 "--agent-config", f"{field}={value}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(f"{field} = {shown} reads the flat state observation; on the pixel "
                        f"track (cameras and proprioception) it must be {off} (off)")
    assert len(err.splitlines()) == 1 and not out.exists()


def test_the_state_tracks_feature_defaults_are_off_on_pixels():
    """bench run's QC-FQL defaults turn on features of the flat state (RUN_DEFAULTS); a pixel
    agent's config has them off unless asked for, and keeps the rest (action companding)."""
    from baselines.qcfql import QCFQLAgent
    from window_bench.harness.methods import agent_class, get_profile
    from window_bench.harness.tracks import get_track

    profile = get_profile("cpu")
    state = QCFQLAgent.make_config(10, profile, {})
    assert state.fine_pose_mm and state.grasp_mm
    pixel = agent_class(get_track("pixels").agent_kind("qcfql")).make_config(10, profile, {})
    assert (pixel.fine_pose_mm, pixel.grasp_mm, pixel.action_power) == (0.0, 0.0, 2.0)
