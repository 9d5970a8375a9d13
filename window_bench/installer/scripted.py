"""Reference controllers that act through the normalized 7-D action interface.

* ``ScriptedInstaller`` - the privileged expert that stands in for the installer: it reads
  simulator state (panel pose, the in-hand grasp transform) but acts only through
  ``env.step(action)``, so its logs are valid demonstrations. Phases: acquire (B), lift,
  transport (neither when the panel starts held in front of the opening), align, insert
  compliantly, detect stalls (wedging, jamming) and recover with retract-pivot-reinsert,
  seat and settle.
* ``StraightPush`` - the naive controller: it transports like the installer, aligns the
  panel once to its estimate of the seat (the same imperfect eye as the installer's), then
  pushes straight along the tool axis and never looks again: no stall detection, no
  recovery.
* ``RandomPolicy`` - uniform random actions.

All three have ``reset()`` and ``act(obs) -> np.ndarray`` of shape (7,).
"""

from __future__ import annotations

import numpy as np

from window_bench.envs import scene as S
from window_bench.envs.env import (POS_SCALE, ROT_SCALE, VACUUM_HOLD_MOMENT, WindowInstallEnv, mat_to_rotvec,
                  rotvec_to_mat)

ENGAGE, RELEASE = 1.0, -1.0


def pose_action(tcp_pos, tcp_mat, des_pos, des_mat, *, max_lin=1.0, max_rot=1.0,
                vacuum=ENGAGE) -> np.ndarray:
    """Action that moves the TCP toward a desired pose, increments capped per step.

    The cap keeps the direction: a vector longer than the cap is scaled, not clipped
    per axis, so straight-line motion stays straight."""
    lin = tcp_mat.T @ (np.asarray(des_pos) - tcp_pos) / POS_SCALE
    rot = mat_to_rotvec(tcp_mat.T @ des_mat) / ROT_SCALE
    for v, cap in ((lin, max_lin), (rot, max_rot)):
        n = np.abs(v).max()
        if n > cap:
            v *= cap / n
    return np.concatenate([lin, rot, [vacuum]]).astype(np.float32)


class _PanelPoseMixin:
    """Converts a desired panel pose into the TCP pose that realizes it."""

    env: WindowInstallEnv

    def _tcp_for_panel_pose(self, grasp, panel_pos, panel_mat):
        rel_pos, rel_mat = grasp          # TCP pose in the panel frame
        return panel_pos + panel_mat @ rel_pos, panel_mat @ rel_mat

    def _measured_grasp(self):
        p_pos, p_mat = self.env.panel_pose()
        t_pos, t_mat = self.env.tcp_pose()
        return p_mat.T @ (t_pos - p_pos), p_mat.T @ t_mat


class ScriptedInstaller(_PanelPoseMixin):
    """Privileged expert installer (see module docstring)."""

    # Distances in metres along the wall normal (toward the robot) from the seated pose.
    STAGING_OFFSET = 0.30
    PREINSERT_OFFSET = S.PREINSERT_OFFSET    # leading face 2 cm in front of the wall face
    NEAR_PREINSERT = 0.05       # a panel held this close to the pre-insertion pose starts at align
    ALIGN_POS_TOL = 0.0003
    ALIGN_ROT_TOL = np.deg2rad(0.1)
    INSERT_SPEED = 0.004        # m per step
    SLOW_SPEED = 0.0015         # m per step at the entry and just before the stop
    STALL_WINDOW = 3
    STALL_PROGRESS = 0.25       # realized / commanded depth progress below this = stall
    RETRACT = 0.012
    MAX_RECOVERIES = 8
    BIND_MOMENT = 0.3           # cup moment / holding limit that backs a bound panel off
    PRESS_ZONE = 0.008          # ``press_at_stop``: this close to the stop the installer presses
    PRESS_MOMENT = 0.9          # ... and backs off only at this fraction of the holding limit

    def __init__(self, env, align_error_mm: float = 1.0, align_error_deg: float = 0.5,
                 seed: int | None = None, grasp_settle_steps: int = 0,
                 coarse_align_error_mm: float = 0.0, coarse_align_error_deg: float = 0.0,
                 pick_error_mm: float = 0.0, press_at_stop: bool = False):
        """``align_error_*``: half-widths of a per-episode uniform error in the installer's
        estimate of where the seat is (lateral per axis, and rotation about each axis) - the
        accuracy of one visual alignment. Contact stalls reveal it: each recovery
        re-measures and shrinks it 4-fold. ``align_error_mm=0, align_error_deg=0`` gives a
        perfect eye. ``grasp_settle_steps`` (B): after the cup latches, hold still with the
        vacuum on for this many steps before lifting (0: lift at once).
        ``coarse_align_error_*``: half-widths of the error of the installer's first, by-eye
        placement in front of the opening; once the panel is there it takes a close look
        (the error drops to the ``align_error_*`` draw) and corrects before inserting, so the
        demonstration shows the correction. 0 and 0: one alignment with the close look.
        ``pick_error_mm`` (B): half-width of a per-episode uniform offset, along each edge of
        the face, of where the cup lands on the panel (0: the face's centre); the transport
        and insertion measure the grip, so a demonstration carries the panel, not the tool,
        to the seat whatever the offset. ``press_at_stop``: within ``PRESS_ZONE`` of the stop,
        a panel whose leading edge meets the stop first (tilted by the eye's error) is
        pressed flat against it, not backed off: no stall check there, and the binding
        check waits for ``PRESS_MOMENT`` of the cup's holding limit (``BIND_MOMENT``
        elsewhere). False: it backs off, re-measures and reinserts."""
        if not 0 <= pick_error_mm <= 20:
            raise ValueError(f"pick_error_mm = {pick_error_mm!r} is outside [0, 20]")
        if min(align_error_mm, align_error_deg, coarse_align_error_mm, coarse_align_error_deg) < 0:
            raise ValueError(f"alignment errors must be >= 0, got {align_error_mm} mm, {align_error_deg} deg, "
                             f"coarse {coarse_align_error_mm} mm, {coarse_align_error_deg} deg")
        if isinstance(grasp_settle_steps, bool) or not 0 <= grasp_settle_steps <= 50:
            raise ValueError(f"grasp_settle_steps = {grasp_settle_steps!r} is outside [0, 50]")
        self.grasp_settle_steps = int(grasp_settle_steps)
        self.env = env.unwrapped
        self.align_error = (align_error_mm / 1000.0, np.deg2rad(align_error_deg))
        self.coarse_align_error = (coarse_align_error_mm / 1000.0, np.deg2rad(coarse_align_error_deg))
        self.pick_error = pick_error_mm / 1000.0
        self.press_at_stop = bool(press_at_stop)
        self.rng = np.random.default_rng(seed)
        self.reset()

    def _draw_error(self, e_lin: float, e_rot: float) -> tuple[np.ndarray, np.ndarray]:
        pos = np.array([self.rng.uniform(-e_lin, e_lin), 0.0, self.rng.uniform(-e_lin, e_lin)])
        return pos, self.rng.uniform(-e_rot, e_rot, 3)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.err_pos, self.err_rot = self._draw_error(*self.align_error)
        # The by-eye placement's error, drawn after the close look's so that a profile
        # without one keeps its demonstrations.
        self.coarse = any(self.coarse_align_error)
        self.coarse_pos, self.coarse_rot = (self._draw_error(*self.coarse_align_error)
                                            if self.coarse else (np.zeros(3), np.zeros(3)))
        # Drawn last, and only when set, so that other profiles keep their demonstrations.
        self.pick_offset = (np.array([*self.rng.uniform(-self.pick_error, self.pick_error, 2), 0.0])
                            if self.pick_error else np.zeros(3))
        self.phase = None
        self.depth_hist: list[float] = []
        self.recoveries = 0
        self.phase_steps = 0
        self.events: list[tuple[int, str]] = []
        self.t = 0

    # -------------------------------------------------------------- helpers
    def _set(self, phase: str) -> None:
        if phase != self.phase:
            self.events.append((self.t, phase))
        self.phase = phase
        self.phase_steps = 0

    def _seated(self):
        """Where the installer believes the seat is (the true seat plus its estimate error)."""
        target, tmat = self.env.seated_pose
        if self.coarse:
            return target + self.coarse_pos, rotvec_to_mat(self.coarse_rot) @ tmat
        return target + self.err_pos, rotvec_to_mat(self.err_rot) @ tmat

    def _remeasure(self) -> None:
        self.err_pos *= 0.25
        self.err_rot *= 0.25

    def _depth(self) -> float:
        p, _ = self.env.panel_pose()
        target, _ = self._seated()
        return float((p - target) @ S.INSERTION_AXIS)   # 0 at the seat, < 0 outside

    def _near_preinsert(self) -> bool:
        """Is the held panel in front of the opening, within ``NEAR_PREINSERT`` of the
        pre-insertion pose (as the insertion alone starts)? Then there is nothing to lift or
        transport."""
        p, _ = self.env.panel_pose()
        target, _ = self._seated()
        offset = p - target - S.WALL_NORMAL * self.PREINSERT_OFFSET
        out = float(offset @ S.WALL_NORMAL)
        return -0.001 < out < self.NEAR_PREINSERT and np.linalg.norm(offset) < self.NEAR_PREINSERT

    def _panel_goal_action(self, panel_pos, panel_mat, *, max_lin=1.0, max_rot=1.0):
        tcp_pos, tcp_mat = self.env.tcp_pose()
        des = self._tcp_for_panel_pose(self._measured_grasp(), panel_pos, panel_mat)
        return pose_action(tcp_pos, tcp_mat, *des, max_lin=max_lin, max_rot=max_rot)

    def _panel_error(self, panel_pos, panel_mat):
        p, R = self.env.panel_pose()
        return float(np.linalg.norm(p - panel_pos)), float(np.linalg.norm(mat_to_rotvec(R.T @ panel_mat)))

    # -------------------------------------------------------------- takeovers
    def take_over(self) -> str:
        """Pick up mid-episode from whatever state another actor left; returns the phase.

        Suction off: re-acquire (approach). Panel held near or in the opening: recovery
        (retract along the axis, re-square, then reinsert). Panel held low (on the ground or
        the rack): lift. Otherwise: transport to the staging pose.
        """
        self.depth_hist = []
        self.recoveries = 0
        if not self.env.suction_engaged:
            self._set("approach")
            return self.phase
        depth = self._depth()
        if depth > -(self.PREINSERT_OFFSET + 0.03):
            self.recoveries = 1
            self._remeasure()   # a close look at the opening before re-squaring
            self.retract_to = min(depth - self.RETRACT, -self.PREINSERT_OFFSET)
            self._set("recover")
        elif self.env.panel_pose()[0][2] < 0.25:
            self.lift_start = self.env.panel_pose()[0].copy()
            self._set("lift")
        else:
            self._set("transport")
        return self.phase

    # -------------------------------------------------------------- policy
    def act(self, obs=None) -> np.ndarray:
        if self.phase is None:
            if not self.env.suction_engaged:
                self._set("approach")
            else:
                self._set("align" if self._near_preinsert() else "lift")
            self.lift_start = self.env.panel_pose()[0].copy()
        a = getattr(self, f"_{self.phase}")()
        self.t += 1
        self.phase_steps += 1
        return a

    def _pick_pose(self, p, R):
        """Where the TCP goes to pick the free panel: the face's centre plus the episode's
        pick offset, tool normal to the face."""
        face, tool = self.env._tcp_for_panel(p, R)
        return face + R @ self.pick_offset, tool

    def _approach(self):
        """B: hover 8 cm above the suction face, tool normal to it."""
        p, R = self.env.panel_pose()
        tcp_pos, tcp_mat = self.env.tcp_pose()
        face, tool = self._pick_pose(p, R)
        hover = face + R[:, 2] * 0.08
        if np.linalg.norm(tcp_pos - hover) < 0.004 and np.linalg.norm(mat_to_rotvec(tcp_mat.T @ tool)) < 0.02:
            self._set("descend")
        return pose_action(tcp_pos, tcp_mat, hover, tool, vacuum=RELEASE)

    def _descend(self):
        p, R = self.env.panel_pose()
        tcp_pos, tcp_mat = self.env.tcp_pose()
        face, tool = self._pick_pose(p, R)
        goal = face + R[:, 2] * 0.002
        close = float((tcp_pos - face) @ R[:, 2]) < 0.006
        if self.env.suction_engaged:
            self._set("settle_grasp" if self.grasp_settle_steps else "lift")
            self.lift_start = p.copy()
        return pose_action(tcp_pos, tcp_mat, goal, tool, max_lin=0.4,
                           vacuum=ENGAGE if close else RELEASE)

    def _settle_grasp(self):
        """B: latched - hold still with the vacuum on before lifting, so the pick in the
        demonstrations is descend, engage, wait, lift rather than a one-step switch."""
        if self.phase_steps >= self.grasp_settle_steps:   # counted from the latch step
            self._set("lift")
            self.lift_start = self.env.panel_pose()[0].copy()
        return np.array([0, 0, 0, 0, 0, 0, ENGAGE], dtype=np.float32)

    def _lift(self):
        """Clear the ground or the rack: straight up (and off the rack's backrest)."""
        p, R = self.env.panel_pose()
        goal = self.lift_start + np.array([0, 0, 0.45 - self.lift_start[2]])
        if self.env.cfg.experiment == "A":
            goal = goal + np.array([-0.10, 0, 0])
        if np.linalg.norm(p - goal) < 0.02 or self.phase_steps > 40:
            self._set("transport")
        return self._panel_goal_action(goal, R, max_rot=0.0)

    def _transport(self):
        """Reorient well clear of the wall, then bring the panel square to the staging pose."""
        target, tmat = self._seated()
        goal = target + S.WALL_NORMAL * self.STAGING_OFFSET
        _, e_rot = self._panel_error(goal, tmat)
        if e_rot > np.deg2rad(3.0):
            # A tilted 0.5 m panel sweeps ~0.25 sin(tilt) toward the wall: reorient higher up
            # (moving it toward the robot instead would fold the elbow onto its J4 limit).
            goal = goal + np.array([0.0, 0.0, 0.12])
        e_pos, e_rot = self._panel_error(goal, tmat)
        if e_pos < 0.01 and e_rot < np.deg2rad(1.0):
            self._set("align")
        return self._panel_goal_action(goal, tmat, max_lin=1.0, max_rot=1.0)

    def _align(self):
        target, tmat = self._seated()
        goal = target + S.WALL_NORMAL * self.PREINSERT_OFFSET
        e_pos, e_rot = self._panel_error(goal, tmat)
        if (e_pos < self.ALIGN_POS_TOL * 3 and e_rot < self.ALIGN_ROT_TOL) or self.phase_steps > 60:
            if self.coarse:   # placed by eye: now the close look, and align again
                self.coarse = False
                self._set("look")
                return self._look()
            self._set("insert")
            self.depth_hist = []
        return self._panel_goal_action(goal, tmat, max_lin=0.6, max_rot=0.3)

    def _look(self):
        """After the by-eye placement: the same alignment, to the close look's estimate."""
        return self._align()

    def _insert(self):
        target, tmat = self._seated()
        depth = self._depth()
        self.depth_hist.append(depth)
        if depth > -0.0015:
            self._set("seat")
            return self._seat()   # with its binding check, from the first seating step
        # Binding felt through the grip (the installer's hands feel the panel twist in the
        # cup): back off before the seal peels.
        pull, shear, moment = self.env.suction_wrench()
        pressing = self.press_at_stop and depth >= -self.PRESS_ZONE
        bind = self.PRESS_MOMENT if pressing else self.BIND_MOMENT
        if moment > bind * VACUUM_HOLD_MOMENT and self.recoveries < self.MAX_RECOVERIES:
            return self._start_recovery(depth)
        # Stall: progress over the last few steps well below what was commanded.
        if len(self.depth_hist) > self.STALL_WINDOW and not pressing:
            progress = self.depth_hist[-1] - self.depth_hist[-1 - self.STALL_WINDOW]
            if progress < self.STALL_PROGRESS * self.SLOW_SPEED * self.STALL_WINDOW:
                if self.recoveries < self.MAX_RECOVERIES:
                    return self._start_recovery(depth)
        # Slow down where contact starts: the leading face crossing the bevelled entry, and
        # the last few millimetres before the back stop (impacts there peel the cup).
        entry = -S.STOP_DEPTH   # depth (seat-relative) at which the leading face meets the wall
        slow = abs(depth - entry) < 0.01 or depth > -0.008
        speed = self.SLOW_SPEED if slow else self.INSERT_SPEED
        goal = target + S.INSERTION_AXIS * min(depth + speed, 0.0)
        if depth > -0.01:
            # Near the stop, let the panel square itself against it: no attitude command,
            # so the OSC target follows the contact instead of twisting the panel in the cup.
            return self._panel_goal_action(goal, self.env.panel_pose()[1], max_lin=0.5, max_rot=0.0)
        return self._panel_goal_action(goal, tmat, max_lin=0.5, max_rot=0.2)

    def _start_recovery(self, depth: float):
        self.recoveries += 1
        self.retract_to = depth - self.RETRACT
        self._remeasure()
        self._set("recover")
        return self._recover()

    def _recover(self):
        """Retract along the axis holding the panel's current attitude (pulling or twisting a
        bound panel would peel the cup off), then re-square it (pivot), then reinsert."""
        target, tmat = self._seated()
        depth = self._depth()
        if depth > self.retract_to + 0.001 and self.phase_steps <= 15:
            p, R = self.env.panel_pose()
            goal = p + S.INSERTION_AXIS * (self.retract_to - depth)
            return self._panel_goal_action(goal, R, max_lin=0.16, max_rot=0.0)
        goal = target + S.INSERTION_AXIS * self.retract_to
        e_pos, e_rot = self._panel_error(goal, tmat)
        if (e_pos < 0.001 and e_rot < self.ALIGN_ROT_TOL * 2) or self.phase_steps > 40:
            self._set("insert")
            self.depth_hist = []
        return self._panel_goal_action(goal, tmat, max_lin=0.3, max_rot=0.2)

    def _seat_action(self):
        target, _ = self._seated()
        # Aim 1 mm past the seat so the front face stays against the stop, then hold; the
        # attitude is left to the stop (compliant seating).
        goal = target + S.INSERTION_AXIS * 0.001
        return self._panel_goal_action(goal, self.env.panel_pose()[1], max_lin=0.2, max_rot=0.0)

    def _seat(self):
        """Hold the panel against the stop until the env accepts the seating; if it does not
        settle into acceptance (off-centre, tilted), back off and re-seat."""
        moment = self.env.suction_wrench()[2]
        if ((self.phase_steps > 15 or moment > self.BIND_MOMENT * VACUUM_HOLD_MOMENT)
                and self.recoveries < self.MAX_RECOVERIES):
            return self._start_recovery(self._depth())
        return self._seat_action()


class StraightPush(_PanelPoseMixin):
    """Naive baseline: align to the nominal target once, push straight, no recovery.

    It acquires and transports like the installer, then aligns the panel, 12 cm in front of
    the seat, with its estimate of the seat: the seat plus a per-episode uniform error of up
    to ``align_error_mm`` laterally and ``align_error_deg`` about each axis (the installer's
    eye; the same draw for the same seed). From then on it pushes along the tool axis with
    constant increments and never looks again. The OSC target is re-based on the measured
    pose every step, so contact deflections are kept, never corrected: there is no stall
    detection and no retract-pivot-reinsert.
    """

    PUSH = 0.2   # x 0.025 m = 5 mm per step along the tool axis

    def __init__(self, env, align_error_mm: float = 1.0, align_error_deg: float = 0.5,
                 seed: int | None = None):
        if align_error_mm < 0 or align_error_deg < 0:
            raise ValueError(f"alignment errors must be >= 0, got {align_error_mm} mm, {align_error_deg} deg")
        self.env = env.unwrapped
        self.align_error = (align_error_mm / 1000.0, np.deg2rad(align_error_deg))
        self.rng = np.random.default_rng(seed)
        self._transport = ScriptedInstaller(env, 0.0, 0.0)
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self._transport.reset()
        self.phase = None
        self.align_steps = 0
        # The same imperfect eye as the installer's (same draw for the same seed), but used
        # once: the push that follows never looks again.
        e_lin, e_rot = self.align_error
        target, tmat = self.env.seated_pose
        lateral = np.array([self.rng.uniform(-e_lin, e_lin), 0.0, self.rng.uniform(-e_lin, e_lin)])
        self.goal = target + S.WALL_NORMAL * ScriptedInstaller.PREINSERT_OFFSET + lateral
        self.goal_mat = rotvec_to_mat(self.rng.uniform(-e_rot, e_rot, 3)) @ tmat

    def act(self, obs=None) -> np.ndarray:
        if self.phase is None:
            self.phase = "transport"
        if self.phase == "transport":
            if self._transport.phase == "align":
                self.phase = "align"
            else:
                return self._transport.act()
        if self.phase == "align":
            self.align_steps += 1
            p, R = self.env.panel_pose()
            if ((np.linalg.norm(p - self.goal) < 0.0005
                    and np.linalg.norm(mat_to_rotvec(R.T @ self.goal_mat)) < np.deg2rad(0.15))
                    or self.align_steps > 40):
                self.phase = "push"
            else:
                tcp_pos, tcp_mat = self.env.tcp_pose()
                des = self._tcp_for_panel_pose(self._measured_grasp(), self.goal, self.goal_mat)
                return pose_action(tcp_pos, tcp_mat, *des, max_lin=0.6, max_rot=0.3)
        return np.array([0, 0, self.PUSH, 0, 0, 0, ENGAGE], dtype=np.float32)


class RandomPolicy:
    def __init__(self, env, seed: int | None = None):
        self.rng = np.random.default_rng(seed)
        self.space = env.action_space

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def act(self, obs=None) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, 7).astype(np.float32)


CONTROLLERS = {"installer": ScriptedInstaller, "straight_push": StraightPush, "random": RandomPolicy}
