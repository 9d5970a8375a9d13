"""The agent interface (``window_bench.harness.agent``): every registered agent keeps its state
as plain data and acts identically from its policy state alone, and a new learner defined
here runs through ``bench run`` with no change to the harness."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from window_bench.cli import main
from window_bench.data.replay import ChunkReplay
from window_bench.harness.agent import (Agent, AgentSpec, check_plain, load_optimizer_state,
                                        module_state, optimizer_state)
from window_bench.harness.methods import AGENTS, METHODS, PROFILES, Method, get_method
from window_bench.harness.run import make_agent
from window_bench.installer.demos import load_demos

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]


class ToyBC(Agent):
    """Behaviour cloning with a one-hidden-layer MLP, step-wise: the smallest learner the
    harness can run (it never asks which one it holds)."""

    h = 1

    def __init__(self, obs_dim: int, seed: int, obs_mean, obs_std):
        self.seed = seed
        gen = torch.Generator().manual_seed(seed)
        self.net = nn.Sequential(nn.Linear(obs_dim, 16), nn.Tanh(), nn.Linear(16, 7))
        with torch.no_grad():
            for p in self.net.parameters():
                p.copy_(0.3 * torch.randn(p.shape, generator=gen))
        self.mean = torch.as_tensor(obs_mean, dtype=torch.float32)
        self.std = torch.as_tensor(obs_std, dtype=torch.float32)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-2)

    @classmethod
    def create(cls, spec: AgentSpec) -> "ToyBC":
        return cls(spec.obs_dim, spec.seed, spec.obs_mean, spec.obs_std)

    def learn(self, sample):
        batch = sample()
        obs = (batch["obs"].float() - self.mean) / self.std
        loss = (self.net(obs) - batch["actions"][:, 0].float()).pow(2).mean()
        self.opt.zero_grad()
        loss.backward()
        self.opt.step()
        return {"bc_loss": loss.item()}, 1

    @torch.no_grad()
    def act(self, obs, deterministic=False):
        o = (torch.as_tensor(np.asarray(obs, np.float32)) - self.mean) / self.std
        return self.net(o).clamp(-1, 1).numpy()[None]

    def policy_state_dict(self):
        return {"obs_dim": int(self.mean.shape[0]), "seed": self.seed, "mean": self.mean,
                "std": self.std, "net": module_state(self.net)}

    @classmethod
    def from_policy_state_dict(cls, state):
        agent = cls(state["obs_dim"], state["seed"], state["mean"], state["std"])
        agent.net.load_state_dict(state["net"])
        return agent

    def state_dict(self):
        return {**self.policy_state_dict(), "opt": optimizer_state(self.opt)}

    def load_state_dict(self, state):
        self.net.load_state_dict(state["net"])
        load_optimizer_state(self.opt, state["opt"])

    @classmethod
    def from_state_dict(cls, state):
        agent = cls.from_policy_state_dict(state)
        agent.load_state_dict(state)
        return agent


def test_a_toy_agent_runs_through_bench_run_with_no_harness_change(tmp_path, demos_root,
                                                                  monkeypatch, capsys):
    monkeypatch.setitem(AGENTS, "toy-bc", ToyBC)
    monkeypatch.setitem(METHODS, "toy-bc", Method("toy-bc", "Toy BC", "toy-bc", 1,
                                                  interventions=False))
    out = tmp_path / "toy"
    assert main(["run", "--method", "toy-bc", "--profile", "smoke", "--seed", "0", "--out",
                 str(out), "--demos", str(demos_root)]) == 0
    r = json.loads((out / "results.json").read_text())
    assert r["method"]["agent"] == "toy-bc"
    assert [c["env_steps"] for c in r["checkpoints"]] == [0, 200, 400]
    # Stage I (20 learner calls), then UTD 0.05 on the 300 steps after the warm start.
    assert r["final"]["grad_steps"] == 20 + round(0.05 * 300)
    assert sum(e["steps"] for e in r["train_episodes"]) <= 400
    # The frozen policies hold the acting state only, and bench eval rebuilds them.
    from window_bench.harness.files import load_state

    pol, meta = load_state(out / "policies" / "step_0000400.safetensors", "policy")
    assert meta["agent_kind"] == "toy-bc" and set(pol) == {"obs_dim", "seed", "mean", "std", "net"}
    capsys.readouterr()
    assert main(["eval", str(out / "policies" / "step_0000400.safetensors"), "--episodes", "2"]) == 0
    assert "toy-bc (400 env steps) on WindowInstall-A-v0: " in capsys.readouterr().out


def test_the_harness_has_no_agent_kind_branch():
    """The harness reads capabilities; only the registry names agent kinds."""
    src = (ROOT / "window_bench" / "harness" / "run.py").read_text()
    kinds = "|".join(sorted({m.agent for m in METHODS.values()} | set(AGENTS)))
    assert not re.search(rf"""["']({kinds})["']""", src)
    assert not re.search(r"\.agent\s*(==|!=|in\b)", src)


def _json_round_trip(state):
    """``state`` as a JSON + tensor store would give it back: arrays kept, the rest
    through JSON."""
    if isinstance(state, (torch.Tensor, np.ndarray)):
        return state
    if isinstance(state, dict):
        return {k: _json_round_trip(v) for k, v in state.items()}
    if isinstance(state, list):
        return [_json_round_trip(v) for v in state]
    return json.loads(json.dumps(state))


@pytest.mark.parametrize("method", ["qcfql", "hil-serl", "act", "sac"])
def test_every_agent_saves_plain_state_and_acts_from_its_policy_state(method, demos_root):
    demos = load_demos(demos_root, "WindowInstall-A-v0")      # the default operator's
    m = get_method(method)
    agent = make_agent(m, PROFILES["smoke"], demos, seed=0)
    agent.attach_demos(demos)
    assert isinstance(agent, Agent)
    rb = ChunkReplay(sum(ep.T for ep in demos), m.h, agent.gamma, seed=0)
    for ep in demos:
        rb.add_episode(ep)
    batch = rb.sample(16)
    for _ in range(3):
        metrics, n = agent.learn(lambda: batch)
        assert n >= 1 and metrics and all(np.isfinite(v) for v in metrics.values())
    state, policy = agent.state_dict(), agent.policy_state_dict()
    check_plain(state)
    check_plain(policy)
    obs = np.concatenate([ep.observations[::7] for ep in demos])
    expected = np.stack([agent.act(o, deterministic=True) for o in obs])

    # The acting state alone gives bit-identical actions, and is smaller than the state.
    actor = type(agent).from_policy_state_dict(_json_round_trip(policy))
    actor.reset()
    assert actor.h == agent.h
    np.testing.assert_array_equal(np.stack([actor.act(o, deterministic=True) for o in obs]),
                                  expected)
    size = lambda sd: sum(v.numel() * v.element_size() if isinstance(v, torch.Tensor)  # noqa: E731
                          else v.nbytes for v in _arrays(sd))
    assert size(policy) < size(state)

    # The full state resumes exactly: the next learner call gives the same metrics.
    resumed = type(agent).from_state_dict(_json_round_trip(state))
    resumed.attach_demos(demos)   # as the harness does after a resume
    np.testing.assert_array_equal(np.stack([resumed.act(o, deterministic=True) for o in obs]),
                                  expected)
    after = []
    for a in (agent, resumed):
        torch.manual_seed(7)
        np.random.seed(7)
        after.append(a.learn(lambda: batch)[0])
    assert after[0] == after[1]


def _arrays(state):
    if isinstance(state, (torch.Tensor, np.ndarray)):
        yield state
    elif isinstance(state, dict):
        for v in state.values():
            yield from _arrays(v)
    elif isinstance(state, list):
        for v in state:
            yield from _arrays(v)


def test_check_plain_names_what_is_not_plain():
    check_plain({"a": [1, 2.0, "x", None, True], "t": torch.zeros(2), "n": np.zeros(2)})
    with pytest.raises(TypeError, match=r"state\['cfg'\]\[0\] is a tuple"):
        check_plain({"cfg": [(1, 2)]})
    with pytest.raises(TypeError, match="key 0 is a int"):
        check_plain({"opt": {0: torch.zeros(1)}})
    with pytest.raises(TypeError, match="is a Linear"):
        check_plain({"net": nn.Linear(1, 1)})
