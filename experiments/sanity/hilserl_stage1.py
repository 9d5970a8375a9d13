"""HIL-SERL right after Stage I (offline pretraining on D_demo): stage-wise evaluation,
commanded releases vs grip breaks, and action statistics against the demonstrations.

Stage I is the harness's (``window_bench.harness.run``): the same demonstrations (operator
``average``, seeds ``1_000_000 + seed``), the same normaliser (``obs_normalizer``) and agent
(``HILSERLConfig`` with the profile's sizes and ``--agent-config`` overrides), batches of
``profile.batch_size`` from D_demo only, ``critic_actor_ratio`` critic steps per update
call. Only ``--steps`` (gradient steps, default the profile's) can be shortened.

    python experiments/sanity/hilserl_stage1.py --tag gaussian --agent-config vacuum_head=gaussian
    python experiments/sanity/hilserl_stage1.py --tag discrete

Writes ``runs/sanity/hilserl_stage1_<tag>.json`` (and the Stage I policy ``.pt``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

import window_bench  # noqa: F401  (registers the envs)
from baselines.hilserl import HILSERLAgent, HILSERLConfig
from window_bench.data.replay import ChunkReplay
from window_bench.envs.env import VACUUM_THRESHOLD
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.methods import get_profile
from window_bench.harness.run import EVAL_SEED0, obs_normalizer, parse_overrides, summarize_eval
from window_bench.installer.demos import collect_demos, load_demos


def demos_for(env_id: str, n: int, root: Path, seed: int):
    try:
        eps = load_demos(root, env_id, "average")
    except ValueError:
        collect_demos(env_id, n, root, operator="average", seed=1_000_000 + seed)
        eps = load_demos(root, env_id, "average")
    return eps[:n]


def stage1(env_id, profile, seed, steps, overrides, demos):
    obs = np.concatenate([ep.observations for ep in demos])
    cfg = HILSERLConfig(**{"hidden": tuple(profile.hidden), "batch_size": profile.batch_size,
                           **overrides})
    mean, std = obs_normalizer(obs)
    agent = HILSERLAgent(obs.shape[1], 7, cfg, seed=seed, obs_mean=mean, obs_std=std)
    demo_rb = ChunkReplay(sum(ep.T for ep in demos), 1, agent.config.gamma, seed=seed)
    for ep in demos:
        demo_rb.add_episode(ep)
    ratio = agent.config.critic_actor_ratio
    last = {}
    t0 = time.process_time()
    for _ in tqdm(range(steps // ratio), desc="Stage I", unit="upd", mininterval=10):
        last = agent.update(lambda: demo_rb.sample(profile.batch_size))
    return agent, last, time.process_time() - t0


def evaluate(agent, env_id, episodes, max_steps):
    """Deterministic rollouts (interventions off) on the harness's evaluation seeds, with
    the per-step cause of every suction loss and the executed actions."""
    env = gym.make(env_id, obs_mode="flat", max_episode_steps=max_steps)
    rows, actions = [], []
    for i in range(episodes):
        seed = EVAL_SEED0 + i
        obs, info = env.reset(seed=seed)
        engaged, commanded, breaks, steps, first_loss = info["suction_engaged"], 0, 0, 0, None
        while True:
            a = agent.act(obs, deterministic=True)[0]
            actions.append(a)
            obs, _, terminated, truncated, info = env.step(a)
            steps += 1
            if info["suction_failed"]:
                breaks += 1
            elif engaged and not info["suction_engaged"]:
                commanded += 1
            if engaged and not info["suction_engaged"] and first_loss is None:
                first_loss = steps
            # The env's own label, where the env reports it (window_bench >= this change).
            if "suction_loss" in info and engaged and not info["suction_engaged"]:
                assert info["suction_loss"] == ("grip_break" if info["suction_failed"]
                                                else "commanded")
            engaged = info["suction_engaged"]
            if terminated or truncated:
                break
        rows.append({"seed": seed, "success": bool(terminated), "steps": steps,
                     "suction_acquired": bool(info["suction_acquired"]),
                     "insertion_entered": bool(info["insertion_entered"]),
                     "failure_mode": "" if terminated else (info["failure_mode"] or "timeout"),
                     "commanded_releases": commanded, "grip_breaks": breaks,
                     "first_suction_loss_step": first_loss})
    env.close()
    return rows, np.asarray(actions)


def action_stats(agent, demos, rollout_actions):
    obs = np.concatenate([ep.observations[:-1] for ep in demos]).astype(np.float32)
    demo_a = np.concatenate([ep.actions for ep in demos])
    pol_a = agent.act(obs, deterministic=True)[:, 0]
    on = lambda a: float(np.mean(a[:, 6] > VACUUM_THRESHOLD))  # noqa: E731
    r = lambda x: [round(float(v), 4) for v in x]  # noqa: E731
    return {"on_demo_states": {
                "demo_mean": r(demo_a.mean(0)), "demo_std": r(demo_a.std(0)),
                "policy_mean": r(pol_a.mean(0)), "policy_std": r(pol_a.std(0)),
                "mae_per_dim": r(np.abs(pol_a - demo_a).mean(0)),
                "vacuum_on_demo": on(demo_a), "vacuum_on_policy": on(pol_a),
                "n_states": int(len(obs))},
            "in_evaluation": {"policy_mean": r(rollout_actions.mean(0)),
                              "policy_std": r(rollout_actions.std(0)),
                              "vacuum_on": on(rollout_actions),
                              "n_steps": int(len(rollout_actions))}}


def q_check(agent, demos, gamma: float = 0.99) -> dict:
    """The critics' values on the demonstrations against what any return can be: the reward
    is 1 on acceptance and 0 otherwise, so the demos' discounted return-to-go is <= 1."""
    obs = torch.as_tensor(np.concatenate([ep.observations[:-1] for ep in demos]),
                          dtype=torch.float32)
    act = torch.as_tensor(np.concatenate([ep.actions for ep in demos]), dtype=torch.float32)
    rtg = np.concatenate([gamma ** np.arange(ep.T)[::-1] * float(ep.terminated[-1])
                          for ep in demos])
    with torch.no_grad():
        o = agent._normalize(obs)
        q_demo = agent.critic(o, act[:, :agent.pose_dim]).mean(0)
        q_pi = agent.critic(o, agent.actor.mode(o)).mean(0)
    return {"demo_return_to_go_mean": float(rtg.mean()), "q_demo_action_mean": float(q_demo.mean()),
            "q_policy_action_mean": float(q_pi.mean()),
            "frac_q_policy_above_q_demo": float((q_pi > q_demo).float().mean())}


def main(argv=None):
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--profile", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None, help="Stage I gradient steps")
    p.add_argument("--episodes", type=int, default=None, help="evaluation episodes (M)")
    p.add_argument("--agent-config", nargs="+", default=None, metavar="KEY=VALUE")
    p.add_argument("--tag", required=True)
    p.add_argument("--out", default="runs/sanity")
    p.add_argument("--eval-only", action="store_true", help="re-evaluate the saved policy")
    a = p.parse_args(argv)
    profile = get_profile(a.profile)
    steps = profile.offline_steps if a.steps is None else a.steps
    episodes = profile.eval_episodes if a.episodes is None else a.episodes
    if steps < 0 or episodes < 1:
        p.error(f"--steps {steps} must be >= 0 and --episodes {episodes} >= 1")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    demos = demos_for(a.env, profile.n_demos, out / f"demos_s{a.seed}", a.seed)
    pol_path = out / f"hilserl_stage1_{a.tag}.pt"
    overrides = parse_overrides(a.agent_config)
    if a.eval_only:
        agent = HILSERLAgent.from_state_dict(torch.load(pol_path, weights_only=True))
        last, cpu_s = {}, None
    else:
        agent, last, cpu_s = stage1(a.env, profile, a.seed, steps, overrides, demos)
        torch.save(agent.state_dict(), pol_path)
    rows, acts = evaluate(agent, a.env, episodes, profile.max_episode_steps)
    summary = summarize_eval([{**r, "cycle_time_s": r["steps"] / 10} for r in rows])
    failed = [r for r in rows if not r["success"]]
    summary["episodes_with_commanded_release"] = sum(r["commanded_releases"] > 0 for r in rows)
    summary["episodes_with_grip_break"] = sum(r["grip_breaks"] > 0 for r in rows)
    summary["suction_lost_commanded_only"] = sum(
        r["failure_mode"] == "suction_lost" and r["grip_breaks"] == 0 for r in failed)
    summary["suction_lost_grip_break"] = sum(
        r["failure_mode"] == "suction_lost" and r["grip_breaks"] > 0 for r in failed)
    result = {"tag": a.tag, "env": a.env, "profile": a.profile, "seed": a.seed,
              "stage1_gradient_steps": steps, "stage1_cpu_s": cpu_s, "agent_config": overrides,
              "config": {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in agent.state_dict()["config"].items()},
              "last_update": last, "summary": summary,
              "actions": action_stats(agent, demos, acts), "q_check": q_check(agent, demos),
              "rows": rows,
              "provenance": provenance()}
    atomic_write_text(out / f"hilserl_stage1_{a.tag}.json", json.dumps(result, indent=1))
    print(json.dumps({"tag": a.tag, "summary": summary,
                      "actions": result["actions"]}, indent=1))


if __name__ == "__main__":
    main()
