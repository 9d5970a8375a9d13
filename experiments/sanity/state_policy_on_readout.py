r"""How much does the pose read-out's error cost a policy that acts on the pose well?

Rolls a **state-track** policy out deterministically on the dev seeds inside the env of a
``pixels-seat`` policy file, observing the privileged flat state with ``window_pos_rel`` and
``window_rot_rel`` replaced by that file's pose read-out of the rendered views
(``--pose readout``), or unchanged (``--pose exact``: the control, the state policy's own
result). Prints the seated count, each failure and the read-out's RMSE on the held steps by
distance to the seat.

    python experiments/sanity/state_policy_on_readout.py STATE_RUN/policies/step_0000000.safetensors \
        PIXEL_RUN/policies/step_0000000.safetensors --pose readout --episodes 20
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

BANDS = ((0.0, 0.02), (0.02, 0.06), (0.06, 0.115), (0.115, 0.2), (0.2, 1.0))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("state_policy", help="a state-track policies/step_*.safetensors file")
    p.add_argument("pixel_policy", help="a pixels-seat policy file: its env and read-out")
    p.add_argument("--pose", choices=("readout", "exact"), default="readout")
    p.add_argument("--episodes", type=int, default=20, help="dev seeds 100000.. (1-200)")
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 200:
        p.error(f"--episodes {args.episodes}: allowed 1-200")
    from window_bench.envs.task import FAILURE_MODE_NAMES
    from rollout_args import load_policy_or_exit
    from window_bench.harness.evaluation import _eval_rollout
    from window_bench.harness.seeds import DEV_SEED0
    from window_bench.installer.supervisor import FLAT_SLICES
    from window_bench.pixels.track import privileged_state

    torch.set_num_threads(1)
    s_cls, s_state, s_meta = load_policy_or_exit(p, args.state_policy)
    p_cls, p_state, p_meta = load_policy_or_exit(p, args.pixel_policy)
    if getattr(s_cls, "track", "state") != "state":
        p.error(f"{args.state_policy}: not a state-track policy")
    state_agent = s_cls.from_policy_state_dict(s_state)
    if p_meta["env_id"] != s_meta["env_id"]:
        p.error(f"the policies are for {s_meta['env_id']} and {p_meta['env_id']}")
    rollout, env = _eval_rollout(p_cls, p_state, p_meta["env_id"], 600)
    readout = getattr(rollout.policy.agent, "encoder", None)
    readout = getattr(readout, "pose_readout", None)
    if readout is None:
        p.error(f"{args.pixel_policy}: not a pixels-seat policy (no pose read-out)")
    pos, rot = FLAT_SLICES["window_pos_rel"], FLAT_SLICES["window_rot_rel"]
    errors = []

    class OnReadout:
        h = state_agent.h

        def reset(self, seed=None):
            state_agent.reset()

        def act(self, obs):
            flat = np.asarray(privileged_state(env), np.float32).copy()
            if args.pose == "readout":
                with torch.no_grad():
                    est = readout.estimate(torch.from_numpy(np.asarray(obs, np.float32))[None])
                est = est[0].numpy()
                if env.unwrapped.suction_engaged:
                    errors.append((float(np.linalg.norm(flat[pos])),
                                   np.concatenate([(est[:3] - flat[pos]) * 1000,
                                                   np.degrees(est[3:] - flat[rot])])))
                flat[pos], flat[rot] = est[:3], est[3:]
            return state_agent.act(flat, deterministic=True)

    rollout.policy = OnReadout()
    seated, modes = 0, Counter()
    for i in range(args.episodes):
        log = rollout.run(seed=DEV_SEED0 + i, episode_id=i)
        if log.terminated[-1]:
            seated += 1
            continue
        mode = FAILURE_MODE_NAMES[rollout.info["failure_code"]] or "timeout"
        modes[mode] += 1
        end = privileged_state(env)[pos] * 1000
        print(f"seed {DEV_SEED0 + i}: {mode}, panel at {end.round(1)} mm from the seat")
    env.close()
    print(f"{args.pose}: seated {seated} of {args.episodes}; failures {dict(modes)}")
    if errors:
        d = np.array([e[0] for e in errors])
        e = np.array([e[1] for e in errors])
        print("read-out RMSE on held steps (x / depth / z mm, then rotation deg):")
        for lo, hi in BANDS:
            m = (d >= lo) & (d < hi)
            if m.any():
                print(f"  {lo * 1000:4.0f}-{hi * 1000:4.0f} mm, {m.sum():4d} steps: "
                      f"{np.sqrt((e[m] ** 2).mean(0)).round(2)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
