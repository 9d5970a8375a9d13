"""The 500 Hz operational-space controller (OSC) that tracks each 10 Hz pose target.

Per substep: task-space spring-damper on the TCP pose scaled by the operational-space
inertia, gravity/Coriolis compensation (``qfrc_bias``), payload compensation for the held
panel while suction is latched, a nullspace joint PD toward a comfortable posture, a
joint-velocity limiter for the 1.92 rad/s limit of Table 10, and the torque limits.

robosuite's OSC does the same algebra in numpy per substep and ran 12 env steps/s here.
The algebra lives in one numba-compiled function; the Python side only makes the MuJoCo
calls that fill the Jacobian and mass matrix, so the controller costs a fraction of the
physics (``benchmarks/env_speed.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numba
import numpy as np

from window_bench.envs.scene import MAX_JOINT_VELOCITY, PHYSICS_PER_CONTROL, TORQUE_LIMITS


@dataclass(frozen=True)
class OSCGains:
    """Task-space gains in acceleration units (1/s^2, 1/s); critically damped by default."""

    kp_pos: float = 1600.0
    kp_rot: float = 1600.0
    damping_ratio: float = 1.0
    kp_null: float = 10.0
    kd_null: float = 40.0             # 1/s: damps internal (self-motion) of the redundant arm
    vel_limit_margin: float = 0.85    # governor and brakes act up to this fraction of 1.92 rad/s
    vel_limit_gain: float = 60.0      # 1/s, per unit joint inertia
    # Compliance (0 = off): the spring's pose error is clipped to this norm, so the force the
    # arm pushes with against an obstacle is bounded (HIL-SERL's impedance controller clips
    # its translational error at 1.6-7.5 mm, ram_insertion/config.py COMPLIANCE_PARAM).
    pos_error_clip: float = 0.0       # m
    rot_error_clip: float = 0.0       # rad

    def as_array(self) -> np.ndarray:
        return np.array([
            self.kp_pos, 2 * self.damping_ratio * np.sqrt(self.kp_pos),
            self.kp_rot, 2 * self.damping_ratio * np.sqrt(self.kp_rot),
            self.kp_null, self.kd_null,
            self.vel_limit_margin * MAX_JOINT_VELOCITY, self.vel_limit_gain,
            self.pos_error_clip, self.rot_error_clip,
        ])


# Small dense products written out: numba's `@` goes through SciPy's BLAS (a dependency we
# avoid), and for 7 x 7 matrices plain loops are as fast.
@numba.njit(cache=True)
def _mm(a, b):
    n, k = a.shape
    m = b.shape[1]
    out = np.zeros((n, m))
    for i in range(n):
        for j in range(m):
            s = 0.0
            for t in range(k):
                s += a[i, t] * b[t, j]
            out[i, j] = s
    return out


@numba.njit(cache=True)
def _mv(a, x):
    n, k = a.shape
    out = np.zeros(n)
    for i in range(n):
        s = 0.0
        for t in range(k):
            s += a[i, t] * x[t]
        out[i] = s
    return out


@numba.njit(cache=True)
def _cholesky(a):
    n = a.shape[0]
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                L[i, i] = np.sqrt(max(s, 1e-12))
            else:
                L[i, j] = s / L[j, j]
    return L


@numba.njit(cache=True)
def _chol_solve(L, b):
    """Solve (L L^T) x = b for a matrix right-hand side b."""
    n, k = b.shape
    x = b.copy()
    for c in range(k):
        for i in range(n):
            s = x[i, c]
            for j in range(i):
                s -= L[i, j] * x[j, c]
            x[i, c] = s / L[i, i]
        for i in range(n - 1, -1, -1):
            s = x[i, c]
            for j in range(i + 1, n):
                s -= L[j, i] * x[j, c]
            x[i, c] = s / L[i, i]
    return x


@numba.njit(cache=True)
def osc_torque(jacp, jacr, M, bias, q, qd, pos, mat, target_pos, target_mat,
               q_null, payload_jac, payload_force, gains, torque_limit, out, max_abs_out):
    """Joint torques for the first 7 dofs. All arrays are float64; writes into ``out`` and
    keeps the running maximum of |torque| per joint in ``max_abs_out``."""
    n = 7
    J = np.empty((6, n))
    for i in range(3):
        for j in range(n):
            J[i, j] = jacp[i, j]
            J[3 + i, j] = jacr[i, j]
    Mr = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            Mr[i, j] = M[i, j]
    kp, kd, kpr, kdr, kpn, kdn, vlim, vgain = (gains[0], gains[1], gains[2], gains[3],
                                               gains[4], gains[5], gains[6], gains[7])
    # Task-space error: position, and orientation as 0.5 * sum(x_i x x_i*) (small-angle).
    err = np.zeros(6)
    for i in range(3):
        err[i] = target_pos[i] - pos[i]
    for c in range(3):
        a0, a1, a2 = mat[0, c], mat[1, c], mat[2, c]
        b0, b1, b2 = target_mat[0, c], target_mat[1, c], target_mat[2, c]
        err[3] += 0.5 * (a1 * b2 - a2 * b1)
        err[4] += 0.5 * (a2 * b0 - a0 * b2)
        err[5] += 0.5 * (a0 * b1 - a1 * b0)
    vel = _mv(J, qd[:n].copy())
    # Velocity governor: as the fastest joint approaches the limit, fade out the task-space
    # spring (keep its damping), so the arm stops accelerating instead of relying on joint
    # brakes that the wrist's 12 N m cannot supply.
    ratio = 0.0
    for i in range(n):
        ratio = max(ratio, abs(qd[i]) / vlim)
    s = min(max((1.0 - ratio) / 0.3, 0.0), 1.0)  # 1 below 70 % of vlim, 0 at vlim
    # Saturate the spring's error so that the approach speed is capped (kp e_max / kd):
    # 0.4 m/s and 1.0 rad/s, enough to realize most of a 25 mm / 5 deg increment in 0.1 s.
    lin_norm = np.sqrt(err[0] ** 2 + err[1] ** 2 + err[2] ** 2)
    rot_norm = np.sqrt(err[3] ** 2 + err[4] ** 2 + err[5] ** 2)
    lin_cap = 0.4 * kd / kp
    rot_cap = 1.0 * kdr / kpr
    if gains[8] > 0.0:      # compliance: a tighter clip of the spring's error
        lin_cap = min(lin_cap, gains[8])
    if gains[9] > 0.0:
        rot_cap = min(rot_cap, gains[9])
    lin_s = 1.0 if lin_norm <= lin_cap else lin_cap / lin_norm
    rot_s = 1.0 if rot_norm <= rot_cap else rot_cap / rot_norm
    acc = np.empty(6)
    for i in range(3):
        acc[i] = s * kp * lin_s * err[i] - kd * vel[i]
        acc[3 + i] = s * kpr * rot_s * err[3 + i] - kdr * vel[3 + i]
    L = _cholesky(Mr)
    MinvJT = _chol_solve(L, J.T.copy())           # 7 x 6
    JMJ = _mm(J, MinvJT)                           # 6 x 6
    for i in range(6):
        JMJ[i, i] += 1e-6
    Lam_L = _cholesky(JMJ)
    Lam = _chol_solve(Lam_L, np.eye(6))            # operational-space inertia
    F = _mv(Lam, acc)
    tau = _mv(J.T.copy(), F)
    # Nullspace PD in acceleration units, projected with the dynamically consistent N.
    qacc_null = np.empty(n)
    for i in range(n):
        qacc_null[i] = kpn * (q_null[i] - q[i]) - kdn * qd[i]
    t_null = _mv(Mr, qacc_null)
    Jbar = _mm(MinvJT, Lam)                        # 7 x 6
    t_null = t_null - _mv(J.T.copy(), _mv(Jbar.T.copy(), t_null))
    # Everything but the task term, with the velocity brakes.
    rest = np.empty(n)
    for i in range(n):
        t = t_null[i] + bias[i]
        for k in range(3):
            t += payload_jac[k, i] * payload_force[k]
        # Velocity limiter: strong viscous braking above the margin (no native limit in MuJoCo).
        over = abs(qd[i]) - vlim
        if over > 0:
            t -= np.sign(qd[i]) * over * vgain * Mr[i, i] * 10.0
        rest[i] = t
    # Scale the task torque uniformly so that no joint saturates: a saturated joint would
    # break the operational-space decoupling and excite the arm's self-motion.
    scale = 1.0
    for i in range(n):
        if tau[i] > 1e-9:
            scale = min(scale, (torque_limit[i] - rest[i]) / tau[i])
        elif tau[i] < -1e-9:
            scale = min(scale, (-torque_limit[i] - rest[i]) / tau[i])
    scale = max(scale, 0.0)
    for i in range(n):
        t = scale * tau[i] + rest[i]
        out[i] = min(max(t, -torque_limit[i]), torque_limit[i])
        max_abs_out[i] = max(max_abs_out[i], abs(out[i]))


class OSC:
    """Holds the scratch buffers and runs the substep loop for one env step."""

    def __init__(self, model: mujoco.MjModel, tcp_site: int, tool_body: int,
                 gains: OSCGains = OSCGains(), q_null: np.ndarray | None = None):
        self.model = model
        self.tcp_site = tcp_site
        self.tool_body = tool_body
        nv = model.nv
        self.jacp = np.zeros((3, nv))
        self.jacr = np.zeros((3, nv))
        self.M = np.zeros((nv, nv))
        self.payload_jacp = np.zeros((3, nv))
        self.payload_force = np.zeros(3)
        self.tau = np.zeros(7)
        self.gains = gains.as_array()
        self.torque_limit = TORQUE_LIMITS.copy()
        self.q_null = np.zeros(7) if q_null is None else np.asarray(q_null, float).copy()
        self.target_pos = np.zeros(3)
        self.target_mat = np.eye(3)
        self.max_abs_tau = np.zeros(7)
        self.weld_force_mean = np.zeros(6)   # suction weld force/torque, mean over the step

    def run(self, data: mujoco.MjData, n_substeps: int, payload_body: int = -1,
            payload_mass: float = 0.0, hold: int = PHYSICS_PER_CONTROL) -> None:
        """Advance ``n_substeps`` controller updates, each held for ``hold`` physics steps."""
        m = self.model
        site = self.tcp_site
        gravity = -m.opt.gravity
        jacp, jacr, M, tau = self.jacp, self.jacr, self.M, self.tau
        pj, pf = self.payload_jacp, self.payload_force
        if payload_body < 0:
            pj[:] = 0.0
            pf[:] = 0.0
        else:
            pf[:] = payload_mass * gravity
        # Views into MjData's buffers are made once: they stay valid across steps.
        pos, mat = data.site_xpos[site], data.site_xmat[site].reshape(3, 3)
        bias, qpos, qvel, ctrl = data.qfrc_bias, data.qpos, data.qvel, data.ctrl
        com = data.xipos[payload_body] if payload_body >= 0 else None
        step1, step2, step, jac_site, full_m = (mujoco.mj_step1, mujoco.mj_step2, mujoco.mj_step,
                                                mujoco.mj_jacSite, mujoco.mj_fullM)
        args = (self.target_pos, self.target_mat, self.q_null, pj, pf, self.gains,
                self.torque_limit, ctrl, self.max_abs_tau)
        weld = self.weld_force_mean
        weld[:] = 0.0
        n_weld = 0
        for k in range(n_substeps):
            step1(m, data)
            jac_site(m, data, jacp, jacr, site)
            full_m(m, data, M)
            if com is not None:
                mujoco.mj_jac(m, data, pj, None, com, self.tool_body)
            osc_torque(jacp, jacr, M, bias, qpos, qvel, pos, mat, *args)
            step2(m, data)
            if hold > 1:  # zero-order hold of the torque for the remaining physics steps
                step(m, data, hold - 1)
            if com is not None and k % 5 == 4 and data.ne >= 6:
                # Every 5th update (10 samples a step, every 10 ms): the suction weld is the
                # model's only equality, its 6 rows come first; re-read the array, the efc
                # arrays resize every step.
                weld += data.efc_force[:6]
                n_weld += 1
        if n_weld:
            weld /= n_weld
        tau[:] = ctrl


def solve_ik(model: mujoco.MjModel, site: int, target_pos: np.ndarray, target_mat: np.ndarray,
             q_seed: np.ndarray, iters: int = 500, tol: float = 1e-6,
             q_rest: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Damped least-squares IK for the 7 arm joints; returns (q, final pose error norm).

    ``q_rest``: the arm is redundant; the nullspace of the task pulls toward this posture
    so that the solution is the natural one (elbow up, wrist untwisted), not a twisted
    branch. Used offline (reset postures), never inside the control loop.
    """
    data = mujoco.MjData(model)
    q = np.array(q_seed, float)
    lo, hi = model.jnt_range[:7, 0], model.jnt_range[:7, 1]
    jacp = np.zeros((3, model.nv))
    jacr = np.zeros((3, model.nv))
    err = np.zeros(6)
    quat_t = np.zeros(4)
    mujoco.mju_mat2Quat(quat_t, np.ascontiguousarray(target_mat).ravel())
    quat, quat_c, neg = np.zeros(4), np.zeros(4), np.zeros(4)
    for _ in range(iters):
        data.qpos[:7] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        err[:3] = target_pos - data.site_xpos[site]
        mujoco.mju_mat2Quat(quat, data.site_xmat[site])
        mujoco.mju_negQuat(neg, quat)
        mujoco.mju_mulQuat(quat_c, quat_t, neg)
        mujoco.mju_quat2Vel(err[3:], quat_c, 1.0)
        if np.linalg.norm(err) < tol and q_rest is None:
            break
        mujoco.mj_jacSite(model, data, jacp, jacr, site)
        J = np.vstack([jacp[:, :7], jacr[:, :7]])
        Jpinv = J.T @ np.linalg.inv(J @ J.T + 1e-4 * np.eye(6))
        dq = Jpinv @ err
        if q_rest is not None:
            dq += (np.eye(7) - Jpinv @ J) @ (0.1 * (q_rest - q))
        q = np.clip(q + np.clip(dq, -0.2, 0.2), lo, hi)
    return q, float(np.linalg.norm(err))
