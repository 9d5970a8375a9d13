"""The pixel track: the paper's observation, registered as the harness's track ``pixels``.

Two 128 x 128 views + 18 proprioceptive values through the frozen ResNet-10
(:class:`~window_bench.pixels.features.PixelFeatures`), instead of the state track's
privileged 52-float ``obs_mode="flat"`` observation. :class:`PixelTrack` tells the harness
(:mod:`window_bench.harness.tracks`) everything that differs: which agent runs a method here
(:data:`PIXEL_KINDS`), what a Stage I of that agent depends on, the env a frozen policy is
evaluated in; for one run, :class:`PixelObservation` resolves the backbone, re-observes the
demonstrations (cached, :mod:`window_bench.pixels.demo_cache`), wraps the training env in
the encoder and lets the installer watch the scene (:class:`StateSupervisor`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np

from window_bench.harness.methods import agent_class
from window_bench.harness.tracks import DEFAULT_TRACK, RunObservation, Track, get_track

# No torch import at module level: `import window_bench` registers this track.
#: Agent kind on the state track -> its kind on the pixel track (window_bench.catalog
#: registers both).
PIXEL_KINDS = {"qcfql": "qcfql-pixels", "hilserl": "hilserl-pixels", "sac": "sac-pixels",
               "act": "act-pixels"}


class PixelTrack(Track):
    """``pixels``: the paper's camera views (see the module docstring)."""

    name = "pixels"
    label = "pixels (2 x RGB 128² + proprioception)"
    description = ("the paper's observation: wrist and side RGB views (128 x 128) through the "
                   "frozen ResNet-10, and 18 proprioceptive values (see [the pixel "
                   "track](../pixels.md))")
    #: The camera set this track renders (:mod:`window_bench.pixels.cameras`).
    cameras = "paper"
    #: The fixed pose read-out its agents see (:mod:`window_bench.pixels.pose_readout`), if any.
    pose_readout: Path | None = None
    #: What every pixel agent adds to its state-track learner's Stage I: the front end
    #: (aggregation, fusion) and the encoder it trains through.
    front_end_modules = ("window_bench.pixels.agent", "window_bench.pixels.encoder")

    def agent_kind(self, kind: str) -> str:
        """``ValueError`` for an agent that has no pixel front end yet."""
        if kind not in PIXEL_KINDS:
            raise ValueError(f"track='pixels' is not available for the {kind!r} agent yet; "
                             f"pixel agents: {', '.join(PIXEL_KINDS)}")
        return PIXEL_KINDS[kind]

    def stage1_modules(self, kind: str) -> tuple[str, ...]:
        """The state-track learner's modules, then the front end's (none without a Stage I)."""
        learner = {v: k for k, v in PIXEL_KINDS.items()}.get(kind)
        if learner is None:
            raise ValueError(f"agent kind {kind!r} does not run on the pixel track; its kinds: "
                             f"{', '.join(PIXEL_KINDS.values())}")
        own = agent_class(learner).stage1_modules()
        return (*own, *self.front_end_modules) if own else ()

    def eval_env(self, env_id: str, policy_state: dict, observe_every: int = 1, **kwargs):
        """The policy's env: a pixel agent names its encoder weights in its state. Pixels are
        rendered and encoded only where the policy reads them (its chunk grid)."""
        from window_bench.pixels.cameras import saved_cameras

        return make_track_env(env_id, self.name, weights=policy_state.get("encoder_weights"),
                              observe_every=observe_every, cameras=saved_cameras(policy_state),
                              **kwargs)

    def for_run(self, encoder_weights: str | None = None) -> "PixelObservation":
        return PixelObservation(self, encoder_weights)


class SeatPixelTrack(PixelTrack):
    """``pixels-seat``: the pixel track with the two seat cameras in place of the wrist and
    side views (:mod:`window_bench.pixels.cameras`); same encoder, agents and layout. The
    policy files name the camera set, so evaluation renders the views the policy learnt on."""

    name = "pixels-seat"
    label = "pixels, seat cameras (2 x RGB 128² + proprioception)"
    description = ("the pixel track with two fixed cameras on opposite corners of the opening "
                   "in place of the wrist and side views (see [the pixel track](../pixels.md))")
    cameras = "seat"

    @property
    def pose_readout(self) -> Path:
        from window_bench.pixels.pose_readout import DEFAULT_READOUT

        return DEFAULT_READOUT


class PixelObservation(RunObservation):
    """One run on the pixel track. The backbone is resolved when the run is made, so a wrong
    weights file fails before any work; ``record`` names the weights and their sha256."""

    def __init__(self, track: PixelTrack, encoder_weights: str | None):
        from window_bench.harness.files import sha256_file
        from window_bench.pixels.encoder import FEATURE_VALUES
        from window_bench.pixels.weights import DEFAULT_WEIGHTS, resolve_backbone, weights_record

        super().__init__(track)
        self.replay_half_obs = FEATURE_VALUES   # both views' maps, float16-exact
        self.cameras = track.cameras
        if encoder_weights is not None:
            encoder_weights = str(Path(encoder_weights).resolve())
        self.backbone, label = resolve_backbone(encoder_weights)
        self.encoder_weights = encoder_weights
        path = DEFAULT_WEIGHTS if encoder_weights is None else Path(encoder_weights)
        record = weights_record(path)
        self.record.update(weights=label, sha256=sha256_file(path),
                           **{k: record[k] for k in ("command", "heldout_quality")
                              if k in record})
        self.record["cameras"] = self.cameras
        if track.pose_readout is not None:
            self.front_end = {"pose_readout": self._pose_readout(track, path)}

    def _pose_readout(self, track: PixelTrack, weights: Path):
        """The track's pose read-out, refused in one line unless it was fitted for this
        backbone and camera set; recorded with its sha256 and held-out quality."""
        from window_bench.harness.files import sha256_file
        from window_bench.pixels.pose_readout import load_pose_readout

        readout, record = load_pose_readout(track.pose_readout, sha256_file(weights),
                                            self.cameras)
        self.record["pose_readout"] = {
            "file": track.pose_readout.name, "sha256": sha256_file(track.pose_readout),
            **{k: record[k] for k in ("command", "heldout_quality", "fine_pose_mm",
                                      "fine_pose_deg")}}
        return readout

    def demos_cache(self, cache_dir: Path | None, demos_root: Path) -> Path:
        from window_bench.pixels.demo_cache import DEFAULT_SUBDIR

        return cache_dir or demos_root / DEFAULT_SUBDIR

    def observe_demos(self, episodes: list, env_id: str, cache: Path,
                      progress: bool) -> tuple[list, dict]:
        """The demos re-observed under the backbone, from the cache when it holds them."""
        from window_bench.pixels.demo_cache import cached_pixel_demos

        return cached_pixel_demos(episodes, env_id, self.backbone, cache, progress,
                                  cameras=self.cameras)

    def configure(self, agent) -> None:
        agent.encoder_weights = self.encoder_weights   # named in its policy files
        agent.cameras = self.cameras

    def training_env(self, env_id: str, acceptance_noise: dict | None, max_episode_steps: int,
                     observe_every: int):
        """Rendered and encoded only on the chunk grid: the replay's chunked transitions and
        the policy read nothing else (h = 1 learners: every step)."""
        from window_bench.envs.wrappers import make_training_env
        from window_bench.pixels.features import PixelFeatures

        env = make_training_env(env_id, acceptance_noise, obs_mode="pixels",
                                max_episode_steps=max_episode_steps)
        return PixelFeatures(env, self.backbone, observe_every=observe_every,
                             cameras=self.cameras)

    def supervisor(self, supervisor):
        return StateSupervisor(supervisor)   # the installer sees the scene


def make_track_env(env_id: str, track: str, backbone=None, *, weights=None,
                   observe_every: int = 1, cameras: str | None = None, **kwargs) -> gym.Env:
    """``gym.make(env_id, obs_mode="flat", **kwargs)`` for ``state``; the env wrapped in
    :class:`PixelFeatures` for a pixel track, with ``backbone`` or else the one
    ``resolve_backbone(weights)`` gives (``None``: the shipped default), rendering
    ``cameras`` (``None``: the track's camera set). ``observe_every``
    (pixels): render and encode only on the chunk grid of a policy with that horizon
    (:class:`PixelFeatures`); the state track's observation costs nothing to make and is
    made every step whatever it says."""
    observed_on = get_track(track)
    if observed_on.name == DEFAULT_TRACK:
        return gym.make(env_id, obs_mode="flat", **kwargs)
    cameras = observed_on.cameras if cameras is None else cameras
    from window_bench.pixels.features import make_pixel_env

    if backbone is None:
        from window_bench.pixels.weights import resolve_backbone

        backbone, _ = resolve_backbone(weights)

    return make_pixel_env(env_id, backbone, observe_every=observe_every, cameras=cameras,
                          **kwargs)


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


def pixel_demos(demos: list, env_id: str, backbone, progress: bool = False,
                cameras: str = "paper") -> list:
    """The state-track demonstrations re-observed on the pixel track: each episode's executed
    actions replayed from its seed under :class:`PixelFeatures`. The env is deterministic and
    rendering does not touch the physics, so the replay is the same episode; rewards and
    terminations are checked step by step and a divergence is an error, never a silently
    different dataset. ``cameras``: the camera set (:mod:`window_bench.pixels.cameras`)."""
    from tqdm import tqdm

    env = make_track_env(env_id, "pixels", backbone, cameras=cameras)
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
