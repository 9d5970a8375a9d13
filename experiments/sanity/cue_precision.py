"""Do the installer's cues fire on episodes that would fail, or on ones the policy would finish?

A frozen policy runs alone (no takeovers) on seeds outside the training, dev and test sets.
Beside it, several ``InstallerSupervisor`` variants watch the same observations in *shadow*:
each is asked every step whether it would take over, and its first cue is recorded, but it
never acts. Paired with each episode's outcome alone this gives, per variant:

* ``false_alarm``: the fraction of the episodes the policy finishes alone in which it would
  have taken over (a takeover there replaces a success with the installer's work);
* ``detection``: the fraction of the failing episodes in which it would have taken over.

The paper's installer takes over "when safe and recoverable completion within the episode
horizon becomes uncertain": many detections, few false alarms.

    python experiments/sanity/cue_precision.py RUN/policies/step_0024000.safetensors \\
        --episodes 40 --variant wedge_steps=2 --variant wedge_steps=10,stall_steps=15

Each ``--variant`` is ``field=value[,field=value]`` over the ``--operator`` profile
(:class:`~window_bench.installer.operators.OperatorProfile` fields). One process, one thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

import numpy as np
import torch

from window_bench.envs.wrappers import make_training_env
from window_bench.harness.evaluation import atomic_write_text, provenance, wilson_interval
from window_bench.harness.run import AgentPolicy, load_policy_file
from window_bench.installer.operators import get_operator
from window_bench.installer.rollout import Rollout
from window_bench.installer.supervisor import InstallerSupervisor

SEED_BASE = 3_000_000


class Shadow:
    """A takeover source that never takes over: it records each watcher's first cue."""

    def __init__(self, watchers: dict[str, InstallerSupervisor]):
        self.watchers = watchers

    def reset(self, env, seed=None) -> None:
        self.first = {name: None for name in self.watchers}
        self.t = -1
        for sup in self.watchers.values():
            sup.reset(env, seed=seed)

    def intervene(self, obs, info):
        self.t += 1
        for name, sup in self.watchers.items():
            if self.first[name] is None and sup.intervene(obs, info) is not None:
                self.first[name] = (self.t, sup.events[-1][1])
        return None


def parse_variant(text: str, base) -> tuple[str, object]:
    fields = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        try:
            fields[key.strip()] = json.loads(value)
        except ValueError:
            raise ValueError(f"{item!r} is not field=value with a JSON value "
                             f"(e.g. wedge_steps=10)") from None
    return text, dataclasses.replace(base, name=text, **fields)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("policy", help="a policy file under a run's policies/")
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--operator", default="attentive")
    ap.add_argument("--variant", action="append", default=[],
                    help="field=value[,field=value] over --operator (repeatable)")
    ap.add_argument("--out", default=None, help="JSON file for the rows and the summary")
    args = ap.parse_args(argv)
    if not 1 <= args.episodes <= 1000:
        ap.error(f"--episodes {args.episodes} is outside [1, 1000]")
    torch.set_num_threads(1)
    try:
        base = get_operator(args.operator)
        variants = dict([(args.operator, base)] + [parse_variant(v, base) for v in args.variant])
    except (ValueError, TypeError) as e:   # unknown profile or field, bad value
        ap.error(f"--operator/--variant: {e}")
    agent_cls, state, meta = load_policy_file(args.policy)
    agent = agent_cls.from_policy_state_dict(state)
    env = make_training_env(meta["env_id"], None, obs_mode="flat", max_episode_steps=600)
    shadow = Shadow({name: InstallerSupervisor(p, coverage=False) for name, p in variants.items()})
    rollout = Rollout(env, AgentPolicy(agent, deterministic=True), supervisor=shadow,
                      env_id=meta["env_id"])
    rows = []
    for i in range(args.episodes):
        log = rollout.run(seed=SEED_BASE + i, episode_id=i)
        ok = bool(log.terminated[-1])
        rows.append({"seed": SEED_BASE + i, "success": ok, "steps": int(log.T),
                     "failure_mode": "" if ok else rollout.info.get("failure_mode") or "timeout",
                     "first_cue": dict(shadow.first)})
        print(f"[{i + 1}/{args.episodes}] {'OK  ' if ok else 'FAIL'} {log.T:4d} steps "
              + " ".join(f"{n}:{c}" for n, c in shadow.first.items()), flush=True)
    env.close()
    n_ok = sum(r["success"] for r in rows)
    n_fail = len(rows) - n_ok
    summary = {"episodes": len(rows), "successes_alone": n_ok,
               "wilson95_alone": list(wilson_interval(n_ok, len(rows))), "variants": {}}
    for name in variants:
        fa = sum(r["success"] and r["first_cue"][name] is not None for r in rows)
        det = sum((not r["success"]) and r["first_cue"][name] is not None for r in rows)
        cues = {}
        for r in rows:
            if r["first_cue"][name] is not None:
                key = f"{r['first_cue'][name][1]}_{'ok' if r['success'] else 'fail'}"
                cues[key] = cues.get(key, 0) + 1
        summary["variants"][name] = {
            "false_alarms": fa, "false_alarm_rate": fa / n_ok if n_ok else None,
            "detections": det, "detection_rate": det / n_fail if n_fail else None,
            "first_cues": cues}
    print(json.dumps(summary, indent=1))
    if args.out:
        atomic_write_text(args.out, json.dumps(
            {"policy": args.policy, "policy_meta": {k: meta[k] for k in ("method", "env_id",
                                                                         "seed", "env_steps")},
             "operator": args.operator, "variants": {n: dataclasses.asdict(p)
                                                     for n, p in variants.items()},
             "seeds": [SEED_BASE, SEED_BASE + args.episodes - 1], "summary": summary,
             "rows": rows, "provenance": provenance()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
