"""Observation tracks: what a run's agent observes, and what the harness needs of it.

A :class:`Track` says which agent runs a method on it (:meth:`Track.agent_kind`), what that
agent's Stage I depends on (:meth:`Track.stage1_modules`) and which env a frozen policy is
evaluated in (:meth:`Track.eval_env`); for one run (:meth:`Track.for_run`) a
:class:`RunObservation` observes the demonstrations, makes the training env and wraps the
installer supervisor. These base classes are the ``state`` track (:data:`DEFAULT_TRACK`): the
privileged 52-float ``obs_mode="flat"`` observation and the demonstrations as recorded. Other
tracks (the paper's pixels) are registered in :data:`TRACKS` from above the harness
(:mod:`window_bench.catalog`); the harness looks a track up by name and never asks which one
it holds.
"""

from __future__ import annotations

from pathlib import Path

from window_bench.harness.methods import agent_class
from window_bench.harness.registry import Registry

#: The track of a run that names none (and of results files written before tracks existed).
DEFAULT_TRACK = "state"


class RunObservation:
    """How one run observes on its track; this base is the state track's."""

    #: Leading observation values the replays store as float16 (a track's feature maps).
    replay_half_obs = 0
    #: Fixed parts the track gives a fresh agent (``AgentSpec.front_end``), or None.
    front_end: dict | None = None

    def __init__(self, track: "Track"):
        #: What ``results.json`` records of the observation (its ``encoder``).
        self.record = {"track_label": track.label}

    def demos_cache(self, cache_dir: Path | None, demos_root: Path) -> Path | None:
        """Where the demonstrations re-observed on this track are cached (``cache_dir``: the
        run's ``--pixel-demos-cache``; None: the track's default place beside the demos), or
        None when the recorded observations are the track's."""
        return None

    def observe_demos(self, episodes: list, env_id: str, cache: Path | None,
                      progress: bool) -> tuple[list, dict | None]:
        """D_demo as this track observes it, and what to record of how it was made (None:
        nothing to record)."""
        return episodes, None

    def configure(self, agent) -> None:
        """A fresh agent of the run, before it learns (a pixel agent learns which encoder
        weights its policy files name)."""

    def training_env(self, env_id: str, acceptance_noise: dict | None, max_episode_steps: int,
                     observe_every: int):
        """The env of Stages II and III (``observe_every``: the policy's chunk horizon)."""
        from window_bench.envs.wrappers import make_training_env

        return make_training_env(env_id, acceptance_noise, obs_mode="flat",
                                 max_episode_steps=max_episode_steps)

    def supervisor(self, supervisor):
        """The installer supervisor as it watches this track's training env."""
        return supervisor


class Track:
    """An observation track (this base: the state track)."""

    name = DEFAULT_TRACK
    label = "privileged state"
    #: One sentence for the tables' notes (Markdown, links relative to the results pages).
    description = ("privileged state (the 52-float simulator state, with the panel's exact pose "
                   "relative to the seat: not what the paper's agents observe)")

    def agent_kind(self, kind: str) -> str:
        """The agent kind that runs a method whose agent is ``kind`` on this track."""
        return kind

    def stage1_modules(self, kind: str) -> tuple[str, ...]:
        """The modules whose source defines the Stage I of this track's agent ``kind`` (the
        Stage I cache hashes them, beside the replay's); () when it has none to cache."""
        return agent_class(kind).stage1_modules()

    def eval_env(self, env_id: str, policy_state: dict, observe_every: int = 1, **kwargs):
        """The env a frozen policy (its ``policy_state``) is evaluated in; ``kwargs`` go to
        the env (``max_episode_steps``, ``clearance`` ...)."""
        import gymnasium as gym

        return gym.make(env_id, obs_mode="flat", **kwargs)

    def for_run(self, encoder_weights: str | None = None) -> RunObservation:
        """The observation of one run (``encoder_weights``: the backbone of a track that has
        one; checked here, before any work)."""
        return RunObservation(self)


#: Track name -> :class:`Track`.
TRACKS = Registry("track", unknown="track={name!r}; allowed: {names}")


def register_track(track: Track) -> None:
    TRACKS.register(track.name, track)


def get_track(name: str) -> Track:
    """The track registered as ``name``; ``ValueError`` naming the registered ones."""
    return TRACKS.lookup(name)
