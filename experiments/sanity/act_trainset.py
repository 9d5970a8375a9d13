r"""Can the ACT pipeline imitate at all? Replay ACT from the initial states of its own
training demonstrations (train-set success), in both evaluation modes (temporal
ensembling, the default, and open-loop chunks), optionally also on the dev seeds, with the
diagnostics that say where failing episodes stall.

    # train a smoke-size ACT on 3 scripted-installer demos, replay it from their starts
    python experiments/sanity/act_trainset.py --profile smoke --demos 3 --steps 3000
    # a trained policy file (python -m baselines.act --policies DIR, or a bench run's
    # policies/): its first 20 training starts and 20 dev seeds
    python experiments/sanity/act_trainset.py --policy DIR/step_0016000.safetensors \
        --operator average --demos-dir DEMOS --demos 20 --train-demos 50 --dev 20 --stall 2

Writes ``<out>/act_trainset_<profile>_<demos>x<steps>.json`` (or ``..._<policy name>.json``).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

from baselines.act import (ACT_PROFILES, ACTAgent, _collect_demos, _harness_demos, _rollout)
from window_bench.harness.evaluation import atomic_write_text, provenance, wilson_interval
from window_bench.harness.files import load_state, sha256_file
from window_bench.harness.seeds import eval_seeds

MODES = ("temporal_ensembling", "chunked")


def summarize(rows: list[dict]) -> dict:
    """k/N with its Wilson interval, and how the failing episodes ended."""
    k, n = sum(r["success"] for r in rows), len(rows)
    fails = [r for r in rows if not r["success"]]
    n_s = sum(r["suction_acquired"] for r in rows)
    n_i = sum(r["insertion_entered"] for r in rows)
    lateral = [max(r["lateral_at_closest_mm"]) for r in fails if "lateral_at_closest_mm" in r]
    return {"successes": k, "episodes": n, "wilson95": list(wilson_interval(k, n)),
            # the paper's per-stage breakdown: suction, insertion entered given suction,
            # seated (terminated) given insertion
            "pr_s": n_s / n if n else None, "pr_i_given_s": n_i / n_s if n_s else None,
            "pr_t_given_i": k / n_i if n_i else None,
            "lateral_at_closest_mm_median": float(np.median(lateral)) if lateral else None,
            "failure_modes": dict(Counter(r["failure_mode"] or "timeout" for r in fails)),
            "furthest_stage": dict(Counter(r["stage"] for r in fails)),
            "furthest_stage_step_median": (float(np.median([r["stage_step"] for r in fails]))
                                           if fails else None),
            "closest_mm_median": (float(np.median([r["closest_mm"] for r in fails]))
                                  if fails else None),
            "progress_end_step_median": (float(np.median([r["progress_end_step"] for r in fails]))
                                         if fails else None),
            "episodes_with_commanded_release": sum(r["commanded_releases"] > 0 for r in rows),
            "episodes_with_grip_break": sum(r["grip_breaks"] > 0 for r in rows),
            "episodes_with_vacuum_off_command": sum(r["vacuum_off_steps"] > 0 for r in rows),
            "final_position_error_mm_median": float(np.median([r["position_error_mm"]
                                                               for r in rows])),
            "abs_action_mean": np.mean([r["abs_action_mean"] for r in rows], 0).round(4).tolist(),
            "abs_action_mean_last50": np.mean([r["abs_action_mean_last50"] for r in rows],
                                              0).round(4).tolist()}


def stall_analysis(agent: ACTAgent, env_id: str, seed: int, demos,
                   max_steps: int | None = None) -> dict:
    """One episode from ``seed``: after the last step that brought the panel 1 mm closer to
    the seat, compare what the policy commands with what the demonstrations did in their
    nearest states (z-scored observation distance): are those states in the data, and did
    the demonstrator move there?"""
    import gymnasium as gym

    norm = agent.norm
    z = lambda o: ((torch.as_tensor(np.asarray(o, np.float32)) - norm["obs_mean"])  # noqa: E731
                   / norm["obs_std"]).numpy()
    demo_obs = z(np.concatenate([ep.observations[:-1] for ep in demos]))
    demo_act = np.concatenate([ep.actions for ep in demos])
    env = gym.make(env_id, obs_mode="flat",
                   **({} if max_steps is None else {"max_episode_steps": max_steps}))
    obs, info = env.reset(seed=int(seed))
    agent.reset()
    trace, closest, progress, done = [], info["position_error"], 0, False
    while not done:
        a = agent.act(obs)[0]
        trace.append((z(obs), a))
        obs, _, term, trunc, info = env.step(a)
        done = term or trunc
        if info["position_error"] < closest - 1e-3:
            closest, progress = info["position_error"], len(trace)
    env.close()
    stalled = trace[progress:] or trace[-1:]
    d = np.stack([((demo_obs - o) ** 2).sum(1) for o, _ in stalled])      # (S, N)
    nearest = d.argmin(1)
    # typical spacing of the demonstrations' own states, for scale
    spacing = np.sqrt([np.partition(((demo_obs - demo_obs[i]) ** 2).sum(1), 1)[1]
                       for i in range(0, len(demo_obs), 97)])
    pose = slice(0, 6)
    return {"seed": int(seed), "steps": len(trace), "progress_end_step": progress,
            "closest_mm": round(1000 * float(closest), 2),
            "stalled_steps": len(stalled),
            "policy_abs_pose_action_stalled": float(np.abs([a[pose] for _, a in stalled]).mean()),
            "demo_abs_pose_action_at_nearest": float(np.abs(demo_act[nearest, pose]).mean()),
            "demo_abs_pose_action_all": float(np.abs(demo_act[:, pose]).mean()),
            "nearest_demo_distance_median": float(np.median(np.sqrt(d.min(1)))),
            "demo_neighbour_spacing_median": float(np.median(spacing)),
            "nearest_demo_step_median": float(np.median(
                [nearest_step(demos, j) for j in nearest]))}


def nearest_step(demos, flat_index: int) -> int:
    """Step index within its episode of the ``flat_index``-th demonstrated step."""
    for ep in demos:
        if flat_index < ep.T:
            return flat_index
        flat_index -= ep.T
    raise IndexError(flat_index)


def main(argv=None):
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--profile", default="smoke", choices=sorted(ACT_PROFILES))
    p.add_argument("--operator", default=None,
                   help="training demos of this operator model (bench's D_demo, seed "
                        "1,000,000 + --seed); default: the scripted installer on seeds 0..N-1")
    p.add_argument("--demos-dir", default="runs/act_demos", help="Minari root for --operator")
    p.add_argument("--demos", type=int, default=3,
                   help="training starts replayed (the first N; 0 with --policy: none)")
    p.add_argument("--train-demos", type=int, default=None,
                   help="demos trained on (default --demos); with --policy: those it was "
                        "trained on, of which the first --demos are replayed")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--policy", default=None,
                   help="evaluate this ACT policy file instead of training one")
    p.add_argument("--dev", type=int, default=0, help="also evaluate on this many dev seeds")
    p.add_argument("--stall", type=int, default=0,
                   help="stall analysis (temporal ensembling) of this many training starts")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES,
                   help="evaluation modes (default both)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="episode step limit (default: the environment's, 600)")
    p.add_argument("--out", default="runs/sanity")
    a = p.parse_args(argv)
    n_train = a.demos if a.train_demos is None else a.train_demos
    if (a.demos < (0 if a.policy else 1) or a.steps < 1 or n_train < a.demos or a.dev < 0
            or not 0 <= a.stall <= a.demos or (a.max_steps is not None and a.max_steps < 1)):
        p.error(f"--demos {a.demos} (>= 0 with --policy), --steps {a.steps} must be >= 1, "
                f"--train-demos {n_train} "
                f">= --demos, --dev {a.dev} >= 0, --stall {a.stall} in [0, --demos], "
                f"--max-steps {a.max_steps} >= 1")
    if a.policy is not None and not Path(a.policy).is_file():
        p.error(f"--policy {a.policy}: no such file")
    if a.operator is None:
        demos = _collect_demos(a.env, range(n_train))
    else:
        demos = _harness_demos(a.env, a.operator, a.demos_dir, n_train, 1_000_000 + a.seed)
    result = {"env": a.env, "operator": a.operator or "scripted", "seed": a.seed,
              "demo_seeds": [ep.seed for ep in demos[: a.demos]],
              "demo_steps": [ep.T for ep in demos[: a.demos]],
              "demo_successes": sum(bool(ep.terminated[-1]) for ep in demos[: a.demos]),
              "demo_abs_action_mean": np.abs(np.concatenate(
                  [ep.actions for ep in demos[: a.demos] or demos])).mean(0).round(4).tolist()}
    if a.policy is None:
        cfg = ACT_PROFILES[a.profile]
        agent = ACTAgent(demos[0].observations.shape[1], config=cfg, seed=a.seed)
        t0 = time.process_time()
        logs = agent.train_offline(demos, a.steps)
        result.update(profile=a.profile, grad_steps=a.steps,
                      train_cpu_s=round(time.process_time() - t0, 1),
                      final_loss=sum(g["loss"] for g in logs[-50:]) / len(logs[-50:]))
        sd, name = agent.policy_state_dict(), f"{a.profile}_{a.demos}x{a.steps}"
    else:
        sd, meta = load_state(a.policy, "policy")
        result.update(policy=str(a.policy), policy_sha256=sha256_file(a.policy),
                      policy_bytes=Path(a.policy).stat().st_size, policy_meta=meta)
        name = f"{a.operator or 'scripted'}_{Path(a.policy).stem}"
    agents = {m: ACTAgent.from_policy_state_dict(
        {**sd, "config": {**sd["config"], "temporal_ensembling": m == "temporal_ensembling"}})
        for m in MODES}
    result["config"] = asdict(replace(agents["chunked"].config, temporal_ensembling=True))
    result["train_l1_z0"] = agents["chunked"].chunk_l1(demos)
    sets = {"train_starts": result["demo_seeds"]} if a.demos else {}
    if a.dev:
        sets["dev"] = eval_seeds("dev", a.dev)
    for set_name, seeds in sets.items():
        for mode in a.modes:
            t0 = time.perf_counter()
            rows = _rollout(agents[mode], a.env, seeds, a.max_steps)
            result[f"{set_name}/{mode}"] = {**summarize(rows), "rows": rows,
                                            "wall_s": round(time.perf_counter() - t0, 1)}
            s = result[f"{set_name}/{mode}"]
            print(f"{set_name:12s} {mode:20s} {s['successes']}/{s['episodes']} "
                  f"Wilson [{s['wilson95'][0]:.3f}, {s['wilson95'][1]:.3f}] "
                  f"{s['failure_modes']} stage {s['furthest_stage']}", flush=True)
    result["stall"] = [stall_analysis(agents["temporal_ensembling"], a.env, ep.seed, demos,
                                      a.max_steps) for ep in demos[: a.stall]]
    for row in result["stall"]:
        print("stall", row, flush=True)
    result["provenance"] = provenance()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(Path(a.out) / f"act_trainset_{name}.json", json.dumps(result, indent=1))
    print({k: result.get(k) for k in ("train_cpu_s", "final_loss", "train_l1_z0")})
    return result


if __name__ == "__main__":
    main()
