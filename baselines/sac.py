"""The ``sac`` baseline: Stable-Baselines3 SAC used as is, step-wise, with the demos in its buffer.

Section 4.3 of the paper: "Standard SAC employs step-wise actions (h = 1), initializes the
replay buffer with D_demo, and performs neither offline pretraining nor human intervention
during online learning." SB3 owns the training loop; this module only

* builds the model with SB3's defaults (:func:`make_sac`; the overrides a caller passes are
  the only departures) and pre-fills its replay buffer with every demonstration
  transition, sized so that the demos are never overwritten during the budget;
* runs ``learn`` with a callback that hands the harness a checkpoint every
  ``checkpoint_every`` environment steps (:func:`train_sac`);
* saves and restores model and replay buffer atomically for resumable runs
  (:func:`save_sac`, :func:`load_sac`);
* wraps the model as an ``h = 1`` policy for evaluation (:class:`SACPolicy`).

Episode ends: a demo step that TERMINATED is stored ``done`` (no bootstrap); a step cut by
the time limit is stored ``done`` with ``info["TimeLimit.truncated"] = True``, which SB3's
buffer (``handle_timeout_termination=True``, its default) records as a timeout and does not
treat as terminal - the same convention SB3 applies to its own online transitions.
"""

from __future__ import annotations

import json
import numbers
import os
from pathlib import Path
from typing import Callable

import numpy as np
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.sac.policies import SACPolicy as SB3SACPolicy

from window_bench.harness.evaluation import atomic_write, atomic_write_text, provenance
from window_bench.data.steplog import EpisodeLog

#: SB3 2.x defaults of ``SAC`` that this baseline keeps (disclosed in docs/baselines.md).
SB3_SAC_DEFAULTS = {
    "policy": "MlpPolicy (actor and 2 critics, 256x256 ReLU each)",
    "learning_rate": 3e-4, "buffer_size": 1_000_000, "learning_starts": 100,
    "batch_size": 256, "tau": 0.005, "gamma": 0.99, "train_freq": 1, "gradient_steps": 1,
    "ent_coef": "auto (init 1.0)", "target_entropy": "auto (-dim(A) = -7)",
    "target_update_interval": 1, "use_sde": False, "optimize_memory_usage": False,
    "handle_timeout_termination": True,
}
CHECKPOINT_FILE = "sac_checkpoint.json"


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} = {value!r} is not allowed: it must be an integer "
                         f">= {minimum}")
    return int(value)


def demo_transitions(demos: list[EpisodeLog]) -> int:
    """Number of transitions (steps) in ``demos``."""
    return int(sum(ep.T for ep in demos))


def prefill_replay_buffer(model: SAC, demos: list[EpisodeLog]) -> int:
    """Append every transition of ``demos`` to ``model.replay_buffer``, in order.

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
            raise ValueError(f"demo episode {ep.episode_id}: observations have size "
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


def make_sac(env, demos: list[EpisodeLog], seed: int, total_steps: int, **overrides) -> SAC:
    """SB3 ``SAC("MlpPolicy", env)`` with SB3's defaults and the demos in its replay buffer.

    Parameters
    ----------
    env : gymnasium.Env
        One environment, e.g. ``gym.make("WindowInstall-A-v0", obs_mode="flat")`` (its
        ``TimeLimit`` of 600 steps marks truncation).
    demos : list of EpisodeLog
        The demonstration dataset ``D_demo``; every transition is pre-filled.
    seed : int
        Passed to SB3 (which seeds Python's, NumPy's and torch's global RNGs and the env).
    total_steps : int
        The online budget in environment steps. The buffer holds
        ``buffer_size = n_demo + total_steps`` transitions unless overridden, so it never
        wraps and the demos stay in it for the whole budget; while it does not wrap, SB3
        samples uniformly over the filled part, exactly as with its default size of 1e6.
    **overrides
        Any ``SAC`` keyword (disclose it). ``buffer_size`` below ``n_demo + total_steps``,
        ``optimize_memory_usage=True`` (it stores ``next_obs`` as the following row, which
        breaks at the demos' episode ends) and ``handle_timeout_termination=False`` raise
        ``ValueError``.
    """
    seed = _check_int("seed", seed, 0)
    total_steps = _check_int("total_steps", total_steps, 1)
    if not demos:
        raise ValueError("make_sac: got no demos; the sac baseline pre-fills its buffer with "
                         "D_demo")
    n_demo = demo_transitions(demos)
    needed = n_demo + total_steps
    kwargs = {"buffer_size": needed, "seed": seed, "device": "cpu", "verbose": 0}
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
    model.n_demo_transitions = prefill_replay_buffer(model, demos)  # saved with the model
    return model


def _no_learning_rate(_progress: float) -> float:
    """The learning-rate schedule of a policy rebuilt for acting only."""
    return 0.0


class SACPolicy:
    """Evaluation adapter: an SB3 SAC policy as an ``h = 1`` chunk policy.

    ``SACPolicy(model)`` wraps ``model.policy`` (a live view: it acts with the model's
    current weights). ``act(obs)`` returns (1, 7) for one observation and (B, 1, 7) for a
    batch, via SB3's ``predict`` (deterministic by default: the tanh of the Gaussian mean).
    :meth:`state_dict` / :meth:`from_state_dict` copy the policy into a plain dict and
    rebuild it without the model, env or replay buffer (for evaluation workers).
    """

    h = 1

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

    def state_dict(self) -> dict:
        """The policy's constructor arguments (spaces, architecture) and a copy of its
        weights; picklable, no optimiser, env or buffer."""
        params = self.policy._get_constructor_parameters()
        params.pop("lr_schedule", None)  # a bound method of this policy; rebuilt as a no-op
        weights = {k: v.detach().clone() for k, v in self.policy.state_dict().items()}
        return {"sb3_policy": params, "weights": weights}

    @classmethod
    def from_state_dict(cls, state: dict) -> "SACPolicy":
        """Rebuild a :meth:`state_dict` copy on the CPU, in evaluation mode."""
        policy = SB3SACPolicy(**state["sb3_policy"], lr_schedule=_no_learning_rate)
        policy.load_state_dict(state["weights"])
        policy.set_training_mode(False)
        return cls(policy)


class _CheckpointCallback(BaseCallback):
    """Calls ``on_checkpoint(k)`` once ``k`` (a multiple of ``every``) environment steps
    AND their gradient steps are done.

    SB3 calls ``on_step`` after ``env.step`` but before it stores the transition and
    trains, so the check runs at the start of the next rollout (after the training of the
    previous one) and once more when ``learn`` ends.
    """

    def __init__(self, every: int, on_checkpoint: Callable[[int], None]):
        super().__init__(verbose=0)
        self.every, self.on_checkpoint = every, on_checkpoint
        self.last_reported = 0

    def _on_training_start(self) -> None:
        # A resumed run does not report the checkpoint it was saved at again.
        self.last_reported = self.model.num_timesteps

    def _report_if_due(self) -> None:
        k = self.model.num_timesteps
        if k > self.last_reported and k % self.every == 0:
            self.last_reported = k
            self.on_checkpoint(k)

    def _on_rollout_start(self) -> None:
        self._report_if_due()

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        self._report_if_due()


def train_sac(model: SAC, total_steps: int, checkpoint_every: int,
              on_checkpoint: Callable[[int], None], progress: bool = False) -> None:
    """Run ``model.learn`` until ``model.num_timesteps == total_steps``.

    ``on_checkpoint(k)`` is called for every multiple ``k`` of ``checkpoint_every`` reached,
    after step ``k``'s transition is stored and its gradient step done (the harness
    evaluates, and may :func:`save_sac`, there). A model restored by :func:`load_sac`
    continues from its ``num_timesteps`` (its env restarts with a fresh episode).
    """
    total_steps = _check_int("total_steps", total_steps, 1)
    checkpoint_every = _check_int("checkpoint_every", checkpoint_every, 1)
    remaining = total_steps - model.num_timesteps
    if remaining <= 0:
        return
    model.learn(total_timesteps=remaining, callback=_CheckpointCallback(checkpoint_every,
                                                                        on_checkpoint),
                reset_num_timesteps=False, progress_bar=progress)


# --------------------------------------------------------------------------- checkpoints
def _atomic_write_binary(path: Path, write: Callable) -> None:
    """``write(fileobj)`` into a temporary file next to ``path``, then rename it into place."""
    atomic_write(path, write)


def save_sac(model: SAC, directory: str | os.PathLike) -> Path:
    """Save model and replay buffer under ``directory`` for a resume; returns the pointer file.

    The model (``model_<k>.zip``) and the buffer (``replay_<k>.pkl``, ``k`` =
    ``num_timesteps``) are each written atomically, then ``sac_checkpoint.json`` is
    atomically replaced to point at them (with the provenance), and older pairs are
    removed: a run killed at any moment leaves the previous complete checkpoint readable.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    k = int(model.num_timesteps)
    model_name, replay_name = f"model_{k}.zip", f"replay_{k}.pkl"
    _atomic_write_binary(directory / model_name, model.save)
    _atomic_write_binary(directory / replay_name, model.save_replay_buffer)
    rb = model.replay_buffer
    meta = {"num_timesteps": k, "model": model_name, "replay_buffer": replay_name,
            "n_demo_transitions": int(getattr(model, "n_demo_transitions", 0)),
            "buffer_pos": int(rb.pos), "buffer_full": bool(rb.full),
            "provenance": provenance()}
    pointer = directory / CHECKPOINT_FILE
    atomic_write_text(pointer, json.dumps(meta, indent=2) + "\n")
    for old in list(directory.glob("model_*.zip")) + list(directory.glob("replay_*.pkl")):
        if old.name not in (model_name, replay_name):
            old.unlink()
    return pointer


def load_sac(directory: str | os.PathLike, env) -> SAC:
    """Restore the checkpoint :func:`save_sac` wrote under ``directory``, bound to ``env``.

    Raises ``FileNotFoundError`` if there is none and ``ValueError`` if the model and the
    buffer disagree with the pointer file.
    """
    directory = Path(directory)
    pointer = directory / CHECKPOINT_FILE
    if not pointer.exists():
        raise FileNotFoundError(f"no SAC checkpoint in {directory} ({CHECKPOINT_FILE} missing)")
    meta = json.loads(pointer.read_text())
    model = SAC.load(directory / meta["model"], env=env, device="cpu")
    model.load_replay_buffer(directory / meta["replay_buffer"])
    rb = model.replay_buffer
    if (model.num_timesteps != meta["num_timesteps"] or rb.pos != meta["buffer_pos"]
            or rb.full != meta["buffer_full"]):
        raise ValueError(f"load_sac: {directory} is inconsistent: model at "
                         f"{model.num_timesteps} steps, buffer at pos {rb.pos} (full "
                         f"{rb.full}); {CHECKPOINT_FILE} says {meta['num_timesteps']}, "
                         f"{meta['buffer_pos']} ({meta['buffer_full']})")
    return model
