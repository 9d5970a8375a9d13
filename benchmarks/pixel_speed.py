"""Pixel track speed against the privileged-state track, side by side (issue 18).

Every block runs in every repeat, so slow phases of a shared machine hit all rows; MEDIANS
over repeats are reported, and each ratio is taken within a repeat.

(a) env steps/s (only ``env.step`` timed, resets excluded, the same seeded random actions
    for every row): the state track (``obs_mode="flat"``), rendering alone
    (``obs_mode="pixels"``: wrist + side 128 x 128 views), and the pixel track
    (``PixelFeatures``: rendering + the frozen ResNet-10 on both views), and the pixel track
    observed on a chunked policy's grid (``PixelFeatures(observe_every=h)``: what the
    harness runs for an h-step policy; views rendered and encoded on every h-th step only).
(b) gradient updates/s at the same network sizes, each including the batch draw from a
    ``ChunkReplay`` (which copies the cached features): ``QCFQLAgent`` on the 52-float state
    and ``PixelQCFQL`` on the 16,402-value pixel observation.
(c) replay memory per stored chunk (measured from the replay's storage) and the
    preallocated replay memory of a ``cpu``-profile run, by chunk horizon.

Usage::

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python benchmarks/pixel_speed.py [--repeats 5]
        [--steps 20] [--updates 10] [--encoder-weights PATH]

Results go to ``benchmarks/results/pixel_speed.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import window_bench  # noqa: F401  (registers the envs)
from window_bench.data.replay import ChunkReplay
from window_bench.data.steplog import EpisodeLog
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.methods import PROFILES
from window_bench.pixels.encoder import OBS_DIM, VIEW_FEATURES
from window_bench.pixels.features import PixelFeatures
from window_bench.pixels.weights import resolve_backbone

STATE_DIM = 52


def env_rates(envs: dict, steps: int, seed: int) -> dict[str, float]:
    """Steps/s of each env on the same seeded random actions."""
    actions = np.random.default_rng(seed).uniform(-0.3, 0.3, (steps, 7)).astype(np.float32)
    actions[:, 6] = 1.0
    out = {}
    for name, env in envs.items():
        env.reset(seed=seed)
        t0 = time.perf_counter()
        for a in actions:
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                raise RuntimeError(f"{name}: the episode ended inside the timed steps")
        out[name] = steps / (time.perf_counter() - t0)
    return out


def synthetic_replay(obs_dim: int, h: int, episodes: int, T: int, seed: int,
                     pixel: bool) -> ChunkReplay:
    """A replay of random episodes (values do not change the cost); pixel feature maps are
    float16-exact, as ``PixelFeatures`` produces them."""
    rng = np.random.default_rng(seed)
    rb = ChunkReplay(episodes * -(-T // h), h, 0.99, seed=seed)
    for e in range(episodes):
        obs = rng.standard_normal((T + 1, obs_dim)).astype(np.float32)
        if pixel:
            obs[:, :2 * VIEW_FEATURES] = obs[:, :2 * VIEW_FEATURES].astype(np.float16)
        rb.add_episode(EpisodeLog(
            observations=obs, actions=rng.uniform(-1, 1, (T, 7)), rewards=np.zeros(T),
            terminated=np.zeros(T, bool), truncated=np.r_[np.zeros(T - 1, bool), True],
            provenance=["policy"] * T, takeover_kind=[""] * T, episode_id=e,
            chunk_horizon=h))
    return rb


def update_rate(agent, rb: ChunkReplay, batch: int, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        agent.update(rb.sample(batch))
    return n / (time.perf_counter() - t0)


def bytes_per_chunk(rb: ChunkReplay) -> int:
    sample = rb.sample(1)
    return int(sum(v.element_size() * v[0].numel() for v in sample.values()))


def cpu_profile_memory(per_chunk: dict[str, int], demo_steps: int) -> list[dict]:
    """Preallocated replay bytes of a ``cpu``-profile run, as the harness sizes its buffers
    (online: budget // h + 2 x max episode steps chunks; demo: n_demos x
    ceil(demo_steps / h) chunks, plus the budget for HIL-SERL, whose takeovers join D_demo).
    Observations dominate a chunk, so the bytes of an h = 10 chunk serve for h = 1 too."""
    p = PROFILES["cpu"]
    rows = []
    for label, h, hil in (("qcfql (h = 10)", 10, False), ("step-wise, h = 1", 1, False),
                          ("hil-serl (h = 1)", 1, True)):
        online = p.budget_steps // h + 2 * p.max_episode_steps
        demo = p.n_demos * -(-demo_steps // h) + (p.budget_steps if hil else 0)
        rows.append({"run": label, "chunks": online + demo,
                     **{f"{k}_GiB": round((online + demo) * v / 2 ** 30, 2)
                        for k, v in per_chunk.items()}})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="WindowInstall-A-v0")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20, help="timed env steps per row and repeat")
    ap.add_argument("--updates", type=int, default=10, help="timed updates per row and repeat")
    ap.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--h", type=int, default=10)
    ap.add_argument("--encoder-weights", default=None)
    ap.add_argument("--demo-steps", type=int, default=600,
                    help="steps per demonstration for the memory estimate (600: the bound)")
    ap.add_argument("--out", default="benchmarks/results/pixel_speed.json")
    args = ap.parse_args(argv)
    for name in ("repeats", "steps", "updates", "batch", "h"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    torch.set_num_threads(1)
    from baselines.qcfql import QCFQLAgent, QCFQLConfig
    from window_bench.pixels.agent import PixelQCFQL

    backbone, label = resolve_backbone(args.encoder_weights, allow_random=True)
    envs = {"state (flat)": gym.make(args.env, obs_mode="flat"),
            "rendering alone (pixels)": gym.make(args.env, obs_mode="pixels"),
            "pixel track (render + ResNet-10)":
                PixelFeatures(gym.make(args.env, obs_mode="pixels"), backbone),
            f"pixel track, observed on the h = {args.h} grid":
                PixelFeatures(gym.make(args.env, obs_mode="pixels"), backbone,
                              observe_every=args.h)}
    cfg = QCFQLConfig(h=args.h, hidden=tuple(args.hidden), batch_size=args.batch)
    agents = {"state": (QCFQLAgent(STATE_DIM, 7, cfg, seed=0),
                        synthetic_replay(STATE_DIM, args.h, 8, 100, 0, False)),
              "pixels": (PixelQCFQL(cfg, seed=0),
                         synthetic_replay(OBS_DIM, args.h, 8, 100, 0, True))}
    env_rates(envs, 2, seed=0)                                # warm-up: renderer, numba
    for agent, rb in agents.values():
        update_rate(agent, rb, args.batch, 2)
    env_rows, upd_rows = [], []
    for r in range(args.repeats):
        env_rows.append(env_rates(envs, args.steps, seed=1 + r))
        upd_rows.append({k: update_rate(a, rb, args.batch, args.updates)
                         for k, (a, rb) in agents.items()})
        print(f"repeat {r + 1}/{args.repeats}: " + ", ".join(
            f"{k} {v:.1f}/s" for k, v in {**env_rows[-1], **upd_rows[-1]}.items()), flush=True)
    med = lambda rows, k: float(np.median([row[k] for row in rows]))  # noqa: E731
    names = list(envs)
    ratio = lambda rows, a, b: float(np.median([row[a] / row[b] for row in rows]))  # noqa: E731
    result = {
        "env": args.env, "encoder": label, "repeats": args.repeats, "steps": args.steps,
        "updates": args.updates, "hidden": args.hidden, "batch": args.batch, "h": args.h,
        "env_steps_per_s": {k: med(env_rows, k) for k in names},
        "env_ratio_pixel_vs_state": ratio(env_rows, names[2], names[0]),
        "env_ratio_pixel_vs_rendering": ratio(env_rows, names[2], names[1]),
        "env_ratio_grid_vs_every_step": ratio(env_rows, names[3], names[2]),
        "env_ratio_grid_vs_state": ratio(env_rows, names[3], names[0]),
        "updates_per_s": {k: med(upd_rows, k) for k in agents},
        "update_cost_pixel_vs_state": ratio(upd_rows, "state", "pixels"),
        "bytes_per_chunk": {k: bytes_per_chunk(rb) for k, (_, rb) in agents.items()},
        "raw": {"env": env_rows, "updates": upd_rows}, "provenance": provenance()}
    per_chunk = {"float32": result["bytes_per_chunk"]["pixels"],
                 "float16_features": result["bytes_per_chunk"]["pixels"]
                 - 2 * 2 * 2 * VIEW_FEATURES}   # obs + next_obs, 2 views, 2 bytes saved each
    result["cpu_profile_replay"] = cpu_profile_memory(per_chunk, args.demo_steps)
    result["demo_steps"] = args.demo_steps
    for env in envs.values():
        env.close()
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(f"\nencoder: {label}; medians of {args.repeats} repeats ({args.steps} env steps, "
          f"{args.updates} updates of batch {args.batch}, MLPs {args.hidden}, h = {args.h})")
    print("| env | steps/s |\n|---|---|")
    for k in names:
        print(f"| {k} | {result['env_steps_per_s'][k]:.1f} |")
    print(f"pixel track / state track: {result['env_ratio_pixel_vs_state']:.3f}; "
          f"pixel track / rendering alone: {result['env_ratio_pixel_vs_rendering']:.3f}")
    print(f"observed on the h = {args.h} grid / every step: "
          f"{result['env_ratio_grid_vs_every_step']:.2f}x; / state track: "
          f"{result['env_ratio_grid_vs_state']:.3f}")
    print("| learner | updates/s |\n|---|---|")
    for k in agents:
        print(f"| {k} | {result['updates_per_s'][k]:.2f} |")
    print(f"pixel update cost / state update cost: {result['update_cost_pixel_vs_state']:.2f}x")
    print("| cpu-profile run | chunks | replay GiB (float32) | replay GiB (float16 features) |"
          "\n|---|---|---|---|")
    for row in result["cpu_profile_replay"]:
        print(f"| {row['run']} | {row['chunks']} | {row['float32_GiB']} | "
              f"{row['float16_features_GiB']} |")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
