"""How soon does undirected exploration break the cup's grip on the insertion task?

Random Gaussian actions (clipped to [-1, 1], vacuum on) on ``WindowInstall-Insert-v0`` (or
``--env WindowInstall-Insert-Compliant-v0``, the compliant arm), 10 episodes per setting, seeds 1000-1009 (neither training, dev nor test seeds): the episodes in
which the grip breaks at the holding limits, the step it breaks, and whether the panel then
touches the buck (opening lining, bevels, wall). One process, one thread, about a minute.

    python experiments/sanity/grip_break_probe.py [--env WindowInstall-Insert-Compliant-v0]
    python experiments/sanity/grip_break_probe.py --compliance 3 1 --installer-on-a 5

``--compliance MM DEG`` clips the controller's pose error (``WindowInstallEnv``'s
``compliance_mm`` / ``compliance_deg``) on ``--env``; ``--installer-on-a N`` also runs the
``attentive`` installer demonstrating A with that clip (seeds 1,000,000...), to show
whether the task still fits its 600 steps.
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
    p.add_argument("--compliance", nargs=2, type=float, metavar=("MM", "DEG"), default=None)
    p.add_argument("--installer-on-a", type=int, default=0, metavar="N")
    args = p.parse_args(argv)
    clip = {}
    if args.compliance is not None:
        mm, deg = args.compliance
        if not (0 <= mm <= 100 and 0 <= deg <= 90):
            p.error(f"--compliance {mm:g} {deg:g}: allowed 0-100 mm, 0-90 deg")
        clip = {"compliance_mm": mm, "compliance_deg": deg}
    if not 0 <= args.installer_on_a <= 100:
        p.error(f"--installer-on-a {args.installer_on_a}: allowed 0-100")
    env = gym.make(args.env, **clip).unwrapped
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
    if args.installer_on_a:
        installer_on_a(args.installer_on_a, clip)


def installer_on_a(n: int, clip: dict) -> None:
    """The ``attentive`` installer demonstrating A with the same clip: seated, and steps."""
    from window_bench.installer.operators import HumanlikeInstaller

    env = gym.make("WindowInstall-A-v0", obs_mode="state", **clip)
    out = []
    for seed in range(1_000_000, 1_000_000 + n):
        obs, _ = env.reset(seed=seed)
        inst = HumanlikeInstaller(env, "attentive", seed=seed)
        steps, done, info = 0, False, {}
        while not done:
            obs, _, term, trunc, info = env.step(inst.act(obs))
            steps, done = steps + 1, term or trunc
        out.append((steps, bool(info.get("is_success"))))
    print(f"installer on A: seated {sum(s for _, s in out)}/{n}, steps {[t for t, _ in out]}")


if __name__ == "__main__":
    main()
