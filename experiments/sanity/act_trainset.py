"""Can the ACT pipeline imitate at all? Train ACT on a few scripted-installer
demonstrations and replay it from the same initial states (train-set success), in both
evaluation modes (temporal ensembling, the default, and open-loop chunks).

    python experiments/sanity/act_trainset.py --profile smoke --demos 3 --steps 3000

Writes ``runs/sanity/act_trainset_<profile>_<demos>x<steps>.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from baselines.act import ACT_PROFILES, ACTAgent, _collect_demos, _rollout
from window_bench.harness.evaluation import atomic_write_text, provenance


def main(argv=None):
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--profile", default="smoke", choices=sorted(ACT_PROFILES))
    p.add_argument("--demos", type=int, default=3, help="demonstrations, seeds 0..N-1")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/sanity")
    a = p.parse_args(argv)
    if a.demos < 1 or a.steps < 1:
        p.error(f"--demos {a.demos} and --steps {a.steps} must be >= 1")
    demos = _collect_demos(a.env, range(a.demos))
    cfg = ACT_PROFILES[a.profile]
    agent = ACTAgent(demos[0].observations.shape[1], config=cfg, seed=a.seed)
    t0 = time.process_time()
    logs = agent.train_offline(demos, a.steps)
    cpu_s = time.process_time() - t0
    chunked = ACTAgent(agent.obs_dim, config=replace(cfg, temporal_ensembling=False))
    chunked.load_state_dict(agent.state_dict())
    seeds = [ep.seed for ep in demos]
    result = {"env": a.env, "profile": a.profile, "config": asdict(cfg), "seed": a.seed,
              "demo_seeds": seeds, "demo_steps": [ep.T for ep in demos],
              "demo_successes": sum(bool(ep.terminated[-1]) for ep in demos),
              "grad_steps": a.steps, "train_cpu_s": round(cpu_s, 1),
              "final_loss": sum(g["loss"] for g in logs[-50:]) / len(logs[-50:]),
              "train_l1_z0": agent.chunk_l1(demos),
              "temporal_ensembling": _rollout(agent, a.env, seeds),
              "chunked": _rollout(chunked, a.env, seeds), "provenance": provenance()}
    Path(a.out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out) / f"act_trainset_{a.profile}_{a.demos}x{a.steps}.json",
                      json.dumps(result, indent=1))
    for mode in ("temporal_ensembling", "chunked"):
        print(mode, [(r["seed"], r["success"], r["failure_mode"], r["position_error_mm"])
                     for r in result[mode]])
    print({k: result[k] for k in ("train_cpu_s", "final_loss", "train_l1_z0")})


if __name__ == "__main__":
    main()
