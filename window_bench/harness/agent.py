"""The agent interface: everything the harness (:mod:`window_bench.harness.run`) asks of a learner.

Every method of Table 1 runs one :class:`Agent` (QC-FQL, HIL-SERL/RLPD, ACT, SB3 SAC); the
agents registry (:data:`window_bench.harness.methods.AGENTS`) maps an agent kind to its class,
and the harness never asks which kind it holds. An agent

* is built by :meth:`Agent.create` from an :class:`AgentSpec` (sizes, seed, profile, the
  demonstrations and their observation statistics, ``--agent-config`` overrides);
* learns in :meth:`Agent.learn`: one learner call on batches it draws from the harness's
  ``sample()`` (D_demo in Stage I, D_demo and D_online 1:1 in Stage III) or from its own data,
  returning its metrics and the gradient steps it took;
* acts with :meth:`Agent.act` ``(obs, deterministic) -> (h, 7)`` and forgets its per-episode
  memory in :meth:`Agent.reset`;
* saves and restores itself as plain data: :meth:`Agent.state_dict` (an exact resume) and
  :meth:`Agent.policy_state_dict` (the acting weights only, for evaluation workers and
  ``policies/``) hold nothing but tensors, numpy arrays and JSON values (:func:`check_plain`),
  so that they can be written without pickle;
* declares its capabilities as data (class attributes below) instead of the harness
  branching on its kind: where takeover steps go (:func:`takeover_segments`), whether it keeps
  its own replay buffer, whether it fits its own normaliser on the demos, its own Stage I step
  count, the observation track it reads, and the code its Stage I depends on.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import numbers
import types
import typing
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from window_bench.data.steplog import ACTION_DIM, EpisodeLog
from window_bench.harness.methods import agent_class
from window_bench.harness.tracks import DEFAULT_TRACK

#: The JSON scalars a plain state may hold besides tensors and arrays.
_JSON_SCALARS = (str, bool, int, float, type(None))
MAX_OVERRIDE_INT = 1_000_000   # --agent-config counts and sizes (the paper's Stage I: 1e6)
MAX_OVERRIDE_WIDTH = 8192      # --agent-config layer widths (the paper's MLPs: 512)


@dataclass(frozen=True)
class AgentSpec:
    """What the harness knows when it builds an agent for a fresh run."""

    obs_dim: int
    action_dim: int
    h: int                          # the method's chunk horizon (Table 1)
    seed: int
    profile: Any                    # window_bench.harness.methods.Profile
    demos: list = field(repr=False)  # D_demo as EpisodeLogs
    obs_mean: np.ndarray | None = None   # demo statistics (None for own_normalizer agents)
    obs_std: np.ndarray | None = None
    overrides: dict = field(default_factory=dict)   # ``--agent-config KEY=VALUE``
    front_end: dict | None = None   # fixed parts the track gives its agents (a pose read-out)


class Agent(ABC):
    """A learner the harness can run. Subclasses set ``h`` and may change the capabilities."""

    #: Actions per :meth:`act` call (the chunk horizon).
    h: int = 1
    #: Takeover transitions also go to D_demo (HIL-SERL), not only to D_online: the harness
    #: adds each finished episode's :func:`takeover_segments` there.
    takeovers_to_demo: bool = False
    #: D_demo's chunk windows start every this many steps (None: on the chunk grid, every
    #: ``h``; 1: at every step, as the QC reference samples its windows).
    demo_chunk_stride: int | None = None
    #: The agent keeps its own replay buffer (SB3 SAC): the harness hands it every finished
    #: training episode through :meth:`add_episode` instead of filling its chunk replays.
    own_replay: bool = False
    #: The agent fits its own normaliser on the demos (ACT): no demo statistics are passed.
    own_normalizer: bool = False
    #: Stage I gradient steps if the agent has its own count (ACT); None: the profile's.
    offline_steps: int | None = None
    #: The agent acts in chunks of the method's ``h`` (``AgentSpec.h``), so a run may set
    #: another one (QC-FQL, Tables 5/6); the others have a fixed horizon.
    follows_method_h: bool = False
    #: The observation track the agent reads (window_bench.harness.tracks): its policy is
    #: evaluated in that track's env.
    track: str = DEFAULT_TRACK

    #: Config fields Stage I never reads (settings of the online phase): the Stage I cache's
    #: key leaves them out, so runs that differ only there share one Stage I.
    ONLINE_FIELDS: tuple[str, ...] = ()

    @classmethod
    def stage1_modules(cls) -> tuple[str, ...]:
        """The modules whose source defines what the agent's Stage I computes: the Stage I
        cache (harness/stage1.py) hashes them into its key, so a code change is a new entry.
        This default is the module that defines the class; () for an agent without a Stage I
        to cache."""
        return (cls.__module__,)

    # ------------------------------------------------------------------ building
    @classmethod
    def make_config(cls, h: int, profile, overrides: dict):
        """The agent's config for a run, ``--agent-config`` overrides applied and validated
        (``ValueError`` naming the field, the value and the allowed range), or None for an
        agent without one. The harness calls it before any demo is collected, so that a bad
        value stops a run before it starts; :meth:`create` builds from it."""
        no_overrides(cls.__name__, overrides)
        return None

    @classmethod
    def create(cls, spec: AgentSpec) -> "Agent":
        """A fresh agent for a run (weights seeded by ``spec.seed``). This default builds
        ``cls(obs_dim, action_dim, make_config(...), seed=, obs_mean=, obs_std=)``; agents
        constructed otherwise override it."""
        return cls(spec.obs_dim, spec.action_dim,
                   cls.make_config(spec.h, spec.profile, spec.overrides), seed=spec.seed,
                   obs_mean=spec.obs_mean, obs_std=spec.obs_std)

    @property
    def gamma(self) -> float:
        """Per-step discount of the harness's chunk replays (unused with ``own_replay``): the
        config's ``gamma``, 0.99 for an agent without one (ACT has no TD learning)."""
        return getattr(getattr(self, "config", None), "gamma", 0.99)

    def attach_demos(self, demos: list) -> None:
        """D_demo, for agents that draw their own batches from the episodes; called after
        :meth:`create` and after a resume (the demos are not part of the state)."""

    # ------------------------------------------------------------------ learning
    @abstractmethod
    def learn(self, sample: Callable[[], Any]) -> tuple[dict[str, float], int]:
        """One learner call; ``sample()`` draws one batch of chunk transitions from the
        harness's buffers (call it as often as needed, or not at all). Returns the metrics
        and the number of gradient steps taken (the harness's update credit)."""

    def begin_online(self) -> None:
        """Called by the harness as Stage II begins, and again when a run resumes in Stages
        II-III (so it must be idempotent): settings of the online phase take effect here."""

    def take_online_settings(self, other: "Agent") -> None:
        """Set this agent's :attr:`ONLINE_FIELDS` to ``other``'s: a Stage I restored from the
        cache keeps the settings of the run that loads it, not of the run that computed it."""
        if self.ONLINE_FIELDS:
            self.config = dataclasses.replace(
                self.config, **{k: getattr(other.config, k) for k in self.ONLINE_FIELDS})

    def add_episode(self, log) -> None:
        """A finished training episode (only called when ``own_replay``)."""
        raise NotImplementedError(f"{type(self).__name__} has no replay buffer of its own")

    # ------------------------------------------------------------------ acting
    @abstractmethod
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """The next chunk ``(h, 7)`` in [-1, 1] for one observation."""

    def reset(self) -> None:
        """Start of an episode (e.g. ACT's temporal-ensembling history)."""

    # ------------------------------------------------------------------ state
    @abstractmethod
    def state_dict(self) -> dict:
        """Everything for an exact resume, as plain data (:func:`check_plain`)."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""

    @classmethod
    @abstractmethod
    def from_state_dict(cls, state: dict) -> "Agent":
        """A new agent restored from :meth:`state_dict` output."""

    @abstractmethod
    def policy_state_dict(self) -> dict:
        """What ``act(obs, deterministic=True)`` needs and nothing else (no critics,
        optimisers or replay), as plain data."""

    @classmethod
    @abstractmethod
    def from_policy_state_dict(cls, state: dict):
        """An object with ``h``, ``reset()`` and ``act(obs, deterministic=True)`` giving
        bit-identical actions to the agent :meth:`policy_state_dict` was taken from."""

    def hyperparameters(self) -> dict:
        """The agent's configuration for ``results.json`` (plain values)."""
        cfg = getattr(self, "config", None)
        return plain(dataclasses.asdict(cfg)) if dataclasses.is_dataclass(cfg) else {}

    def stage1_hyperparameters(self) -> dict:
        """:meth:`hyperparameters` without :attr:`ONLINE_FIELDS`: what Stage I depends on."""
        return {k: v for k, v in self.hyperparameters().items() if k not in self.ONLINE_FIELDS}


# ---------------------------------------------------------------------------- building one
def make_agent(method, profile, demos: list, seed: int, overrides: dict | None = None,
               front_end: dict | None = None) -> Agent:
    """A fresh learner for ``method`` (a :class:`~window_bench.harness.methods.Method`; its
    class from the registry) with the ``profile``'s sizes; ``overrides`` replace fields of the
    agent's config (``bench run --agent-config KEY=VALUE``); ``front_end``: what the run's
    track gives its agents (:attr:`~window_bench.harness.tracks.RunObservation.front_end`)."""
    cls = agent_class(method.agent)
    obs = np.concatenate([ep.observations for ep in demos])
    mean, std = (None, None) if cls.own_normalizer else obs_normalizer(obs)
    return cls.create(AgentSpec(obs_dim=int(obs.shape[1]), action_dim=ACTION_DIM, h=method.h,
                                seed=seed, profile=profile, demos=demos, obs_mean=mean,
                                obs_std=std, overrides=dict(overrides or {}),
                                front_end=front_end))


def arm_power(actions: torch.Tensor, exponent: float) -> torch.Tensor:
    """``sign(x) |x|^exponent`` on the arm's entries of (..., A) actions, the vacuum (last
    entry) unchanged: the action companding of QC-FQL's and ACT's ``action_power``."""
    if exponent == 1.0:
        return actions
    arm, vac = actions[..., :-1], actions[..., -1:]
    return torch.cat([arm.sign() * arm.abs().pow(exponent), vac], dim=-1)


def obs_normalizer(obs: np.ndarray, floor: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std of the demonstrations' observations, for the agents' fixed z-scoring.

    A feature constant in the demonstrations (the vacuum flag in A, which never drops in a
    good demonstration) keeps scale 1: it is only centred, because flooring its std would
    blow a value seen only online (the flag at 0) up to ``1 / floor`` units. Other stds are
    floored at ``floor``; the agents also clip normalised inputs (QC-FQL: +-10).
    """
    mean, std = obs.mean(0), obs.std(0)
    std = np.where(std < 1e-6, 1.0, np.maximum(std, floor))
    return mean.astype(np.float32), std.astype(np.float32)


# ---------------------------------------------------------------------------- takeovers
def takeover_segments(episode: EpisodeLog) -> list[EpisodeLog]:
    """The maximal runs of ``"takeover"`` steps of ``episode``, each as its own step log.

    With ``h = 1`` every transition ``(s_t, a_t, r_t, s_t+1)`` stands alone, so a run
    ``[t0, t1)`` becomes a log with observations ``s_t0 .. s_t1`` that ends ``terminated`` if
    the episode terminated on its last step and ``truncated`` otherwise (its last
    transition then bootstraps from ``s_t1``, as in the full episode). These are what the
    harness adds to D_demo for an agent with ``takeovers_to_demo`` (HIL-SERL stores
    intervened transitions as demonstrations too). Per-step fields are sliced generically
    (rows ``T`` or ``T + 1``), so fields added to :class:`EpisodeLog` later travel along;
    the chunk grid is reset to ``h = 1``.
    """
    episode.validate()
    T = episode.T
    takeover = np.asarray(episode.provenance) == "takeover"
    edges = np.flatnonzero(np.diff(np.concatenate([[0], takeover.astype(np.int8), [0]])))
    segments = []
    for t0, t1 in zip(edges[0::2], edges[1::2]):
        kwargs = {}
        for f in dataclasses.fields(episode):
            value = getattr(episode, f.name)
            if isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == T + 1:
                value = value[t0:t1 + 1].copy()
            elif isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == T:
                value = value[t0:t1].copy()
            elif isinstance(value, (dict, list)):
                value = copy.deepcopy(value)
            kwargs[f.name] = value
        ends_episode = t1 == T
        terminated = np.zeros(t1 - t0, bool)
        truncated = np.zeros(t1 - t0, bool)
        if ends_episode and bool(episode.terminated[-1]):
            terminated[-1] = True
        else:
            truncated[-1] = True
        kwargs.update(terminated=terminated, truncated=truncated, chunk_horizon=1,
                      chunk_index=None, policy_chunk_start=None)
        segment = type(episode)(**kwargs)
        segment.validate()
        segments.append(segment)
    return segments


# ---------------------------------------------------------------------------- plain data
def plain(value):
    """``value`` with tuples as lists and numpy scalars as Python numbers; tensors and
    arrays are kept (not copied). Raises ``TypeError`` for anything else that is not plain."""
    if isinstance(value, (torch.Tensor, np.ndarray)) or isinstance(value, _JSON_SCALARS):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"plain state: key {k!r} is a {type(k).__name__}, not a str")
            out[k] = plain(v)
        return out
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    raise TypeError(f"plain state: a {type(value).__name__} is not a tensor, an array or a "
                    f"JSON value")


def check_plain(state, path: str = "state") -> None:
    """Raise ``TypeError`` naming the first entry of ``state`` that is not a tensor, a numpy
    array, a dict with str keys, a list or a JSON scalar (a tuple is not plain: JSON would
    return it as a list)."""
    if isinstance(state, (torch.Tensor, np.ndarray)) or isinstance(state, _JSON_SCALARS):
        return
    if isinstance(state, dict):
        for k, v in state.items():
            if not isinstance(k, str):
                raise TypeError(f"{path}: key {k!r} is a {type(k).__name__}, not a str")
            check_plain(v, f"{path}[{k!r}]")
        return
    if isinstance(state, list):
        for i, v in enumerate(state):
            check_plain(v, f"{path}[{i}]")
        return
    raise TypeError(f"{path} is a {type(state).__name__}, not a tensor, an array or a JSON "
                    f"value")


def optimizer_state(optimizer: torch.optim.Optimizer) -> dict:
    """A copy of ``optimizer.state_dict()`` as plain data (parameter indices as str keys).
    A copy: torch's state dict holds the live moment tensors, which a loaded optimizer would
    otherwise share and update in place."""
    sd = copy.deepcopy(optimizer.state_dict())
    return plain({"state": {str(k): v for k, v in sd["state"].items()},
                  "param_groups": sd["param_groups"]})


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict) -> None:
    """Restore :func:`optimizer_state` output (torch matches the state by int index)."""
    groups = [{**g, "betas": tuple(g["betas"])} if "betas" in g else g
              for g in state["param_groups"]]
    optimizer.load_state_dict({"state": {int(k): v for k, v in state["state"].items()},
                               "param_groups": groups})


def module_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """A copy of ``module.state_dict()`` as a plain dict of tensors."""
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def generator_state(rng: np.random.Generator) -> dict:
    """A numpy Generator's bit-generator state (plain: its ints are JSON ints)."""
    return plain(rng.bit_generator.state)


def config_from_plain(cls, saved: dict, **replace):
    """A config dataclass ``cls`` from a saved dict: fields missing there take their
    defaults, unknown keys are ignored (added or removed since it was saved) and lists
    become tuples where the field is a tuple (JSON has no tuples)."""
    defaults = cls()
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name in saved:
            v = saved[f.name]
            as_tuple = isinstance(getattr(defaults, f.name), tuple) or "tuple" in str(f.type)
            kwargs[f.name] = tuple(v) if isinstance(v, list) and as_tuple else v
    kwargs.update(replace)
    return cls(**kwargs)


def with_overrides(cfg, overrides: dict):
    """``cfg`` (a dataclass) with the ``--agent-config`` fields replaced; an unknown field
    raises ``ValueError`` naming the allowed ones."""
    names = [f.name for f in dataclasses.fields(cfg)]
    for key in overrides:
        if key not in names:
            raise ValueError(f"unknown agent config field {key!r}; fields of "
                             f"{type(cfg).__name__}: {', '.join(names)}")
    return dataclasses.replace(cfg, **overrides)


def no_overrides(kind: str, overrides: dict) -> None:
    """For agents without a configurable dataclass: refuse ``--agent-config``."""
    if overrides:
        raise ValueError(f"--agent-config {', '.join(overrides)}: the {kind} agent takes no "
                         f"config overrides")


def check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} = {value!r} is not allowed: it must be an integer "
                         f">= {minimum}")
    return int(value)


# ---------------------------------------------------------------------------- --agent-config
def parse_overrides(items: list[str] | None) -> dict:
    """``["alpha=100", "act_noise_scale=0"]`` -> ``{"alpha": 100, "act_noise_scale": 0}``
    (values parsed as JSON where possible: numbers, booleans, lists)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--agent-config {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
        if isinstance(out[key], list):
            out[key] = tuple(out[key])
    return out


def _fits(value, tp) -> bool:
    """``value`` (parsed from JSON, lists as tuples) has the annotated type ``tp``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in args)
    if origin is tuple:
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(v, args[0]) for v in value)
        return len(value) == len(args) and all(_fits(v, a) for v, a in zip(value, args))
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is str:
        return isinstance(value, str)
    return True   # a type the configs do not use: their own checks decide


def _type_name(tp) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_type_name(args[0]).removeprefix('an ').removeprefix('a ')}s"
        return f"a list [{', '.join(_type_name(a) for a in args)}]"
    return {type(None): "null", bool: "true or false", int: "an integer", float: "a number",
            str: "a string"}.get(tp, getattr(tp, "__name__", str(tp)))


def check_agent_config(agent_cls: type, h: int, profile, overrides: dict):
    """The agent's config with ``--agent-config`` applied, or a one-line ``ValueError``: each
    value must have its field's declared type (read from the config dataclass) and be finite;
    the config's own checks then hold the ranges (positive sizes, rates in [0, 1] ...)."""
    try:   # the config's own checks first: their messages name the allowed range
        config, error = agent_cls.make_config(h, profile, overrides), None
    except TypeError as e:   # a value of a type its checks did not expect
        config, error = None, e
    default = agent_cls.make_config(h, profile, {})
    if dataclasses.is_dataclass(default):
        name, hints = type(default).__name__, typing.get_type_hints(type(default))
        for key, value in overrides.items():
            if key in hints and not _fits(value, hints[key]):
                raise ValueError(f"{name}.{key} = {value!r} is not allowed: it must be "
                                 f"{_type_name(hints[key])}")
    if error is not None:   # still one line, naming the values
        raise ValueError(f"--agent-config {overrides}: {str(error).splitlines()[0]}")
    for key, value in overrides.items():
        # sizes the configs bound only from below: a width or a count that exhausts memory
        # would stop the run after its directory was made
        most = MAX_OVERRIDE_WIDTH if isinstance(value, tuple) else MAX_OVERRIDE_INT
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{type(config).__name__}.{key} = {value!r} is not allowed: "
                                 f"it must be finite")
            if isinstance(v, int) and not isinstance(v, bool) and v > most:
                raise ValueError(f"{type(config).__name__}.{key} = {value!r} is not allowed: "
                                 f"{'each entry' if isinstance(value, tuple) else 'it'} must "
                                 f"be at most {most}")
    return config
