"""Physics and interface unit tests: action validation, clipping, suction rules, the Table 9
randomizations having a physical effect, torque margins and the joint-velocity limit."""

import mujoco
import numpy as np
import pytest

from conftest import drive_tcp, tcp_action
from window_bench.envs import scene as S

A, B = "WindowInstall-A-v0", "WindowInstall-B-v0"
HOLD = np.array([0, 0, 0, 0, 0, 0, 1.0], np.float32)   # zero motion, vacuum on
IDLE = np.zeros(7, np.float32)                           # zero motion, vacuum off


def _state(env):
    d = env.unwrapped.data
    return d.qpos.copy(), d.qvel.copy(), float(d.time)


# ----------------------------------------------------------------------------- actions
@pytest.mark.parametrize("bad, words", [
    (np.array([np.nan, 0, 0, 0, 0, 0, 0]), ("non-finite", "[0]")),
    (np.array([0, 0, 0, np.inf, 0, 0, 0]), ("non-finite", "[3]")),
    (np.array([0, 0, 0, 0, 0, 0, -np.inf]), ("non-finite", "[6]")),
    (np.zeros(6), ("shape", "(6,)")),
    (np.zeros((1, 7)), ("shape", "(1, 7)")),
    (np.zeros(8), ("shape", "(8,)")),
])
def test_invalid_action_raises_and_env_stays_usable(bad, words, make_env):
    env = make_env(A)
    env.reset(seed=0)
    env.step(HOLD)
    before = _state(env)
    with pytest.raises(ValueError) as exc:
        env.unwrapped.step(bad)
    msg = str(exc.value)
    for w in words:
        assert w in msg, msg
    # The rejected action did not advance or perturb the simulation.
    after = _state(env)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
    assert before[2] == after[2]
    obs, r, term, trunc, info = env.step(HOLD)
    assert np.all(np.isfinite(obs["robot0_joint_pos"]))
    assert env.unwrapped.data.time > before[2]
    assert not trunc and not info["sim_unstable"]


def test_step_before_reset_raises(make_env):
    env = make_env(B).unwrapped
    with pytest.raises(RuntimeError, match="reset"):
        env.step(IDLE)


@pytest.mark.parametrize("big, unit", [
    ([5, 0, 0, 0, 0, 0, 5], [1, 0, 0, 0, 0, 0, 1]),
    ([0, -5, 3, 0, 0, 0, 0], [0, -1, 1, 0, 0, 0, 0]),
    ([0, 0, 0, 7, -2, 1e6, 0], [0, 0, 0, 1, -1, 1, 0]),
])
def test_out_of_range_actions_are_clipped(big, unit, make_env):
    e1, e2, e3 = make_env(A), make_env(A), make_env(A)
    for e in (e1, e2, e3):
        e.reset(seed=11)
    for _ in range(3):
        o1, *_ = e1.unwrapped.step(np.array(big, float))
        o2, *_ = e2.unwrapped.step(np.array(unit, float))
        o3, *_ = e3.unwrapped.step(0.5 * np.array(unit, float))
    s1, s2, s3 = _state(e1), _state(e2), _state(e3)
    np.testing.assert_array_equal(s1[0], s2[0])
    np.testing.assert_array_equal(s1[1], s2[1])
    for k in o1:
        np.testing.assert_array_equal(o1[k], o2[k])
    # The comparison is discriminating: half the action gives a different state.
    assert np.abs(s3[0][:7] - s2[0][:7]).max() > 1e-4


# ----------------------------------------------------------------------------- suction
def _face(env):
    c, R = env.unwrapped.panel_pose()
    return c + R[:, 2] * env.unwrapped.cfg.panel_thickness / 2


@pytest.mark.parametrize("seed", [0, 3])
def test_suction_engage_latch_release_on_B(seed, make_env):
    env = make_env(B)
    u = env.unwrapped
    obs, info = env.reset(seed=seed)
    assert not u.suction_engaged and obs["robot0_vacuum"][0] == 0.0
    # Tool z points down at the B reset.
    np.testing.assert_allclose(u.tcp_pose()[1][:, 2], [0, 0, -1], atol=1e-4)
    panel0 = u.panel_pose()
    face = _face(env)

    # (a) g=1 far from the panel does not engage.
    assert np.linalg.norm(u.tcp_pose()[0] - face) > 0.2
    obs, *_, info = env.step(HOLD)
    assert not u.suction_engaged and obs["robot0_vacuum"][0] == 0.0
    assert not info["suction_engaged"] and not info["suction_acquired"]

    # Above the face, outside the 1 cm snap distance: still no engagement.
    drive_tcp(env, face + [0, 0, 0.05])
    drive_tcp(env, face + [0, 0, 0.02])
    gap = (u.tcp_pose()[0] - face)[2]
    assert 0.015 < gap < 0.025
    obs, *_ = env.step(tcp_action(env, face + [0, 0, 0.02], g=1.0))
    assert not u.suction_engaged and obs["robot0_vacuum"][0] == 0.0

    # (b) down onto the face: within 1 cm, g=1 engages.
    drive_tcp(env, face + [0, 0, 0.005])
    gap = (u.tcp_pose()[0] - face)[2]
    assert 0.0 < gap <= 0.01
    before = u.panel_pose()
    obs, *_, info = env.step(tcp_action(env, face + [0, 0, 0.005], g=1.0))
    assert u.suction_engaged and obs["robot0_vacuum"][0] == 1.0
    assert info["suction_engaged"] and info["suction_acquired"]
    # (d) latching does not snap the panel to the cup.
    after = u.panel_pose()
    assert np.linalg.norm(after[0] - before[0]) < 1e-3
    assert np.abs(after[1] - before[1]).max() < 1e-3
    # The panel never moved while the robot approached it.
    assert np.linalg.norm(after[0] - panel0[0]) < 1e-3

    # Latched: lifting the tool lifts the panel.
    lift_target = u.tcp_pose()[0] + [0, 0, 0.08]
    *_, info = drive_tcp(env, lift_target, g=1.0, max_steps=8)
    lifted = u.panel_pose()[0]
    assert lifted[2] - panel0[0][2] > 0.06
    assert u.suction_engaged and not info["suction_failed"]

    # (c) g=0 releases: vacuum off in obs, the panel falls back to the floor.
    obs, *_, info = env.step(IDLE)
    assert not u.suction_engaged and obs["robot0_vacuum"][0] == 0.0
    assert info["suction_acquired"] and not info["suction_engaged"]
    for _ in range(6):
        env.step(IDLE)
    assert u.panel_pose()[0][2] < u.cfg.panel_thickness / 2 + 2e-3


def test_suction_latched_at_reset_on_A_and_release(make_env):
    env = make_env(A)
    u = env.unwrapped
    obs, info = env.reset(seed=2)
    assert u.suction_engaged and obs["robot0_vacuum"][0] == 1.0
    p0 = u.panel_pose()[0]
    for _ in range(3):
        obs, *_ = env.step(HOLD)
    assert u.suction_engaged
    assert np.linalg.norm(u.panel_pose()[0] - p0) < 2e-3   # held, not dropped
    obs, *_ = env.step(IDLE)
    assert not u.suction_engaged and obs["robot0_vacuum"][0] == 0.0
    # Released, the panel drops onto the rack ledge (RACK_GAP below it) and leaves the cup.
    assert u.panel_pose()[0][2] < p0[2] - 0.01
    # Back the cup 25 mm off along the tool axis: out of the snap distance, g = 1 must not
    # re-engage.
    obs, *_ = env.step(np.array([0, 0, -1.0, 0, 0, 0, -1.0], dtype=np.float32))
    obs, *_ = env.step(HOLD)
    assert not u.suction_engaged


# ----------------------------------------------------------------------------- friction
def _panel_slide(env, seed, direction, tan_theta=0.55, steps=5):
    """Tilt gravity so the panel on the floor sees a tangential load of tan_theta x normal
    load along ``direction``; return (sampled friction_window, horizontal slide in m)."""
    u = env.unwrapped
    _, info = env.reset(seed=seed)
    g0 = u.model.opt.gravity.copy()
    th = np.arctan(tan_theta)
    try:
        u.model.opt.gravity[:] = 9.81 * np.array([np.sin(th) * direction[0],
                                                  np.sin(th) * direction[1], -np.cos(th)])
        p0 = u.panel_pose()[0]
        for _ in range(steps):
            env.step(IDLE)
        p1 = u.panel_pose()[0]
    finally:
        u.model.opt.gravity[:] = g0
    return info["randomization"]["friction_window"], float(np.linalg.norm((p1 - p0)[:2]))


def _seed_with(env, key, pred):
    for s in range(500):
        _, info = env.reset(seed=s)
        if pred(info["randomization"][key]):
            return s
    raise AssertionError(f"no seed with the requested {key}")


def test_friction_values_reach_the_model(make_env):
    env = make_env(A)
    u = env.unwrapped
    m, sc = u.model, u.scene
    for seed in (0, 1, 2):
        _, info = env.reset(seed=seed)
        r = info["randomization"]
        for group, key in (("buck", "friction_buck"), ("window", "friction_window")):
            # Both tangential directions carry the sampled coefficient (condim 3).
            np.testing.assert_array_equal(m.pair_friction[sc.pairs[group], 0], r[key])
            np.testing.assert_array_equal(m.pair_friction[sc.pairs[group], 1], r[key])
            assert np.all(m.pair_dim[sc.pairs[group]] == 3)
        np.testing.assert_array_equal(m.geom_friction[sc.tool_geoms, 0], r["friction_cup"])
        # The cup's friction wins the mix with every geom it touches.
        assert np.all(m.geom_priority[sc.tool_geoms] > m.geom_priority[sc.panel_geom])
    # Every floor/wall/stop/(rack) pair belongs to the window group, the lining to the buck group.
    def partners(rows):
        out = set()
        for i in rows:
            g1, g2 = m.pair_geom1[i], m.pair_geom2[i]
            assert sc.panel_geom in (g1, g2)
            out.add(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g2 if g1 == sc.panel_geom else g1))
        return out

    assert partners(sc.pairs["buck"]) == set(S.BUCK_GEOMS)
    assert partners(sc.pairs["window"]) == set(S.STOP_GEOMS) | set(S.WALL_GEOMS) | {"floor"} | set(S.RACK_GEOMS)


@pytest.mark.parametrize("direction", [(1, 0), (0, 1), (-1, 0), (0.6, -0.8)])
def test_window_friction_decides_sliding(direction, make_env):
    """Panel on the floor under gravity tilted to tan(theta)=0.55: a low sampled friction_window
    (<= 0.45) slides, a high one (>= 0.65) sticks, in every horizontal direction."""
    env = make_env(B)
    lo = _seed_with(env, "friction_window", lambda v: v <= 0.45)
    hi = _seed_with(env, "friction_window", lambda v: v >= 0.65)
    mu_lo, slide_lo = _panel_slide(env, lo, direction)
    mu_hi, slide_hi = _panel_slide(env, hi, direction)
    assert mu_lo <= 0.45 and mu_hi >= 0.65
    assert slide_lo > 0.03, f"low friction {mu_lo:.3f}: slid only {slide_lo * 1e3:.1f} mm"
    assert slide_hi < 1e-3, f"high friction {mu_hi:.3f}: slid {slide_hi * 1e3:.1f} mm"


# ----------------------------------------------------------------------------- solref
def _resting_penetration(env, timeconst, seed=3, steps=5):
    u = env.unwrapped
    env.reset(seed=seed)
    u.model.pair_solref[:, 0] = timeconst
    for _ in range(steps):
        *_, info = env.step(IDLE)
    assert not info["sim_unstable"]
    d = u.data
    dist = [d.contact[i].dist for i in range(d.ncon) if u.scene.panel_geom in d.contact[i].geom]
    assert dist, "panel lost contact with the floor"
    return -min(dist)


def test_solref_timeconst_changes_penetration(make_env):
    env = make_env(B)
    m = env.unwrapped.model
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_REFSAFE
    assert m.opt.timestep == pytest.approx(S.TIMESTEP)
    stiff = _resting_penetration(env, 0.002)
    soft = _resting_penetration(env, 0.004)
    assert stiff > 0 and soft > 0
    # Penetration scales roughly with timeconst^2: a factor ~4 between the Table 9 bounds.
    assert 2.0 < soft / stiff < 8.0, (stiff, soft)


def test_refsafe_clamp_is_off(make_env):
    """A time constant below 2 x timestep is used as given, not clamped to 2 x timestep."""
    env = make_env(B)
    m = env.unwrapped.model
    below = 1.5 * S.TIMESTEP
    at = 2.0 * S.TIMESTEP
    p_below = _resting_penetration(env, below)
    p_at = _resting_penetration(env, at)
    assert p_below < 0.8 * p_at, (p_below, p_at)
    # Control: with MuJoCo's refsafe clamp enabled the two would be identical.
    flags = m.opt.disableflags
    try:
        m.opt.disableflags = flags & ~int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
        assert _resting_penetration(env, below) == pytest.approx(_resting_penetration(env, at), rel=1e-9)
    finally:
        m.opt.disableflags = flags


# ----------------------------------------------------------------------------- torque margin
def _torque_profile(env_id, make_env, seed=0):
    """Hold the panel 20 zero-action steps, then a short, slow motion toward the wall."""
    env = make_env(env_id)
    u = env.unwrapped
    env.reset(seed=seed)
    assert u.osc.max_abs_tau.max() == 0.0
    for _ in range(20):
        env.step(HOLD)
    hold = u.osc.max_abs_tau.copy()
    y0 = u.tcp_pose()[0][1]
    for _ in range(10):
        p, R = u.tcp_pose()
        a = HOLD.copy()
        a[:3] = np.clip(R.T @ np.array([0.0, -0.1, 0.0]), -1, 1)   # 2.5 mm/step toward the wall
        env.step(a)
    assert u.suction_engaged
    assert u.tcp_pose()[0][1] < y0 - 0.015   # it moved toward the wall
    return hold, u.osc.max_abs_tau.copy()


def test_torque_margin_wrist_J5_J7(make_env):
    hold, total = _torque_profile(A, make_env)
    lim = S.TORQUE_LIMITS
    assert np.all(hold[4:] <= 0.7 * lim[4:]), hold[4:] / lim[4:]
    assert np.all(total[4:] <= 0.7 * lim[4:]), total[4:] / lim[4:]
    assert total.max() > 0


def test_torque_margin_shoulder_J1_J4(make_env):
    hold, total = _torque_profile(A, make_env)
    lim = S.TORQUE_LIMITS
    assert np.all(hold[:4] <= 0.7 * lim[:4]), hold[:4] / lim[:4]
    assert np.all(total[:4] <= 0.7 * lim[:4]), total[:4] / lim[:4]


# ----------------------------------------------------------------------------- joint velocity
def _random_play(env, seed, n=100, vacuum=None):
    """100 uniform random actions; returns (max |qd| at every 500 Hz controller update,
    max |qd| in the observations)."""
    u = env.unwrapped
    orig = u.osc.run
    peak = [0.0]

    def run(data, n_substeps, **kw):
        for _ in range(n_substeps):
            orig(data, 1, **kw)
            peak[0] = max(peak[0], float(np.abs(data.qvel[:7]).max()))

    u.osc.run = run
    try:
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        obs_peak = 0.0
        for _ in range(n):
            a = rng.uniform(-1, 1, 7).astype(np.float32)
            if vacuum is not None:
                a[6] = vacuum
            obs, _, term, trunc, info = env.step(a)
            assert not info["sim_unstable"]
            obs_peak = max(obs_peak, float(np.abs(obs["robot0_joint_vel"]).max()))
            if term or trunc:
                env.reset(seed=seed + 1000)
    finally:
        u.osc.run = orig
    return peak[0], obs_peak


VEL_LIMIT = S.MAX_JOINT_VELOCITY * 1.05


@pytest.mark.parametrize("env_id", [A, B])
def test_joint_velocity_limit_at_observations(env_id, make_env):
    _, obs_peak = _random_play(make_env(env_id), seed=0)
    assert 0.2 < obs_peak <= VEL_LIMIT


def test_joint_velocity_limit_within_steps_B(make_env):
    peak, _ = _random_play(make_env(B), seed=0)
    assert peak <= VEL_LIMIT


def test_joint_velocity_limit_within_steps_A(make_env):
    # Vacuum held on: a released panel lets the cup strike it, and an impact impulse can
    # momentarily exceed any controller limit (as on a real arm). The controller itself
    # (task-error saturation, torque scaling, velocity governor) keeps every 500 Hz sample
    # under the limit.
    peak, _ = _random_play(make_env(A), seed=0, vacuum=1.0)
    assert peak <= VEL_LIMIT


def test_broken_grip_needs_a_fresh_vacuum_command(make_env, monkeypatch):
    # Lower the pull-off limit below the panel's weight: lifting breaks the grip at once.
    import window_bench.envs.env as E
    env = make_env(A)
    u = env.unwrapped
    env.reset(seed=0)
    monkeypatch.setattr(E, "VACUUM_HOLD_FORCE", 1.0)
    monkeypatch.setattr(E, "VACUUM_HOLD_MOMENT", 0.01)
    obs, r, term, trunc, info = env.step(HOLD)
    assert info["suction_failed"] and not u.suction_engaged and info["suction_failures"] == 1
    monkeypatch.setattr(E, "VACUUM_HOLD_FORCE", 200.0)
    monkeypatch.setattr(E, "VACUUM_HOLD_MOMENT", 25.0)
    # Vacuum still commanded, cup still on the face: no silent re-latch.
    for _ in range(2):
        obs, *_ = env.step(HOLD)
        assert not u.suction_engaged and obs["robot0_vacuum"][0] == 0.0
    # A fresh command (g = 0, then 1) re-engages if the face is still within the snap distance.
    env.step(IDLE)
    if u.suction_valid():
        env.step(HOLD)
        assert u.suction_engaged


def test_physics_divergence_truncates_instead_of_crashing(make_env):
    env = make_env(B, info_strings=True)
    u = env.unwrapped
    env.reset(seed=0)
    # Kick the panel to an absurd speed: the step must end the episode as truncated with
    # sim_unstable, roll the state back to the last good one, and return finite values.
    a = u.scene.panel_dof_adr
    u.data.qvel[a:a + 3] = [1e4, -1e4, 1e4]
    obs, reward, terminated, truncated, info = env.step(IDLE)
    assert truncated and not terminated and reward == 0.0
    assert info["sim_unstable"] and info["failure_mode"] == "sim_unstable"
    assert all(np.all(np.isfinite(v)) for v in obs.values())
    assert np.all(np.isfinite(u.data.qpos)) and np.abs(u.data.qvel).max() < 20
    # The env stays usable: a reset starts a clean episode.
    obs, info = env.reset(seed=1)
    obs, reward, terminated, truncated, info = env.step(IDLE)
    assert not truncated and not info["sim_unstable"]
