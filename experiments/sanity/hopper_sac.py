"""Wiring sanity outside the window task: SB3 SAC and this project's HIL-SERL/RLPD learner
(``baselines.hilserl.HILSERLAgent``, no demonstrations, no takeovers) on Gymnasium's
``Hopper-v5`` with the same budget and seed.

* ``--learner sb3``: ``stable_baselines3.SAC("MlpPolicy")`` with SB3's defaults, as
  ``baselines.sac.make_sac`` builds it (``seed``, ``device="cpu"``; no demos to pre-fill).
* ``--learner hilserl``: ``HILSERLAgent`` with ``HILSERLConfig(vacuum_head="gaussian")``
  (Hopper has no vacuum; every other setting is the ``hil-serl`` baseline's), one
  ``update`` call (2 critic steps, 1 actor step) per environment step on uniform batches of
  256 from one replay of every transition, no observation normalisation; the same 100
  uniformly random warm-up steps as SB3's ``learning_starts``.
* ``--learner rlpd``: the same loop with :data:`baselines.hilserl.RLPD_CONFIG`.

Evaluation: mean undiscounted return of 10 deterministic episodes (seeds 10_000..10_009)
every ``--eval-every`` steps. Truncation at 1,000 steps bootstraps; falling terminates.

    python experiments/sanity/hopper_sac.py --learner sb3 --steps 20000
    python experiments/sanity/hopper_sac.py --learner hilserl --steps 20000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict
from tqdm import tqdm

from window_bench.harness.evaluation import atomic_write_text, provenance

ENV_ID = "Hopper-v5"
EVAL_SEED0 = 10_000
WARMUP = 100          # SB3's learning_starts default: uniformly random actions, no updates


def evaluate(act, episodes: int = 10) -> list[float]:
    env = gym.make(ENV_ID)
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=EVAL_SEED0 + i)
        total, done = 0.0, False
        while not done:
            obs, r, terminated, truncated, _ = env.step(act(obs))
            total += float(r)
            done = terminated or truncated
        returns.append(total)
    env.close()
    return returns


def run_sb3(steps: int, seed: int, eval_every: int, curve: list):
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback

    env = gym.make(ENV_ID)
    model = SAC("MlpPolicy", env, seed=seed, device="cpu", verbose=0)

    class Eval(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % eval_every == 0:
                rets = evaluate(lambda o: model.predict(o, deterministic=True)[0])
                curve.append({"env_steps": self.num_timesteps, "returns": rets})
                print(json.dumps({"env_steps": self.num_timesteps,
                                  "mean_return": float(np.mean(rets))}), flush=True)
            return True

    model.learn(total_timesteps=steps, callback=Eval(), progress_bar=False)
    return {"sb3_defaults": {k: str(getattr(model, k)) for k in (
        "learning_rate", "batch_size", "gamma", "tau", "learning_starts", "train_freq",
        "gradient_steps", "ent_coef", "target_entropy", "buffer_size")}}


def run_ours(steps: int, seed: int, eval_every: int, curve: list, preset: str):
    from baselines.hilserl import RLPD_CONFIG, HILSERLAgent, HILSERLConfig

    cfg = (HILSERLConfig(vacuum_head="gaussian") if preset == "hilserl"
           else RLPD_CONFIG)
    env = gym.make(ENV_ID)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    agent = HILSERLAgent(obs_dim, act_dim, cfg, seed=seed)
    cap = steps
    buf = {"obs": torch.zeros(cap, obs_dim), "next_obs": torch.zeros(cap, obs_dim),
           "actions": torch.zeros(cap, 1, act_dim), "reward": torch.zeros(cap),
           "terminal": torch.zeros(cap, dtype=torch.bool)}
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)

    def sample() -> TensorDict:
        idx = torch.randint(n, (cfg.batch_size,), generator=gen)
        td = TensorDict({k: v[idx] for k, v in buf.items()}, batch_size=[cfg.batch_size])
        td["discount"] = torch.full((cfg.batch_size,), cfg.gamma)
        return td

    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    n = 0
    for t in tqdm(range(1, steps + 1), desc=preset, mininterval=30):
        a = (env.action_space.sample() if t <= WARMUP
             else agent.act(obs.astype(np.float32))[0])
        next_obs, r, terminated, truncated, _ = env.step(a)
        buf["obs"][n] = torch.as_tensor(obs)
        buf["next_obs"][n] = torch.as_tensor(next_obs)   # the true last state on truncation
        buf["actions"][n, 0] = torch.as_tensor(a)
        buf["reward"][n] = float(r)
        buf["terminal"][n] = bool(terminated)
        n += 1
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
        if t > WARMUP:
            agent.update(sample)
        if t % eval_every == 0:
            rets = evaluate(lambda o: agent.act(o.astype(np.float32), deterministic=True)[0])
            curve.append({"env_steps": t, "returns": rets})
            print(json.dumps({"env_steps": t, "mean_return": float(np.mean(rets)),
                              "temperature": agent.temperature}), flush=True)
    return {"config": {k: (list(v) if isinstance(v, tuple) else v)
                       for k, v in dataclasses.asdict(cfg).items()}}


def main(argv=None):
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--learner", choices=("sb3", "hilserl", "rlpd"), required=True)
    p.add_argument("--steps", type=int, default=20_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-every", type=int, default=5_000)
    p.add_argument("--out", default="runs/sanity")
    a = p.parse_args(argv)
    if a.steps < 1 or a.eval_every < 1 or a.seed < 0:
        p.error(f"--steps {a.steps} and --eval-every {a.eval_every} must be >= 1, "
                f"--seed {a.seed} >= 0")
    curve: list = []
    t0, c0 = time.perf_counter(), time.process_time()
    extra = (run_sb3(a.steps, a.seed, a.eval_every, curve) if a.learner == "sb3"
             else run_ours(a.steps, a.seed, a.eval_every, curve, a.learner))
    result = {"env": ENV_ID, "learner": a.learner, "steps": a.steps, "seed": a.seed,
              "eval_episodes": 10, "eval_seeds": [EVAL_SEED0, EVAL_SEED0 + 9],
              "wall_s": round(time.perf_counter() - t0, 1),
              "cpu_s": round(time.process_time() - c0, 1), "curve": curve, **extra,
              "provenance": provenance()}
    Path(a.out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out) / f"hopper_{a.learner}_s{a.seed}.json",
                      json.dumps(result, indent=1))
    print(json.dumps({"learner": a.learner, "wall_s": result["wall_s"], "cpu_s": result["cpu_s"],
                      "final_mean_return": float(np.mean(curve[-1]["returns"])) if curve else None}))


if __name__ == "__main__":
    main()
