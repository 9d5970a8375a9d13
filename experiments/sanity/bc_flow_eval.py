r"""Is ACT's 0 % a property of imitation on this task? Evaluate QC-FQL's Stage I from the cache:
its flow teacher alone (pure chunked behaviour cloning, h = 10, no Q-guidance) and its
distilled one-step student (what ``qcfql-offline`` deploys), deterministically (z = 0), on
the dev seeds and on the initial states of its own training demonstrations, with the same
per-episode diagnostics as ``act_trainset.py``.

    # the seed-0 Stage I entry (demos = the harness's 50 average-operator demos, seed 0)
    python experiments/sanity/bc_flow_eval.py \
        leaderboard/runs/stage1_cache/849017b6...safetensors \
        --demos-dir leaderboard/runs/demos/WindowInstall-A-v0-average-n50-s0 \
        --policy teacher student --dev 20 --train-starts 20

    # or a finished offline run: its state holds the same agent
    python experiments/sanity/bc_flow_eval.py RUN/state.safetensors \
        --env WindowInstall-B-v0 --train-starts 0 --dev 20

The file is only read. Writes ``<out>/bc_flow_<key[:8]>.json`` (a run: ``bc_flow_<run directory name>.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from act_trainset import summarize  # noqa: E402

from baselines.act import _harness_demos, _rollout  # noqa: E402
from baselines.qcfql import QCFQLAgent  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text, provenance  # noqa: E402
from window_bench.harness.files import RunFileError, load_state, sha256_file  # noqa: E402
from window_bench.harness.seeds import eval_seeds  # noqa: E402

POLICIES = ("teacher", "student")


class ChunkPolicy:
    """QC-FQL acting with one of its two policies, ``z = 0``, the ``h``-step chunk executed
    open-loop (the harness's protocol for QC-FQL): the interface ``_rollout`` drives."""

    def __init__(self, agent: QCFQLAgent, policy: str):
        self.agent, self.policy, self.h = agent, policy, agent.h

    def reset(self) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self.agent.act(obs, deterministic=True, policy=self.policy)


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("entry", help="a Stage I cache entry (<key>.safetensors), or the "
                   "state.safetensors of a finished qcfql-offline run; read only")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--demos-dir", default=None,
                   help="the Minari root of the demos this entry was trained on (for the "
                        "training starts); omit with --train-starts 0")
    p.add_argument("--operator", default="average")
    p.add_argument("--policy", nargs="+", default=list(POLICIES), choices=POLICIES)
    p.add_argument("--dev", type=int, default=20, help="dev seeds 100000..")
    p.add_argument("--train-starts", type=int, default=20,
                   help="replay from the first N training demonstrations' initial states")
    p.add_argument("--max-steps", type=int, default=None,
                   help="episode step limit (default: the environment's, 600)")
    p.add_argument("--out", default="experiments/sanity/results")
    a = p.parse_args(argv)
    entry = Path(a.entry)
    if not entry.is_file():
        p.error(f"{entry}: no such Stage I cache entry or run state")
    if a.dev < 0 or a.train_starts < 0 or (a.max_steps is not None and a.max_steps < 1):
        p.error(f"--dev {a.dev} and --train-starts {a.train_starts} must be >= 0, "
                f"--max-steps {a.max_steps} >= 1")
    if a.train_starts and a.demos_dir is None:
        p.error("--train-starts needs --demos-dir (the demos the entry was trained on)")
    material_path = entry.with_suffix(".json")
    material = json.loads(material_path.read_text()) if material_path.is_file() else {}
    run_state = entry.name == "state.safetensors"
    try:
        tree, _ = load_state(entry, "state" if run_state else "stage1")
    except RunFileError as e:
        p.error(str(e))
    agent = QCFQLAgent.from_state_dict(tree["agent"])
    seed = int(material.get("material", {}).get("seed", agent.seed))
    result = {"entry": str(entry), "entry_sha256": sha256_file(entry),
              "material": material.get("material"), "num_updates": agent.num_updates,
              "env": a.env, "acting": "z = 0, open-loop chunks of h = %d" % agent.h,
              "sets": {}}
    sets = {}
    if a.dev:
        sets["dev"] = list(eval_seeds("dev", a.dev))
    if a.train_starts:
        demos = _harness_demos(a.env, a.operator, a.demos_dir, a.train_starts, 1_000_000 + seed)
        sets["train_starts"] = [int(ep.seed) for ep in demos]
        result["demo_steps"] = [ep.T for ep in demos]
    for set_name, seeds in sets.items():
        for policy in a.policy:
            t0 = time.perf_counter()
            rows = _rollout(ChunkPolicy(agent, policy), a.env, seeds, a.max_steps)
            s = {**summarize(rows), "seeds": [seeds[0], seeds[-1]], "rows": rows,
                 "wall_s": round(time.perf_counter() - t0, 1)}
            result["sets"][f"{set_name}/{policy}"] = s
            print(f"{set_name:12s} {policy:8s} {s['successes']}/{s['episodes']} "
                  f"Wilson [{s['wilson95'][0]:.3f}, {s['wilson95'][1]:.3f}] "
                  f"S {s['pr_s']} I|S {s['pr_i_given_s']} T|I {s['pr_t_given_i']} "
                  f"{s['failure_modes']} {s['wall_s']} s", flush=True)
    tag = entry.parent.name if run_state else entry.stem[:8]
    return save_result(result, Path(a.out) / f"bc_flow_{tag}.json")


def save_result(result: dict, out: Path) -> dict:
    """``result`` with its provenance, written atomically to ``out`` (the sanity scripts'
    one way of leaving a result)."""
    result["provenance"] = provenance()
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1))
    print(out)
    return result


if __name__ == "__main__":
    main()
