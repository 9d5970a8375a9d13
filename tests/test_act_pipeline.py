"""ACT's data path end to end (issue 15's defect hunt): what training feeds the network and
what the rollout feeds it must be the same, and the chunks it is trained to predict must be
the ones the rollout executes.

An *oracle* network replaces ACT's: it answers every observation it is given with the
normalised target chunk that the training sampler built for the nearest training
observation. If observations were built, ordered or normalised differently at evaluation,
if actions were un-normalised with other statistics, if the target chunk for ``s_t`` were
not ``a_t .. a_{t+k-1}``, or if temporal ensembling took the wrong row of a past chunk, the
rollout would not replay the demonstration; the negative control (targets shifted by one
step) shows that it then indeed does not.
"""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from baselines.act import ACT_PROFILES, ACTAgent, _collect_demos, _rollout

torch.set_num_threads(1)
ENV = "WindowInstall-A-v0"


class Oracle(nn.Module):
    """Looks up the normalised target chunk of the nearest training observation (the
    normalised observations the training sampler drew, as ``ACTAgent.update`` sees them)."""

    def __init__(self, agent: ACTAgent, episodes, shift: int = 0):
        super().__init__()
        b = agent.sample_batch(episodes, 5000, np.random.default_rng(0))
        _, first = np.unique(b["start"], return_index=True)
        assert len(first) == episodes[0].T     # every start step was drawn
        actions = np.asarray(b["actions"][first], np.float32)
        if shift:   # negative control: the chunk of s_t is a_{t+shift} ..
            actions = np.concatenate([actions[:, shift:], actions[:, -1:].repeat(shift, 1)], 1)
        norm = agent.norm
        self.obs_n = agent.normalize_obs(torch.as_tensor(b["obs"][first], dtype=torch.float32))
        self.target_n = (torch.as_tensor(actions) - norm["act_mean"]) / norm["act_std"]
        self.starts = b["start"][first]
        self.misses, self.matched = [], []

    def forward(self, obs_n, actions=None, is_pad=None, noise=None):
        miss, idx = torch.cdist(obs_n, self.obs_n,
                                compute_mode="donot_use_mm_for_euclid_dist").min(1)
        self.misses += miss.tolist()
        self.matched += self.starts[idx.numpy()].tolist()
        return self.target_n[idx], None, None


@pytest.fixture(scope="module")
def demo():
    (ep,) = _collect_demos(ENV, [0])
    assert ep.terminated[-1]
    return ep


@pytest.mark.parametrize("ensembling", [True, False])
def test_the_rollout_replays_a_demonstration_through_acts_own_data_path(demo, ensembling):
    agent = ACTAgent(demo.observations.shape[1],
                     config=replace(ACT_PROFILES["smoke"], temporal_ensembling=ensembling))
    agent.fit_normalizer([demo])
    agent.model = Oracle(agent, [demo])
    (row,) = _rollout(agent, ENV, [demo.seed], max_steps=demo.T + 20)
    assert row["success"] and row["steps"] == demo.T
    # Each query's observation is the training observation of the same step, up to the
    # float32 rounding of the un-normalised actions (measured 2.5e-6 z-scored units; scaling
    # window_pos_rel by 1.001 at evaluation gives 6e-3, a wrong ensembling row 1e2).
    oracle = agent.model
    assert oracle.matched == list(range(0, demo.T, agent.h))
    assert max(oracle.misses) < 1e-4


def test_a_chunk_misaligned_by_one_step_does_not_replay_it(demo):
    agent = ACTAgent(demo.observations.shape[1], config=ACT_PROFILES["smoke"])
    agent.fit_normalizer([demo])
    agent.model = Oracle(agent, [demo], shift=1)
    (row,) = _rollout(agent, ENV, [demo.seed], max_steps=demo.T + 20)
    assert not (row["success"] and row["steps"] == demo.T)


def test_mlp_control_trains_the_same_pipeline_with_only_the_network_swapped(tmp_path):
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location(
        "act_mlp_control",
        Path(__file__).parents[1] / "experiments/sanity/act_mlp_control.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    agent = script.make_agent("mlp", 52, "smoke", {"cvae": False, "dropout": 0.0},
                              (32, 32), seed=0)
    assert isinstance(agent.model, script.MLPChunk) and agent.h == 1
    assert all(p is q for p, q in zip(agent.optimizer.param_groups[0]["params"],
                                      agent.model.parameters()))
    out = tmp_path / "mlp.json"
    result = script.main(["--arch", "mlp", "--operator", "scripted", "--profile", "smoke",
                          "--hidden", "32", "32", "--train-demos", "1", "--heldout", "1",
                          "--steps", "30", "--batch", "16", "--lr", "1e-3",
                          "--train-starts", "1", "--max-steps", "15", "--out", str(out)])
    assert json.loads(out.read_text())["heldout_l1"] == result["heldout_l1"] > 0
    assert result["config"]["cvae"] is False and result["config"]["batch_size"] == 16
    s = result["train_starts/temporal_ensembling"]
    assert s["episodes"] == 1 and s["rows"][0]["steps"] <= 15
    assert set(result["gain_panel"]) == {f"{b}/{x}" for b in ("0.30-2.00 m", "0.13-0.30 m",
                                                              "0.09-0.13 m") for x in "xz"}


def test_latent_check_separates_a_used_latent_from_an_ignored_one():
    import importlib.util

    from test_act import synthetic_episode

    spec = importlib.util.spec_from_file_location(
        "act_latent_check",
        Path(__file__).parents[1] / "experiments/sanity/act_latent_check.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    eps = [synthetic_episode(23, 0), synthetic_episode(17, 1)]
    agent = ACTAgent(52, config=ACT_PROFILES["smoke"], seed=0)
    agent.train_offline(eps, 5)
    with torch.no_grad():   # a latent that reaches the decoder changes the prediction ...
        agent.model.latent_out_proj.weight.normal_(0, 3.0)
    used = script.latent_check(agent, eps)
    assert used["rollout_vs_offline_max_abs_diff"] == 0.0
    assert used["l1_zmu"] != pytest.approx(used["l1_z0"], rel=1e-4) and used["kl_mean_nats"] > 0
    with torch.no_grad():   # ... one whose projection is zero cannot
        agent.model.latent_out_proj.weight.zero_()
    ignored = script.latent_check(agent, eps)
    assert ignored["l1_zmu"] == pytest.approx(ignored["l1_z0"], abs=1e-7)
