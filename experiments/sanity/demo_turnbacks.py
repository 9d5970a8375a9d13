r"""Where do the installer's demonstrations turn back, and what does a policy imitate there?

Runs the demonstrator (``HumanlikeInstaller``, as ``bench demos`` does, seeds 1,000,000-) for
each operator profile and records every retract-and-reinsert it starts (a recovery), with
the panel's depth and tilt at that moment. Near the back stop a recovery usually means the
panel's leading edge met the stop first (the eye's tilt error). Also: of the demonstration
steps with the panel within ``--near-mm`` of the seat that are not followed by acceptance
within the chunk (h = 10 steps), the share whose next 10 commands turn back (a meant
insertion command below -0.01): what a chunked learner sees as the continuation there.

    python experiments/sanity/demo_turnbacks.py --env WindowInstall-A-v0 \
        --operators average flush --episodes 50 \
        --out experiments/sanity/results/demo_turnbacks_A.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, episodes_errors, out_errors  # noqa: E402

H = 10


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="WindowInstall-A-v0")
    p.add_argument("--operators", nargs="+", default=["average", "flush"])
    p.add_argument("--episodes", type=int, default=50, help="demonstrations, seeds 1,000,000-")
    p.add_argument("--near-mm", type=float, default=6.0, help="(0, 50]")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    from window_bench.installer.operators import OPERATORS

    errs = env_errors(args.env) + episodes_errors(args.episodes) + out_errors(args.out)
    bad = [o for o in args.operators if o not in OPERATORS]
    if bad:
        errs.append(f"--operators {bad[0]!r}; allowed: {', '.join(sorted(OPERATORS))}")
    if not 0 < args.near_mm <= 50:
        errs.append(f"--near-mm {args.near_mm}; allowed: (0, 50]")
    if errs:
        p.error("; ".join(errs))

    import gymnasium as gym

    from window_bench.envs import scene as S
    from window_bench.envs.env import mat_to_rotvec
    from window_bench.harness.evaluation import provenance
    from window_bench.installer.operators import HumanlikeInstaller
    from window_bench.installer.rollout import Rollout
    from window_bench.installer.scripted import ScriptedInstaller
    from window_bench.installer.supervisor import FLAT_SLICES

    env = gym.make(args.env, obs_mode="flat")
    out = {"env_id": args.env, "episodes": args.episodes, "near_mm": args.near_mm,
           "operators": {}, "provenance": provenance()}
    for op in args.operators:
        demonstrator = HumanlikeInstaller(env, op)
        starts: list[tuple[float, float]] = []
        begin = demonstrator.installer._start_recovery

        def spy(depth, begin=begin, starts=starts):
            u = env.unwrapped
            tilt = np.rad2deg(np.linalg.norm(mat_to_rotvec(u._target_mat.T @ u.panel_pose()[1])))
            starts.append((depth * 1000.0, float(tilt)))
            return begin(depth)

        demonstrator.installer._start_recovery = spy
        rollout = Rollout(env, demonstrator, provenance="demo", operator=op, env_id=args.env)
        seated, steps, near, turn = 0, [], 0, 0
        for i in range(args.episodes):
            log = rollout.run(seed=1_000_000 + i, episode_id=i)
            seated += bool(log.terminated[-1])
            steps.append(log.T)
            depth = log.observations[:, FLAT_SLICES["window_pos_rel"]] @ S.INSERTION_AXIS * 1000
            for t in range(log.T - H):   # the chunk ends before the episode does
                if depth[t] >= -args.near_mm:
                    near += 1
                    turn += bool((log.meant_actions[t:t + H, 2] < -0.01).any())
        at_stop = [s for s in starts if s[0] >= -ScriptedInstaller.PRESS_ZONE * 1000.0]
        out["operators"][op] = {
            "seated": seated, "steps_mean": round(float(np.mean(steps)), 1),
            "recoveries": len(starts), "recoveries_within_8mm_of_stop": len(at_stop),
            "their_depth_mm": [round(min(s[0] for s in at_stop), 1),
                               round(max(s[0] for s in at_stop), 1)] if at_stop else None,
            "their_tilt_deg": [round(min(s[1] for s in at_stop), 2),
                               round(max(s[1] for s in at_stop), 2)] if at_stop else None,
            "near_steps_not_accepted_within_chunk": near,
            "of_which_turn_back_within_chunk": turn,
        }
        print(op, json.dumps(out["operators"][op]), flush=True)
    env.close()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
