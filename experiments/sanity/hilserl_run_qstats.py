"""Q statistics of a ``hil-serl`` run directory: the critics on the demonstrations against
what any return can be, the actor against the demonstrations, the grasp critic, and the
learner's ``q_mean`` / ``target_mean`` over gradient steps (its TensorBoard scalars).

The reward is 1 on acceptance and 0 otherwise and acceptance terminates, so no discounted
return exceeds 1; a critic far above 1 is extrapolating. Reads the run's last saved state
(``state.safetensors``, checked against its manifest), so it also works on a running run.

    python experiments/sanity/hilserl_run_qstats.py /tmp/hil_nooff --demos runs/sanity/demos_s0

``--eval M`` also evaluates the saved policy (or ``--policy-step N``'s checkpoint policy)
deterministically on the first M development seeds (100,000...) with the vacuum forced to
"hold" (the pose actor alone; the policy as it is was evaluated at the run's checkpoints),
which separates what the grasp critic's releases cost from what the pose actor can do.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hilserl_stage1 import evaluate, q_check  # noqa: E402  (same statistics as right after Stage I)

from baselines.hilserl import HILSERLAgent  # noqa: E402
from window_bench.envs.env import VACUUM_THRESHOLD  # noqa: E402
from window_bench.harness.files import load_state, verify_files  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text  # noqa: E402
from window_bench.harness.run import load_policy_file, summarize_eval  # noqa: E402
from window_bench.installer.demos import load_demos  # noqa: E402


def tb_scalars(run_dir: Path, tags=("loss/q_mean", "loss/target_mean", "loss/grasp_q_mean",
                                    "loss/temperature", "loss/entropy")) -> dict:
    """``{tag: [(grad_step, value), ...]}`` thinned to at most 12 points per tag."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    out = {}
    for tag in tags:
        if tag in acc.Tags()["scalars"]:
            ev = acc.Scalars(tag)
            idx = np.unique(np.linspace(0, len(ev) - 1, min(12, len(ev))).astype(int))
            out[tag] = [(int(ev[i].step), round(float(ev[i].value), 4)) for i in idx]
    return out


class HoldVacuum:
    """The agent's pose actions with the vacuum command forced to hold (+1)."""

    def __init__(self, agent):
        self.agent = agent

    def act(self, obs, deterministic=True):
        a = self.agent.act(obs, deterministic=deterministic).copy()
        a[..., -1] = 1.0
        return a


def eval_summary(agent, env_id: str, episodes: int) -> dict:
    rows, actions = evaluate(agent, env_id, episodes, 600)
    s = summarize_eval([{**r, "cycle_time_s": r["steps"] / 10} for r in rows])
    s["median_first_suction_loss_step"] = (
        float(np.median([r["first_suction_loss_step"] for r in rows
                         if r["first_suction_loss_step"] is not None]))
        if any(r["first_suction_loss_step"] is not None for r in rows) else None)
    s["eval_pose_action_mean"] = [round(float(v), 3) for v in actions.mean(0)[:6]]
    return s


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--demos", type=Path, default=None, help="Minari root (default: RUN/demos)")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--n-demos", type=int, default=50)
    p.add_argument("--eval", type=int, default=0, metavar="M",
                   help="evaluate the policy with the vacuum held, M episodes")
    p.add_argument("--policy-step", type=int, default=None, metavar="N",
                   help="evaluate policies/step_N.safetensors instead of the saved state's")
    p.add_argument("--json", type=Path, default=None, help="also write the result here")
    a = p.parse_args(argv)
    if a.eval < 0 or a.n_demos < 1:
        p.error(f"--eval {a.eval} must be >= 0 and --n-demos {a.n_demos} >= 1")
    verify_files(a.run_dir, ["state.safetensors"])
    state, _ = load_state(a.run_dir / "state.safetensors", "state")
    agent = HILSERLAgent.from_state_dict(state["agent"])
    demos = load_demos(a.demos or a.run_dir / "demos", a.env, "average")[:a.n_demos]
    obs = np.concatenate([ep.observations[:-1] for ep in demos]).astype(np.float32)
    demo_a = np.concatenate([ep.actions for ep in demos])
    pol_a = agent.act(obs, deterministic=True)[:, 0]
    out = {"run_dir": str(a.run_dir), "counters": {k: state["counters"][k] for k in
                                                   ("stage", "env_steps", "grad_steps")},
           "temperature": agent.temperature, "q_check": q_check(agent, demos),
           "pose_mae_vs_demo": [round(float(v), 3) for v in
                                np.abs(pol_a - demo_a).mean(0)[:6]],
           "policy_pose_mean": [round(float(v), 3) for v in pol_a.mean(0)[:6]],
           "demo_pose_mean": [round(float(v), 3) for v in demo_a.mean(0)[:6]],
           "vacuum_hold_on_demo_states": float(np.mean(pol_a[:, 6] > VACUUM_THRESHOLD))}
    if agent.discrete_vacuum:
        with torch.no_grad():
            qg = agent.grasp_critic(agent._normalize(torch.as_tensor(obs))).numpy()
            start = torch.as_tensor(np.stack([ep.observations[0] for ep in demos]),
                                    dtype=torch.float32)
            qg0 = agent.grasp_critic(agent._normalize(start)).numpy()
        rtg0 = [agent.config.gamma ** (ep.T - 1) for ep in demos]
        out["grasp_q_on_demo_states"] = {"release_mean": float(qg[:, 0].mean()),
                                         "hold_mean": float(qg[:, 1].mean()),
                                         "frac_release_above_hold": float(np.mean(qg[:, 0] >
                                                                                  qg[:, 1]))}
        # At the first state the demos' own discounted return is only gamma^(T-1).
        out["grasp_q_on_demo_start_states"] = {
            "release_mean": float(qg0[:, 0].mean()), "hold_mean": float(qg0[:, 1].mean()),
            "frac_release_above_hold": float(np.mean(qg0[:, 0] > qg0[:, 1])),
            "demo_return_mean": float(np.mean(rtg0))}
    out["tb"] = tb_scalars(a.run_dir)
    if a.eval:
        if a.policy_step is not None:
            _, policy, _ = load_policy_file(
                a.run_dir / "policies" / f"step_{a.policy_step:07d}.safetensors")
            agent = HILSERLAgent.from_policy_state_dict(policy)
            out["eval_policy_step"] = a.policy_step
        out["eval_vacuum_held"] = eval_summary(HoldVacuum(agent), a.env, a.eval)
    text = json.dumps(out, indent=1)
    print(text)
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.json, text)
    return out


if __name__ == "__main__":
    main()
