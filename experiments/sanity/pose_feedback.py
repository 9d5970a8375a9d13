r"""Does a policy act on the panel's pose? Its feedback gain at the demonstrations' states.

Replays the first ``--demos`` demonstrations step by step in the env of the policy's track
(state or ``pixels-seat``) and, at each chunk boundary, asks the policy for its chunk:

1. its imitation error there (mean |chunk - demonstrated actions| per action entry, by
   distance to the seat);
2. its feedback: the change of the chunk's summed translation command (action entries 0-2)
   when the observed panel is shifted 5 mm along the seat's x axis, then along z, at the
   states 20-200 mm from the seat. A state policy's ``window_pos_rel`` is shifted (its
   z-score and fine pose features follow); a ``pixels-seat`` policy's 12 pose features are
   computed from the true pose, shifted (``--pose exact``), in place of its read-out.

    python experiments/sanity/pose_feedback.py RUN/policies/step_0000000.safetensors \
        leaderboard/runs/demos/WindowInstall-A-v0-average-n50-s0 --demos 8
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

SHIFT_M = 0.005
BANDS = ((0.0, 0.02), (0.02, 0.1), (0.1, 0.3), (0.3, 9.0))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policies/step_*.safetensors file (state or pixels-seat)")
    p.add_argument("demos_dir", help="a Minari root holding the env's demonstrations")
    p.add_argument("--operator", default="average")
    p.add_argument("--demos", type=int, default=8, help="demonstrations to replay (1-50)")
    args = p.parse_args(argv)
    if not 1 <= args.demos <= 50:
        p.error(f"--demos {args.demos}: allowed 1-50")
    from rollout_args import load_policy_or_exit
    from window_bench.harness.evaluation import _eval_rollout
    from window_bench.installer.demos import load_demos
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.track import privileged_state

    torch.set_num_threads(1)
    agent_cls, policy, meta = load_policy_or_exit(p, args.policy)
    rollout, env = _eval_rollout(agent_cls, policy, meta["env_id"], 600)
    agent = rollout.policy.agent
    demos = load_demos(args.demos_dir, meta["env_id"], args.operator)[: args.demos]
    pos, rot = FLAT_SLICES["window_pos_rel"], FLAT_SLICES["window_rot_rel"]
    encoder = getattr(agent, "encoder", None)
    pose = torch.zeros(1, 6)          # what a pixels-seat policy's read-out is made to say
    if encoder is not None:
        if encoder.pose_readout is None:
            p.error(f"{args.policy}: a pixel policy without a pose read-out")
        encoder.pose_readout.estimate = lambda obs: pose.expand(obs.shape[0], 6)

    def chunk(obs, flat, axis=None):
        shift = np.zeros(6, np.float32)
        if axis is not None:
            shift[axis] = SHIFT_M
        if encoder is not None:
            pose[0] = torch.from_numpy(np.concatenate([flat[pos], flat[rot]]) + shift)
            return agent.act(obs, deterministic=True)
        obs = obs.copy()
        obs[pos] += shift[:3]
        return agent.act(obs, deterministic=True)

    errors, gains = [], []
    for ep in demos:
        obs, _ = env.reset(seed=int(ep.seed))
        agent.reset()
        for t in range(ep.T):
            o = np.asarray(obs, np.float32)
            if t % agent.h == 0 and not np.isnan(o).all():
                flat = np.asarray(privileged_state(env), np.float32)
                dist = float(np.linalg.norm(flat[pos]))
                base = chunk(o, flat)
                demo = ep.actions[t:t + agent.h]
                errors.append((dist, np.abs(base[:len(demo)] - demo).mean(0)))
                if 0.02 < dist < 0.2:
                    gains.append([chunk(o, flat, ax)[:, :3].sum(0) - base[:, :3].sum(0)
                                  for ax in (0, 2)])
            obs, *_ = env.step(ep.actions[t])
    env.close()
    d = np.array([e[0] for e in errors])
    err = np.array([e[1] for e in errors])
    print(f"{args.policy}: imitation error, mean |chunk - demonstration| per entry")
    for lo, hi in BANDS:
        m = (d >= lo) & (d < hi)
        if m.any():
            print(f"  {lo * 1000:4.0f}-{hi * 1000:4.0f} mm from the seat, {m.sum():4d} states: "
                  f"{err[m].mean(0).round(3)}")
    g = np.array(gains)
    print(f"feedback at {len(g)} states 20-200 mm from the seat: summed translation command "
          f"change for +5 mm x {g[:, 0].mean(0).round(3)}, for +5 mm z {g[:, 1].mean(0).round(3)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
