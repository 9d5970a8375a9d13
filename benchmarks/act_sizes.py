"""ACT sizes side by side: parameters, the policy file the harness writes (acting weights,
safetensors), and the median time of a training step and of an ``act()`` query, for the
`cpu` profile and the former `cpu` size (d_model 256, FF 1024, 4 policy-encoder layers).

    OMP_NUM_THREADS=1 python benchmarks/act_sizes.py --repeats 5 --steps 20
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import numpy as np
import torch

from baselines.act import ACT_PROFILES, ACTAgent
from window_bench.data.steplog import EpisodeLog
from window_bench.harness.files import dump_state

SIZES = {"cpu": ACT_PROFILES["cpu"],
         "former cpu (d_model 256)": replace(ACT_PROFILES["cpu"], d_model=256, n_heads=8,
                                              ff=1024, enc_layers=4),
         "smoke": ACT_PROFILES["smoke"]}


def episode(T=150, seed=0) -> EpisodeLog:
    rng = np.random.default_rng(seed)
    return EpisodeLog(observations=rng.normal(size=(T + 1, 52)),
                      actions=rng.uniform(-1, 1, (T, 7)), rewards=np.zeros(T),
                      terminated=np.arange(T) == T - 1, truncated=np.zeros(T, bool),
                      provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=seed)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--steps", type=int, default=20, help="training steps per repeat")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    eps = [episode(150, 0), episode(120, 1)]
    print("| size | parameters (all / acting) | policy file | training step (median) | "
          "act() (median) |\n|---|---|---|---|---|")
    for name, cfg in SIZES.items():
        agent = ACTAgent(52, config=cfg, seed=0)
        agent.train_offline(eps, 3)   # warm-up
        step, query = [], []
        for _ in range(a.repeats):
            t = time.perf_counter()
            agent.train_offline(eps, a.steps)
            step.append((time.perf_counter() - t) / a.steps)
            t = time.perf_counter()
            for o in eps[0].observations[:20]:
                agent.act(o)
            query.append((time.perf_counter() - t) / 20)
        sd = agent.policy_state_dict()
        acting = sum(v.numel() for v in sd["model"].values())
        total = sum(q.numel() for q in agent.model.parameters())
        size = len(dump_state(sd, "policy", {"agent_kind": "act"}))
        print(f"| {name} | {total / 1e6:.3f} M / {acting / 1e6:.3f} M | {size / 1e6:.3f} MB | "
              f"{1e3 * statistics.median(step):.1f} ms | {1e3 * statistics.median(query):.2f} ms |",
              flush=True)


if __name__ == "__main__":
    main()
