"""How fast does the acceptance reward reach the start of an episode through ``hil-serl``'s
critics? Policy evaluation of the demonstrations' own actions, the best case for h = 1 TD.

The reward is 1 on the accepting step and 0 on the ~190 steps before it, so the value of a
start state, ``gamma^(T-1)`` (0.145 on average at gamma = 0.99), exists in the critics only
once the TD backups have carried the reward back ~190 steps. This script measures that
speed with nothing else in the way: ``hil-serl``'s critic ensemble (the ``cpu`` profile's
256 x 256, tanh, LayerNorm, 2 members, Adam 3e-4, Polyak tau = 0.005 after every step, batch
256) trained by SARSA on the 50 demonstrations only, the target bootstrapping from the
demonstrations' own next action (``y = r + gamma (1 - d) min_k Qbar_k(s', a'_demo)``):
no actor, no out-of-distribution action, no online data. Every ``--every`` critic steps it
records the critics' mean value at the 50 start states and on all demonstration states
against the true discounted returns, and their correlation with the return-to-go.

    python experiments/sanity/hilserl_propagation.py --steps 10000 \\
        --out experiments/sanity/results/hilserl_propagation.json

With ``--h 10`` the same critic (still on the step's own action) is trained on 10-step
returns (``y = R_10 + gamma^10 (1 - d) min_k Qbar_k(s_{t+10}, a_{t+10})``), the backup
length of QC-FQL's chunks, to show what a longer backup changes at the same budget.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from baselines.hilserl import HILSERLAgent, HILSERLConfig
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.run import obs_normalizer
from window_bench.installer.demos import load_demos


def transitions(demos, gamma: float, h: int) -> dict[str, np.ndarray]:
    """Per demonstration step t: s_t, a_t, R = sum_{i<h} gamma^i r_{t+i}, s_{t+h'}, a_{t+h'}
    (h' = min(h, T - t)), done (the episode terminated inside the window), the window's
    discount gamma^h', and the true discounted return-to-go."""
    cols = {k: [] for k in ("obs", "act", "ret", "next_obs", "next_act", "done", "disc", "rtg",
                            "start")}
    for ep in demos:
        T, r = ep.T, ep.rewards.astype(np.float64)
        rtg = np.array([sum(gamma ** i * r[t + i] for i in range(T - t)) for t in range(T)])
        for t in range(T):
            k = min(h, T - t)
            cols["obs"].append(ep.observations[t])
            cols["act"].append(ep.actions[t])
            cols["ret"].append(sum(gamma ** i * r[t + i] for i in range(k)))
            cols["next_obs"].append(ep.observations[t + k])
            cols["next_act"].append(ep.actions[min(t + k, T - 1)])
            cols["done"].append(float(t + k == T and ep.terminated[-1]))
            cols["disc"].append(gamma ** k)
            cols["rtg"].append(rtg[t])
            cols["start"].append(t == 0)
    return {k: np.asarray(v, np.float32 if k != "start" else bool) for k, v in cols.items()}


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--demos", type=Path, default=Path("runs/sanity/demos_s0"))
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--n-demos", type=int, default=50)
    p.add_argument("--steps", type=int, default=10_000, help="critic steps")
    p.add_argument("--every", type=int, default=1_000)
    p.add_argument("--h", type=int, default=1, help="backup length (1: hil-serl)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    if a.steps < 1 or a.every < 1 or a.h < 1 or a.n_demos < 1:
        p.error(f"--steps {a.steps}, --every {a.every}, --h {a.h} and --n-demos {a.n_demos} "
                f"must all be >= 1")
    demos = load_demos(a.demos, a.env, "average")[:a.n_demos]
    cfg = HILSERLConfig()
    mean, std = obs_normalizer(np.concatenate([ep.observations for ep in demos]))  # the harness's
    agent = HILSERLAgent(demos[0].observations.shape[1], 7, cfg, seed=a.seed,
                         obs_mean=mean, obs_std=std)
    d = transitions(demos, cfg.gamma, a.h)
    P = agent.pose_dim
    t = {k: torch.as_tensor(v) for k, v in d.items()}
    obs, nobs = agent._normalize(t["obs"]), agent._normalize(t["next_obs"])
    act, nact = t["act"][:, :P], t["next_act"][:, :P]
    g = torch.Generator().manual_seed(a.seed)
    n, rows, t0 = len(obs), [], time.process_time()

    def record(step: int) -> None:
        with torch.no_grad():
            q = agent.critic(obs, act).mean(0)
        rtg, start = t["rtg"], t["start"]
        rows.append({"critic_steps": step,
                     "q_start_mean": float(q[start].mean()),
                     "true_start_mean": float(rtg[start].mean()),
                     "q_all_mean": float(q.mean()), "true_all_mean": float(rtg.mean()),
                     "corr_q_rtg": float(np.corrcoef(q.numpy(), rtg.numpy())[0, 1]),
                     "abs_err_mean": float((q - rtg).abs().mean())})
        print(json.dumps(rows[-1]))

    record(0)
    for step in tqdm(range(1, a.steps + 1), desc="SARSA on demos", unit="step", mininterval=10):
        i = torch.randint(n, (cfg.batch_size,), generator=g)
        with torch.no_grad():
            next_v = agent.target_critic(nobs[i], nact[i]).min(dim=0).values
            y = t["ret"][i] + t["disc"][i] * (1.0 - t["done"][i]) * next_v
        loss = (agent.critic(obs[i], act[i]) - y).pow(2).mean()
        agent.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        agent.critic_opt.step()
        agent._polyak()
        if step % a.every == 0:
            record(step)
    out = {"env": a.env, "demos": a.n_demos, "h": a.h, "gamma": cfg.gamma, "tau": cfg.tau,
           "batch_size": cfg.batch_size, "hidden": list(cfg.hidden), "seed": a.seed,
           "cpu_s": round(time.process_time() - t0, 1), "rows": rows,
           "provenance": provenance()}
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.out, json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
