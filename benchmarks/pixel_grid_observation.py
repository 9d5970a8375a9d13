"""A pixel-track policy evaluated observing every step and observing on its chunk grid, side
by side: the same episodes (checked row by row) and the time each takes.

The harness observes a pixel policy with horizon ``h`` only on its chunk grid
(``PixelFeatures(observe_every=h)``, docs/pixels.md). This script takes a committed policy
file, builds both envs in one process and runs each seed in both, alternating which goes
first, so a slow phase of a shared machine hits both. Every evaluation row (success, cycle
time, stages, failure mode, suction losses) must be equal; it reports the median seconds per
episode of each and the median of the per-seed ratios.

Usage::

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/pixel_grid_observation.py \\
        leaderboard/runs/WindowInstall-A-v0/qcfql-offline-pixels-cpu-s0/policies/step_0000000.safetensors \\
        --episodes 4 [--seed-set dev] [--out benchmarks/results/pixel_grid_observation.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # run from a checkout
import window_bench  # noqa: F401  (registers the envs)
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.evaluation import AgentPolicy, _eval_episode, load_policy_file
from window_bench.harness.seeds import eval_seeds
from window_bench.installer.rollout import Rollout
from window_bench.pixels.track import make_track_env


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("policy", help="a pixel-track policy file (policies/step_N.safetensors)")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--seed-set", default="dev", choices=("dev", "test"))
    ap.add_argument("--max-steps", type=int, default=600)
    ap.add_argument("--out", default="benchmarks/results/pixel_grid_observation.json")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"--episodes must be >= 1, got {args.episodes}")
    torch.set_num_threads(1)
    try:
        agent_cls, state, meta = load_policy_file(args.policy)
    except ValueError as e:          # RunFileError included: missing, cut, a pickle
        ap.error(str(e))
    if getattr(agent_cls, "track", "state") != "pixels":
        ap.error(f"{args.policy}: a {meta['method']} policy of the state track; this compares "
                 "ways of observing the pixel track")
    agent = agent_cls.from_policy_state_dict(state)
    h = int(agent.h)
    if h == 1:
        ap.error(f"{args.policy}: h = 1, so the grid is every step: nothing to compare")
    modes = {"every step": 1, f"h = {h} grid": h}
    rollouts = {}
    for name, every in modes.items():
        env = make_track_env(meta["env_id"], "pixels", weights=state.get("encoder_weights"),
                             max_episode_steps=args.max_steps, observe_every=every)
        rollouts[name] = (Rollout(env, AgentPolicy(agent, deterministic=True),
                                  env_id=meta["env_id"]), env)
    rows, times = {m: [] for m in modes}, {m: [] for m in modes}
    for i, seed in enumerate(eval_seeds(args.seed_set, args.episodes)):
        order = list(modes) if i % 2 == 0 else list(modes)[::-1]
        for name in order:
            t0 = time.perf_counter()
            rows[name].append(_eval_episode(rollouts[name][0], seed))
            times[name].append(time.perf_counter() - t0)
        a, b = (rows[m][-1] for m in modes)
        if a != b:
            raise SystemExit(f"seed {seed}: the rows differ: {a} vs {b}")
        print(f"seed {seed}: {a['failure_mode'] or 'seated'}, {a['cycle_time_s']} s; "
              + ", ".join(f"{m} {times[m][-1]:.1f} s" for m in modes), flush=True)
    for _, env in rollouts.values():
        env.close()
    every, grid = modes
    result = {
        "policy": args.policy, "method": meta["method"], "env_id": meta["env_id"], "h": h,
        "seed_set": args.seed_set, "episodes": args.episodes,
        "rows_equal": True, "rows": rows[every],
        "seconds_per_episode_median": {m: float(np.median(times[m])) for m in modes},
        "speedup_median": float(np.median(np.array(times[every]) / np.array(times[grid]))),
        "seconds": times, "provenance": provenance()}
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(f"{args.episodes} episodes, rows equal; median s/episode: " + ", ".join(
        f"{m} {v:.1f}" for m, v in result["seconds_per_episode_median"].items())
        + f"; grid speed-up (median of per-seed ratios) {result['speedup_median']:.2f}x")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
