r"""How does a Stage I policy miss the grasp on setting B? Rolls the flow teacher and the
one-step student of a Stage I cache entry (read only) on the dev seeds, acting as the
harness does (z = 0, open-loop chunks), and records until the suction first latches: the
cup's gap to the suction face (the env's engage test: latch iff the vacuum is commanded
(``a[6] > 0.5``) while the lip is within ``SNAP_DISTANCE`` of the face, over it and
roughly normal to it), the vacuum command, and how often the policy reverses from descending
to rising above the face.

    python experiments/sanity/grasp_timing.py \
        leaderboard/runs/stage1_cache/421c1bfa....safetensors --dev 20

Writes ``<out>/grasp_timing_<key[:8]>.json``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bc_flow_eval import POLICIES, ChunkPolicy, save_result  # noqa: E402

import window_bench  # noqa: E402,F401  (registers the env ids)
from baselines.qcfql import QCFQLAgent  # noqa: E402
from window_bench.envs.env import SNAP_DISTANCE, VACUUM_THRESHOLD  # noqa: E402
from window_bench.harness.evaluation import wilson_interval  # noqa: E402
from window_bench.harness.files import load_state, sha256_file  # noqa: E402
from window_bench.harness.seeds import eval_seeds  # noqa: E402


def face_gap(env) -> float:
    """Signed distance (m) of the TCP (cup lip) above the panel's suction face, along its
    normal: the quantity the env's engage test bounds by ``SNAP_DISTANCE``."""
    return float(env.tcp_on_face()[2])


def episode(policy: ChunkPolicy, env_id: str, seed: int) -> dict:
    env = gym.make(env_id, obs_mode="flat")
    obs, _ = env.reset(seed=seed)
    u = env.unwrapped
    gaps, vac, done, acquired, step = [], [], False, False, 0
    while not done and not acquired:
        for a in policy.act(obs):
            gaps.append(face_gap(u))
            vac.append(float(a[6]))
            obs, _, term, trunc, _ = env.step(a)
            step += 1
            acquired = bool(obs[21] > 0.5)
            done = term or trunc
            if done or acquired:
                break
    env.close()
    g, v = np.array(gaps), np.array(vac)
    on = v > VACUUM_THRESHOLD
    dg = np.diff(g)
    # a reversal: the lip stops descending and rises again while still out of reach
    reversals = int(np.sum((dg[:-1] < -1e-4) & (dg[1:] > 1e-4) & (g[1:-1] > SNAP_DISTANCE)))
    return {"seed": seed, "acquired": acquired, "steps": step,
            "min_gap_mm": round(1000 * float(g.min()), 1),
            "vacuum_on_steps": int(on.sum()),
            "gap_at_first_vacuum_on_mm": (round(1000 * float(g[on][0]), 1) if on.any() else None),
            "vacuum_on_within_reach_steps": int(np.sum(on & (g <= SNAP_DISTANCE))),
            "reversals_above_reach": reversals}


def summarize(rows: list[dict]) -> dict:
    k, n = sum(r["acquired"] for r in rows), len(rows)
    miss = [r for r in rows if not r["acquired"]]
    med = (lambda key: float(np.median([r[key] for r in miss])) if miss else None)
    return {"acquired": k, "episodes": n, "wilson95": list(wilson_interval(k, n)),
            "missed": len(miss),
            "missed_min_gap_mm_median": med("min_gap_mm"),
            "missed_never_commanded_vacuum": sum(r["vacuum_on_steps"] == 0 for r in miss),
            "missed_reversals_median": med("reversals_above_reach"),
            "acquired_steps_median": (float(np.median([r["steps"] for r in rows if r["acquired"]]))
                                      if k else None)}


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("entry", help="a Stage I cache entry (<key>.safetensors), read only")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--policy", nargs="+", default=list(POLICIES), choices=POLICIES)
    p.add_argument("--dev", type=int, default=20, help="dev seeds 100000..")
    p.add_argument("--out", default="experiments/sanity/results")
    a = p.parse_args(argv)
    entry = Path(a.entry)
    if not entry.is_file():
        p.error(f"{entry}: no such Stage I cache entry")
    if a.dev < 1:
        p.error(f"--dev {a.dev} must be >= 1")
    tree, _ = load_state(entry, "stage1")
    agent = QCFQLAgent.from_state_dict(tree["agent"])
    result = {"entry": str(entry), "entry_sha256": sha256_file(entry), "env": a.env,
              "snap_distance_mm": 1000 * SNAP_DISTANCE, "policies": {}}
    for policy in a.policy:
        rows = [episode(ChunkPolicy(agent, policy), a.env, s) for s in eval_seeds("dev", a.dev)]
        s = {**summarize(rows), "rows": rows}
        result["policies"][policy] = s
        print(f"{policy:8s} acquired {s['acquired']}/{s['episodes']}; missed: min gap median "
              f"{s['missed_min_gap_mm_median']} mm, never commanded vacuum "
              f"{s['missed_never_commanded_vacuum']}/{s['missed']}, reversals above reach "
              f"median {s['missed_reversals_median']}", flush=True)
    return save_result(result, Path(a.out) / f"grasp_timing_{entry.stem[:8]}.json")


if __name__ == "__main__":
    main()
