"""What the installer's takeovers are made of, for a frozen policy acting as it does in training.

The complete pipeline's training intervention rate (takeover steps over all steps of the last
20 training episodes, ``checkpoints.csv``) did not decay in our runs, where the paper's falls
from about 0.25 to near zero (issue 17). This script replays a committed final policy the way
Stage III acts: the stochastic acting policy (``deterministic=False``), the training env, the
``InstallerSupervisor`` of the run's operator, and records for every takeover its cue, its kind,
its length, whether it ran into the operator's ``max_takeover_steps`` (the installer did not
restore the recoverable envelope and handed back anyway), and each episode's outcome. With
``--deterministic`` the same episodes run on the policy's mean action, which separates what the
acting noise costs; with ``--no-supervisor`` they run with no takeovers at all (the policy
alone on the same seeds), which separates what the takeovers themselves cost.

    python experiments/sanity/intervention_anatomy.py \\
        leaderboard/runs/WindowInstall-A-v0/qcfql-cpu-s0/policies/step_0024000.safetensors \\
        --episodes 30 --out experiments/sanity/results/intervention_anatomy_A_s0.json

Seeds are 3,000,000 + i (neither training, dev nor test seeds). One process, one thread.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from window_bench.envs.wrappers import make_training_env
from window_bench.harness.evaluation import atomic_write_text, provenance, wilson_interval
from window_bench.harness.run import AgentPolicy, load_policy_file
from window_bench.installer.rollout import Rollout
from window_bench.installer.supervisor import InstallerSupervisor

SEED_BASE = 3_000_000


def takeover_segments(prov: np.ndarray) -> list[tuple[int, int]]:
    """``(start, length)`` of each contiguous run of takeover steps."""
    out, start = [], None
    for t, p in enumerate(list(prov) + ["end"]):
        if p == "takeover" and start is None:
            start = t
        elif p != "takeover" and start is not None:
            out.append((start, t - start))
            start = None
    return out


def episode(rollout: Rollout, sup: InstallerSupervisor, seed: int) -> dict:
    log = rollout.run(seed=seed, episode_id=seed)
    info = rollout.info
    cap = sup.profile.max_takeover_steps
    segs = takeover_segments(log.provenance)
    # One event per takeover; segments can be longer than the takeover by the hold-still steps
    # up to the policy's next chunk boundary (< h), so "hit the cap" is length >= cap.
    takeovers = [{"step": int(t), "cue": cue, "kind": kind,
                  "steps": int(segs[i][1]) if i < len(segs) else None,
                  "hit_cap": bool(i < len(segs) and segs[i][1] >= cap)}
                 for i, (t, cue, kind) in enumerate(sup.events)]
    success = bool(log.terminated[-1])
    return {"seed": seed, "steps": int(log.T), "success": success,
            "failure_mode": "" if success else (info.get("failure_mode") or "timeout"),
            "takeover_steps": int((log.provenance == "takeover").sum()), "takeovers": takeovers}


def summary(rows: list[dict]) -> dict:
    steps = sum(r["steps"] for r in rows)
    take = sum(r["takeover_steps"] for r in rows)
    k = sum(r["success"] for r in rows)
    by_outcome = {}
    for name, sel in (("accepted", [r for r in rows if r["success"]]),
                      ("failed", [r for r in rows if not r["success"]])):
        by_outcome[name] = {"episodes": len(sel), "steps": sum(r["steps"] for r in sel),
                            "takeover_steps": sum(r["takeover_steps"] for r in sel)}
    events = [e for r in rows for e in r["takeovers"]]
    cues = Counter(e["cue"] for e in events)
    cue_steps = Counter()
    for e in events:
        cue_steps[e["cue"]] += e["steps"] or 0
    return {"episodes": len(rows), "successes": k, "success_rate": k / len(rows),
            "wilson95": list(wilson_interval(k, len(rows))),
            "intervention_rate": take / steps, "takeover_steps": take, "steps": steps,
            "episodes_with_takeover": sum(bool(r["takeovers"]) for r in rows),
            "by_outcome": by_outcome, "takeovers": len(events),
            "takeovers_hit_cap": sum(e["hit_cap"] for e in events),
            "cues": dict(cues), "cue_steps": dict(cue_steps),
            "failure_modes": dict(Counter(r["failure_mode"] for r in rows if not r["success"]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("policy", help="a policy file under a run's policies/")
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--operator", default="average")
    ap.add_argument("--deterministic", action="store_true",
                    help="act on the mean action (evaluation's acting), not training's")
    ap.add_argument("--no-supervisor", action="store_true",
                    help="no takeovers: the policy alone on the same seeds")
    ap.add_argument("--out", default=None, help="JSON file for the per-episode rows and summary")
    args = ap.parse_args(argv)
    if not 1 <= args.episodes <= 1000:
        ap.error(f"--episodes {args.episodes} is outside [1, 1000]")
    torch.set_num_threads(1)
    agent_cls, state, meta = load_policy_file(args.policy)
    agent = agent_cls.from_policy_state_dict(state)
    env = make_training_env(meta["env_id"], None, obs_mode="flat", max_episode_steps=600)
    sup = InstallerSupervisor(args.operator, safety=not args.no_supervisor,
                              coverage=not args.no_supervisor)
    rollout = Rollout(env, AgentPolicy(agent, deterministic=args.deterministic), supervisor=sup,
                      env_id=meta["env_id"], operator=args.operator)
    rows, t0 = [], time.perf_counter()
    for i in range(args.episodes):
        rows.append(episode(rollout, sup, SEED_BASE + i))
        r = rows[-1]
        rate = (time.perf_counter() - t0) / (i + 1)
        print(f"[{i + 1}/{args.episodes}] seed {r['seed']} {'OK ' if r['success'] else 'FAIL'} "
              f"{r['steps']} steps, takeover {r['takeover_steps']} "
              f"{[(e['cue'], e['steps']) for e in r['takeovers']]}  "
              f"ETA {rate * (args.episodes - i - 1):.0f} s", flush=True)
    env.close()
    s = summary(rows)
    print(json.dumps(s, indent=1))
    if args.out:
        out = {"policy": args.policy, "policy_meta": {k: meta[k] for k in ("method", "env_id",
                                                                         "seed", "env_steps")},
               "operator": args.operator, "deterministic": args.deterministic,
               "supervisor": not args.no_supervisor,
               "seeds": [SEED_BASE, SEED_BASE + args.episodes - 1], "summary": s, "rows": rows,
               "provenance": provenance()}
        atomic_write_text(args.out, json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
