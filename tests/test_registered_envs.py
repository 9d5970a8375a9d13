"""Suite-wide checks over every registered id (``window_bench.ENV_IDS``).

API conformance with the three ecosystems the benchmark targets (Gymnasium, Stable-Baselines3,
TorchRL), seeded determinism, the Table 9 reset distribution and the observation layouts.
"""

import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch

import window_bench
from window_bench.envs import scene as S
from window_bench.envs.env import STATE_KEYS

torch.set_num_threads(1)

IDS = window_bench.ENV_IDS
A_IDS = [i for i in IDS if "-A" in i]
B_IDS = [i for i in IDS if "-B" in i]

# Gymnasium's checker warns about +-inf observation bounds; those are by design here.
_BENIGN = ("observation space minimum value is -infinity",
           "observation space maximum value is infinity")


def _rot(axis, angle):
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


# ----------------------------------------------------------------------------- registry
def _episode_steps(env_id):
    return 200 if env_id.startswith("WindowInstall-Insert") else 600


def test_ids_registered():
    assert len(IDS) == 10
    assert set(IDS) == {f"WindowInstall-{e}{s}-v0" for e in "AB"
                        for s in ("", "-Panel40x40", "-Panel60x60", "-Panel60x40")} \
        | {"WindowInstall-Insert-v0", "WindowInstall-Insert-Compliant-v0"}
    for env_id in IDS:
        assert env_id in gym.registry
        assert gym.spec(env_id).max_episode_steps == _episode_steps(env_id)


@pytest.mark.parametrize("env_id", IDS)
def test_model_data_types_and_panel_size(env_id, make_env):
    env = make_env(env_id)
    u = env.unwrapped
    assert isinstance(u.model, mujoco.MjModel)
    assert isinstance(u.data, mujoco.MjData)
    assert env.spec.max_episode_steps == u.max_episode_steps == _episode_steps(env_id)
    # The id's footprint reaches the compiled model (geom half-sizes) and the opening.
    w, h = gym.spec(env_id).kwargs["panel_width"], gym.spec(env_id).kwargs["panel_height"]
    assert np.allclose(u.model.geom_size[u.scene.panel_geom], [w / 2, h / 2, S.PANEL_THICKNESS / 2])
    assert u.cfg.experiment == env_id.split("-")[1]
    ow, oh = u.cfg.opening
    assert ow - w == pytest.approx(0.004) and oh - h == pytest.approx(0.004)


# ----------------------------------------------------------------------------- checkers
@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_check_env(env_id, make_env):
    from gymnasium.utils.env_checker import check_env

    env = make_env(env_id)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)  # includes the rgb_array render check (headless EGL)
    bad = [str(w.message) for w in caught if not any(b in str(w.message) for b in _BENIGN)]
    assert not bad, bad


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("obs_mode", ["state", "flat"])
def test_sb3_check_env(env_id, obs_mode, make_env):
    from stable_baselines3.common.env_checker import check_env

    env = make_env(env_id, obs_mode=obs_mode)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, warn=True)
    bad = [str(w.message) for w in caught if not any(b in str(w.message) for b in _BENIGN)]
    assert not bad, bad


@pytest.mark.parametrize("env_id", IDS)
def test_torchrl_check_env_specs(env_id):
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv(env_id)
    try:
        assert set(STATE_KEYS) <= set(env.observation_spec.keys())
        check_env_specs(env, seed=0)
        td = env.rollout(3)
        assert td["next", "robot0_proprio"].shape == (3, 18)
        assert td["action"].shape == (3, 7)
    finally:
        env.close()


def test_torchrl_module_prefixed_id():
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    env = GymEnv("window_bench:WindowInstall-B-v0")
    try:
        check_env_specs(env, seed=1)
    finally:
        env.close()


# ----------------------------------------------------------------------------- determinism
def _rollout(env, seed, actions):
    obs, info = env.reset(seed=seed)
    traj = [(obs, 0.0, False, False, info)]
    for a in actions:
        traj.append(env.step(a))
    return traj


def _assert_bit_identical(t1, t2):
    assert len(t1) == len(t2)
    for (o1, r1, te1, tr1, i1), (o2, r2, te2, tr2, i2) in zip(t1, t2):
        assert o1.keys() == o2.keys()
        for k in o1:
            assert o1[k].dtype == o2[k].dtype
            assert o1[k].tobytes() == o2[k].tobytes(), k   # bit for bit
        assert r1 == r2 and te1 == te2 and tr1 == tr2
        assert i1 == i2


@pytest.mark.parametrize("env_id", IDS)
def test_seeded_determinism(env_id, make_env):
    rng = np.random.default_rng(1234)
    actions = rng.uniform(-1, 1, (30, 7)).astype(np.float32)
    e1, e2 = make_env(env_id), make_env(env_id)
    t1 = _rollout(e1, 7, actions)
    t2 = _rollout(e2, 7, actions)
    _assert_bit_identical(t1, t2)
    # The trajectory actually moved (a frozen env would pass the comparison trivially).
    assert np.abs(t1[-1][0]["robot0_joint_pos"] - t1[0][0]["robot0_joint_pos"]).max() > 1e-3
    # Re-seeding the used env reproduces the episode: reset restores every mutated model field.
    t3 = _rollout(e1, 7, actions)
    _assert_bit_identical(t1, t3)
    # A different seed gives a different randomization.
    _, i_other = e2.reset(seed=8)
    r7, r8 = t1[0][4]["randomization"], i_other["randomization"]
    assert r7.keys() == r8.keys()
    assert all(r7[k] != r8[k] for k in r7)


# ----------------------------------------------------------------------------- Table 9
TABLE9 = {
    "friction_buck": (0.6, 0.9),
    "friction_window": (0.4, 0.7),
    "friction_cup": (0.8, 1.1),
    "solref_timeconst": (0.002, 0.004),
}


@pytest.mark.parametrize("env_id", IDS)
def test_reset_randomization_within_table9(env_id, make_env):
    env = make_env(env_id)
    u = env.unwrapped
    m, sc = u.model, u.scene
    exp = u.cfg.experiment
    seen = {k: [] for k in TABLE9}
    for seed in range(20):
        _, info = env.reset(seed=seed)
        r = info["randomization"]
        for k, (lo, hi) in TABLE9.items():
            assert lo <= r[k] <= hi, (k, r[k])
            seen[k].append(r[k])
        # The model holds the sampled values (isotropic sliding friction on every pair).
        for group, key in (("buck", "friction_buck"), ("window", "friction_window")):
            rows = sc.pairs[group]
            assert len(rows) > 0
            np.testing.assert_array_equal(m.pair_friction[rows, 0], r[key])
            np.testing.assert_array_equal(m.pair_friction[rows, 1], r[key])
        np.testing.assert_array_equal(m.geom_friction[sc.tool_geoms, 0], r["friction_cup"])
        np.testing.assert_array_equal(m.pair_solref[:, 0], r["solref_timeconst"])
        np.testing.assert_array_equal(m.geom_solref[:, 0], r["solref_timeconst"])

        pos, mat = u.panel_pose()
        if exp in ("A", "Insert"):
            assert {"panel_dx", "panel_dy", "panel_dz", "panel_roll_deg", "panel_pitch_deg",
                    "panel_yaw_deg"} <= r.keys()
            for k in ("panel_dx", "panel_dz"):
                assert abs(r[k]) <= 0.005, (k, r[k])
            # Insert: 0-3 cm further out than the pre-insertion pose, along the wall normal.
            assert (abs(r["panel_dy"]) <= 0.005) if exp == "A" else (0 <= r["panel_dy"] <= 0.03)
            for k in ("panel_roll_deg", "panel_pitch_deg", "panel_yaw_deg"):
                assert abs(r[k]) <= 2.0, (k, r[k])
            c0, R0 = S.rack_panel_pose(u.cfg) if exp == "A" else \
                (u.cfg.seated_center + S.WALL_NORMAL * S.PREINSERT_OFFSET, S.SEATED_PANEL_MAT)
            np.testing.assert_allclose(pos, c0 + [r["panel_dx"], r["panel_dy"], r["panel_dz"]], atol=1e-9)
            R = R0 @ _rot(0, np.deg2rad(r["panel_roll_deg"])) @ _rot(1, np.deg2rad(r["panel_pitch_deg"])) \
                @ _rot(2, np.deg2rad(r["panel_yaw_deg"]))
            np.testing.assert_allclose(mat, R, atol=1e-9)
            assert info["suction_engaged"] and u.suction_engaged
        else:
            assert 0.4 <= r["panel_x"] <= 0.6
            assert -0.3 <= r["panel_y"] <= 0.3
            assert abs(r["panel_yaw_deg"]) <= 15.0
            np.testing.assert_allclose(pos, [r["panel_x"], r["panel_y"], u.cfg.panel_thickness / 2], atol=1e-9)
            yaw = np.rad2deg(np.arctan2(mat[1, 0], mat[0, 0]))
            assert yaw == pytest.approx(r["panel_yaw_deg"], abs=1e-6)
            np.testing.assert_allclose(mat[:, 2], [0, 0, 1], atol=1e-9)
            assert not info["suction_engaged"] and not u.suction_engaged
    # 20 seeds spread over the range (not a constant).
    for k, (lo, hi) in TABLE9.items():
        assert max(seen[k]) - min(seen[k]) > 0.3 * (hi - lo), k


# ----------------------------------------------------------------------------- vector env
def test_async_vector_env_spawn():
    env_id = "window_bench:WindowInstall-A-v0"
    venv = gym.vector.AsyncVectorEnv([lambda: gym.make(env_id)] * 2, context="spawn")
    try:
        obs, info = venv.reset(seed=[3, 4])
        assert obs["robot0_joint_pos"].shape == (2, 7)
        assert obs["window_pos_rel"].shape == (2, 3)
        # Different seeds -> different per-worker randomization.
        assert info["randomization"]["friction_buck"][0] != info["randomization"]["friction_buck"][1]
        for _ in range(3):
            obs, rew, term, trunc, info = venv.step(np.zeros((2, 7), np.float32) + [0, 0, 0, 0, 0, 0, 1])
        assert rew.shape == (2,) and term.shape == (2,) and trunc.shape == (2,)
        assert not term.any() and not trunc.any()
        assert np.all(np.isfinite(obs["robot0_eef_pos"]))
    finally:
        venv.close()


# ----------------------------------------------------------------------------- observations
@pytest.mark.parametrize("env_id", IDS)
def test_state_observation_layout(env_id, make_env):
    env = make_env(env_id)
    obs, _ = env.reset(seed=0)
    shapes = {"robot0_joint_pos": (7,), "robot0_joint_vel": (7,), "robot0_eef_pos": (3,),
              "robot0_eef_quat": (4,), "robot0_vacuum": (1,), "robot0_proprio": (18,),
              "window_pos_rel": (3,), "window_rot_rel": (3,), "contact_proxy": (6,)}
    assert tuple(obs.keys()) == STATE_KEYS
    assert {k: v.shape for k, v in obs.items()} == shapes
    assert all(v.dtype == np.float32 for v in obs.values())
    assert env.observation_space.contains(obs)
    u = env.unwrapped
    # Named quantities agree with the privileged state.
    np.testing.assert_allclose(obs["robot0_eef_pos"], u.tcp_pose()[0], atol=1e-6)
    np.testing.assert_allclose(obs["window_pos_rel"], u.panel_pose()[0] - u.seated_pose[0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(obs["robot0_eef_quat"]), 1.0, atol=1e-6)
    assert obs["robot0_vacuum"][0] == (0.0 if u.cfg.experiment == "B" else 1.0)


@pytest.mark.parametrize("env_id", IDS)
def test_flat_observation_is_state_concatenation(env_id, make_env):
    e_state, e_flat = make_env(env_id), make_env(env_id, obs_mode="flat")
    o_state, _ = e_state.reset(seed=5)
    o_flat, _ = e_flat.reset(seed=5)
    a = np.full(7, 0.3, np.float32)
    o_state, *_ = e_state.step(a)
    o_flat, *_ = e_flat.step(a)
    assert o_flat.dtype == np.float32 and o_flat.ndim == 1
    assert e_flat.observation_space.shape == o_flat.shape
    assert e_flat.observation_space.contains(o_flat)
    np.testing.assert_array_equal(o_flat, np.concatenate([o_state[k] for k in STATE_KEYS]))


def test_flat_observation_length(make_env):
    # 7 + 7 + 3 + 4 + 1 + 18 + 3 + 3 + 6: every state key, in STATE_KEYS order.
    env = make_env("WindowInstall-A-v0", obs_mode="flat")
    obs, _ = env.reset(seed=0)
    assert env.observation_space.shape == (52,)
    assert obs.shape == (52,)


def test_pixel_observations(make_env):
    env = make_env("WindowInstall-B-v0", obs_mode="pixels")
    obs, _ = env.reset(seed=0)
    assert set(obs.keys()) == {"wrist_rgb", "side_rgb", "robot0_proprio"}
    for k in ("wrist_rgb", "side_rgb"):
        assert obs[k].shape == (128, 128, 3) and obs[k].dtype == np.uint8
        assert obs[k].std() > 1.0, f"{k} is (nearly) constant"
        assert not np.array_equal(obs[k], np.full_like(obs[k], obs[k].flat[0]))
    assert obs["robot0_proprio"].shape == (18,) and obs["robot0_proprio"].dtype == np.float32
    assert not np.array_equal(obs["wrist_rgb"], obs["side_rgb"])
    assert env.observation_space.contains(obs)
    # Moving the arm changes the wrist view.
    obs2 = obs
    for _ in range(2):
        obs2, *_ = env.step(np.array([0.0, 0.0, 1.0, 0, 0, 0, 0], np.float32))
    assert np.abs(obs2["wrist_rgb"].astype(int) - obs["wrist_rgb"].astype(int)).mean() > 1.0


def test_render_rgb_array(make_env):
    env = make_env("WindowInstall-A-v0", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8
    assert frame.std() > 1.0
    plain = make_env("WindowInstall-A-v0")
    plain.reset(seed=0)
    assert plain.render() is None


@pytest.mark.parametrize("kwargs,needle", [
    ({"panel_width": 0.7}, "panel_width=0.7 is outside the supported range [0.3, 0.6]"),
    ({"panel_height": 0.2}, "panel_height=0.2 is outside the supported range [0.3, 0.6]"),
    ({"clearance": 0.0}, "clearance=0.0 is outside the supported range [0.0005, 0.02]"),
    ({"panel_mass": 9.0}, "panel_mass=9.0 is outside [0.2, 5.0] kg"),
    ({"experiment": "C"}, "experiment must be one of 'A', 'B', 'Insert', got 'C'"),
    ({"obs_mode": "rgb"}, "obs_mode='rgb'"),
    ({"render_mode": "human"}, "render_mode='human'"),
    ({"image_size": 8}, "image_size=8 is outside [16, 512]"),
    ({"compliance_mm": -1.0}, "compliance_mm=-1.0 is outside [0, 100] (0: off)"),
    ({"compliance_deg": 95}, "compliance_deg=95 is outside [0, 90] (0: off)"),
])
def test_bad_constructor_arguments_name_the_value_and_range(kwargs, needle):
    from window_bench.envs.env import WindowInstallEnv
    with pytest.raises(ValueError) as exc:
        WindowInstallEnv(**kwargs)
    assert needle in str(exc.value)


def test_clearance_kwarg_resizes_the_opening():
    from window_bench.envs.env import WindowInstallEnv
    import mujoco
    for c in (0.002, 0.005):
        env = WindowInstallEnv(experiment="A", clearance=c)
        m = env.model
        left = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "buck_jamb_left")
        right = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "buck_jamb_right")
        inner = (m.geom_pos[right, 0] - m.geom_size[right, 0]) - (m.geom_pos[left, 0] + m.geom_size[left, 0])
        assert inner == pytest.approx(0.5 + 2 * c, abs=1e-9)
