"""``WindowInstallEnv``: the Gymnasium environment of Experiments A and B (and of the
insertion alone, ``experiment="Insert"``).

One class serves every registered id; the experiment, the panel footprint and the
clearance are constructor arguments (``window_bench/__init__.py`` registers the ids).
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import gymnasium as gym
from gymnasium import spaces

from window_bench.envs import scene as S
from window_bench.envs.controller import OSC, OSCGains, solve_ik
from window_bench.envs.task import FAILURE_CODES, StageTracker, acceptance
from window_bench.gl import renderer

POS_SCALE = 0.025         # m per unit action (Appendix)
ROT_SCALE = 0.0873        # rad per unit action (5 deg)
VACUUM_THRESHOLD = 0.5
MAX_EPISODE_STEPS = 600   # 60 s at 10 Hz
CONTROL_DT = S.TIMESTEP * S.PHYSICS_PER_CONTROL * S.CONTROL_SUBSTEPS  # 0.1 s

# TCP target bounds in the base frame. The paper clips to x in [0, 0.9], y in [-0.4, 0],
# z in [0, 0.44] in its own (unpublished) layout; ours puts the ground region in front of
# the robot and the wall on its right, so y spans the wall (-0.75) to the far side of the
# ground region (+0.45), and z reaches the opening's head (1.0).
WORKSPACE_LOW = np.array([0.0, -0.75, 0.03])
WORKSPACE_HIGH = np.array([0.9, 0.45, 1.0])

# Suction validity (Table 9 snap distance; holding limits of a PowerPick-class cup).
SNAP_DISTANCE = 0.01      # m, cup lip to the suction face
SNAP_MAX_ANGLE_DEG = 15.0 # tool axis vs face normal
VACUUM_HOLD_FORCE = 200.0 # N, pull-off limit along the cup axis
VACUUM_HOLD_MOMENT = 25.0 # N m, peel moment limit
# shear limit = friction_cup x VACUUM_HOLD_FORCE

# Table 9.
RANDOMIZATION_RANGES = {
    "friction_buck": (0.6, 0.9),
    "friction_window": (0.4, 0.7),
    "friction_cup": (0.8, 1.1),
    "solref_timeconst": (0.002, 0.004),
}
A_POS_RANGE = 0.005                  # m per axis
A_ROT_RANGE = np.deg2rad(2.0)        # rad, roll/pitch/yaw
INSERT_STANDOFF = 0.03               # m beyond the pre-insertion pose, along the wall normal
B_X_RANGE = (0.4, 0.6)
B_Y_RANGE = (-0.3, 0.3)
B_YAW_RANGE = np.deg2rad(15.0)

OBS_MODES = ("state", "pixels", "flat")
# ``info["suction_loss_code"]``: index of ``info["suction_loss"]`` here.
SUCTION_LOSS_NAMES = ("", "commanded", "grip_break")
SUCTION_LOSS_CODES = {name: code for code, name in enumerate(SUCTION_LOSS_NAMES)}
STATE_KEYS = ("robot0_joint_pos", "robot0_joint_vel", "robot0_eef_pos", "robot0_eef_quat",
              "robot0_vacuum", "robot0_proprio", "window_pos_rel", "window_rot_rel",
              "contact_proxy")


def _rot(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def rotvec_to_mat(v: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, v / (np.linalg.norm(v) + 1e-12), float(np.linalg.norm(v)))
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q)
    return R.reshape(3, 3)


def mat_to_rotvec(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    v = np.zeros(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return v


class WindowInstallEnv(gym.Env):
    """Seat a window panel into a wall opening lined by a wood buck with 2 mm clearance.

    **Task.** A KUKA LBR iiwa 14 with a vacuum cup moves a rigid panel (0.5 x 0.5 x 0.08 m,
    2.0 kg by default) into the opening until its front face rests against the back stop.
    Experiment A starts with the panel held on a 15-degree staging rack; Experiment B starts
    with the panel flat on the ground and suction off; ``"Insert"`` starts with the panel
    held square in front of the opening at the pre-insertion pose (the insertion alone).

    **Action.** ``Box(-1, 1, (7,))``: TCP position increment (x 0.025 m) and rotation
    increment (rotation vector, x 0.0873 rad), both in the current TCP frame, then vacuum
    (engage iff ``a[6] > 0.5``). Target = measured TCP pose + increment, clipped to
    ``WORKSPACE_LOW/HIGH``, tracked for 0.1 s by a 500 Hz OSC. Finite out-of-range actions
    are clipped to the box; NaN/inf or a wrong shape raise ``ValueError``.

    **Observation.** ``obs_mode="state"`` (default) is a Dict of ``STATE_KEYS``;
    ``"pixels"`` is ``wrist_rgb`` and ``side_rgb`` (128x128x3 uint8) plus ``robot0_proprio``;
    ``"flat"`` is the state Dict concatenated in ``STATE_KEYS`` order (52 floats).

    **Randomizations** (Table 9, independent per episode from the reset seed): buck,
    window/frame and cup friction, contact solref time constant, and the panel pose (A: +-5 mm,
    +-2 deg around the staged pose; B: x in [0.4, 0.6], y in [-0.3, 0.3] m, yaw +-15 deg;
    Insert: +-5 mm across the insertion axis, 0-3 cm further out along it, +-2 deg, the arm
    holding the panel with the cup square on its face).

    **Success conditions.** Reward 1 and termination when the panel centre is within 2 mm of
    the seated target, cos(n_window, n_wall) > 0.95 and the panel speed is below 1 cm/s.
    Truncation at ``max_episode_steps`` (600; 200 for the registered Insert id). Physics
    divergence truncates with ``info["sim_unstable"]``.
    ``info["accepted"]`` says whether the acceptance test passes on this step, and
    ``info["is_success"]`` whether the episode, if it ends on this step, ends with the panel
    accepted (in the default mode both are true exactly on the terminating step).

    **Acceptance without termination.** ``terminate_on_acceptance=False`` (default ``True``)
    keeps the episode running through acceptance: ``terminated`` is never set, the episode
    ends only by truncation, and the reward is ``1.0`` on every step with ``accepted`` true
    (so ``reward == float(info["accepted"])`` in both modes). ``is_success`` equals
    ``accepted``; ``seated`` records that acceptance was reached at some point, and
    ``failure_mode`` labels a panel that is not accepted now as if it had never been
    (``""`` while it is accepted): a panel disturbed after acceptance is typically
    ``unstable_seating``, a released one ``suction_lost``. This mode exists for
    ``window_bench.envs.wrappers.NoisyAcceptance``, which decides reward and termination from a
    noisy acceptance sensor; it sets the attribute ``terminate_on_acceptance`` itself.

    **Info holds numbers.** Every info value is a number or a bool, except ``randomization``
    (a dict, at reset only), so that code which stacks every info key (TorchRL's batched
    ``GymEnv``) works as typed. Outcomes are codes: ``failure_code``
    (``task.FAILURE_MODE_NAMES[code]``, 0 = none), ``suction_loss_code``
    (``SUCTION_LOSS_NAMES[code]``), and ``stage``, the furthest stage event reached
    (``task.STAGES``). ``info_strings=True`` adds their labels for people, ``failure_mode``
    and ``suction_loss``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, experiment: str = "A", panel_width: float = 0.5,
                 panel_height: float = 0.5, clearance: float = 0.002,
                 panel_mass: float | None = None, obs_mode: str = "state",
                 render_mode: str | None = None, image_size: int = 128,
                 max_episode_steps: int = MAX_EPISODE_STEPS,
                 terminate_on_acceptance: bool = True, info_strings: bool = False,
                 compliance_mm: float = 0.0, compliance_deg: float = 0.0):
        for name, v, hi in (("compliance_mm", compliance_mm, 100.0),
                            ("compliance_deg", compliance_deg, 90.0)):
            if (isinstance(v, bool) or not isinstance(v, (int, float, np.floating))
                    or not 0.0 <= float(v) <= hi):
                raise ValueError(f"{name}={v!r} is outside [0, {hi:g}] (0: off)")
        if obs_mode not in OBS_MODES:
            raise ValueError(f"obs_mode={obs_mode!r}; allowed: {OBS_MODES}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r}; allowed: None, 'rgb_array'")
        if not (16 <= int(image_size) <= 512):
            raise ValueError(f"image_size={image_size!r} is outside [16, 512]")
        if not (1 <= int(max_episode_steps)):
            raise ValueError(f"max_episode_steps={max_episode_steps!r} must be >= 1")
        if not isinstance(terminate_on_acceptance, (bool, np.bool_)):
            raise ValueError(f"terminate_on_acceptance={terminate_on_acceptance!r}; allowed: True, False")
        self.terminate_on_acceptance = bool(terminate_on_acceptance)
        if not isinstance(info_strings, (bool, np.bool_)):
            raise ValueError(f"info_strings={info_strings!r}; allowed: True, False")
        self.info_strings = bool(info_strings)
        self.cfg = S.SceneConfig(experiment=experiment, panel_width=panel_width,
                                 panel_height=panel_height, clearance=clearance,
                                 panel_mass=panel_mass)
        self.obs_mode = obs_mode
        self.render_mode = render_mode
        self.image_size = int(image_size)
        self.max_episode_steps = int(max_episode_steps)
        self.scene = S.Scene(self.cfg)
        self.model = self.scene.model
        assert self.model.neq == 1, "suction_wrench assumes the suction weld is the only equality"
        self.data = mujoco.MjData(self.model)
        sc = self.scene
        self._target_pos = self.cfg.seated_center
        self._target_mat = S.SEATED_PANEL_MAT
        self._postures()
        self.osc = OSC(self.model, sc.tcp_site, sc.tool_body,
                       OSCGains(pos_error_clip=float(compliance_mm) / 1000.0,
                                rot_error_clip=float(np.deg2rad(compliance_deg))),
                       q_null=self.q_null)
        self._renderer = None
        self._render_renderer = None
        # Set only by PixelFeatures(observe_every > 1) around a step whose observation no one
        # reads: the views are not rendered (blank) and the physics is untouched.
        self._skip_views = False
        self._lining_mask = np.zeros(self.model.ngeom, bool)
        self._lining_mask[np.concatenate([sc.buck_geoms, sc.stop_geoms, sc.wall_geoms])] = True

        f32 = np.float32
        inf = np.inf
        state = {
            "robot0_joint_pos": spaces.Box(-inf, inf, (7,), f32),
            "robot0_joint_vel": spaces.Box(-inf, inf, (7,), f32),
            "robot0_eef_pos": spaces.Box(-inf, inf, (3,), f32),
            "robot0_eef_quat": spaces.Box(-1.0, 1.0, (4,), f32),
            "robot0_vacuum": spaces.Box(0.0, 1.0, (1,), f32),
            "robot0_proprio": spaces.Box(-inf, inf, (18,), f32),
            "window_pos_rel": spaces.Box(-inf, inf, (3,), f32),
            "window_rot_rel": spaces.Box(-np.pi, np.pi, (3,), f32),
            "contact_proxy": spaces.Box(-inf, inf, (6,), f32),
        }
        if obs_mode == "state":
            self.observation_space = spaces.Dict(state)
        elif obs_mode == "flat":
            n = sum(s.shape[0] for s in state.values())
            self.observation_space = spaces.Box(-inf, inf, (n,), f32)
        else:
            sz = self.image_size
            self.observation_space = spaces.Dict({
                "wrist_rgb": spaces.Box(0, 255, (sz, sz, 3), np.uint8),
                "side_rgb": spaces.Box(0, 255, (sz, sz, 3), np.uint8),
                "robot0_proprio": state["robot0_proprio"],
            })
        self.action_space = spaces.Box(-1.0, 1.0, (7,), f32)
        self._stages = StageTracker(self.cfg.seated_depth)
        self._steps = 0
        self._latched = False
        self._contact_proxy = np.zeros(6)
        self._randomization: dict = {}
        self._sim_unstable = False
        self._suction_lockout = False
        self._suction_failures = 0
        self._suction_releases = 0
        self._needs_reset = True

    # ------------------------------------------------------------------ postures
    def _postures(self) -> None:
        """Reset postures by IK, computed once per geometry."""
        m, site = self.model, self.scene.tcp_site
        # Natural postures (elbow up, wrist untwisted): the IK's nullspace pulls toward a
        # hand-picked rest posture, so that the start, staging and seated postures belong to
        # one family and the wrist never has to wind through its joint limits.
        rest_seat = np.array([-1.1, 0.6, 0.0, -1.3, 0.0, 1.2, 0.0])
        self.q_seat, err = solve_ik(m, site, *self._tcp_for_panel(self._target_pos, self._target_mat),
                                    q_seed=rest_seat, q_rest=rest_seat)
        if err > 1e-4:
            raise RuntimeError(f"seated posture unreachable (IK error {err:.2e}) for {self.cfg}")
        if self.cfg.starts_latched:
            # Seeded from the seated posture: the wrist then unwinds the same way it winds.
            self.q_start, err = solve_ik(m, site, *self._tcp_for_panel(*self._held_start_pose()),
                                         q_seed=self.q_seat, q_rest=self.q_seat)
        else:
            down = np.column_stack([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])  # tool z down
            rest = np.array([0.0, 0.5, 0.0, -1.5, 0.0, 1.1, 0.0])
            self.q_start, err = solve_ik(m, site, np.array([0.45, 0.0, 0.35]), down, q_seed=rest, q_rest=rest)
        # The nullspace PD holds the elbow swivel of the start posture; it acts only in the
        # one-dimensional nullspace of the 6-D task, so it never fights the pose target.
        self.q_null = self.q_start.copy()
        if err > 1e-4:
            raise RuntimeError(f"reset posture unreachable (IK error {err:.2e}) for {self.cfg}")

    def _held_start_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Nominal start pose (centre, rotation matrix) of a panel that starts in the cup: on
        the staging rack (A), or square in front of the opening at the pre-insertion pose
        (Insert)."""
        if self.cfg.experiment == "A":
            return S.rack_panel_pose(self.cfg)
        return self._target_pos + S.WALL_NORMAL * S.PREINSERT_OFFSET, self._target_mat

    def _tcp_for_panel(self, center: np.ndarray, mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nominal grasp: TCP at the suction-face centre, tool z into the face, tool y along
        the panel's height (so a panel lying with its width along +x is picked with the
        wrist untwisted from the home posture)."""
        face = center + mat[:, 2] * self.cfg.panel_thickness / 2
        tool = np.column_stack([-mat[:, 0], mat[:, 1], -mat[:, 2]])
        return face, tool

    # ------------------------------------------------------------------ reset
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        m, d, sc, rng = self.model, self.data, self.scene, self.np_random
        r = {k: float(rng.uniform(*v)) for k, v in RANDOMIZATION_RANGES.items()}
        m.pair_friction[sc.pairs["buck"], :2] = r["friction_buck"]
        m.pair_friction[sc.pairs["buck"], 2] = r["friction_buck"] * 0.005
        m.pair_friction[sc.pairs["window"], :2] = r["friction_window"]
        m.pair_friction[sc.pairs["window"], 2] = r["friction_window"] * 0.005
        m.geom_friction[sc.tool_geoms, 0] = r["friction_cup"]
        m.pair_solref[:, 0] = r["solref_timeconst"]
        m.geom_solref[:, 0] = r["solref_timeconst"]

        mujoco.mj_resetData(m, d)
        d.qpos[:7] = self.q_start
        if self.cfg.starts_latched:
            center, mat = self._held_start_pose()
            if self.cfg.experiment == "A":
                dp = rng.uniform(-A_POS_RANGE, A_POS_RANGE, 3)
            else:   # Insert: x, z as A; y (the wall normal) up to INSERT_STANDOFF further out
                dp = rng.uniform([-A_POS_RANGE, 0.0, -A_POS_RANGE],
                                 [A_POS_RANGE, INSERT_STANDOFF, A_POS_RANGE])
            rpy = rng.uniform(-A_ROT_RANGE, A_ROT_RANGE, 3)
            r.update(panel_dx=dp[0], panel_dy=dp[1], panel_dz=dp[2],
                     panel_roll_deg=np.rad2deg(rpy[0]), panel_pitch_deg=np.rad2deg(rpy[1]),
                     panel_yaw_deg=np.rad2deg(rpy[2]))
            mat = mat @ _rot(0, rpy[0]) @ _rot(1, rpy[1]) @ _rot(2, rpy[2])
            center = center + dp
        else:
            x, y = rng.uniform(*B_X_RANGE), rng.uniform(*B_Y_RANGE)
            yaw = rng.uniform(-B_YAW_RANGE, B_YAW_RANGE)
            r.update(panel_x=x, panel_y=y, panel_yaw_deg=np.rad2deg(yaw))
            mat = _rot(2, yaw)
            center = np.array([x, y, self.cfg.panel_thickness / 2])
        self._randomization = {k: float(v) for k, v in r.items()}
        self._set_panel_pose(center, mat)
        if self.cfg.experiment == "Insert":
            # The arm holds the panel where it starts: the cup square on the face centre.
            q, err = solve_ik(m, sc.tcp_site, *self._tcp_for_panel(center, mat), q_seed=self.q_start)
            if err > 1e-4:
                raise RuntimeError(f"start posture unreachable (IK error {err:.2e}) for "
                                   f"{self._randomization}")
            d.qpos[:7] = q
        mujoco.mj_forward(m, d)
        self._set_latch(self.cfg.starts_latched)
        mujoco.mj_forward(m, d)
        self._steps = 0
        self._stages = StageTracker(self.cfg.seated_depth)
        self._stages.suction_acquired = self._latched  # A, Insert: Pr(S) = 100 % by design
        self._stages.latched = self._latched
        self._contact_proxy[:] = 0
        self._sim_unstable = False
        self._suction_lockout = False
        self._suction_failures = 0
        self._suction_releases = 0
        self._warnings = int(d.warning.number.sum())
        self._needs_reset = False
        self.osc.max_abs_tau[:] = 0
        self.osc.weld_force_mean[:] = 0
        obs = self._observation()
        info = {"randomization": dict(self._randomization), **self._info()}
        if not self.info_strings:
            del info["failure_mode"], info["suction_loss"]
        return obs, info

    def _set_panel_pose(self, center, mat) -> None:
        a = self.scene.panel_qpos_adr
        self.data.qpos[a:a + 3] = center
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(mat).ravel())
        self.data.qpos[a + 3:a + 7] = q
        self.data.qvel[self.scene.panel_dof_adr:self.scene.panel_dof_adr + 6] = 0

    # ------------------------------------------------------------------ suction
    def _set_latch(self, on: bool) -> None:
        """Latch = weld at the current relative pose (no snap); release = weld off."""
        m, d, sc = self.model, self.data, self.scene
        if on:
            t, p = sc.tool_body, sc.panel_body
            R1 = d.xmat[t].reshape(3, 3)
            rel_pos = R1.T @ (d.xpos[p] - d.xpos[t])
            q1inv, rel_q = np.zeros(4), np.zeros(4)
            mujoco.mju_negQuat(q1inv, d.xquat[t])
            mujoco.mju_mulQuat(rel_q, q1inv, d.xquat[p])
            m.eq_data[sc.suction_eq, 0:3] = 0.0
            m.eq_data[sc.suction_eq, 3:6] = rel_pos
            m.eq_data[sc.suction_eq, 6:10] = rel_q
            m.eq_data[sc.suction_eq, 10] = 1.0
        d.eq_active[sc.suction_eq] = on
        # The lip contact would fight the weld: off while latched.
        m.geom_contype[sc.cup_geom] = 0 if on else S.CUP_PANEL_BIT
        self._latched = on

    def tcp_on_face(self) -> np.ndarray:
        """The TCP's offset from the centre of the panel's suction face, in the panel's frame
        (m): across, vertical, and the gap along the face normal."""
        d, sc = self.data, self.scene
        pm = d.xmat[sc.panel_body].reshape(3, 3)
        face_c = d.xpos[sc.panel_body] + pm[:, 2] * self.cfg.panel_thickness / 2
        return pm.T @ (d.site_xpos[sc.tcp_site] - face_c)

    def suction_valid(self) -> bool:
        """Engage rule: cup lip within the snap distance of the suction face, roughly normal
        to it, and over the face (not past its edge)."""
        d, sc = self.data, self.scene
        tool_z = d.site_xmat[sc.tcp_site].reshape(3, 3)[:, 2]
        pm = d.xmat[sc.panel_body].reshape(3, 3)
        local = self.tcp_on_face()
        margin = S.CUP_RADIUS
        over_face = (abs(local[0]) <= self.cfg.panel_width / 2 - margin
                     and abs(local[1]) <= self.cfg.panel_height / 2 - margin)
        gap_ok = -0.005 <= local[2] <= SNAP_DISTANCE
        angle_ok = float(-tool_z @ pm[:, 2]) >= np.cos(np.deg2rad(SNAP_MAX_ANGLE_DEG))
        return bool(over_face and gap_ok and angle_ok)

    def suction_wrench(self) -> tuple[float, float, float]:
        """(pull force along the cup axis, shear force, moment) carried by the suction weld,
        averaged over the last 0.1 s step, in N / N m. Pull > 0: the panel is pulled off the
        cup. A cup's seal fails under a sustained load, not a millisecond impact spike,
        hence the mean rather than the last physics step."""
        if not self._latched:
            return 0.0, 0.0, 0.0
        w = self.osc.weld_force_mean
        f, tau = w[:3], w[3:]
        axis = self.data.site_xmat[self.scene.tcp_site].reshape(3, 3)[:, 2]
        pull = float(f @ axis)
        shear = float(np.linalg.norm(f - pull * axis))
        return pull, shear, float(np.linalg.norm(tau))

    def suction_load(self) -> float:
        """How hard the cup is loaded over the last step, as a fraction of its nearest holding
        limit (pull-off force, shear, peel moment): the reading of a vacuum cup's seal sensor.
        0 when nothing is held; past 1 the grip breaks."""
        if not self._latched:
            return 0.0
        pull, shear, moment = self.suction_wrench()
        mu = self._randomization["friction_cup"]
        return max(pull / VACUUM_HOLD_FORCE, shear / (mu * VACUUM_HOLD_FORCE),
                   moment / VACUUM_HOLD_MOMENT, 0.0)

    # ------------------------------------------------------------------ step
    def _validate(self, action) -> np.ndarray:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (7,):
            raise ValueError(f"action must have shape (7,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = [i for i in range(7) if not np.isfinite(a[i])]
            raise ValueError(f"action has non-finite entries at indices {bad}: {a.tolist()}")
        return np.clip(a, -1.0, 1.0)

    def step(self, action):
        if self._needs_reset:
            raise RuntimeError("call reset() before step() (episode ended or never started)")
        a = self._validate(action)
        m, d, sc = self.model, self.data, self.scene
        p = d.site_xpos[sc.tcp_site].copy()
        R = d.site_xmat[sc.tcp_site].reshape(3, 3).copy()
        dp_world = R @ (a[:3] * POS_SCALE)
        dR = rotvec_to_mat(a[3:6] * ROT_SCALE)
        self.osc.target_pos[:] = np.clip(p + dp_world, WORKSPACE_LOW, WORKSPACE_HIGH)
        self.osc.target_mat[:] = R @ dR
        cmd_pos = self.osc.target_pos - p
        # Grasp-validity check at the 10 Hz step. After the grip broke (holding limit), the
        # cup re-engages only on a fresh command: g must drop to 0 first (re-evacuation), so a
        # lost grip is never silently restored by a vacuum command that stayed on.
        g = a[6] > VACUUM_THRESHOLD
        if not g:
            self._suction_lockout = False
        if g and not self._latched and not self._suction_lockout and self.suction_valid():
            self._set_latch(True)
        released = not g and self._latched
        if released:
            self._set_latch(False)
            self._suction_releases += 1
        qpos0 = d.qpos.copy()
        self.osc.run(d, S.CONTROL_SUBSTEPS,
                     payload_body=sc.panel_body if self._latched else -1,
                     payload_mass=self.cfg.mass)
        self._steps += 1
        unstable = (int(d.warning.number.sum()) > self._warnings
                    or not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel)))
                    or float(np.abs(d.qvel).max()) > 20.0)  # 20 m/s or rad/s: no real motion here
        if unstable:
            self._warnings = int(d.warning.number.sum())
            # Roll back to the pose at the start of the step, at rest: the last observation of
            # the truncated episode is then finite and physical.
            d.qpos[:], d.qvel[:] = qpos0, 0.0
            d.qacc_warmstart[:] = 0
            mujoco.mj_forward(m, d)
            self._sim_unstable = True
        # Holding limits: a failed validity check releases the panel.
        suction_failed = False
        if self._latched and not unstable:
            pull, shear, moment = self.suction_wrench()
            mu = self._randomization["friction_cup"]
            if pull > VACUUM_HOLD_FORCE or shear > mu * VACUUM_HOLD_FORCE or moment > VACUUM_HOLD_MOMENT:
                self._set_latch(False)
                self._suction_lockout = True
                self._suction_failures += 1
                suction_failed = True
        # Contact proxy: realized minus commanded increment, in the TCP frame at step start.
        p1 = d.site_xpos[sc.tcp_site]
        R1 = d.site_xmat[sc.tcp_site].reshape(3, 3)
        realized_pos = p1 - p
        self._contact_proxy[:3] = R.T @ (realized_pos - cmd_pos)
        self._contact_proxy[3:] = mat_to_rotvec(R.T @ R1) - a[3:6] * ROT_SCALE
        acc = self._acceptance()
        q = self._panel_quantities()
        self._stages.update(latched=self._latched, depth=q["depth"], front_depth=q["front_depth"],
                            in_opening=q["in_opening"], buck_contact=self._buck_contact(),
                            commanded=float(np.linalg.norm(cmd_pos)),
                            realized=float(np.linalg.norm(realized_pos)), accepted=acc.accepted,
                            suction_failed=suction_failed)
        accepted = acc.accepted and not unstable
        terminated = accepted and self.terminate_on_acceptance
        truncated = unstable or (not terminated and self._steps >= self.max_episode_steps)
        reward = 1.0 if accepted else 0.0
        info = self._info(acc)
        info["suction_failed"] = suction_failed
        # Why suction was lost on this step: the vacuum commanded off, or the grip broke at
        # the holding limit (pull-off force, shear or peel moment).
        info["suction_loss"] = "grip_break" if suction_failed else "commanded" if released else ""
        info["suction_loss_code"] = SUCTION_LOSS_CODES[info["suction_loss"]]
        # The label this episode gets if it ends now: valid on whichever step a wrapper
        # (e.g. gym.make(..., max_episode_steps=N)) or the env's own horizon ends it.
        if self.terminate_on_acceptance or accepted:
            info["failure_mode"] = self._stages.failure_mode(self._sim_unstable) or ""
        else:
            # Accepted earlier, not now (the episode ran on): label the current state as if
            # acceptance had never been reached.
            unseated = dataclasses.replace(self._stages, seated=False)
            info["failure_mode"] = unseated.failure_mode(self._sim_unstable) or ""
        info["failure_code"] = FAILURE_CODES[info["failure_mode"]]
        info["accepted"] = bool(accepted)
        info["is_success"] = bool(accepted)
        if not self.info_strings:
            del info["failure_mode"], info["suction_loss"]
        if terminated or truncated:
            self._needs_reset = True
        return self._observation(), reward, terminated, truncated, info

    # ------------------------------------------------------------------ quantities
    def _panel_quantities(self) -> dict:
        d, sc, cfg = self.data, self.scene, self.cfg
        c = d.xpos[sc.panel_body]
        depth = float((c - np.array([0, -S.WALL_Y, 0])) @ S.INSERTION_AXIS)
        pm = d.xmat[sc.panel_body].reshape(3, 3)
        # Leading-face depth: the corner of the panel furthest along the insertion axis.
        half = np.array([cfg.panel_width, cfg.panel_height, cfg.panel_thickness]) / 2
        reach = float(np.abs(pm.T @ S.INSERTION_AXIS) @ half)
        ow, oh = cfg.opening
        in_opening = abs(c[0] - S.OPENING_CENTER_X) < ow / 2 and abs(c[2] - S.OPENING_CENTER_Z) < oh / 2
        return {"depth": depth, "front_depth": depth + reach, "in_opening": bool(in_opening)}

    def _buck_contact(self) -> bool:
        """Is the panel touching the buck lining, the bevels, the back stop or the wall?"""
        d = self.data
        if d.ncon == 0:
            return False
        g1 = d.contact.geom1[:d.ncon]
        g2 = d.contact.geom2[:d.ncon]
        pg = self.scene.panel_geom
        lining = self._lining_mask
        return bool(np.any(((g1 == pg) & lining[g2]) | ((g2 == pg) & lining[g1])))

    def _acceptance(self):
        d, sc = self.data, self.scene
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(self.model, d, mujoco.mjtObj.mjOBJ_BODY, sc.panel_body, vel, 0)
        pm = d.xmat[sc.panel_body].reshape(3, 3)
        return acceptance(d.xpos[sc.panel_body], pm[:, 2], vel[3:], self._target_pos, S.WALL_NORMAL)

    def _info(self, acc=None) -> dict:
        acc = acc or self._acceptance()
        st = self._stages
        return {
            "suction_acquired": st.suction_acquired,
            "insertion_entered": st.insertion_entered,
            "seated": st.seated,
            "suction_engaged": self._latched,
            "position_error": acc.position_error,
            "normal_cos": acc.normal_cos,
            "panel_speed": acc.speed,
            "cycle_time_s": self._steps * CONTROL_DT,
            "sim_unstable": self._sim_unstable,
            # The same keys at reset and at every step (Minari requires it).
            "suction_failed": False,
            "suction_failures": self._suction_failures,
            "suction_loss": "",
            "suction_releases": self._suction_releases,
            "failure_mode": "",
            "accepted": False,
            "is_success": False,
            # Numbers for the two labels above and the stage events, for consumers that stack
            # info across envs (vector envs, TensorDicts); see the class docstring.
            "stage": st.stage,
            "suction_loss_code": 0,
            "failure_code": 0,
        }

    def _observation(self):
        d, sc = self.data, self.scene
        q, qd = d.qpos[:7], d.qvel[:7]
        eef = d.site_xpos[sc.tcp_site]
        vac = np.array([1.0 if self._latched else 0.0])
        proprio = np.concatenate([q, qd, eef, vac])
        if self.obs_mode == "pixels":
            wrist, side = self._blank_views() if self._skip_views else self._render_views()
            return {"wrist_rgb": wrist, "side_rgb": side, "robot0_proprio": proprio.astype(np.float32)}
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, d.site_xmat[sc.tcp_site])
        pm = d.xmat[sc.panel_body].reshape(3, 3)
        obs = {
            "robot0_joint_pos": q,
            "robot0_joint_vel": qd,
            "robot0_eef_pos": eef,
            "robot0_eef_quat": quat,
            "robot0_vacuum": vac,
            "robot0_proprio": proprio,
            "window_pos_rel": d.xpos[sc.panel_body] - self._target_pos,
            "window_rot_rel": mat_to_rotvec(self._target_mat.T @ pm),
            "contact_proxy": self._contact_proxy,
        }
        if self.obs_mode == "flat":
            return np.concatenate([obs[k] for k in STATE_KEYS]).astype(np.float32)
        return {k: np.asarray(v, dtype=np.float32).copy() for k, v in obs.items()}

    # ------------------------------------------------------------------ rendering
    def _render_views(self):
        if self._renderer is None:
            self._renderer = renderer(self.model, self.image_size, self.image_size)
        out = []
        for cam in ("robot0_wrist", "side"):
            self._renderer.update_scene(self.data, camera=cam)
            out.append(self._renderer.render().copy())
        return out

    def _blank_views(self):
        blank = np.zeros((self.image_size, self.image_size, 3), np.uint8)
        return blank, blank

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._render_renderer is None:
            self._render_renderer = renderer(self.model, 480, 640)
        self._render_renderer.update_scene(self.data, camera="overview")
        return self._render_renderer.render().copy()

    def close(self):
        for r in (self._renderer, self._render_renderer):
            if r is not None:
                r.close()
        self._renderer = self._render_renderer = None

    # ------------------------------------------------------------------ pickling
    def __getstate__(self) -> dict:
        """Everything but the renderers (GL contexts, rebuilt on first use). MjModel and
        MjData pickle whole, the randomized model values and the solver's warm start
        included, so a copy taken mid-episode continues bit-identically."""
        state = self.__dict__.copy()
        state["_renderer"] = state["_render_renderer"] = None
        return state

    # ------------------------------------------------------------------ privileged access
    def panel_pose(self) -> tuple[np.ndarray, np.ndarray]:
        d, sc = self.data, self.scene
        return d.xpos[sc.panel_body].copy(), d.xmat[sc.panel_body].reshape(3, 3).copy()

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        d, sc = self.data, self.scene
        return d.site_xpos[sc.tcp_site].copy(), d.site_xmat[sc.tcp_site].reshape(3, 3).copy()

    def holding_torque(self) -> np.ndarray:
        """Joint torques that hold the current posture against gravity, including the panel
        while it is held (the static part of what the OSC commands), N m."""
        m, d, sc = self.model, self.data, self.scene
        tau = d.qfrc_bias[:7].copy()   # gravity (+ small Coriolis terms when moving)
        if self._latched:
            jacp = np.zeros((3, m.nv))
            mujoco.mj_jac(m, d, jacp, None, d.xipos[sc.panel_body], sc.tool_body)
            tau += jacp[:, :7].T @ (self.cfg.mass * -m.opt.gravity)
        return tau

    @property
    def suction_engaged(self) -> bool:
        return self._latched

    @property
    def seated_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self._target_pos.copy(), self._target_mat.copy()
