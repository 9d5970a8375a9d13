"""Can the installer's takeover bring a dropped panel back to the opening within its cap?

A ``hil-serl`` policy on ``WindowInstall-A-v0`` drops the panel early (a commanded release
or a grip break, docs/baselines.md), and the installer's ``suction_lost`` takeover then
has to re-acquire it (approach, descend, lift, transport, align) before it hands back in
front of the opening. This script isolates that recovery from any learner: a fixed policy
holds still and releases the vacuum at step ``--drop-step``, then holds still with the
vacuum on; the ``InstallerSupervisor`` of the ``average`` operator watches as in Stage III.
For every takeover it records the cue, its length, whether it ran into
``max_takeover_steps`` and what it handed back (the installer's phase, the panel held or
not). ``--cap N`` replaces the operator's cap (200 steps) to measure how long the whole
re-acquisition takes when nothing cuts it short. ``--policy FILE`` puts a frozen policy
file in the fixed policy's place, acting stochastically as in Stage III, to see what the
takeovers hand back to the learner itself.

    python experiments/sanity/hilserl_drop_recovery.py --episodes 5
    python experiments/sanity/hilserl_drop_recovery.py --episodes 5 --cap 600
    python experiments/sanity/hilserl_drop_recovery.py --episodes 5 \
        --policy /tmp/hil_slt/policies/step_0024000.safetensors

Training-env seeds 4,000,000 + i. One process, one thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from window_bench.envs.wrappers import make_training_env
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.run import AgentPolicy, load_policy_file
from window_bench.installer.operators import get_operator
from window_bench.installer.rollout import Rollout
from window_bench.installer.supervisor import InstallerSupervisor

SEED_BASE = 4_000_000


class DropPolicy:
    """Zero motion; the vacuum released at step ``drop_step`` only, held otherwise."""

    h = 1

    def __init__(self, drop_step: int):
        self.drop_step, self.t = drop_step, 0

    def reset(self, seed=None):
        self.t = 0

    def act(self, obs):
        a = np.zeros(7, np.float32)
        a[6] = -1.0 if self.t == self.drop_step else 1.0
        self.t += 1
        return a


class WatchedSupervisor(InstallerSupervisor):
    """The supervisor, noting what each takeover hands back."""

    def reset(self, env, seed=None):
        super().reset(env, seed)
        self.handbacks: list[dict] = []

    def intervene(self, obs, info):
        was = self.active
        out = super().intervene(obs, info)
        if was is not None and self.active is None:
            self.handbacks.append({"step": self.t, "phase": self.installer.phase,
                                   "panel_held": bool(self.env.suction_engaged),
                                   "steps": self.steps_in,
                                   "hit_cap": self.steps_in >= self.profile.max_takeover_steps})
        return out


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--drop-step", type=int, default=15)
    p.add_argument("--cap", type=int, default=None, help="max_takeover_steps (default: the "
                   "operator's)")
    p.add_argument("--max-steps", type=int, default=600)
    p.add_argument("--policy", type=Path, default=None,
                   help="a frozen policy file acting stochastically instead of the drop policy")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    if a.episodes < 1 or a.drop_step < 0 or (a.cap is not None and not 1 <= a.cap <= 600):
        p.error(f"--episodes {a.episodes} must be >= 1, --drop-step {a.drop_step} >= 0, "
                f"--cap {a.cap} in [1, 600]")
    profile = get_operator("average")
    if a.cap is not None:
        profile = dataclasses.replace(profile, max_takeover_steps=a.cap)
    env = make_training_env(a.env, None, obs_mode="flat", max_episode_steps=a.max_steps)
    if a.policy is not None:
        agent_cls, state, _ = load_policy_file(a.policy)
        policy = AgentPolicy(agent_cls.from_policy_state_dict(state), deterministic=False)
    else:
        policy = DropPolicy(a.drop_step)
    rows = []
    for i in range(a.episodes):
        sup = WatchedSupervisor(profile, coverage=False)
        r = Rollout(env, policy, supervisor=sup, env_id=a.env)
        log = r.run(SEED_BASE + i, i)
        rows.append({"seed": SEED_BASE + i, "steps": log.T, "success": bool(log.terminated[-1]),
                     "takeover_steps": int((log.provenance == "takeover").sum()),
                     "takeovers": [{"step": s, "cue": c} for s, c, _ in sup.events],
                     "handbacks": sup.handbacks})
        print(json.dumps(rows[-1]))
    env.close()
    hb = [h for r in rows for h in r["handbacks"]]
    first = [r["handbacks"][0] for r in rows if r["handbacks"]]
    out = {"env": a.env, "policy": str(a.policy) if a.policy else "drop",
           "drop_step": a.drop_step, "cap": profile.max_takeover_steps,
           "episodes": a.episodes, "rows": rows,
           "summary": {"accepted": sum(r["success"] for r in rows),
                       "handbacks": len(hb), "hit_cap": sum(h["hit_cap"] for h in hb),
                       "first_handback_in_insert_with_panel": sum(
                           h["phase"] == "insert" and h["panel_held"] for h in first),
                       "first_takeover_steps": [h["steps"] for h in first]},
           "provenance": provenance()}
    print(json.dumps(out["summary"]))
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.out, json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
