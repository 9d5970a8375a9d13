r"""Where do a policy's failed episodes end? Roll a frozen policy on the development seeds
(no takeovers) and report, per episode, the outcome, the panel's deepest and final depth
relative to the seat, its final lateral offset and tilt, the mean |motion command| of
its last 10 steps (a policy that stops moving has a value near 0), and where it stood when
it first reached the seating depth: its lateral offset and the distance of its centre from
the seated target (acceptance needs < 2 mm), and how many times it reached that depth.

    python experiments/sanity/failure_trace.py POLICY --env WindowInstall-A-v0 \
        --episodes 20 --out experiments/sanity/results/failure_trace_act_fine_pose_A_s0.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, episodes_errors, out_errors  # noqa: E402


#: Within this of the seating depth (mm) the panel is at the stop.
STOP_MM = 0.05


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policies/step_*.safetensors file (state track)")
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--episodes", type=int, default=20, help="dev seeds 100000.. (1-500)")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    import gymnasium as gym

    from window_bench.envs import scene as S
    from window_bench.envs.task import FAILURE_MODE_NAMES
    from window_bench.harness.evaluation import AgentPolicy, load_policy_file, provenance
    from window_bench.harness.seeds import DEV_SEED0
    from window_bench.installer.rollout import Rollout
    from window_bench.installer.supervisor import FLAT_SLICES

    errs = env_errors(args.env) + episodes_errors(args.episodes) + out_errors(args.out)
    if errs:
        print("error: " + "; ".join(errs), file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    cls, policy, _ = load_policy_file(args.policy)
    if getattr(cls, "track", "state") != "state":
        print(f"error: {args.policy} is not a state-track policy", file=sys.stderr)
        return 2
    agent = cls.from_policy_state_dict(policy)
    env = gym.make(args.env, obs_mode="flat")
    rollout = Rollout(env, AgentPolicy(agent, deterministic=True), env_id=args.env)
    rows = []
    for i in range(args.episodes):
        log = rollout.run(seed=DEV_SEED0 + i, episode_id=i)
        rel = log.observations[:, FLAT_SLICES["window_pos_rel"]].astype(np.float64)
        rot = log.observations[:, FLAT_SLICES["window_rot_rel"]].astype(np.float64)
        depth = rel @ S.INSERTION_AXIS
        lateral = rel[-1] - depth[-1] * S.INSERTION_AXIS
        ok = bool(log.terminated[-1])
        stop = depth >= -STOP_MM / 1000
        at_stop = np.flatnonzero(stop)
        first = rel[at_stop[0]] - depth[at_stop[0]] * S.INSERTION_AXIS if at_stop.size else None
        reached = int(np.sum(stop[1:] & ~stop[:-1]) + stop[0])
        row = {"seed": DEV_SEED0 + i, "success": ok, "steps": int(log.T),
               "failure_mode": "" if ok else (FAILURE_MODE_NAMES[rollout.info["failure_code"]]
                                              or "timeout"),
               "max_depth_mm": round(float(depth.max()) * 1000, 1),
               "final_depth_mm": round(float(depth[-1]) * 1000, 1),
               "final_lateral_mm": [round(float(lateral[0]) * 1000, 2),
                                    round(float(lateral[2]) * 1000, 2)],
               "final_tilt_deg": round(float(np.rad2deg(np.linalg.norm(rot[-1]))), 2),
               "last10_motion": round(float(np.abs(log.actions[-10:, :6]).mean()), 4),
               "at_stop_lateral_mm": None if first is None else
               [round(float(first[0]) * 1000, 2), round(float(first[2]) * 1000, 2)],
               "at_stop_centre_error_mm": None if first is None else
               round(float(np.linalg.norm(rel[at_stop[0]])) * 1000, 2),
               "times_at_stop": reached}
        rows.append(row)
        print(json.dumps(row), flush=True)
    env.close()
    out = {"policy": str(args.policy), "env_id": args.env, "episodes": rows,
           "successes": sum(r["success"] for r in rows), "provenance": provenance()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
