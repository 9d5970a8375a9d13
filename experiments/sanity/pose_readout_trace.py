"""Is the pose read-out right on a pixel policy's own states?

Rolls a ``pixels-seat`` policy file deterministically on the development seeds (no
takeovers, as evaluation does) and, at every step the policy observes, compares the pose
read-out it carries (``PoseReadout.estimate`` of that observation) with the true
``window_pos_rel`` from the simulator, on the steps the cup holds the panel (a read-out of
the proprioception cannot follow a dropped panel). Prints the RMSE (x / depth / z, mm) by
distance to the seat, separately for episodes that end seated and those that fail, and
each failed episode's read-out error over its last 20 held steps.

``--exact-pose`` is a privileged diagnostic: the policy acts on the simulator's true pose in
place of its read-out (the same 12 features, computed from ``window_pos_rel`` and
``window_rot_rel``), optionally shifted by a per-episode lateral bias (``--bias-mm B``: x
and z each drawn uniformly from +-B mm). Does the policy seat when its pose is exact, and
how much read-out error does it tolerate?

    python experiments/sanity/pose_readout_trace.py RUN/policies/step_0000000.safetensors \
        --episodes 20
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

BINS = ((0.0, 0.005), (0.005, 0.02), (0.02, 0.05), (0.05, 0.1), (0.1, 0.2))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("policy", help="a policies/step_*.safetensors file of a pixels-seat run")
    p.add_argument("--episodes", type=int, default=20, help="dev seeds 100000.. (1-200)")
    p.add_argument("--exact-pose", action="store_true",
                   help="act on the true pose instead of the read-out (privileged diagnostic)")
    p.add_argument("--bias-mm", type=float, default=0.0,
                   help="with --exact-pose: a per-episode lateral bias of up to this many mm "
                        "(0-20)")
    p.add_argument("--save", default=None, help="also write the observed steps (pixel "
                   "observation, true window_pos_rel + window_rot_rel, episode) to this .npz")
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 200:
        p.error(f"--episodes {args.episodes}: allowed 1-200")
    if not 0.0 <= args.bias_mm <= 20.0 or (args.bias_mm and not args.exact_pose):
        p.error(f"--bias-mm {args.bias_mm}: allowed 0-20, and only with --exact-pose")
    from window_bench.envs.task import FAILURE_MODE_NAMES
    from rollout_args import load_policy_or_exit
    from window_bench.harness.evaluation import _eval_rollout
    from window_bench.harness.seeds import DEV_SEED0
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.track import privileged_state

    torch.set_num_threads(1)
    agent_cls, policy, meta = load_policy_or_exit(p, args.policy)
    rollout, env = _eval_rollout(agent_cls, policy, meta["env_id"], 600)
    readout = rollout.policy.agent.encoder.pose_readout
    if readout is None:
        p.error(f"{args.policy}: the policy carries no pose read-out (not a pixels-seat run)")
    pos = FLAT_SLICES["window_pos_rel"]
    rot = FLAT_SLICES["window_rot_rel"]
    true_pose = torch.zeros(1, 6)      # the pose the policy acts on with --exact-pose
    if args.exact_pose:
        read_out = readout.estimate    # kept for the comparison below
        readout.estimate = lambda obs: true_pose.expand(obs.shape[0], 6)
    else:
        read_out = readout.estimate
    rng = np.random.default_rng(0)
    seated_count = 0
    rows = {True: [], False: []}
    saved = {"x": [], "y": [], "ep": []}
    for i in range(args.episodes):
        rollout.reset(seed=DEV_SEED0 + i, episode_id=i)
        bias = np.zeros(6)
        bias[[0, 2]] = rng.uniform(-args.bias_mm, args.bias_mm, 2) / 1000.0
        est, true = [], []
        while not rollout.done:
            if args.exact_pose:
                flat = privileged_state(env)
                true_pose[0] = torch.from_numpy(np.concatenate([flat[pos], flat[rot]]) + bias)
            obs = np.asarray(rollout.obs, np.float32)[None]
            held = bool(env.unwrapped.suction_engaged)
            if held and not np.isnan(obs).all():   # rendered on the policy's chunk grid only
                with torch.no_grad():
                    est.append(read_out(torch.from_numpy(obs))[0, :3].double().numpy())
                flat = privileged_state(env)
                true.append(flat[pos])
                if args.save:
                    saved["x"].append(obs[0]), saved["ep"].append(i)
                    saved["y"].append(np.concatenate([flat[pos], flat[rot]]))
            rollout.step()
        seated = bool(rollout.terminated)
        seated_count += seated
        e, t = np.array(est), np.array(true)
        rows[seated].append((e, t))
        if not seated:
            mode = FAILURE_MODE_NAMES[rollout.info["failure_code"]] or "timeout"
            last = (e[-20:] - t[-20:]) * 1000
            print(f"seed {DEV_SEED0 + i}: {mode:16s} last 20 steps: true pose mm "
                  f"{(t[-1] * 1000).round(1)}, read-out error mm mean {last.mean(0).round(2)}, "
                  f"rms {np.sqrt((last ** 2).mean(0)).round(2)}")
    for seated, eps in rows.items():
        if not eps:
            continue
        e = np.concatenate([a for a, _ in eps])
        t = np.concatenate([b for _, b in eps])
        d = np.linalg.norm(t, axis=1)
        print(f"{'seated' if seated else 'failed'} episodes: {len(eps)}")
        for lo, hi in BINS:
            m = (d >= lo) & (d < hi)
            if m.any():
                err = np.sqrt((((e[m] - t[m]) * 1000) ** 2).mean(0))
                print(f"  {lo * 1000:5.0f}-{hi * 1000:3.0f} mm: {m.sum():5d} steps, RMSE "
                      f"{err.round(2)}, true spread {(t[m].std(0) * 1000).round(2)}")
    print(f"seated {seated_count} of {args.episodes} ({'true pose' if args.exact_pose else 'read-out'}"
          f"{f', bias up to {args.bias_mm:g} mm' if args.bias_mm else ''})")
    env.close()
    if args.save:
        np.savez(args.save, **{k: np.asarray(v) for k, v in saved.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
