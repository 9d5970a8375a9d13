r"""How much does ACT's temporal-ensembling weight decide? Evaluate one trained ACT policy
file with several ensembling coefficients ``m`` (weights ``exp(-m i)``, ``i`` = 0 the
oldest prediction for the current step; ACT uses 0.01, m < 0 weighs the newest most) on the
same development seeds, a query every step, no takeovers. Only the inference setting
changes: the weights are the file's.

    python experiments/sanity/act_ensemble.py POLICY --coeffs 0.01 -0.1 -0.2 -0.5 -1.0 \
        --episodes 60 --first 40 --out experiments/sanity/results/act_ensemble_A_s0.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import episodes_errors, load_policy_or_exit, out_errors  # noqa: E402

MAX_FIRST = 10_000


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="an ACT policies/step_*.safetensors file")
    p.add_argument("--coeffs", type=float, nargs="+", required=True,
                   help="ensembling coefficients m to compare, each in [-5, 5]")
    p.add_argument("--episodes", type=int, default=40, help="dev seeds per coefficient (1-500)")
    p.add_argument("--first", type=int, default=0,
                   help=f"first dev seed, as an offset from 100,000 (0-{MAX_FIRST})")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    errs = episodes_errors(args.episodes) + out_errors(args.out)
    errs += [f"--coeffs {c}; allowed: -5..5" for c in args.coeffs
             if not (math.isfinite(c) and -5 <= c <= 5)]
    if not 0 <= args.first <= MAX_FIRST:
        errs.append(f"--first {args.first}; allowed: 0..{MAX_FIRST}")
    if errs:
        p.error("; ".join(errs))
    cls, policy, meta = load_policy_or_exit(p, args.policy)
    if meta["agent_kind"] != "act" or not policy["config"]["temporal_ensembling"]:
        p.error(f"{args.policy}: not an ACT policy with temporal ensembling "
                f"(agent {meta['agent_kind']!r})")

    from window_bench.harness.evaluation import (_eval_episode, _eval_rollout, provenance,
                                                 summarize_eval)
    from window_bench.harness.seeds import DEV_SEED0

    torch.set_num_threads(1)
    seeds = [DEV_SEED0 + args.first + i for i in range(args.episodes)]
    results = []
    for m in args.coeffs:
        state = {**policy, "config": {**policy["config"], "ensemble_coeff": float(m)}}
        rollout, env = _eval_rollout(cls, state, meta["env_id"], 600)
        rows = [_eval_episode(rollout, s) for s in seeds]
        env.close()
        s = summarize_eval(rows)
        row = {"ensemble_coeff": m, "successes": sum(r["success"] for r in rows),
               "episodes": len(rows), "wilson95": s["wilson95"],
               "pr_T_given_I": s["pr_T_given_I"], "failure_modes": s["failure_modes"],
               "seated_seeds": [r["seed"] for r in rows if r["success"]]}
        results.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "seated_seeds"}), flush=True)
    out = {"policy": str(args.policy), "env_id": meta["env_id"], "seeds": [seeds[0], seeds[-1]],
           "results": results, "provenance": provenance()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
