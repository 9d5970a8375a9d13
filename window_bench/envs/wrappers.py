"""Training-time wrappers: a noisy acceptance sensor in place of the simulator's truth.

The paper's Section 5 notes that on a real site the acceptance signal is itself noisy: an
installer or a sensor signs off late, misses a seated panel, or signs off on one that is not
seated. ``NoisyAcceptance`` gives the learner that signal. The simulator still computes the
true acceptance (``window_bench.envs.task.acceptance``) on every step; the wrapper passes it
through a sensor model and lets the *sensor* decide the reward and the end of the episode.

Sensor model (``AcceptanceSensor``), one reading per env step:

* **delay** ``d``: the reading on step ``t`` concerns the panel's state on step ``t - d``
  (steps before the first one read the reset state, which is never accepted);
* **false negative** ``p_fn``: when that state was accepted, the sensor misses it with
  probability ``p_fn``, independently on every step (a sensor that keeps looking, not a
  one-shot decision per episode);
* **false positive** ``p_fp``: when that state was not accepted, the sensor fires anyway
  with probability ``p_fp``, independently on every step.

When the sensor fires the operator signs off: reward 1.0 and ``terminated=True``. Until then
the episode runs on, also after a true acceptance that the sensor has not reported yet; the
robot may then disturb the seated panel, which is the cost of a late or missed signal.

Evaluation keeps the truth: the harness does not wrap its evaluation envs, and the wrapper's
``info["is_success"]`` is the *true* acceptance (a false positive ends an episode with reward
1.0 and ``is_success`` False), so logs and success rates stay honest.
"""

from __future__ import annotations

from collections import deque
from numbers import Integral, Real

import gymnasium as gym
import numpy as np

MAX_DELAY_STEPS = 100
NOISE_KEYS = ("false_positive_rate", "false_negative_rate", "delay_steps")

# Mixed into the reset seed so that the sensor's stream is not the env's own np_random
# stream (which Gymnasium seeds from the same integer).
_SENSOR_STREAM = 0x5E45


def _check_rate(name: str, value) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise ValueError(f"{name}={value!r} must be a number in [0, 1]")
    value = float(value)
    if not (0.0 <= value <= 1.0):   # also rejects NaN
        raise ValueError(f"{name}={value!r} is outside [0, 1]")
    return value


def _check_delay(value) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Integral):
        raise ValueError(f"delay_steps={value!r} must be an integer in [0, {MAX_DELAY_STEPS}]")
    if not (0 <= int(value) <= MAX_DELAY_STEPS):
        raise ValueError(f"delay_steps={value!r} is outside [0, {MAX_DELAY_STEPS}]")
    return int(value)


def sensor_rng(seed: int | None) -> np.random.Generator:
    """The sensor's generator for a reset seed (fresh OS entropy for ``None``)."""
    if seed is None:
        return np.random.default_rng()
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(_SENSOR_STREAM,)))


class AcceptanceSensor:
    """The acceptance sensor alone: delay, per-step misses and per-step spurious firings.

    Nothing here steps a simulator, so the noise model is testable on a constructed sequence
    of true acceptance values.

    Parameters
    ----------
    false_positive_rate : float
        Probability in [0, 1] that a reading of a not-accepted state fires.
    false_negative_rate : float
        Probability in [0, 1] that a reading of an accepted state does not fire.
    delay_steps : int
        Steps in [0, 100] between a state and its reading.
    seed : int or None
        Seeds the sensor's own generator until a ``reset(seed=...)`` re-seeds it.
    """

    def __init__(self, false_positive_rate: float = 0.0, false_negative_rate: float = 0.0,
                 delay_steps: int = 0, seed: int | None = None):
        self.false_positive_rate = _check_rate("false_positive_rate", false_positive_rate)
        self.false_negative_rate = _check_rate("false_negative_rate", false_negative_rate)
        self.delay_steps = _check_delay(delay_steps)
        self._pending: deque[bool] = deque(maxlen=self.delay_steps + 1)
        self.rng = sensor_rng(seed)
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Start an episode: every state before the first reading counts as not accepted.
        ``seed`` re-seeds the generator; ``None`` continues its stream."""
        if seed is not None:
            self.rng = sensor_rng(seed)
        self._pending.clear()
        self._pending.extend([False] * (self.delay_steps + 1))

    def read(self, accepted_now: bool) -> bool:
        """One step: record this step's true acceptance, return whether the sensor fires.

        Exactly one uniform draw per call, whatever the state, so the random stream stays
        aligned with the steps (the same seed gives the same draws on the same step).

        Parameters
        ----------
        accepted_now : bool
            True acceptance on this step.

        Returns
        -------
        bool
            The sensor's reading of the state ``delay_steps`` steps ago.
        """
        u = float(self.rng.random())
        self._pending.append(bool(accepted_now))
        if self._pending[0]:
            return u >= self.false_negative_rate
        return u < self.false_positive_rate

    def as_dict(self) -> dict:
        return {"false_positive_rate": self.false_positive_rate,
                "false_negative_rate": self.false_negative_rate,
                "delay_steps": self.delay_steps}


class NoisyAcceptance(gym.Wrapper):
    """Reward and termination from a noisy acceptance sensor (training only).

    Wrapping switches the underlying ``WindowInstallEnv`` to
    ``terminate_on_acceptance=False`` (it sets that attribute on ``env.unwrapped``), so the
    episode no longer ends on the true acceptance; this wrapper ends it when its sensor fires
    (reward 1.0, ``terminated=True``). Otherwise the reward is 0.0 and the episode runs until
    truncation. On a termination the env's own truncation flag is cleared (as the unwrapped
    env does on an accepting last step); on a physics divergence (``info["sim_unstable"]``)
    the sensor is not read and the step is truncated as usual.

    Extra ``info`` keys, present at reset (all False) and at every step:

    ``sensed_acceptance``
        the sensor fired on this step (equals ``terminated``);
    ``true_acceptance``
        the acceptance test passes on this step (the env's ``info["accepted"]``);
    ``accepted_ever``
        the acceptance test has passed on some step of this episode.

    ``info["is_success"]`` is the true acceptance on this step: on the step that ends the
    episode it says whether the panel really is accepted, whatever the sensor said.

    Parameters
    ----------
    env : gymnasium.Env
        A ``WindowInstallEnv``, possibly wrapped (e.g. by ``gym.make``).
    false_positive_rate, false_negative_rate : float
        Per-step probabilities in [0, 1] (see ``AcceptanceSensor``).
    delay_steps : int
        Sensing delay in steps, in [0, 100].
    seed : int or None
        Seeds the sensor until the first ``reset(seed=...)``; every ``reset(seed=s)``
        re-seeds it from ``s``, so the same seed and actions give the same noisy signal.
    """

    def __init__(self, env: gym.Env, false_positive_rate: float = 0.0,
                 false_negative_rate: float = 0.0, delay_steps: int = 0,
                 seed: int | None = None):
        self.sensor = AcceptanceSensor(false_positive_rate, false_negative_rate, delay_steps, seed)
        base = env.unwrapped
        if not hasattr(base, "terminate_on_acceptance"):
            raise ValueError(f"NoisyAcceptance needs a WindowInstallEnv (an env with a "
                             f"terminate_on_acceptance attribute), got {type(base).__name__}")
        super().__init__(env)
        base.terminate_on_acceptance = False
        self._accepted_ever = False
        self._needs_reset = True

    @property
    def false_positive_rate(self) -> float:
        return self.sensor.false_positive_rate

    @property
    def false_negative_rate(self) -> float:
        return self.sensor.false_negative_rate

    @property
    def delay_steps(self) -> int:
        return self.sensor.delay_steps

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.sensor.reset(seed)
        self._accepted_ever = False
        self._needs_reset = False
        info = dict(info)
        info.update(sensed_acceptance=False, true_acceptance=False, accepted_ever=False,
                    is_success=False)
        return obs, info

    def step(self, action):
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (episode ended or never started)")
        obs, _, env_terminated, truncated, info = self.env.step(action)
        if env_terminated:
            raise RuntimeError("the wrapped env terminated on its own: NoisyAcceptance needs "
                               "env.unwrapped.terminate_on_acceptance=False (set at wrap time)")
        true_now = bool(info["accepted"])
        self._accepted_ever |= true_now
        fired = self.sensor.read(true_now)   # read (one draw) on every step
        if info["sim_unstable"]:
            fired = False   # no sign-off on a diverged simulation
        terminated = fired
        truncated = bool(truncated) and not fired
        info = dict(info)
        info.update(sensed_acceptance=fired, true_acceptance=true_now,
                    accepted_ever=self._accepted_ever, is_success=true_now)
        if terminated or truncated:
            self._needs_reset = True
        return obs, (1.0 if fired else 0.0), terminated, truncated, info


def make_training_env(env_id: str, acceptance_noise: dict | None = None, **kwargs) -> gym.Env:
    """``gym.make(env_id, **kwargs)``, wrapped in ``NoisyAcceptance`` iff noise is given.

    Parameters
    ----------
    env_id : str
        A registered window-bench id, e.g. ``"WindowInstall-A-v0"``.
    acceptance_noise : dict or None
        ``None``: the plain env (true acceptance). A dict with any of ``false_positive_rate``,
        ``false_negative_rate``, ``delay_steps`` and ``seed``: the wrapped env (an empty dict
        wraps with a noiseless sensor).
    **kwargs
        Passed to ``gym.make`` (``obs_mode``, ``max_episode_steps``, ...).
    """
    if acceptance_noise is None:
        return gym.make(env_id, **kwargs)
    allowed = (*NOISE_KEYS, "seed")
    unknown = sorted(set(acceptance_noise) - set(allowed))
    if unknown:
        raise ValueError(f"acceptance_noise has unknown keys {unknown}; allowed: {list(allowed)}")
    if kwargs.get("terminate_on_acceptance", False):
        raise ValueError("terminate_on_acceptance=True contradicts acceptance_noise: the noisy "
                         "sensor decides termination; leave it out")
    # Validate before building the (comparatively slow) env.
    AcceptanceSensor(**{k: v for k, v in acceptance_noise.items() if k != "seed"})
    return NoisyAcceptance(gym.make(env_id, **kwargs), **acceptance_noise)

