"""The observation tracks as the harness needs them: envs, demonstrations, agents.

``state`` is the privileged 52-float ``obs_mode="flat"`` observation every result so far
uses; ``pixels`` is the paper's (two 128 x 128 views + 18 proprioceptive values through the
frozen ResNet-10, :class:`~window_bench.pixels.features.PixelFeatures`). These functions
keep the track out of the harness's logic: it asks for an env, the demonstrations and an
agent of a track and gets objects with the same interfaces on both.
"""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np

# No torch import at module level: `bench tables` / `bench leaderboard` read TRACK_LABELS.
TRACKS = ("state", "pixels")
TRACK_LABELS = {"state": "privileged state", "pixels": "pixels (2 x RGB 128² + proprioception)"}
#: Agent kind on the state track -> its kind on the pixel track (harness/methods.py AGENTS).
PIXEL_KINDS = {"qcfql": "qcfql-pixels", "hilserl": "hilserl-pixels", "sac": "sac-pixels",
               "act": "act-pixels"}


def check_track(track: str) -> str:
    if track not in TRACKS:
        raise ValueError(f"track={track!r}; allowed: {', '.join(TRACKS)}")
    return track


def track_agent_kind(kind: str, track: str) -> str:
    """The agent kind that runs ``kind``'s method on ``track``; ``ValueError`` for an agent
    that has no pixel front end yet."""
    if check_track(track) == "state":
        return kind
    if kind not in PIXEL_KINDS:
        raise ValueError(f"track='pixels' is not available for the {kind!r} agent yet; "
                         f"pixel agents: {', '.join(PIXEL_KINDS)}")
    return PIXEL_KINDS[kind]


def make_track_env(env_id: str, track: str, backbone=None, *, weights=None,
                   observe_every: int = 1, **kwargs) -> gym.Env:
    """``gym.make(env_id, obs_mode="flat", **kwargs)`` for ``state``; the env wrapped in
    :class:`PixelFeatures` for ``pixels``, with ``backbone`` or else the one
    ``resolve_backbone(weights)`` gives (``None``: the shipped default). ``observe_every``
    (pixels): render and encode only on the chunk grid of a policy with that horizon
    (:class:`PixelFeatures`); the state track's observation costs nothing to make and is
    made every step whatever it says."""
    if check_track(track) == "state":
        return gym.make(env_id, obs_mode="flat", **kwargs)
    from window_bench.pixels.features import make_pixel_env

    if backbone is None:
        from window_bench.pixels.weights import resolve_backbone

        backbone, _ = resolve_backbone(weights)

    return make_pixel_env(env_id, backbone, observe_every=observe_every, **kwargs)


def privileged_state(env) -> np.ndarray:
    """The flat 52-float state of a pixel-mode env's current step (what ``obs_mode="flat"``
    would have returned), without rendering."""
    base = env.unwrapped
    mode, base.obs_mode = base.obs_mode, "flat"
    try:
        return base._observation()
    finally:
        base.obs_mode = mode


class StateSupervisor:
    """The installer supervising a pixel-track policy: it watches the scene (in the paper a
    person at the robot), not the learner's features, so its cues and its takeover actions
    read the privileged state of the env it was reset on. Everything else is the wrapped
    supervisor's (e.g. :class:`~window_bench.installer.supervisor.InstallerSupervisor`)."""

    def __init__(self, supervisor):
        self.supervisor, self._env = supervisor, None

    def reset(self, env, seed: int | None = None) -> None:
        self._env = env
        self.supervisor.reset(env, seed=seed)

    def intervene(self, obs, info: dict):
        return self.supervisor.intervene(privileged_state(self._env), info)

    def __getattr__(self, name):
        return getattr(self.supervisor, name)


def pixel_demos(demos: list, env_id: str, backbone, progress: bool = False) -> list:
    """The state-track demonstrations re-observed on the pixel track: each episode's executed
    actions replayed from its seed under :class:`PixelFeatures`. The env is deterministic and
    rendering does not touch the physics, so the replay is the same episode; rewards and
    terminations are checked step by step and a divergence is an error, never a silently
    different dataset."""
    from tqdm import tqdm

    env = make_track_env(env_id, "pixels", backbone)
    out = []
    for ep in tqdm(demos, desc="pixel demos", unit="demo", disable=not progress):
        obs, _ = env.reset(seed=int(ep.seed))
        observations = [obs]
        for t, a in enumerate(ep.actions):
            obs, r, term, trunc, _ = env.step(a)
            observations.append(obs)
            if r != ep.rewards[t] or term != bool(ep.terminated[t]):
                env.close()
                raise RuntimeError(f"demo {ep.episode_id} (seed {ep.seed}) diverges on replay "
                                   f"at step {t}: reward {r} vs {ep.rewards[t]}, terminated "
                                   f"{term} vs {bool(ep.terminated[t])}")
        out.append(dataclasses.replace(ep, observations=np.stack(observations)))
    env.close()
    return out


def proprio_normalizer(pixel_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std of the proprioception (the last 18 values) of pixel observations: the
    pixel agent's fixed normaliser, computed from the demonstrations like the state track's."""
    from window_bench.pixels.encoder import PROPRIO_DIM

    p = np.asarray(pixel_obs, np.float64)[:, -PROPRIO_DIM:]
    return p.mean(0), p.std(0)
