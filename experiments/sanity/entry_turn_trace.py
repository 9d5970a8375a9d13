r"""Does the panel turn with the arm or in the cup as it reaches the opening? Roll a frozen
state-track policy on given development seeds (no takeovers) and report, every 10 steps from
the first step within 150 mm of the seat, the panel's depth, how far the panel and the TCP
have turned since then (world frame) and how far the panel has turned in the cup (its
orientation relative to the TCP), with the largest rotation command of those steps.

    python experiments/sanity/entry_turn_trace.py POLICY --env WindowInstall-B-v0 \
        --seeds 100006 100013 100015 100000 \
        --out experiments/sanity/results/entry_turn_qcfql_offline_fine_B_s2.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, load_policy_or_exit, out_errors  # noqa: E402

FROM_MM = 150.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policies/step_*.safetensors file (state track)")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--seeds", type=int, nargs="+", required=True,
                   help="development seeds (100000-100499), at most 20")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    from window_bench.harness.seeds import DEV_SEED0

    errs = env_errors(args.env) + out_errors(args.out)
    errs += [f"--seeds {s}; allowed: {DEV_SEED0}..{DEV_SEED0 + 499}" for s in args.seeds
             if not DEV_SEED0 <= s < DEV_SEED0 + 500]
    if len(args.seeds) > 20:
        errs.append(f"--seeds: {len(args.seeds)} given; allowed: at most 20")
    if errs:
        p.error("; ".join(errs))
    cls, policy, _ = load_policy_or_exit(p, args.policy)
    if getattr(cls, "track", "state") != "state":
        p.error(f"{args.policy} is not a state-track policy")

    import gymnasium as gym
    from scipy.spatial.transform import Rotation

    from window_bench.envs import scene as S
    from window_bench.harness.evaluation import AgentPolicy, provenance
    from window_bench.installer.rollout import Rollout
    from window_bench.installer.supervisor import FLAT_SLICES

    torch.set_num_threads(1)
    agent = cls.from_policy_state_dict(policy)
    env = gym.make(args.env, obs_mode="flat")
    rollout = Rollout(env, AgentPolicy(agent, deterministic=True), env_id=args.env)
    episodes = []
    for seed in args.seeds:
        log = rollout.run(seed=seed, episode_id=seed)
        obs = log.observations.astype(np.float64)
        target = Rotation.from_matrix(env.unwrapped._target_mat)
        panel = target * Rotation.from_rotvec(obs[:, FLAT_SLICES["window_rot_rel"]])
        quat = obs[:, FLAT_SLICES["robot0_eef_quat"]]             # MuJoCo order w, x, y, z
        tcp = Rotation.from_quat(quat[:, [1, 2, 3, 0]])
        in_cup = tcp.inv() * panel
        depth_mm = obs[:, FLAT_SLICES["window_pos_rel"]] @ S.INSERTION_AXIS * 1000
        near = np.flatnonzero(depth_mm > -FROM_MM)
        rows = []
        if near.size:
            i0 = int(near[0])
            for t in range(i0, log.T, 10):
                rows.append({
                    "step": t, "depth_mm": round(float(depth_mm[t]), 1),
                    "panel_turn_deg": round(float(np.rad2deg((panel[t] * panel[i0].inv()).magnitude())), 2),
                    "tcp_turn_deg": round(float(np.rad2deg((tcp[t] * tcp[i0].inv()).magnitude())), 2),
                    "in_cup_turn_deg": round(float(np.rad2deg((in_cup[t] * in_cup[i0].inv()).magnitude())), 2),
                    "max_rotation_command": round(float(np.abs(log.actions[t:t + 10, 3:6]).max()), 3)})
        ep = {"seed": seed, "success": bool(log.terminated[-1]), "rows": rows}
        episodes.append(ep)
        print(json.dumps({"seed": seed, "success": ep["success"],
                          "max_in_cup_turn_deg": max((r["in_cup_turn_deg"] for r in rows), default=None)}),
              flush=True)
    env.close()
    out = {"policy": str(args.policy), "env_id": args.env, "from_mm": FROM_MM,
           "episodes": episodes, "provenance": provenance()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
