"""How soon does undirected exploration break the cup's grip on the insertion task?

Random Gaussian actions (clipped to [-1, 1], vacuum on) on ``WindowInstall-Insert-v0`` (or
``--env WindowInstall-Insert-Compliant-v0``, the compliant arm), 10 episodes per setting, seeds 1000-1009 (neither training, dev nor test seeds): the episodes in
which the grip breaks at the holding limits, the step it breaks, and whether the panel then
touches the buck (opening lining, bevels, wall). One process, one thread, about a minute.

    python experiments/sanity/grip_break_probe.py [--env WindowInstall-Insert-Compliant-v0]
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import window_bench  # noqa: F401  (registers the envs)

SETTINGS = (("all", 1.0, [1] * 6), ("all", 0.3, [1] * 6), ("all", 0.1, [1] * 6),
            ("translation", 1.0, [1, 1, 1, 0, 0, 0]), ("rotation", 1.0, [0, 0, 0, 1, 1, 1]))


INSERT_IDS = ("WindowInstall-Insert-v0", "WindowInstall-Insert-Compliant-v0")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default=INSERT_IDS[0], choices=INSERT_IDS)
    env = gym.make(p.parse_args(argv).env).unwrapped
    rng = np.random.default_rng(0)
    for name, std, mask in SETTINGS:
        steps, contact = [], 0
        for ep in range(10):
            env.reset(seed=1000 + ep)
            for t in range(200):
                a = np.zeros(7)
                a[:6] = np.clip(rng.normal(0.0, std, 6), -1.0, 1.0) * mask
                a[6] = 1.0
                _, _, term, trunc, info = env.step(a)
                if info["suction_failed"]:
                    steps.append(t)
                    contact += env._buck_contact()
                    break
                if term or trunc:
                    break
        print(f"{name:11s} std {std:.1f}: grip broke in {len(steps)}/10 episodes, at steps "
              f"{steps}, {contact} in contact with the buck", flush=True)


if __name__ == "__main__":
    main()
