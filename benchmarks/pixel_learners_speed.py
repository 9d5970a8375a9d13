"""Learner calls per second of HIL-SERL and SB3 SAC on the pixel track against the state
track, at the same network sizes (the ``cpu`` profile's: MLPs 256 x 256, batch 256).

Each learner is built by the harness's own ``create`` from an ``AgentSpec`` on random
episodes (state: 52 values; pixels: 16,402 with float16-exact feature maps, as
``PixelFeatures`` makes them) and timed on ``learn``: HIL-SERL draws from a ``ChunkReplay``
(the pixel one storing features as float16, as ``bench run --track pixels``) and takes two
critic steps and one actor step per call; SAC runs SB3's ``train(gradient_steps=1)`` on its
own buffer. Rows run interleaved in every repeat (the machine is shared), MEDIANS over repeats
are reported and each ratio is taken within a repeat.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/pixel_learners_speed.py [--repeats 5] [--calls 5]

Results go to ``benchmarks/results/pixel_learners_speed.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import torch

from window_bench.data.replay import ChunkReplay
from window_bench.data.steplog import EpisodeLog
from window_bench.harness.agent import AgentSpec
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.methods import PROFILES, agent_class
from window_bench.pixels.encoder import FEATURE_VALUES, OBS_DIM

STATE_DIM = 52
KINDS = {"hil-serl": ("hilserl", "hilserl-pixels"), "sac": ("sac", "sac-pixels")}


def episodes(obs_dim: int, n: int = 4, T: int = 100, seed: int = 0) -> list[EpisodeLog]:
    rng = np.random.default_rng(seed)
    out = []
    for e in range(n):
        obs = rng.standard_normal((T + 1, obs_dim)).astype(np.float32)
        if obs_dim == OBS_DIM:
            obs[:, :FEATURE_VALUES] = np.abs(obs[:, :FEATURE_VALUES]).astype(np.float16)
        out.append(EpisodeLog(
            observations=obs, actions=rng.uniform(-1, 1, (T, 7)), rewards=rng.uniform(-1, 0, T),
            terminated=np.zeros(T, bool), truncated=np.r_[np.zeros(T - 1, bool), True],
            provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=e, seed=e))
    return out


def learner(kind: str, obs_dim: int):
    """A learner of ``kind`` and its ``learn`` argument (a sampler of 256-chunk batches)."""
    demos = episodes(obs_dim)
    obs = np.concatenate([ep.observations for ep in demos])
    profile = dataclasses.replace(PROFILES["cpu"], budget_steps=1_000)   # SAC's buffer size
    agent = agent_class(kind).create(AgentSpec(
        obs_dim=obs_dim, action_dim=7, h=1, seed=0, profile=profile, demos=demos,
        obs_mean=obs.mean(0), obs_std=obs.std(0)))
    rb = ChunkReplay(sum(ep.T for ep in demos), 1, agent.gamma, seed=0,
                     half_obs=FEATURE_VALUES if obs_dim == OBS_DIM else 0)
    for ep in demos:
        rb.add_episode(ep)
    return agent, lambda: rb.sample(profile.batch_size)


def rate(agent, sample, calls: int) -> float:
    t0 = time.perf_counter()
    for _ in range(calls):
        agent.learn(sample)
    return calls / (time.perf_counter() - t0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--calls", type=int, default=5, help="timed learner calls per row and repeat")
    ap.add_argument("--out", default="benchmarks/results/pixel_learners_speed.json")
    args = ap.parse_args(argv)
    for name in ("repeats", "calls"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    torch.set_num_threads(1)
    rows = {f"{m} {track}": learner(kind, OBS_DIM if track == "pixels" else STATE_DIM)
            for m, kinds in KINDS.items() for track, kind in zip(("state", "pixels"), kinds)}
    for agent, sample in rows.values():                        # warm-up
        rate(agent, sample, 1)
    raw = []
    for r in range(args.repeats):
        raw.append({k: rate(a, s, args.calls) for k, (a, s) in rows.items()})
        print(f"repeat {r + 1}/{args.repeats}: "
              + ", ".join(f"{k} {v:.2f}/s" for k, v in raw[-1].items()), flush=True)
    med = {k: float(np.median([x[k] for x in raw])) for k in rows}
    cost = {m: float(np.median([x[f"{m} state"] / x[f"{m} pixels"] for x in raw])) for m in KINDS}
    result = {"learner_calls_per_s": med, "pixel_call_cost_vs_state": cost,
              "repeats": args.repeats, "calls": args.calls, "batch": 256, "hidden": [256, 256],
              "raw": raw, "provenance": provenance()}
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("learner_calls_per_s", "pixel_call_cost_vs_state")},
                     indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
