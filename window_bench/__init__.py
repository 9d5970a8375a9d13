"""window-bench: tolerance-critical robotic window installation in MuJoCo.

Importing the package registers the environments with Gymnasium.
"""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

# Table 7's out-of-distribution footprints (width x height, metres).
OOD_PANELS = {"Panel40x40": (0.4, 0.4), "Panel60x60": (0.6, 0.6), "Panel60x40": (0.6, 0.4)}


def _register() -> list[str]:
    ids = []
    for exp in ("A", "B"):
        variants = {"": (0.5, 0.5), **{f"-{k}": v for k, v in OOD_PANELS.items()}}
        for suffix, (w, h) in variants.items():
            env_id = f"WindowInstall-{exp}{suffix}-v0"
            if env_id not in registry:
                register(id=env_id, entry_point="window_bench.env:WindowInstallEnv",
                         max_episode_steps=600,
                         kwargs={"experiment": exp, "panel_width": w, "panel_height": h})
            ids.append(env_id)
    return ids


ENV_IDS = tuple(_register())
