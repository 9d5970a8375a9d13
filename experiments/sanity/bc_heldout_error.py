r"""Imitation error on held-out demonstrations, ACT against QC-FQL's Stage I policies, in raw
action units (no environment): the mean |predicted - demonstrated| per action dimension, of
the first action of each chunk and over the whole chunk, every held-out step, ``z = 0``.

    python experiments/sanity/bc_heldout_error.py \
        --act /tmp/act15/curve/policies/step_0016000.safetensors \
        --stage1 leaderboard/runs/stage1_cache/849017b6...safetensors \
        --demos-dir /tmp/act15/demos/heldout --out experiments/sanity/results/bc_heldout_error.json

Held-out demonstrations: ``--heldout`` episodes of ``--operator`` from seed 2,000,000 (as
``python -m baselines.act`` draws them). The Stage I entry is only read.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from baselines.act import ACTAgent, _harness_demos
from baselines.qcfql import QCFQLAgent
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.files import load_state, sha256_file


def chunk_errors(predict, episodes, k: int) -> dict:
    """``predict(obs (n, D)) -> (n, k, A)``; mean |error| per dim, first action and chunk."""
    first, whole, count = 0.0, 0.0, 0
    for ep in episodes:
        n = ep.T
        steps = np.arange(n)[:, None] + np.arange(k)[None, :]
        real = steps < n
        target = ep.actions[np.minimum(steps, n - 1)]
        err = np.abs(predict(ep.observations[:-1]) - target)            # (n, k, A)
        first = first + err[:, 0].sum(0)
        whole = whole + (err * real[..., None]).sum((0, 1))
        count += n
    n_real = sum(min(k, ep.T - t) for ep in episodes for t in range(ep.T))
    return {"first_action": (first / count).round(5).tolist(),
            "chunk": (whole / n_real).round(5).tolist()}


def policy_parser(doc: str) -> argparse.ArgumentParser:
    """The arguments every held-out-demo probe of ACT and the flow policies takes."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--act", nargs="*", default=[], help="ACT policy files")
    p.add_argument("--stage1", nargs="*", default=[], help="Stage I cache entries (read only)")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--operator", default="average")
    p.add_argument("--demos-dir", required=True, help="Minari root of the held-out demos")
    p.add_argument("--heldout", type=int, default=10)
    p.add_argument("--out", required=True)
    return p


def parse_policy_args(p: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    a = p.parse_args(argv)
    for f in [*a.act, *a.stage1]:
        if not Path(f).is_file():
            p.error(f"{f}: no such file")
    return a


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    a = parse_policy_args(policy_parser(__doc__), argv)
    eps = _harness_demos(a.env, a.operator, a.demos_dir, a.heldout, 2_000_000)
    acts = np.concatenate([ep.actions for ep in eps])
    result = {"heldout_seeds": [eps[0].seed, eps[-1].seed], "heldout_steps": int(len(acts)),
              "demo_abs_action_mean": np.abs(acts).mean(0).round(5).tolist(),
              "mean_action_predictor": np.abs(acts - acts.mean(0)).mean(0).round(5).tolist(),
              "policies": {}}
    for f in a.act:
        agent = ACTAgent.from_policy_state_dict(load_state(f, "policy")[0])
        predict = agent.predict_chunks
        result["policies"][f"act:{f}"] = {"sha256": sha256_file(f),
                                          **chunk_errors(predict, eps, agent.config.chunk)}
    for f in a.stage1:
        agent = QCFQLAgent.from_state_dict(load_state(f, "stage1")[0]["agent"])
        for policy in ("teacher", "student"):
            def predict(obs, agent=agent, policy=policy):
                return agent.act(obs, deterministic=True, policy=policy)
            result["policies"][f"qcfql-{policy}:{f}"] = {
                "sha256": sha256_file(f), **chunk_errors(predict, eps, agent.h)}
    for name, r in result["policies"].items():
        print(name[:60], "first", r["first_action"][:6], "chunk", r["chunk"][:6])
    result["provenance"] = provenance()
    atomic_write_text(a.out, json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
