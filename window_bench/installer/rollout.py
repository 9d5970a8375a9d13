"""The rollout loop every method shares: action queue on the fixed chunk grid, takeovers, logging.

:class:`Rollout` runs one environment with one policy, step by step, so that the harness can
interleave gradient updates with environment steps. It implements the paper's convention
(Section 3.2, "Logging and chunk-transition construction under takeovers"):

* the policy proposes a chunk of ``h`` actions only when its action queue is empty, which is
  on the fixed grid ``t = k*h``; the chunk runs open loop;
* a takeover source (:mod:`window_bench.installer.supervisor`) may override any step; it clears the
  queue. When it hands back mid-chunk, the operator holds the robot still (zero motion, the
  vacuum as last commanded) until the next grid boundary, still logged as takeover; the
  policy then proposes a fresh chunk from the observation at that boundary;
* every executed action is logged with its provenance in an :class:`EpisodeLog`; where the
  demonstrator or the takeover source says what it meant (``meant_action``: the command
  before the hand's noise), that is logged too (``EpisodeLog.meant_actions``; the executed
  action elsewhere).

A *policy* is anything with ``act(obs) -> array`` of shape ``(h, 7)`` (a chunk) or ``(7,)``
(one action, ``h = 1``), an optional attribute ``h`` (default 1) and an optional
``reset(seed=None)``. The scripted controllers, the human-like demonstrator and every agent
fit.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from window_bench.data.steplog import ACTION_DIM, STAGE_FLAGS, EpisodeLog

PROVENANCE_OF_POLICY = ("demo", "policy")


class Rollout:
    """Step one env with a policy and an optional takeover source, logging every step.

    ``provenance`` labels the policy's own steps: ``"policy"`` (default) or ``"demo"`` (a
    demonstrator). ``h`` defaults to ``policy.h`` (or 1).
    """

    def __init__(self, env, policy, *, supervisor=None, h: int | None = None,
                 provenance: str = "policy", operator: str = "", env_id: str | None = None):
        if provenance not in PROVENANCE_OF_POLICY:
            raise ValueError(f"provenance={provenance!r}; allowed {PROVENANCE_OF_POLICY}")
        h = getattr(policy, "h", 1) if h is None else h
        if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1:
            raise ValueError(f"h = {h!r} is not allowed: the chunk horizon must be an integer >= 1")
        self.env, self.policy, self.supervisor = env, policy, supervisor
        self.h, self.provenance, self.operator = int(h), provenance, operator
        spec = getattr(env, "spec", None)
        self.env_id = env_id if env_id is not None else (spec.id if spec is not None else "")
        self.done = True

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int, episode_id: int = 0):
        """Start an episode; returns the first observation."""
        obs, info = self.env.reset(seed=seed)
        if hasattr(self.policy, "reset"):
            self.policy.reset(seed=seed)
        if self.supervisor is not None:
            self.supervisor.reset(self.env, seed=seed)
        self.seed, self.episode_id = int(seed), int(episode_id)
        self.obs, self.info = obs, info
        self.queue: deque[np.ndarray] = deque()
        self.in_takeover = ""          # kind of the takeover still holding control, or ""
        self.last_vacuum = 1.0 if info.get("suction_engaged") else -1.0
        self.t = 0
        self.done = False
        self._obs = [self._vector(obs)]
        self._act, self._rew, self._prov, self._kind, self._start, self._stages = [], [], [], [], [], []
        self._meant = []
        self._randomization = dict(info.get("randomization", {}) or
                                   getattr(self.env.unwrapped, "_randomization", {}))
        self.terminated = self.truncated = False
        return obs

    @staticmethod
    def _vector(obs) -> np.ndarray:
        if isinstance(obs, dict):
            raise ValueError("Rollout logs flat observations: make the env with obs_mode='flat'")
        return np.asarray(obs, dtype=np.float32)

    def _propose(self) -> None:
        if self._obs[-1].size and np.isnan(self._obs[-1]).all():
            raise RuntimeError(f"step {self.t}: the policy would act on an unobserved step (the "
                               f"env observes every {getattr(self.env, 'observe_every', '?')} "
                               f"steps; this rollout's chunk grid is h = {self.h})")
        chunk = np.asarray(self.policy.act(self.obs), dtype=np.float32)
        if chunk.shape == (ACTION_DIM,):
            chunk = chunk[None]
        if chunk.ndim != 2 or chunk.shape[1] != ACTION_DIM or not 1 <= chunk.shape[0] <= self.h:
            raise ValueError(f"policy.act returned shape {chunk.shape}; expected ({self.h}, "
                             f"{ACTION_DIM}) or ({ACTION_DIM},)")
        self.queue.extend(chunk)

    def step(self):
        """Execute one 10 Hz step; returns ``(obs, reward, terminated, truncated, info)``."""
        if self.done:
            raise RuntimeError("episode is over: call reset(seed) first")
        t, h = self.t, self.h
        decision = None
        if self.supervisor is not None:
            decision = self.supervisor.intervene(self.obs, self.info)
        starts = False
        if decision is not None:
            action, kind = decision
            if kind not in ("safety", "coverage"):
                raise ValueError(f"takeover source returned kind {kind!r}; allowed "
                                 "'safety', 'coverage'")
            self.queue.clear()
            self.in_takeover = kind
            prov = "takeover"
            meant = getattr(self.supervisor, "meant_action", None)
        elif self.in_takeover and t % h != 0:
            # Handed back mid-chunk: hold still until the policy's next grid boundary.
            action = np.array([0, 0, 0, 0, 0, 0, self.last_vacuum], dtype=np.float32)
            kind, prov, meant = self.in_takeover, "takeover", None
        else:
            self.in_takeover = ""
            if not self.queue:
                self._propose()
                starts = True
            action, kind, prov = self.queue.popleft(), "", self.provenance
            # A one-step demonstrator says what it meant; a chunk's steps mean what they are.
            meant = getattr(self.policy, "meant_action", None) if starts and self.h == 1 else None
        action = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.last_vacuum = float(action[6])
        self._obs.append(self._vector(obs))
        self._act.append(action)
        self._meant.append(action if meant is None else
                           np.clip(np.asarray(meant, dtype=np.float32), -1.0, 1.0))
        self._rew.append(float(reward))
        self._prov.append(prov)
        self._kind.append(kind)
        self._start.append(starts and prov == "policy")
        self._stages.append([bool(info.get(k, False)) for k in STAGE_FLAGS])
        self.obs, self.info = obs, info
        self.t += 1
        if terminated or truncated:
            self.done = True
            self.terminated, self.truncated = bool(terminated), not terminated
        return obs, reward, terminated, truncated, info

    def episode_log(self) -> EpisodeLog:
        """The finished episode's step log (validated)."""
        if not self.done or not self._act:
            raise RuntimeError("the episode is not finished")
        T = len(self._act)
        term = np.zeros(T, bool)
        trunc = np.zeros(T, bool)
        (term if self.terminated else trunc)[-1] = True
        log = EpisodeLog(
            observations=np.stack(self._obs), actions=np.stack(self._act),
            meant_actions=np.stack(self._meant),
            rewards=np.asarray(self._rew, np.float32), terminated=term, truncated=trunc,
            provenance=np.asarray(self._prov), takeover_kind=np.asarray(self._kind),
            episode_id=self.episode_id, env_id=self.env_id, seed=self.seed,
            chunk_horizon=self.h, chunk_index=np.arange(T, dtype=np.int64) // self.h,
            policy_chunk_start=np.asarray(self._start, bool),
            stage_flags=np.asarray(self._stages, bool).reshape(T, len(STAGE_FLAGS)),
            randomization={k: float(v) for k, v in self._randomization.items()},
            operator=self.operator,
        )
        log.validate()
        return log

    def run(self, seed: int, episode_id: int = 0) -> EpisodeLog:
        """A whole episode; returns its log."""
        self.reset(seed, episode_id)
        while not self.done:
            self.step()
        return self.episode_log()
