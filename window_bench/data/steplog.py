"""The 10 Hz step log of one episode, whoever issued each action.

Section 3.2 of the paper records interaction at the 10 Hz environment step as
``(s_t, a_t, r_t, s_{t+1})``, where ``a_t`` is the *executed* action regardless of its
provenance: a teleoperated demonstration, the policy, or an installer takeover. All learning
quantities (chunk transitions, Bellman backups, intervention statistics) are defined on this
step index. :class:`EpisodeLog` holds one complete episode in that form; chunked transitions
(Eq. 4) are built from it by :func:`window_bench.data.chunks.chunk_transitions`.

Conventions:

* ``observations`` has ``T + 1`` rows ``s_0 .. s_T`` (flat vectors); every other per-step
  field has ``T`` rows, step ``t`` covering the transition ``s_t -> s_{t+1}``. A row that is
  all NaN is a step the env did not observe (:attr:`EpisodeLog.observed`; the pixel track
  observing on a chunked policy's grid); ``s_0`` and ``s_T`` are always observed.
* An episode log is complete: exactly one of ``terminated`` / ``truncated`` is set, and only
  on the last step ``T - 1``. ``terminated`` means the MDP ended (seating accepted; no
  bootstrap); ``truncated`` means the time limit cut it (bootstrap from ``s_T``).
* ``provenance[t]`` is one of :data:`PROVENANCES`; ``takeover_kind[t]`` is one of
  :data:`TAKEOVER_KINDS` and is ``""`` unless ``provenance[t] == "takeover"``.
* ``chunk_index[t] = t // chunk_horizon`` is the step's cell on the fixed chunk grid;
  ``policy_chunk_start[t]`` is True where the policy proposed a new chunk (only on grid
  boundaries, and only on ``"policy"`` steps). ``stage_flags[t]`` holds the cumulative stage
  events of :data:`STAGE_FLAGS` after step ``t``.
* ``meant_actions`` (optional, T rows like ``actions``): the command the demonstrator or the
  installer meant at each step, before its hand's noise (the executed action on the policy's
  steps); ``None`` where the log does not record it. ``actions`` stays the executed record.
* Per episode: ``env_id``, ``seed``, ``randomization`` (Table 9 values drawn at reset),
  ``operator`` (the operator profile that produced demos/takeovers, ``""`` if none) and
  ``chunk_horizon``.

Optional fields left out of the constructor get defaults consistent with the rest (``h = 1``
grid, policy chunk starts on every ``"policy"`` step, stage flags all False).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

PROVENANCES = ("demo", "policy", "takeover")
TAKEOVER_KINDS = ("", "safety", "coverage")

#: Action dimension of the shared interface: 6-D pose increment + vacuum command.
ACTION_DIM = 7
#: Duration of one environment step in seconds (10 Hz).
STEP_DT = 0.1
#: Stage events logged per step (the env's ``info`` keys of the same names).
STAGE_FLAGS = ("suction_acquired", "insertion_entered", "seated")


@dataclass
class EpisodeLog:
    """One episode's step log as numpy arrays (see the module docstring for conventions).

    The constructor converts array-likes with ``np.asarray``: float fields to float32,
    ``provenance`` / ``takeover_kind`` to numpy string arrays. Booleans are not cast, so
    :meth:`validate` can reject a non-boolean ``terminated`` / ``truncated``. The
    constructor does not validate; call :meth:`validate`.
    """

    observations: np.ndarray  # (T+1, obs_dim) float32
    actions: np.ndarray  # (T, 7) float32, executed
    rewards: np.ndarray  # (T,) float32
    terminated: np.ndarray  # (T,) bool
    truncated: np.ndarray  # (T,) bool
    provenance: np.ndarray  # (T,) str from PROVENANCES
    takeover_kind: np.ndarray  # (T,) str from TAKEOVER_KINDS
    episode_id: int = 0
    env_id: str = ""
    seed: int = 0
    chunk_horizon: int = 1
    chunk_index: np.ndarray | None = None  # (T,) int64, t // chunk_horizon
    policy_chunk_start: np.ndarray | None = None  # (T,) bool
    stage_flags: np.ndarray | None = None  # (T, 3) bool, STAGE_FLAGS order
    randomization: dict = field(default_factory=dict)
    operator: str = ""
    meant_actions: np.ndarray | None = None  # (T, 7) float32, before the hand's noise

    def __post_init__(self):
        self.observations = np.asarray(self.observations, dtype=np.float32)
        self.actions = np.asarray(self.actions, dtype=np.float32)
        self.rewards = np.asarray(self.rewards, dtype=np.float32)
        self.terminated = np.asarray(self.terminated)
        self.truncated = np.asarray(self.truncated)
        self.provenance = np.asarray(self.provenance).astype(str)
        self.takeover_kind = np.asarray(self.takeover_kind).astype(str)
        T = int(self.rewards.shape[0]) if self.rewards.ndim == 1 else 0
        h = self.chunk_horizon
        if self.chunk_index is None:
            hh = h if isinstance(h, (int, np.integer)) and h >= 1 else 1
            self.chunk_index = np.arange(T, dtype=np.int64) // hh
        if self.policy_chunk_start is None:
            hh = h if isinstance(h, (int, np.integer)) and h >= 1 else 1
            on_grid = (np.arange(T) % hh) == 0
            prev_policy = np.concatenate([[False], self.provenance[:-1] == "policy"])
            # Default: a chunk starts on a grid boundary, or where control comes back to
            # the policy (the convention of the rollout loop).
            self.policy_chunk_start = (self.provenance == "policy") & (on_grid | ~prev_policy)
        if self.stage_flags is None:
            self.stage_flags = np.zeros((T, len(STAGE_FLAGS)), dtype=bool)
        self.chunk_index = np.asarray(self.chunk_index)
        self.policy_chunk_start = np.asarray(self.policy_chunk_start)
        self.stage_flags = np.asarray(self.stage_flags)
        self.randomization = dict(self.randomization or {})
        if self.meant_actions is not None:
            self.meant_actions = np.asarray(self.meant_actions, dtype=np.float32)

    # ------------------------------------------------------------------ derived
    @property
    def T(self) -> int:
        """Number of steps (transitions) in the episode."""
        return int(np.asarray(self.rewards).shape[0])

    @property
    def observed(self) -> np.ndarray:
        """(T+1,) bool: False for a row the env did not observe (all NaN; the pixel track's
        ``PixelFeatures(observe_every=h)`` skips the steps between a chunked policy's grid
        points). Everything else about the step (action, reward, flags) is logged."""
        obs = np.asarray(self.observations)
        if obs.ndim != 2 or obs.shape[1] == 0:
            return np.ones(len(obs), bool)
        return ~np.isnan(obs).all(axis=1)

    @property
    def step_index(self) -> np.ndarray:
        """``np.arange(T)``: the 10 Hz step index of each transition."""
        return np.arange(self.T)

    @property
    def time_s(self) -> np.ndarray:
        """Time of each step's start in seconds: ``step_index * 0.1``."""
        return self.step_index * STEP_DT

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise ``ValueError`` naming the field and the problem if the log is malformed."""
        obs = np.asarray(self.observations)
        act = np.asarray(self.actions)
        rew = np.asarray(self.rewards)
        term = np.asarray(self.terminated)
        trunc = np.asarray(self.truncated)
        prov = np.asarray(self.provenance)
        kind = np.asarray(self.takeover_kind)

        # --- shapes: T is taken from rewards; everything else must agree with it.
        if rew.ndim != 1:
            raise ValueError(f"EpisodeLog.rewards: expected shape (T,), got {rew.shape}")
        T = rew.shape[0]
        if T < 1:
            raise ValueError("EpisodeLog.rewards: episode has no steps (T = 0)")
        for name, arr in (("terminated", term), ("truncated", trunc),
                          ("provenance", prov), ("takeover_kind", kind)):
            if arr.shape != (T,):
                raise ValueError(f"EpisodeLog.{name}: expected shape ({T},) to match "
                                 f"rewards (T = {T}), got {arr.shape}")
        if act.ndim != 2 or act.shape[1] != ACTION_DIM:
            raise ValueError(f"EpisodeLog.actions: expected shape (T, {ACTION_DIM}), "
                             f"got {act.shape}")
        if act.shape[0] != T:
            raise ValueError(f"EpisodeLog.actions: expected {T} rows to match rewards "
                             f"(T = {T}), got {act.shape[0]}")
        if obs.ndim != 2 or obs.shape[1] < 1:
            raise ValueError(f"EpisodeLog.observations: expected shape (T+1, obs_dim), "
                             f"got {obs.shape}")
        if obs.shape[0] != T + 1:
            raise ValueError(f"EpisodeLog.observations: expected T+1 = {T + 1} rows "
                             f"(s_0..s_T), got {obs.shape[0]}")

        meant = self.meant_actions
        if meant is not None:
            if np.shape(meant) != act.shape:
                raise ValueError(f"EpisodeLog.meant_actions: expected shape {act.shape} like "
                                 f"actions, got {np.shape(meant)}")
            if not np.isfinite(meant).all() or np.abs(meant).max() > 1.0:
                raise ValueError("EpisodeLog.meant_actions: values must be finite and in "
                                 f"[-1, 1]^{ACTION_DIM}")

        # --- values
        for name, arr in (("observations", obs), ("actions", act), ("rewards", rew)):
            if not np.issubdtype(arr.dtype, np.floating):
                raise ValueError(f"EpisodeLog.{name}: expected a float array, got {arr.dtype}")
            bad = ~np.isfinite(arr)
            if name == "observations":
                observed = self.observed
                if not (observed[0] and observed[-1]):
                    raise ValueError("EpisodeLog.observations: s_0 and s_T must be observed "
                                     "(an all-NaN row marks an unobserved step)")
                bad &= observed[:, None]
            if bad.any():
                where = np.argwhere(bad)[0]
                raise ValueError(f"EpisodeLog.{name}: non-finite value {arr[tuple(where)]} "
                                 f"at index {tuple(int(i) for i in where)}")

        # --- episode end flags
        for name, arr in (("terminated", term), ("truncated", trunc)):
            if arr.dtype != np.bool_:
                raise ValueError(f"EpisodeLog.{name}: expected a bool array, got {arr.dtype}")
            early = np.flatnonzero(arr[:-1])
            if early.size:
                raise ValueError(f"EpisodeLog.{name}: set at step {int(early[0])}, but only "
                                 f"the last step (T-1 = {T - 1}) may end the episode")
        if term[-1] and trunc[-1]:
            raise ValueError("EpisodeLog.terminated/truncated: both set on the last step; "
                             "exactly one must be")
        if not (term[-1] or trunc[-1]):
            raise ValueError("EpisodeLog.terminated/truncated: neither set on the last step; "
                             "an episode log must be complete (exactly one set)")

        # --- provenance
        unknown = ~np.isin(prov, PROVENANCES)
        if unknown.any():
            i = int(np.flatnonzero(unknown)[0])
            raise ValueError(f"EpisodeLog.provenance: unknown value {str(prov[i])!r} at step "
                             f"{i}; allowed {PROVENANCES}")
        unknown = ~np.isin(kind, TAKEOVER_KINDS)
        if unknown.any():
            i = int(np.flatnonzero(unknown)[0])
            raise ValueError(f"EpisodeLog.takeover_kind: unknown value {str(kind[i])!r} at "
                             f"step {i}; allowed {TAKEOVER_KINDS}")
        stray = (kind != "") & (prov != "takeover")
        if stray.any():
            i = int(np.flatnonzero(stray)[0])
            raise ValueError(f"EpisodeLog.takeover_kind: {str(kind[i])!r} at step {i} whose "
                             f"provenance is {str(prov[i])!r}, not 'takeover'")
        unkinded = (kind == "") & (prov == "takeover")
        if unkinded.any():
            i = int(np.flatnonzero(unkinded)[0])
            raise ValueError(f"EpisodeLog.takeover_kind: empty at takeover step {i}; allowed "
                             f"{TAKEOVER_KINDS[1:]}")

        # --- chunk grid, stage flags, episode attributes
        h = self.chunk_horizon
        if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1:
            raise ValueError(f"EpisodeLog.chunk_horizon: {h!r} is not an integer >= 1")
        ci = np.asarray(self.chunk_index)
        if ci.shape != (T,) or not np.issubdtype(ci.dtype, np.integer):
            raise ValueError(f"EpisodeLog.chunk_index: expected an int array of shape ({T},), "
                             f"got {ci.dtype} {ci.shape}")
        expected = np.arange(T) // int(h)
        if not np.array_equal(ci, expected):
            i = int(np.flatnonzero(ci != expected)[0])
            raise ValueError(f"EpisodeLog.chunk_index: {int(ci[i])} at step {i}, the fixed grid "
                             f"with chunk_horizon {int(h)} gives {int(expected[i])}")
        pcs = np.asarray(self.policy_chunk_start)
        if pcs.shape != (T,) or pcs.dtype != np.bool_:
            raise ValueError(f"EpisodeLog.policy_chunk_start: expected a bool array of shape "
                             f"({T},), got {pcs.dtype} {pcs.shape}")
        bad = pcs & (prov != "policy")
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"EpisodeLog.policy_chunk_start: set at step {i} whose provenance "
                             f"is {str(prov[i])!r}; only policy steps start policy chunks")
        sf = np.asarray(self.stage_flags)
        if sf.shape != (T, len(STAGE_FLAGS)) or sf.dtype != np.bool_:
            raise ValueError(f"EpisodeLog.stage_flags: expected a bool array of shape "
                             f"({T}, {len(STAGE_FLAGS)}) for {STAGE_FLAGS}, got {sf.dtype} "
                             f"{sf.shape}")
        if not isinstance(self.operator, str):
            raise ValueError(f"EpisodeLog.operator: expected a str, got {self.operator!r}")
        if not isinstance(self.randomization, dict):
            raise ValueError(f"EpisodeLog.randomization: expected a dict, got "
                             f"{type(self.randomization).__name__}")


def without_noops(ep: EpisodeLog, before: str | None = None) -> EpisodeLog:
    """``ep`` without its no-op steps: steps whose six motion commands are all zero and whose
    vacuum command repeats the previous step's (an operator's hesitation pause); with
    ``before`` (a name in :data:`STAGE_FLAGS`), only those before that stage event.

    The idle frames of teleoperated data teach a deterministic imitator to stand still where
    a demonstrator paused, and a policy that stands still sees the same state again; OpenVLA's
    LIBERO data preparation (Kim et al. 2024, Sec. 5.1) drops them for that reason. The kept
    steps keep their own observation, action and flags in order; the last step and ``s_T``
    are always kept, so the log stays complete.
    """
    act = np.asarray(ep.actions)
    prev_vacuum = np.concatenate([[np.nan], act[:-1, 6]])
    keep = (np.abs(act[:, :6]).max(axis=1) > 0) | (act[:, 6] != prev_vacuum)
    if before is not None:
        if before not in STAGE_FLAGS:
            raise ValueError(f"without_noops: before={before!r}; allowed: {STAGE_FLAGS}")
        keep |= np.asarray(ep.stage_flags)[:, STAGE_FLAGS.index(before)]
    keep[-1] = True
    idx = np.flatnonzero(keep)
    return EpisodeLog(
        observations=np.concatenate([ep.observations[idx], ep.observations[-1:]]),
        actions=act[idx], rewards=ep.rewards[idx], terminated=ep.terminated[idx],
        truncated=ep.truncated[idx], provenance=ep.provenance[idx],
        takeover_kind=ep.takeover_kind[idx], episode_id=ep.episode_id, env_id=ep.env_id,
        seed=ep.seed, chunk_horizon=ep.chunk_horizon, stage_flags=ep.stage_flags[idx],
        randomization=dict(ep.randomization), operator=ep.operator,
        meant_actions=None if ep.meant_actions is None else ep.meant_actions[idx])


#: What a learner may train on as D_demo's actions (``--demo-actions``).
DEMO_ACTIONS = ("executed", "meant")
#: What learners train on from D_demo unless told otherwise (``--demo-actions``): the
#: demonstrator's meant commands (revision 2 of the defaults; revision 1: ``executed``).
DEFAULT_DEMO_ACTIONS = "meant"


def check_demo_actions(which) -> str:
    """``which`` if it is one of :data:`DEMO_ACTIONS`, else a one-line ``ValueError``."""
    if which not in DEMO_ACTIONS:
        raise ValueError(f"--demo-actions {which!r}; allowed: {', '.join(DEMO_ACTIONS)}")
    return which


def demo_actions(episodes: list[EpisodeLog], which: str) -> list[EpisodeLog]:
    """The demonstrations a learner trains on: as recorded (``"executed"``, the paper's
    ``a_t``), or with each step's action replaced by the command the demonstrator meant
    (``"meant"``: the same step without the hand's noise, as DART labels noisy
    demonstrations; Laskey et al. 2017). The observations stay the executed trajectory's.
    A log without meant actions is a one-line ``ValueError``."""
    if check_demo_actions(which) == "executed":
        return list(episodes)
    out = []
    for ep in episodes:
        if ep.meant_actions is None:
            raise ValueError(f"demonstration {ep.episode_id} (seed {ep.seed}) records no meant "
                             f"actions: collect the demonstrations again (bench demos) to "
                             f"train on them")
        out.append(replace(ep, actions=ep.meant_actions.copy()))
    return out
