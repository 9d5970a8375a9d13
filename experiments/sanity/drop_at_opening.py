"""Can the installer re-acquire a panel dropped in front of the opening?

On ``WindowInstall-A-v0`` the scripted installer carries the panel to the opening; from its
``align`` phase on, random Gaussian actions (std 1.0, vacuum on) push it until the grip
breaks. A fresh scripted installer then takes over (``take_over()``, as a ``suction_lost``
takeover does) for 300 steps; every 30 steps the script prints its phase, the panel's
height and suction-face normal, and the tool's distance to the hover pose 8 cm over the
face. Seeds 0..N-1, one process, about 20 s.

    python experiments/sanity/drop_at_opening.py --episodes 6
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import window_bench  # noqa: F401  (registers the envs)
from window_bench.installer.scripted import ScriptedInstaller


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=6)
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 100:
        p.error(f"--episodes {args.episodes}: allowed 1-100")
    env = gym.make("WindowInstall-A-v0", obs_mode="state")
    u = env.unwrapped
    rng = np.random.default_rng(0)
    seated = 0
    for seed in range(args.episodes):
        obs, _ = env.reset(seed=seed)
        inst = ScriptedInstaller(env, seed=seed)
        t, broke, info = 0, False, {}
        while t < 600:
            if inst.phase in ("align", "insert"):
                a = np.zeros(7, np.float32)
                a[:6], a[6] = np.clip(rng.normal(0, 1.0, 6), -1, 1), 1.0
            else:
                a = inst.act(obs)
            obs, _, term, trunc, info = env.step(a)
            t += 1
            if info.get("suction_failed") or not u.suction_engaged:
                broke = True
                break
            if term or trunc:
                break
        if not broke:
            print(seed, "no grip break")
            continue
        p_, R = u.panel_pose()
        print(f"{seed}: grip broke at step {t}, panel z {p_[2]:.3f} m, face normal {R[:, 2].round(2)}")
        rec = ScriptedInstaller(env, seed=seed)
        rec.take_over()
        for k in range(300):
            obs, _, term, trunc, info = env.step(rec.act(obs))
            if k % 30 == 0 or term or trunc:
                p_, R = u.panel_pose()
                tcp, _ = u.tcp_pose()
                face, _ = u._tcp_for_panel(p_, R)
                hover = face + R[:, 2] * 0.08
                print(f"   step {k:3d} phase {rec.phase:9s} panel z {p_[2]:.3f} normal "
                      f"{R[:, 2].round(2)} tool-hover {np.linalg.norm(tcp - hover):.3f} m "
                      f"held {u.suction_engaged}")
            if term or trunc:
                seated += bool(info.get("is_success"))
                break
    print(f"seated after the drop: {seated} of {args.episodes}")


if __name__ == "__main__":
    main()
