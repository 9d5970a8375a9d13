"""Event-driven binary takeovers (paper Section 3.4.2): who may override the policy, and when.

A *takeover source* is anything with

    reset(env, seed=None) -> None
    intervene(obs, info) -> (action, kind) | None

``intervene`` is called once per 10 Hz step, before the action executes, with the current
observation and the ``info`` of the previous step (the reset info at ``t = 0``). It returns
the action to execute instead of the policy's and the takeover kind (``"safety"`` or
``"coverage"``), or ``None`` to leave control with the policy. The rollout loop
(:mod:`window_bench.installer.rollout`) does the rest: it clears the policy's action queue, logs the
step with provenance ``"takeover"``, and resumes the policy only at the next fixed chunk
boundary. Two sources ship: :class:`InstallerSupervisor` (the scripted installer watching
the same observations as the policy) and ``window_bench.installer.teleop.DeviceTakeover`` (a person
with a keyboard or SpaceMouse; a takeover whenever the device is active, as in HIL-SERL).

:class:`InstallerSupervisor` watches only cues available at the observation interface, as
the paper's installer does: the panel's pose relative to the opening (``window_pos_rel``,
``window_rot_rel``), the contact proxy (realized minus commanded motion) and the vacuum
state. Safety takeovers fire on

* ``suction_lost`` - the vacuum flag drops while the panel is not seated (with the operator's
  ``suction_cue_in_opening`` false, not for a panel already in the opening that the policy
  lets go of or that comes off the cup more than half-way in: it cannot fall, and acceptance
  judges it; ``info["suction_failed"]`` tells a broken grip from a release);
* ``unstable_suction`` (profiles with ``strain_threshold``) - the cup's load reaches that
  fraction of its holding limit (``WindowInstallEnv.suction_load``, the cup's seal sensor,
  which the demonstrator also watches) while the held panel is more than ``HOVER_ZONE`` in
  front of the wall face: the panel grinds against the rack, the floor or the wall on the
  way. Not in the first ``LATCH_GRACE_STEPS`` after a fresh latch (a cup pressed onto a panel
  is loaded while it seals). The installer lifts it clear (a panel still low, as on the
  rack) and hands back;
* ``wedging`` - at the entry (the leading face within 5 mm of the wall face) or inside the
  opening, tilt or lateral offset past the operator's thresholds while the commanded motion
  is blocked (contact proxy above ``BLOCKED_MIN``) for the operator's ``wedge_steps``
  steps: binding under asymmetric
  contact. A misaligned panel that still moves freely is left to the policy (earlier
  versions also fired on misalignment alone within 2 cm of the wall; that preempted a
  competent policy on most approaches, see CHANGELOG and ``docs/installer-loop.md``);
* ``stall`` - inside the opening, insertion progress stalls while commanded motion is not
  realized, for ``stall_steps`` steps;
* ``reinsertion`` - more than ``max_reinsertions`` entries into the opening;
* ``hover`` (profiles with ``hover_steps``) - the held panel has spent that many steps within
  ``HOVER_ZONE`` in front of the wall face since it last entered the opening: a policy
  circling in front of the opening without going in (the demonstrator spends a median 30,
  at most 80 steps there);
* ``no_progress`` - no new best distance to the goal (the panel while not held, the seat
  while held) for ``patience_steps`` steps;
* ``acquisition`` (profiles with ``acquire_patience_steps``) - the tool within
  ``ACQUIRE_REACH`` of the free panel for that many steps without a latch: a failed or
  unstable pick. The installer picks the panel up and hands back once it is lifted.

After ``reaction_latency_steps`` the installer takes over with its recovery (retract,
re-square, reinsert; or re-acquire and re-stage the panel) and hands back as soon as the
state is back inside the recoverable envelope: the panel held, square and aligned in front of
the opening (the installer's ``insert`` phase). With ``seat_after_insertion_takeover`` a
takeover on an insertion cue (:data:`INSERTION_CUES`) instead runs on to the seat, so its
data shows the whole recovery of what failed. Coverage interventions happen at most once
per episode, with probability ``coverage_rate``: when the panel is held near the opening, the
installer inserts with a deliberately coarse eye (mild misalignment) until it has been
through one contact recovery or reached the seat, exposing recovery behaviour that
autonomous exploration rarely reaches; with the operator's ``coverage_stop_after`` they pause
once that many episodes in a row needed no safety takeover (:meth:`state_dict` carries the
count across a resumed run). Every trigger is recorded in :attr:`events`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from window_bench.envs import scene as S
from window_bench.envs.env import STATE_KEYS
from window_bench.installer.scripted import ScriptedInstaller
from window_bench.installer.operators import (FINE_NOISE_SCALE, FINE_PHASES, OperatorProfile,
                                              OUNoise, get_operator)

#: Sizes of the state observation fields, in ``STATE_KEYS`` order (the flat layout).
STATE_SIZES = {"robot0_joint_pos": 7, "robot0_joint_vel": 7, "robot0_eef_pos": 3,
               "robot0_eef_quat": 4, "robot0_vacuum": 1, "robot0_proprio": 18,
               "window_pos_rel": 3, "window_rot_rel": 3, "contact_proxy": 6}
_OFFSETS = np.cumsum([0] + [STATE_SIZES[k] for k in STATE_KEYS])
FLAT_SLICES = {k: slice(int(_OFFSETS[i]), int(_OFFSETS[i + 1])) for i, k in enumerate(STATE_KEYS)}
FLAT_DIM = int(_OFFSETS[-1])


def fine_pose_features(obs, mm: float, deg: float):
    """The panel's pose relative to the seat at millimetre resolution: ``tanh`` of
    ``window_pos_rel / mm`` (metres / millimetres) and of ``window_rot_rel / deg``, 6 values
    in (-1, 1) per flat observation (a torch tensor ``(..., FLAT_DIM)``). A z-score over whole
    episodes cannot resolve the clearance (on WindowInstall-B the vertical std of
    ``window_pos_rel`` over the demonstrations is 0.24 m: 3 mm is 0.01 standard deviations);
    these saturate away from the seat and are linear within a few ``mm`` of it."""
    import torch

    pos = obs[..., FLAT_SLICES["window_pos_rel"]] / (mm / 1000.0)
    rot = obs[..., FLAT_SLICES["window_rot_rel"]] / float(np.deg2rad(deg))
    return torch.tanh(torch.cat([pos, rot], dim=-1))


def tool_in_panel(obs):
    """The TCP's offset from the panel's centre in the panel's frame (x: across, y:
    vertical, z: the face normal; metres), ``(..., 3)`` per flat observation (a torch tensor
    ``(..., FLAT_DIM)``), computed with the family's seat (every ``WindowInstall`` id seats
    the panel at the same pose). The state carries it only as the difference of two z-scored
    positions (``robot0_eef_pos`` and the seat plus ``window_pos_rel``), each spread over
    tenths of a metre; a grip 3 mm off centre is 0.01 of their standard deviations."""
    import torch

    seat = torch.as_tensor(S.SceneConfig().seated_center, dtype=obs.dtype)
    seat_mat = torch.as_tensor(S.SEATED_PANEL_MAT, dtype=obs.dtype)
    v = obs[..., FLAT_SLICES["window_rot_rel"]]
    angle = v.norm(dim=-1, keepdim=True)
    k = v / angle.clamp_min(1e-9)
    kx, ky, kz = k.unbind(-1)
    zero = torch.zeros_like(kx)
    K = torch.stack([torch.stack([zero, -kz, ky], -1), torch.stack([kz, zero, -kx], -1),
                     torch.stack([-ky, kx, zero], -1)], -2)
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    rel = torch.eye(3, dtype=obs.dtype) + s * K + (1 - c) * (K @ K)   # Rodrigues
    panel_mat = seat_mat @ rel                          # world <- panel body
    panel_pos = seat + obs[..., FLAT_SLICES["window_pos_rel"]]
    tcp = obs[..., FLAT_SLICES["robot0_eef_pos"]]
    return ((tcp - panel_pos)[..., None, :] @ panel_mat)[..., 0, :]


def grasp_features(obs, mm: float):
    """Where the cup holds the panel at millimetre resolution: ``tanh`` of
    :func:`tool_in_panel` in the face plane (across, vertical) over ``mm``, 2 values per flat
    observation; far from the panel (before a pick) both saturate."""
    import torch

    return torch.tanh(tool_in_panel(obs)[..., :2] / (mm / 1000.0))


def tool_features(obs, m: float):
    """Where the tool is relative to the panel at the scale of the reach: ``tanh`` of
    :func:`tool_in_panel` over ``m`` metres, 3 values per flat observation. With the
    absolute positions left out of the input (``observed_keys``), the pick is steered by these
    and the insertion by the panel's pose relative to the seat."""
    import torch

    return torch.tanh(tool_in_panel(obs) / m)


def extra_features(obs, fine_pose_mm: float = 0.0, fine_pose_deg: float = 1.0,
                   grasp_mm: float = 0.0, tool_in_panel_m: float = 0.0) -> list:
    """The features a state-track learner reads beside its z-scored observation, in this
    order, each only when its scale is set (not 0): :func:`fine_pose_features`,
    :func:`grasp_features`, :func:`tool_features` (QC-FQL's and ACT's options of the same
    names)."""
    extra = []
    if fine_pose_mm:
        extra.append(fine_pose_features(obs, fine_pose_mm, fine_pose_deg))
    if grasp_mm:
        extra.append(grasp_features(obs, grasp_mm))
    if tool_in_panel_m:
        extra.append(tool_features(obs, tool_in_panel_m))
    return extra


def check_fine_pose(owner: str, mm, deg) -> None:
    """The fine pose scales a learner's config may hold: ``mm`` in [0, 1000] (0: off),
    ``deg`` in (0, 90]; ``ValueError`` naming ``owner`` (e.g. ``"ACTConfig"``) otherwise."""
    def real(v) -> bool:
        return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
            and bool(np.isfinite(v))

    if not (real(mm) and 0 <= mm <= 1000):
        raise ValueError(f"{owner}.fine_pose_mm = {mm!r} is not allowed: it must lie in "
                         f"[0.0, 1000.0] (0: off)")
    if not (real(deg) and 0 < deg <= 90):
        raise ValueError(f"{owner}.fine_pose_deg = {deg!r} is not allowed: it must lie in "
                         f"(0.0, 90.0]")


#: Learner config fields whose features read the flat state observation (nonzero: on).
STATE_ONLY_FIELDS = ("fine_pose_mm", "grasp_mm", "tool_in_panel_m", "safety_box")


def check_flat_state_fields(config, observation: str) -> None:
    """``ValueError`` (one line) when ``config`` turns on a feature of
    :data:`STATE_ONLY_FIELDS` for a learner that observes ``observation``, not the state."""
    for field in STATE_ONLY_FIELDS:
        value = getattr(config, field, 0)
        if value:
            off = "0" if isinstance(value, (int, float)) else "none"
            raise ValueError(f"{type(config).__name__}.{field} = {value!r} reads the flat state "
                             f"observation; on {observation} it must be {off} (off)")


#: Values each feature kind of :func:`extra_features` adds, keyed by its config field.
EXTRA_INPUTS = {"fine_pose_mm": 6, "grasp_mm": 2, "tool_in_panel_m": 3}


def extra_inputs(config, obs_dim: int) -> int:
    """How many values :func:`extra_features` adds for ``config`` (its ``fine_pose_mm``,
    ``grasp_mm`` and ``tool_in_panel_m``, each 0 when off or absent) to an ``obs_dim``
    observation; ``ValueError`` naming the field when one is on and the observation is not
    the flat state."""
    n = 0
    for field, k in EXTRA_INPUTS.items():
        value = getattr(config, field, 0)
        if not value:
            continue
        if obs_dim != FLAT_DIM:
            raise ValueError(f"{type(config).__name__}.{field} = {value} needs the flat state "
                             f"observation ({FLAT_DIM} values); obs_dim = {obs_dim}")
        n += k
    return n


#: Safety cues, in the order they are checked.
CUES = ("suction_lost", "unstable_suction", "wedging", "stall", "reinsertion", "hover", "acquisition",
        "no_progress")
#: Cues raised while the panel is being inserted (or about to be).
INSERTION_CUES = ("wedging", "stall", "reinsertion", "hover")
HOVER_ZONE = 0.05             # m in front of the wall face: "at the opening, not yet in"
ACQUIRE_REACH = 0.08          # m between the tool and the free panel's centre: "at the pick"
LIFT_CLEAR_Z = 0.43           # m: a strained panel below this is lifted before transport
LATCH_GRACE_STEPS = 15        # steps after a latch in which the cup's load is not a cue

ENTRY_DEPTH = -S.STOP_DEPTH   # seat-relative depth at which the leading face meets the wall
SEATED_DEPTH = -0.002
BLOCKED_MIN = 0.001           # m of commanded-but-unrealized translation = in contact


class TakeoverSource(Protocol):
    def reset(self, env, seed: int | None = None) -> None: ...

    def intervene(self, obs, info: dict) -> tuple[np.ndarray, str] | None: ...


def observation_fields(obs) -> dict[str, np.ndarray]:
    """The state fields of a flat (52,) or dict observation."""
    if isinstance(obs, dict):
        return {k: np.asarray(obs[k], dtype=np.float64) for k in STATE_KEYS}
    obs = np.asarray(obs, dtype=np.float64)
    if obs.shape != (FLAT_DIM,):
        raise ValueError(f"observation of shape {obs.shape}: the supervisor reads the state "
                         f"observation, flat ({FLAT_DIM},) or the Dict of {STATE_KEYS}")
    return {k: obs[s] for k, s in FLAT_SLICES.items()}


class InstallerSupervisor:
    """The scripted installer as the takeover source (module docstring).

    ``operator`` is a profile name from :data:`window_bench.installer.operators.OPERATORS` or an
    :class:`OperatorProfile`. ``safety`` / ``coverage`` switch the two kinds on and off.
    """

    def __init__(self, operator: str | OperatorProfile = "average", *, safety: bool = True,
                 coverage: bool = True):
        self.profile = get_operator(operator)
        self.safety, self.coverage = bool(safety), bool(coverage)
        self.events: list[tuple[int, str, str]] = []   # (step, cue, kind) per takeover
        self.env = None
        # Episodes in a row that needed no safety takeover (``coverage_stop_after``); the
        # episode that just ran is counted at the next reset.
        self.calm_episodes = 0
        self._count_last = False

    # ------------------------------------------------------------------ episode
    def reset(self, env, seed: int | None = None) -> None:
        p = self.profile
        self.calm_episodes = self.state_dict()["calm_episodes"]
        self._count_last = True
        self.env = env.unwrapped
        self.rng = np.random.default_rng([0 if seed is None else seed, 7])
        self.installer = ScriptedInstaller(self.env, p.align_error_mm, p.align_error_deg,
                                           seed=int(self.rng.integers(2**31)),
                                           grasp_settle_steps=p.grasp_settle_steps,
                                           press_at_stop=p.press_at_stop)
        self.noise = OUNoise(6, p.recovery_noise, p.noise_tau_steps, self.rng)
        self.events = []
        self.t = -1
        self.active: str | None = None      # kind of the running takeover
        self.active_cue: str | None = None
        self.pending: tuple[int, str] | None = None   # (start step, cue)
        paused = bool(p.coverage_stop_after) and self.calm_episodes >= p.coverage_stop_after
        # drawn whether or not paused, so that pausing leaves the noise stream as it was
        self.coverage_planned = (self.coverage and self.rng.random() < p.coverage_rate
                                 and not paused)
        self._clear_history()

    def state_dict(self) -> dict:
        """What carries from one episode to the next (a training run saves it between
        episodes and restores it on resume): the count of episodes in a row, the one just
        run included, that needed no safety takeover."""
        if not self._count_last:
            return {"calm_episodes": self.calm_episodes}
        rescued = any(kind == "safety" for _, _, kind in self.events)
        return {"calm_episodes": 0 if rescued else self.calm_episodes + 1}

    def load_state_dict(self, state: dict) -> None:
        n = state.get("calm_episodes") if isinstance(state, dict) else None
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"supervisor state calm_episodes = {n!r}: must be an integer >= 0")
        self.calm_episodes, self._count_last = n, False

    def _clear_history(self) -> None:
        self.depth_hist: list[float] = []
        self.blocked_hist: list[float] = []
        self.in_zone = False
        self.entries = 0
        self.best = np.inf
        self.best_t = self.t
        self.off_axis_steps = 0
        self.vacuum_was_on = None
        self.at_pick_steps = 0
        self.front_steps = 0
        self.since_latch = LATCH_GRACE_STEPS     # a panel held from the start has settled

    # ------------------------------------------------------------------ cues
    def _cue(self, f: dict, info: dict) -> str | None:
        """Update the histories with this observation (and the ``info`` of the step that led
        to it); return the first cue that fires."""
        p = self.profile
        pos_rel = f["window_pos_rel"]
        depth = float(pos_rel @ S.INSERTION_AXIS)
        lateral = float(np.linalg.norm(pos_rel - depth * S.INSERTION_AXIS))
        tilt = float(np.linalg.norm(f["window_rot_rel"]))
        vac = bool(f["robot0_vacuum"][0] > 0.5)
        seated = depth > SEATED_DEPTH and lateral < 0.002
        zone = vac and depth > ENTRY_DEPTH - 0.005

        # A panel already in the opening that the policy lets go of, or that comes off the
        # cup more than half-way in, cannot fall: acceptance judges it. A grip that breaks
        # at the entry or in front of the wall, or a release there, is a cue.
        inside = depth > ENTRY_DEPTH
        deep = depth > ENTRY_DEPTH + S.STOP_DEPTH / 2
        broke = bool(info.get("suction_failed", False))
        judged_by_acceptance = (not p.suction_cue_in_opening
                                and inside and (deep or not broke))
        lost = self.vacuum_was_on is True and not vac and not seated and not judged_by_acceptance
        self.since_latch = (0 if vac and self.vacuum_was_on is False
                            else self.since_latch + 1 if vac else 0)
        self.vacuum_was_on = vac
        if zone and not self.in_zone:
            self.entries += 1
        self.in_zone = zone
        if vac and ENTRY_DEPTH - HOVER_ZONE < depth <= ENTRY_DEPTH:
            self.front_steps += 1
        elif vac and depth > ENTRY_DEPTH:
            self.front_steps = 0
        self.depth_hist.append(depth)
        self.blocked_hist.append(float(np.linalg.norm(f["contact_proxy"][:3])))
        # Wedging is a contact event: misaligned past the operator's thresholds AND the
        # commanded motion blocked, at the entry or inside the opening. A misaligned panel
        # that is still moving freely is the policy's business (it may yet correct).
        off_axis = (zone and not seated and self.blocked_hist[-1] > BLOCKED_MIN
                    and (tilt > np.deg2rad(p.tilt_threshold_deg)
                         or lateral > p.lateral_threshold_mm / 1000.0))
        self.off_axis_steps = self.off_axis_steps + 1 if off_axis else 0
        # Progress toward the goal: the panel while it is not held, the seat while it is.
        if vac:
            dist = float(np.linalg.norm(pos_rel))
            self.at_pick_steps = 0
        else:
            panel = self.env.seated_pose[0] + pos_rel   # the opening's place is known
            reach = float(np.linalg.norm(f["robot0_eef_pos"] - panel))
            dist = 1.0 + reach
            self.at_pick_steps = self.at_pick_steps + 1 if reach < ACQUIRE_REACH else 0
        if dist < self.best - 0.005:
            self.best, self.best_t = dist, self.t

        if lost:
            return "suction_lost"
        if (p.strain_threshold and vac and self.since_latch >= LATCH_GRACE_STEPS
                and depth <= ENTRY_DEPTH - HOVER_ZONE
                and self.env.suction_load() >= p.strain_threshold):
            return "unstable_suction"
        if self.off_axis_steps >= p.wedge_steps:
            return "wedging"
        n = p.stall_steps
        if zone and not seated and len(self.depth_hist) > n:
            progress = self.depth_hist[-1] - self.depth_hist[-1 - n]
            blocked = np.mean(self.blocked_hist[-n:])
            if progress < 0.0005 and blocked > BLOCKED_MIN:
                return "stall"
        if self.entries > p.max_reinsertions:
            return "reinsertion"
        if p.hover_steps and self.front_steps >= p.hover_steps:
            return "hover"
        if p.acquire_patience_steps and self.at_pick_steps >= p.acquire_patience_steps:
            return "acquisition"
        if self.t - self.best_t >= p.patience_steps:
            return "no_progress"
        return None

    def _coverage_moment(self, f: dict) -> bool:
        pos_rel = f["window_pos_rel"]
        depth = float(pos_rel @ S.INSERTION_AXIS)
        lateral = float(np.linalg.norm(pos_rel - depth * S.INSERTION_AXIS))
        return (f["robot0_vacuum"][0] > 0.5 and -0.25 < depth < ENTRY_DEPTH - 0.01
                and lateral < 0.03)

    # ------------------------------------------------------------------ control
    def _start(self, kind: str, cue: str) -> None:
        self.active, self.active_cue = kind, cue
        self.events.append((self.t, cue, kind))
        self.steps_in = 0
        self.start_recoveries = 0
        self.noise.reset()
        if kind == "coverage":
            # Mild misalignment on purpose: twice the operator's eye error, fresh draw.
            e_lin, e_rot = self.installer.align_error
            self.installer.err_pos = np.array([self.rng.choice([-1, 1]) * 2 * e_lin, 0.0,
                                               self.rng.choice([-1, 1]) * 2 * e_lin])
            self.installer.err_rot = self.rng.uniform(-2 * e_rot, 2 * e_rot, 3)
            self.installer.recoveries = 0
            self.installer._set("align")
        else:
            phase = self.installer.take_over()
            self.start_recoveries = self.installer.recoveries
            panel = self.env.panel_pose()[0]
            if cue == "unstable_suction" and phase == "transport" and panel[2] < LIFT_CLEAR_Z:
                self.installer.lift_start = panel.copy()   # clear of what it grinds on first
                self.installer._set("lift")

    def _restored(self) -> bool:
        """Back inside the recoverable envelope (time to hand back)?"""
        inst = self.installer
        if self.steps_in >= self.profile.max_takeover_steps:
            return True
        if self.active == "coverage":
            return inst.phase == "seat" or (inst.phase == "insert" and inst.recoveries > 0)
        if self.active_cue == "acquisition":
            return inst.phase == "transport"    # picked up and lifted clear
        if self.active_cue == "unstable_suction" and inst.phase == "transport":
            return self.steps_in > 1            # lifted clear
        if self.active_cue in INSERTION_CUES and self.profile.seat_after_insertion_takeover:
            return False                        # on to the seat (or max_takeover_steps)
        return inst.phase == "insert" and self.steps_in > 1

    def intervene(self, obs, info: dict) -> tuple[np.ndarray, str] | None:
        if self.env is None:
            raise RuntimeError("call reset(env, seed) before intervene()")
        self.t += 1
        f = observation_fields(obs)
        if self.active is not None:
            if self._restored():
                self.active = None
                self._clear_history()
                self.best_t = self.t
                return None
            return self._installer_action(obs)

        cue = self._cue(f, info) if self.safety else None
        if cue is not None and self.pending is None:
            self.pending = (self.t + self.profile.reaction_latency_steps, cue)
        if self.pending is not None and self.t >= self.pending[0]:
            self._start("safety", self.pending[1])
            self.pending = None
        elif self.coverage_planned and self.pending is None and self._coverage_moment(f):
            self.coverage_planned = False
            self._start("coverage", "coverage")
        else:
            return None
        return self._installer_action(obs)

    def _installer_action(self, obs) -> tuple[np.ndarray, str]:
        self.steps_in += 1
        a = self.installer.act(obs).astype(np.float64)
        steady = self.profile.steady_near_contact and self.installer.phase in FINE_PHASES
        self.meant_action = np.clip(a, -1.0, 1.0).astype(np.float32)   # before the hand's noise
        a[:6] = np.clip(a[:6] + (FINE_NOISE_SCALE if steady else 1.0) * self.noise(), -1.0, 1.0)
        return a.astype(np.float32), self.active
