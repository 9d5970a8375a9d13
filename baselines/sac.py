"""The ``sac`` baseline: Stable-Baselines3 SAC used as is, step-wise, with the demos in its buffer.

Section 4.3 of the paper: "Standard SAC employs step-wise actions (h = 1), initializes the
replay buffer with D_demo, and performs neither offline pretraining nor human intervention
during online learning." SB3 stays the SAC implementation (its policy, losses, entropy
tuning and replay buffer); the harness owns the loop, as for every other method. This
module

* builds the model with SB3's defaults (:func:`make_sac`; the overrides a caller passes are
  the only departures) and pre-fills its replay buffer with every demonstration
  transition, sized so that the demos are never overwritten during the budget;
* adapts it to the harness's :class:`~window_bench.harness.agent.Agent` interface
  (:class:`SACAgent`): the harness's rollouts fill SB3's buffer (one finished episode at a
  time, :func:`add_episodes`), each learner call is SB3's own
  ``model.train(gradient_steps=1, batch_size)``, and the resume state is plain data (the
  networks, the entropy coefficient, the three optimisers and the buffer's arrays), not
  SB3's pickled ``save``;
* wraps the actor as an ``h = 1`` policy for evaluation (:class:`SACPolicy`).

Episode ends: a step that TERMINATED is stored ``done`` (no bootstrap); a step cut by
the time limit is stored ``done`` with ``info["TimeLimit.truncated"] = True``, which SB3's
buffer (``handle_timeout_termination=True``, its default) records as a timeout and does not
treat as terminal - the convention SB3 applies to its own online transitions.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.sac.policies import SACPolicy as SB3SACPolicy
from torch import nn

from window_bench.data.steplog import EpisodeLog
from window_bench.harness.agent import (Agent, AgentSpec, check_int, load_optimizer_state,
                                        module_state, no_overrides, optimizer_state, plain)

#: SB3 2.x defaults of ``SAC`` that this baseline keeps (disclosed in docs/baselines.md), and
#: the three settings of SB3's ``learn`` loop that the harness's loop replaces.
SB3_SAC_DEFAULTS = {
    "policy": "MlpPolicy (actor and 2 critics, 256x256 ReLU each)",
    "learning_rate": 3e-4, "buffer_size": 1_000_000, "batch_size": 256, "tau": 0.005,
    "gamma": 0.99, "ent_coef": "auto (init 1.0)", "target_entropy": "auto (-dim(A) = -7)",
    "target_update_interval": 1, "use_sde": False, "optimize_memory_usage": False,
    "handle_timeout_termination": True,
    "learning_starts": "none (SB3 default 100): the buffer starts with D_demo, training "
                       "starts at the first step as for the other methods",
    "train_freq / gradient_steps": "the profile's UTD (cpu: 1 per env step = SB3's default)",
    "replay insertion": "a training episode enters the buffer when it ends (SB3: each step)",
}
#: The replay buffer's per-transition arrays (the resume state keeps the filled rows).
_BUFFER_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones",
                  "timeouts")


def demo_transitions(demos: list[EpisodeLog]) -> int:
    """Number of transitions (steps) in ``demos``."""
    return int(sum(ep.T for ep in demos))


def add_episodes(model: SAC, demos: list[EpisodeLog]) -> int:
    """Append every transition of ``demos`` (the demonstrations, or a finished training
    episode) to ``model.replay_buffer``, in order.

    Actions are clipped to the action space (the env executes them clipped) and scaled to
    [-1, 1] as SB3 stores its own. ``done = terminated or truncated`` with
    ``info["TimeLimit.truncated"] = truncated and not terminated``, so a time-limit cut is
    stored as a timeout, not as a terminal. Returns the number of transitions added.
    """
    rb = model.replay_buffer
    low, high = model.action_space.low, model.action_space.high
    added = 0
    for ep in demos:
        ep.validate()
        obs = np.asarray(ep.observations, dtype=np.float32)
        if obs.shape[1:] != model.observation_space.shape:
            raise ValueError(f"episode {ep.episode_id}: observations have size "
                             f"{obs.shape[1:]}, the env's observation space "
                             f"{model.observation_space.shape}")
        actions = np.clip(ep.actions, low, high)
        if not (np.all(low == -1.0) and np.all(high == 1.0)):
            # SB3 stores actions scaled to [-1, 1]; on such a box the scaling is the identity
            # (skipped there, so the stored demos equal the logged ones bit for bit).
            actions = model.policy.scale_action(actions)
        for t in range(ep.T):
            terminated, truncated = bool(ep.terminated[t]), bool(ep.truncated[t])
            rb.add(obs[t][None], obs[t + 1][None], actions[t][None],
                   np.array([ep.rewards[t]], dtype=np.float32),
                   np.array([terminated or truncated]),
                   [{"TimeLimit.truncated": truncated and not terminated}])
            added += 1
    return added


def make_sac(env, demos: list[EpisodeLog], seed: int, total_steps: int,
             policy_kwargs: dict | None = None, replay_buffer_class: type | None = None,
             **overrides) -> SAC:
    """SB3 ``SAC("MlpPolicy", env)`` with SB3's defaults and the demos in its replay buffer.

    Parameters
    ----------
    env : gymnasium.Env
        One environment, e.g. ``gym.make("WindowInstall-A-v0", obs_mode="flat")``, or
        :func:`spaces_env` (SB3 only reads the spaces: the harness steps the environment).
    demos : list of EpisodeLog
        The demonstration dataset ``D_demo``; every transition is pre-filled.
    seed : int
        Passed to SB3 (which seeds Python's, NumPy's and torch's global RNGs and the env;
        SB3 samples actions and batches with the global RNGs, which the harness saves).
    total_steps : int
        The online budget in environment steps. The buffer holds
        ``buffer_size = n_demo + total_steps`` transitions unless overridden, so it never
        wraps and the demos stay in it for the whole budget; while it does not wrap, SB3
        samples uniformly over the filled part, exactly as with its default size of 1e6.
    policy_kwargs : dict, optional
        SB3's ``policy_kwargs`` of the observation track (the pixel track's features
        extractor, :mod:`window_bench.pixels.sac`); not an override of SAC's settings.
    replay_buffer_class : type, optional
        SB3's replay buffer class of the observation track (the pixel track's stores the
        feature maps as float16); ``None``: SB3's ``ReplayBuffer``.
    **overrides
        Any ``SAC`` keyword (disclose it). ``buffer_size`` below ``n_demo + total_steps``,
        ``optimize_memory_usage=True`` (it stores ``next_obs`` as the following row, which
        breaks at the demos' episode ends) and ``handle_timeout_termination=False`` raise
        ``ValueError``.
    """
    seed = check_int("seed", seed, 0)
    total_steps = check_int("total_steps", total_steps, 1)
    if not demos:
        raise ValueError("make_sac: got no demos; the sac baseline pre-fills its buffer with "
                         "D_demo")
    n_demo = demo_transitions(demos)
    needed = n_demo + total_steps
    kwargs = {"buffer_size": needed, "seed": seed, "device": "cpu", "verbose": 0,
              **({"policy_kwargs": policy_kwargs} if policy_kwargs else {}),
              **({"replay_buffer_class": replay_buffer_class} if replay_buffer_class else {})}
    kwargs.update(overrides)
    if kwargs["buffer_size"] < needed:
        raise ValueError(f"buffer_size = {kwargs['buffer_size']} is not allowed: it must be "
                         f">= n_demo + total_steps = {n_demo} + {total_steps} = {needed}, or "
                         f"the demos would be overwritten during the budget")
    if kwargs.get("optimize_memory_usage", False):
        raise ValueError("optimize_memory_usage = True is not allowed: it stores next_obs as "
                         "the next row, which is wrong at the demos' episode ends")
    rb_class = kwargs.get("replay_buffer_class") or ReplayBuffer
    if not issubclass(rb_class, ReplayBuffer):
        raise ValueError(f"replay_buffer_class = {rb_class!r} is not allowed: it must be an "
                         f"SB3 ReplayBuffer (subclass)")
    if not (kwargs.get("replay_buffer_kwargs") or {}).get("handle_timeout_termination", True):
        raise ValueError("handle_timeout_termination = False is not allowed: time-limit "
                         "truncations would be treated as terminal")
    model = SAC("MlpPolicy", env, **kwargs)
    if model.n_envs != 1:
        raise ValueError(f"make_sac needs a single environment, got n_envs = {model.n_envs}")
    model.n_demo_transitions = add_episodes(model, demos)
    model.overrides = dict(overrides)   # in the resume state (SACAgent.state_dict)
    return model


def spaces_env(obs_dim: int, action_dim: int = 7) -> gym.Env:
    """An env with the flat track's spaces (``WindowInstallEnv(obs_mode="flat")``: unbounded
    float32 observations, actions in [-1, 1]) for building the model: SB3 reads the spaces
    from an env, the harness steps the real one."""
    env = gym.Env()
    env.observation_space = spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
    env.action_space = spaces.Box(-1.0, 1.0, (action_dim,), np.float32)
    return env


def _no_learning_rate(_progress: float) -> float:
    """The learning-rate schedule of a policy rebuilt for acting only."""
    return 0.0


class SACPolicy:
    """Evaluation adapter: an SB3 SAC policy as an ``h = 1`` chunk policy.

    ``SACPolicy(model)`` wraps ``model.policy`` (a live view: it acts with the model's
    current weights). ``act(obs)`` returns (1, 7) for one observation and (B, 1, 7) for a
    batch, via SB3's ``predict`` (deterministic by default: the tanh of the Gaussian mean).
    :meth:`policy_state_dict` / :meth:`from_policy_state_dict` copy the actor and the
    architecture into plain data and rebuild it without the model, env or replay buffer
    (for evaluation workers).
    """

    h = 1
    #: SB3's features extractor of the policy (the pixel track's subclass sets its own).
    features_extractor_class = FlattenExtractor

    def __init__(self, model: SAC | SB3SACPolicy):
        self.policy = model.policy if isinstance(model, SAC) else model
        if not isinstance(self.policy, SB3SACPolicy):
            raise TypeError(f"SACPolicy needs an SB3 SAC model or SACPolicy, got "
                            f"{type(model).__name__}")

    def reset(self, seed: int | None = None) -> None:
        """Nothing to reset (the policy is memoryless); present for the controller
        interface."""

    def act(self, obs, deterministic: bool = True) -> np.ndarray:
        x = np.asarray(obs, dtype=np.float32)
        shape = self.policy.observation_space.shape
        if x.shape != shape and x.shape[1:] != shape:
            raise ValueError(f"obs has shape {x.shape}; expected {shape} or (B, *{shape})")
        action, _ = self.policy.predict(x, deterministic=deterministic)
        action = np.asarray(action, dtype=np.float32)
        return action.reshape(1, -1) if x.shape == shape else action[:, None, :]

    def policy_state_dict(self) -> dict:
        """The actor's weights, the spaces and the architecture, as plain data."""
        p = self.policy
        params = p._get_constructor_parameters()
        if (params["features_extractor_class"] is not self.features_extractor_class
                or params["features_extractor_kwargs"]):
            raise ValueError(f"{type(self).__name__}.policy_state_dict: features extractor "
                             f"{params['features_extractor_class'].__name__} is not "
                             f"supported (this policy uses "
                             f"{self.features_extractor_class.__name__})")
        return {"obs_dim": int(p.observation_space.shape[0]),
                "action_low": p.action_space.low.copy(), "action_high": p.action_space.high.copy(),
                "architecture": plain({**{k: params[k] for k in (
                    "net_arch", "use_sde", "log_std_init", "use_expln", "clip_mean",
                    "n_critics", "normalize_images")},
                    "share_features_extractor": p.share_features_extractor}),
                "activation": params["activation_fn"].__name__,
                "actor": module_state(p.actor)}

    @classmethod
    def from_policy_state_dict(cls, state: dict) -> "SACPolicy":
        """Rebuild a :meth:`policy_state_dict` copy on the CPU, in evaluation mode."""
        activation = getattr(nn, state["activation"], None)
        if not (isinstance(activation, type) and issubclass(activation, nn.Module)):
            raise ValueError(f"activation {state['activation']!r} is not a torch.nn module")
        low, high = np.asarray(state["action_low"]), np.asarray(state["action_high"])
        policy = SB3SACPolicy(spaces.Box(-np.inf, np.inf, (state["obs_dim"],), np.float32),
                              spaces.Box(low, high, dtype=np.float32), _no_learning_rate,
                              activation_fn=activation,
                              features_extractor_class=cls.features_extractor_class,
                              **state["architecture"])
        policy.actor.load_state_dict(state["actor"])
        policy.set_training_mode(False)
        return cls(policy)


class SACAgent(Agent):
    """SB3 SAC as a harness agent (see the module docstring); ``SACAgent(model)`` wraps a
    model from :func:`make_sac`."""

    h = 1
    own_replay = True   # SB3's buffer, with D_demo pre-filled
    #: The acting adapter, SB3's ``policy_kwargs`` and replay buffer class (the pixel track
    #: sets its own).
    policy_class = SACPolicy
    policy_kwargs: dict | None = None
    replay_buffer_class: type | None = None

    @classmethod
    def stage1_modules(cls) -> tuple[str, ...]:
        return ()   # SB3 SAC has no offline pretraining: no Stage I to cache

    def __init__(self, model: SAC):
        self.model = model
        self.policy = self.policy_class(model)
        # SB3's train() records its losses in the model's logger; nothing is written.
        model.set_logger(Logger(None, []))

    @classmethod
    def create(cls, spec: AgentSpec) -> "SACAgent":
        no_overrides("sac", spec.overrides)
        return cls(make_sac(spaces_env(spec.obs_dim, spec.action_dim), spec.demos, spec.seed,
                            spec.profile.budget_steps, cls.policy_kwargs,
                            cls.replay_buffer_class))

    @property
    def gamma(self) -> float:
        return self.model.gamma

    def learn(self, sample) -> tuple[dict[str, float], int]:
        """SB3's own ``train(gradient_steps=1, batch_size)`` on its buffer (``sample`` is not
        used); returns the losses SB3 recorded."""
        self.model.train(gradient_steps=1, batch_size=self.model.batch_size)
        log = self.model.logger
        metrics = {k.split("/", 1)[-1]: float(v) for k, v in log.name_to_value.items()
                   if isinstance(v, (int, float, np.floating))}
        log.dump()   # clears the recorded values
        return metrics, 1

    def add_episode(self, log: EpisodeLog) -> None:
        self.model.num_timesteps += add_episodes(self.model, [log])

    def act(self, obs, deterministic: bool = False) -> np.ndarray:
        return self.policy.act(obs, deterministic)

    def hyperparameters(self) -> dict:
        return {**SB3_SAC_DEFAULTS, "buffer_size": int(self.model.buffer_size),
                "seed": int(self.model.seed),
                "demo_transitions": int(self.model.n_demo_transitions)}

    # ------------------------------------------------------------------ state
    def policy_state_dict(self) -> dict:
        return self.policy.policy_state_dict()

    @classmethod
    def from_policy_state_dict(cls, state: dict) -> SACPolicy:
        return cls.policy_class.from_policy_state_dict(state)

    def state_dict(self) -> dict:
        """Everything SB3's ``train`` reads, as plain data: the policy (actor, critics,
        target critics), the entropy coefficient, the three optimisers, the filled rows of
        the replay buffer and the counters. SB3 draws with the global RNGs, which the
        harness saves with its own state."""
        m, rb = self.model, self.model.replay_buffer
        n = rb.buffer_size if rb.full else rb.pos
        return {"obs_dim": int(m.observation_space.shape[0]),
                "action_dim": int(m.action_space.shape[0]), "seed": int(m.seed),
                "buffer_size": int(rb.buffer_size), "overrides": plain(m.overrides),
                "num_timesteps": int(m.num_timesteps),
                "n_updates": int(m._n_updates), "n_demo_transitions": int(m.n_demo_transitions),
                "policy": module_state(m.policy),
                "log_ent_coef": m.log_ent_coef.detach().clone(),
                "actor_optimizer": optimizer_state(m.actor.optimizer),
                "critic_optimizer": optimizer_state(m.critic.optimizer),
                "ent_coef_optimizer": optimizer_state(m.ent_coef_optimizer),
                "replay": {"pos": int(rb.pos), "full": bool(rb.full),
                           **{f: getattr(rb, f)[:n].copy() for f in _BUFFER_FIELDS}}}

    def load_state_dict(self, state: dict) -> None:
        m, rb = self.model, self.model.replay_buffer
        if state["buffer_size"] != rb.buffer_size:
            raise ValueError(f"SACAgent.load_state_dict: buffer_size = {state['buffer_size']} "
                             f"in the state, {rb.buffer_size} in this agent")
        m.policy.load_state_dict(state["policy"])
        with torch.no_grad():
            m.log_ent_coef.copy_(state["log_ent_coef"])
        load_optimizer_state(m.actor.optimizer, state["actor_optimizer"])
        load_optimizer_state(m.critic.optimizer, state["critic_optimizer"])
        load_optimizer_state(m.ent_coef_optimizer, state["ent_coef_optimizer"])
        replay = state["replay"]
        for f in _BUFFER_FIELDS:
            getattr(rb, f)[: len(replay[f])] = replay[f]
        rb.pos, rb.full = int(replay["pos"]), bool(replay["full"])
        m.num_timesteps, m._n_updates = int(state["num_timesteps"]), int(state["n_updates"])
        m.n_demo_transitions = int(state["n_demo_transitions"])

    @classmethod
    def from_state_dict(cls, state: dict) -> "SACAgent":
        """A new agent restored from :meth:`state_dict` output. Building the SB3 model
        reseeds the global RNGs: restore them afterwards (the harness does)."""
        model = SAC("MlpPolicy", spaces_env(state["obs_dim"], state["action_dim"]),
                    **{"buffer_size": state["buffer_size"], "seed": state["seed"],
                       "device": "cpu", "verbose": 0, "policy_kwargs": cls.policy_kwargs,
                       **({"replay_buffer_class": cls.replay_buffer_class}
                          if cls.replay_buffer_class else {}),
                       **state["overrides"]})
        model.overrides = dict(state["overrides"])
        agent = cls(model)
        agent.load_state_dict(state)
        return agent
