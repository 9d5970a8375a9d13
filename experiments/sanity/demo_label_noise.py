r"""Does a demonstration's recorded command carry the installer's correction near the opening?

Runs the demonstrator (``HumanlikeInstaller``, as ``bench demos`` does) and records at every
step with the panel held both the command it executed (what D_demo stores: the installer's
command plus its hand noise) and the command it meant (the same without the noise), with the
panel's offset from the seat. Per band of distance to the seat and per lateral axis (x across
the opening, z vertical), the least-squares slope of each command on the offset (millimetres
of commanded motion per millimetre of offset) and their correlation. A learner that imitates
the executed command can only learn the relation the executed command shows.

    python experiments/sanity/demo_label_noise.py --env WindowInstall-B-v0 --operator attentive \
        --episodes 20 --out experiments/sanity/results/demo_label_noise_B_attentive.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, episodes_errors, operator_errors, out_errors  # noqa: E402

BANDS_MM = ((20, 90), (90, 200), (200, 400))
STEP_MM = 25.0          # commanded translation per action unit (s_pos = 0.025 m)


def fit(offset: np.ndarray, command: np.ndarray) -> dict:
    if len(offset) < 3 or np.std(offset) == 0 or np.std(command) == 0:
        return {"slope": None, "r": None}
    slope = float(np.polyfit(offset, command, 1)[0])
    return {"slope": round(slope, 3), "r": round(float(np.corrcoef(offset, command)[0, 1]), 2)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--operator", default="attentive")
    p.add_argument("--episodes", type=int, default=20, help="demonstrations, seeds 1,000,000-")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    errs = (env_errors(args.env) + episodes_errors(args.episodes) + out_errors(args.out)
            + operator_errors(args.operator))
    if errs:
        p.error("; ".join(errs))

    import gymnasium as gym

    from window_bench.envs import scene as S
    from window_bench.harness.evaluation import provenance
    from window_bench.installer.operators import OPERATORS, HumanlikeInstaller
    from window_bench.installer.supervisor import observation_fields

    profile = OPERATORS[args.operator]
    env = gym.make(args.env, obs_mode="flat")
    demo = HumanlikeInstaller(env, profile)
    rows = []          # (distance mm, offset x, offset z, executed x, z, meant x, z)
    seated = 0
    meant = {}         # the scripted installer's command of this step, before the hand noise
    scripted_act = demo.installer.act

    def act_and_keep(o=None):
        a = scripted_act(o)
        meant["a"] = np.asarray(a, dtype=np.float64).copy()
        return a

    demo.installer.act = act_and_keep
    for i in range(args.episodes):
        seed = 1_000_000 + i
        obs, _ = env.reset(seed=seed)
        demo.reset(seed)
        done = False
        while not done:
            meant.clear()
            a = demo.act(obs)
            f = observation_fields(obs)
            if f["robot0_vacuum"][0] > 0.5:
                rel = f["window_pos_rel"]
                dist = -float(rel @ S.INSERTION_AXIS) * 1000.0
                m = (np.clip(meant["a"][:6] * profile.demo_speed, -1, 1) if meant
                     else np.asarray(a[:6], dtype=np.float64))
                rows.append((dist, rel[0] * 1000, rel[2] * 1000, a[0] * STEP_MM, a[2] * STEP_MM,
                             m[0] * STEP_MM, m[2] * STEP_MM))
            obs, _, terminated, truncated, _ = env.step(a)
            done = terminated or truncated
        seated += bool(terminated)
    env.close()
    r = np.array(rows, dtype=np.float64).reshape(-1, 7)
    bands = []
    for lo, hi in BANDS_MM:
        b = r[(r[:, 0] >= lo) & (r[:, 0] < hi)]
        spread = {"x": round(float(b[:, 1].std()), 2), "z": round(float(b[:, 2].std()), 2)} \
            if len(b) else {"x": None, "z": None}
        bands.append({"distance_mm": [lo, hi], "steps": len(b), "offset_std_mm": spread,
                      "executed": {"x": fit(b[:, 1], b[:, 3]), "z": fit(b[:, 2], b[:, 4])},
                      "meant": {"x": fit(b[:, 1], b[:, 5]), "z": fit(b[:, 2], b[:, 6])}})
        print(json.dumps(bands[-1]))
    out = {"env_id": args.env, "operator": args.operator, "episodes": args.episodes,
           "seated": seated, "bands": bands, "provenance": provenance()}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
