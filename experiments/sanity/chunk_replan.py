r"""Does a chunked policy get better when it re-plans before its chunk is used up? Execute
only the first ``k`` actions of every proposed chunk, then ask the policy again from the
state reached (receding-horizon execution; ``k = h`` is how the policy is trained and
evaluated), on the development seeds, no takeovers.

    python experiments/sanity/chunk_replan.py RUN/policies/step_0000000.safetensors \
        --env WindowInstall-B-v0 --episodes 20 --execute 10 5 2 \
        --out experiments/sanity/results/chunk_replan_B_s2.json

A policy that closes the loop on what it sees should do at least as well with a smaller
``k``; one whose chunks only make sense whole (their first steps a pause, a vacuum toggle)
does worse.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, episodes_errors, out_errors  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policies/step_*.safetensors file of a chunked agent")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--episodes", type=int, default=20, help="dev seeds 100000.. (1-500)")
    p.add_argument("--execute", type=int, nargs="+", default=[10, 5, 2],
                   help="actions executed per chunk before re-planning (1..h)")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)

    from window_bench.harness.evaluation import _eval_episode, load_policy_file, provenance
    from window_bench.harness.seeds import DEV_SEED0

    errs = env_errors(args.env) + episodes_errors(args.episodes) + out_errors(args.out)
    if errs:
        print("error: " + "; ".join(errs), file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    cls, policy, meta = load_policy_file(args.policy)
    agent = cls.from_policy_state_dict(policy)
    h = int(agent.h)
    bad = [k for k in args.execute if not 1 <= k <= h]
    if bad:
        print(f"error: --execute {bad}; allowed: 1..h = {h}", file=sys.stderr)
        return 2

    import gymnasium as gym

    from window_bench.installer.rollout import Rollout

    class FirstSteps:
        """The agent's deterministic chunk, cut to its first ``k`` actions."""

        def __init__(self, k: int):
            self.h = k

        def reset(self, seed=None):
            agent.reset()

        def act(self, obs):
            return agent.act(obs, deterministic=True)[: self.h]

    rows = {}
    for k in args.execute:
        env = gym.make(args.env, obs_mode="flat")
        rollout = Rollout(env, FirstSteps(k), env_id=args.env, h=h)
        eps = [_eval_episode(rollout, DEV_SEED0 + i) for i in range(args.episodes)]
        env.close()
        ok = sum(e["success"] for e in eps)
        modes = Counter(e["failure_mode"] for e in eps if not e["success"])
        print(f"execute {k} of {h}: {ok}/{args.episodes} seated; failures {dict(modes)}",
              flush=True)
        rows[str(k)] = {"successes": ok, "episodes": args.episodes,
                        "failure_modes": dict(modes), "per_episode": eps}
    out = {"policy": str(args.policy), "env_id": args.env, "h": h,
           "seeds": f"dev {DEV_SEED0}..{DEV_SEED0 + args.episodes - 1}",
           "execute": rows, "provenance": provenance()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
