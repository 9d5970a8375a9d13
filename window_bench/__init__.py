"""window-bench: tolerance-critical robotic window installation in MuJoCo.

Importing the package registers the environments with Gymnasium. The package is laid out by
what each part owns:

* :mod:`window_bench.envs` - the scene, controller, task and the Gymnasium env;
* :mod:`window_bench.installer` - the scripted installer, operators, takeovers, rollouts,
  demonstrations and teleoperation;
* :mod:`window_bench.data` - step logs, chunk transitions, Minari datasets, replay, effort;
* :mod:`window_bench.harness` - methods and profiles, training runs, evaluation, leaderboard;
* :mod:`window_bench.pixels` - the pixel observation track;
* :mod:`window_bench.catalog` - the agents, tracks and presets the harness runs, by name
  (imported here, so that every process registers them);
* :mod:`window_bench.cli` - the ``bench`` command on top.

The names users import most (``WindowInstallEnv``, ``ScriptedInstaller``, ``Run``, ...) are
available here too; they are loaded on first use so that ``import window_bench`` stays light.
"""

from importlib import import_module

from window_bench.gl import choose_headless_backend

# Before anything imports mujoco, which reads MUJOCO_GL once (see window_bench/gl.py).
choose_headless_backend()

from gymnasium.envs.registration import register, registry  # noqa: E402

__version__ = "0.1.0"

# Table 7's out-of-distribution footprints (width x height, metres).
OOD_PANELS = {"Panel40x40": (0.4, 0.4), "Panel60x60": (0.6, 0.6), "Panel60x40": (0.6, 0.4)}


#: The insertion alone (a sanity task for learners): the 0.5 x 0.5 m panel starts held in
#: front of the opening; a short task, hence its episode limit.
INSERT_ENV_ID = "WindowInstall-Insert-v0"
INSERT_EPISODE_STEPS = 200
#: The same with a compliant arm: the controller clips its pose error at 1.5 mm and 0.5 deg,
#: so the arm pushes gently against the buck (as HIL-SERL's impedance controller does) and
#: undirected actions rarely break the cup's grip.
INSERT_COMPLIANT_ENV_ID = "WindowInstall-Insert-Compliant-v0"


def _register_id(env_id: str, step_limit: int, **kwargs) -> str:
    if env_id not in registry:
        register(id=env_id, entry_point="window_bench.envs.env:WindowInstallEnv",
                 max_episode_steps=step_limit, kwargs=kwargs)
    return env_id


def _register() -> list[str]:
    ids = []
    for exp in ("A", "B"):
        variants = {"": (0.5, 0.5), **{f"-{k}": v for k, v in OOD_PANELS.items()}}
        for suffix, (w, h) in variants.items():
            ids.append(_register_id(f"WindowInstall-{exp}{suffix}-v0", 600, experiment=exp,
                                    panel_width=w, panel_height=h))
    # The env truncates at the limit itself too, whatever TimeLimit a caller wraps it in.
    ids.append(_register_id(INSERT_ENV_ID, INSERT_EPISODE_STEPS, experiment="Insert",
                            panel_width=0.5, panel_height=0.5,
                            max_episode_steps=INSERT_EPISODE_STEPS))
    ids.append(_register_id(INSERT_COMPLIANT_ENV_ID, INSERT_EPISODE_STEPS, experiment="Insert",
                            panel_width=0.5, panel_height=0.5,
                            max_episode_steps=INSERT_EPISODE_STEPS, compliance_mm=1.5,
                            compliance_deg=0.5))
    return ids


ENV_IDS = tuple(_register())


_EXPORTS = {
    "WindowInstallEnv": "window_bench.envs.env",
    "ScriptedInstaller": "window_bench.installer.scripted",
    "StraightPush": "window_bench.installer.scripted",
    "RandomPolicy": "window_bench.installer.scripted",
    "HumanlikeInstaller": "window_bench.installer.operators",
    "InstallerSupervisor": "window_bench.installer.supervisor",
    "Rollout": "window_bench.installer.rollout",
    "EpisodeLog": "window_bench.data.steplog",
    "ChunkReplay": "window_bench.data.replay",
    "METHODS": "window_bench.harness.methods",
    "PROFILES": "window_bench.harness.methods",
    "Run": "window_bench.harness.run",
}


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'window_bench' has no attribute {name!r}")


__all__ = ["ENV_IDS", "OOD_PANELS", *_EXPORTS]

# The harness's registries, filled in every process that imports the package (a spawned
# evaluation worker too); it imports no learner.
from window_bench import catalog  # noqa: E402,F401
