"""The agent interface: everything the harness (:mod:`window_bench.harness.run`) asks of a learner.

Every method of Table 1 runs one :class:`Agent` (QC-FQL, HIL-SERL/RLPD, ACT, SB3 SAC); the
methods registry (:data:`window_bench.harness.methods.AGENTS`) maps an agent kind to its class,
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
  branching on its kind: where takeover steps go, whether it keeps its own replay buffer,
  whether it fits its own normaliser on the demos, its own Stage I step count.
"""

from __future__ import annotations

import copy
import dataclasses
import numbers
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

#: The JSON scalars a plain state may hold besides tensors and arrays.
_JSON_SCALARS = (str, bool, int, float, type(None))


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


class Agent(ABC):
    """A learner the harness can run. Subclasses set ``h`` and may change the capabilities."""

    #: Actions per :meth:`act` call (the chunk horizon).
    h: int = 1
    #: Takeover transitions also go to D_demo (HIL-SERL), not only to D_online.
    takeovers_to_demo: bool = False
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
            kwargs[f.name] = (tuple(v) if isinstance(v, list)
                              and isinstance(getattr(defaults, f.name), tuple) else v)
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
