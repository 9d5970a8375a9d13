"""The acceptance-sensing wrapper: noisy training reward, true acceptance for evaluation."""

import gymnasium as gym
import numpy as np
import pytest

from window_bench.envs.env import WindowInstallEnv
from window_bench.installer.scripted import RandomPolicy, ScriptedInstaller
from window_bench.envs.wrappers import AcceptanceSensor, NoisyAcceptance, make_training_env

A = "WindowInstall-A-v0"
HOLD = np.array([0, 0, 0, 0, 0, 0, 1.0], np.float32)     # no motion, vacuum on
RELEASE = np.zeros(7, np.float32)                         # no motion, vacuum off
WRAPPER_KEYS = {"sensed_acceptance", "true_acceptance", "accepted_ever"}


def _rollout(env, seed, hold_after_acceptance=False, max_steps=600):
    """Scripted installer from ``reset(seed)``; after the first true acceptance either keep
    running the installer or hold still (vacuum on). Returns per-step records."""
    obs, info0 = env.reset(seed=seed)
    installer = ScriptedInstaller(env, seed=seed)
    out = {"obs": [obs], "reward": [], "terminated": [], "truncated": [], "info": [info0]}
    accepted_once = False
    for _ in range(max_steps):
        a = HOLD if (hold_after_acceptance and accepted_once) else installer.act(obs)
        obs, r, term, trunc, info = env.step(a)
        accepted_once |= bool(info["accepted"])
        for k, v in (("obs", obs), ("reward", r), ("terminated", term), ("truncated", trunc),
                     ("info", info)):
            out[k].append(v)
        if term or trunc:
            break
    return out


# ----------------------------------------------------------------------------- the sensor alone
def test_sensor_without_noise_reads_the_truth_delayed():
    truth = np.random.default_rng(0).random(200) < 0.5
    for d in (0, 1, 7):
        sensor = AcceptanceSensor(delay_steps=d, seed=0)
        reads = [sensor.read(t) for t in truth]
        expected = [False] * d + list(truth[:len(truth) - d])
        assert reads == expected, d


def test_sensor_rates_match_within_binomial_bounds():
    n = 20000
    for p_fp, p_fn in ((0.05, 0.2), (0.01, 0.5)):
        sensor = AcceptanceSensor(false_positive_rate=p_fp, false_negative_rate=p_fn, seed=1)
        spurious = sum(sensor.read(False) for _ in range(n))
        missed = n - sum(sensor.read(True) for _ in range(n))
        for k, p in ((spurious, p_fp), (missed, p_fn)):
            sd = np.sqrt(n * p * (1 - p))
            assert abs(k - n * p) < 5 * sd, (k, n, p)


def test_sensor_extreme_rates_are_certain():
    sensor = AcceptanceSensor(false_positive_rate=1.0, false_negative_rate=1.0, seed=2)
    assert all(sensor.read(False) for _ in range(500))
    assert not any(sensor.read(True) for _ in range(500))
    sensor = AcceptanceSensor(seed=3)
    assert not any(sensor.read(False) for _ in range(500))
    assert all(sensor.read(True) for _ in range(500))


def test_sensor_seeding():
    truth = np.random.default_rng(4).random(300) < 0.3

    def reads(seed):
        sensor = AcceptanceSensor(0.1, 0.3, 2)
        sensor.reset(seed=seed)
        return [sensor.read(t) for t in truth]

    assert reads(5) == reads(5)
    assert reads(5) != reads(6)
    # The sensor's stream is not the env's np_random stream for the same integer seed.
    env_stream = np.random.default_rng(5).random(300) < 0.1
    sensor = AcceptanceSensor(0.1, 0.0, 0, seed=5)
    assert [sensor.read(False) for _ in range(300)] != list(env_stream)


@pytest.mark.parametrize("kwargs,needle", [
    ({"false_positive_rate": -0.1}, "false_positive_rate=-0.1 is outside [0, 1]"),
    ({"false_positive_rate": 1.5}, "false_positive_rate=1.5 is outside [0, 1]"),
    ({"false_negative_rate": float("nan")}, "false_negative_rate=nan is outside [0, 1]"),
    ({"false_negative_rate": "0.1"}, "false_negative_rate='0.1' must be a number in [0, 1]"),
    ({"false_positive_rate": True}, "false_positive_rate=True must be a number in [0, 1]"),
    ({"delay_steps": 101}, "delay_steps=101 is outside [0, 100]"),
    ({"delay_steps": -1}, "delay_steps=-1 is outside [0, 100]"),
    ({"delay_steps": 2.5}, "delay_steps=2.5 must be an integer in [0, 100]"),
    ({"delay_steps": 3.0}, "delay_steps=3.0 must be an integer in [0, 100]"),
])
def test_bad_arguments_name_the_value_and_range(kwargs, needle):
    with pytest.raises(ValueError) as exc:
        AcceptanceSensor(**kwargs)
    assert needle in str(exc.value)
    with pytest.raises(ValueError) as exc:
        make_training_env(A, acceptance_noise=kwargs)
    assert needle in str(exc.value)


def test_numpy_scalars_are_accepted():
    s = AcceptanceSensor(np.float32(0.25), np.float64(0.5), np.int64(4))
    assert s.as_dict() == {"false_positive_rate": 0.25, "false_negative_rate": 0.5, "delay_steps": 4}


# ----------------------------------------------------------------------------- construction
def test_wrapper_needs_a_window_install_env():
    with pytest.raises(ValueError, match="needs a WindowInstallEnv.*CartPoleEnv"):
        NoisyAcceptance(gym.make("CartPole-v1"))


def test_make_training_env_wraps_only_with_noise():
    plain = make_training_env(A, None, obs_mode="flat")
    assert not isinstance(plain, NoisyAcceptance)
    assert plain.unwrapped.terminate_on_acceptance is True
    noisy = make_training_env(A, {"false_positive_rate": 0.01, "delay_steps": 3}, obs_mode="flat")
    assert isinstance(noisy, NoisyAcceptance)
    assert noisy.unwrapped.terminate_on_acceptance is False
    assert (noisy.false_positive_rate, noisy.false_negative_rate, noisy.delay_steps) == (0.01, 0.0, 3)
    assert noisy.observation_space.shape == (52,)
    with pytest.raises(ValueError, match=r"unknown keys \['fp'\]; allowed"):
        make_training_env(A, {"fp": 0.1})
    with pytest.raises(ValueError, match="terminate_on_acceptance=True contradicts"):
        make_training_env(A, {}, terminate_on_acceptance=True)
    for env in (plain, noisy):
        env.close()


def test_step_before_reset_and_after_the_end_raises(make_env):
    env = NoisyAcceptance(make_env(A), false_positive_rate=1.0)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(HOLD)
    env.reset(seed=0)
    env.step(HOLD)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(HOLD)


def test_env_switched_back_to_terminating_is_an_error(make_env):
    env = NoisyAcceptance(make_env(A, obs_mode="flat"))
    run = _rollout(env, seed=0)   # noiseless: signs off on the first accepted step
    assert run["terminated"][-1]
    env.unwrapped.terminate_on_acceptance = True
    _, info = env.reset(seed=0)
    installer = ScriptedInstaller(env, seed=0)
    obs = None
    with pytest.raises(RuntimeError, match="terminated on its own"):
        for _ in range(len(run["reward"])):
            obs, *_ = env.step(installer.act(obs))


# ----------------------------------------------------------------------------- the env keyword
def test_env_without_termination_runs_past_acceptance(make_env):
    env = make_env(A, obs_mode="flat", terminate_on_acceptance=False, info_strings=True)
    assert env.unwrapped.terminate_on_acceptance is False
    run = _rollout(env, seed=0, hold_after_acceptance=True, max_steps=130)
    infos = run["info"]
    first = next(i for i, info in enumerate(infos) if info["accepted"])   # index = step number
    assert 80 < first < 130
    assert not any(run["terminated"])
    assert run["truncated"][-1] is False and len(run["reward"]) == 130   # still running
    for info, r in zip(infos[1:], run["reward"]):
        assert r == float(info["accepted"])
        assert info["is_success"] == info["accepted"]
    held = infos[first:]
    assert all(i["accepted"] and i["seated"] and i["failure_mode"] == "" for i in held)
    assert set(infos[0]) - {"randomization"} == set(infos[-1])
    assert infos[0]["accepted"] is False
    # Releasing the seated panel drops it onto the sill: no longer accepted, labelled by the
    # current state although the seating stage was reached.
    for _ in range(5):
        obs, r, term, trunc, info = env.step(RELEASE)
    assert not term and r == 0.0
    assert not info["accepted"] and not info["is_success"]
    assert info["seated"] and info["failure_mode"] == "suction_lost"


def test_env_terminate_on_acceptance_validated():
    with pytest.raises(ValueError, match="terminate_on_acceptance='no'; allowed: True, False"):
        WindowInstallEnv(terminate_on_acceptance="no")


# ----------------------------------------------------------------------------- the wrapper on the env
def test_zero_noise_reproduces_the_unwrapped_env(make_env):
    clean = _rollout(make_env(A, obs_mode="flat"), seed=0)
    wrapped = _rollout(NoisyAcceptance(make_env(A, obs_mode="flat")), seed=0)
    assert clean["terminated"][-1] and clean["reward"][-1] == 1.0
    assert len(clean["reward"]) < 150                   # the installer's short success
    for k in ("reward", "terminated", "truncated"):
        assert wrapped[k] == clean[k], k
    np.testing.assert_array_equal(np.array(wrapped["obs"]), np.array(clean["obs"]))
    assert wrapped["info"][-1]["is_success"] and clean["info"][-1]["is_success"]
    last = wrapped["info"][-1]
    assert last["sensed_acceptance"] and last["true_acceptance"] and last["accepted_ever"]
    # Same keys at reset and at every step (Minari's rule), the wrapper's included.
    keys = set(wrapped["info"][1])
    assert WRAPPER_KEYS <= keys
    assert set(wrapped["info"][0]) - {"randomization"} == keys
    assert all(set(i) == keys for i in wrapped["info"][1:])


@pytest.mark.parametrize("delay", [1, 4, 10])
def test_delayed_reward_arrives_exactly_delay_steps_after_acceptance(delay, make_env):
    env = NoisyAcceptance(make_env(A, obs_mode="flat"), delay_steps=delay)
    run = _rollout(env, seed=1, hold_after_acceptance=True, max_steps=300)
    infos = run["info"][1:]
    t0 = next(t for t, info in enumerate(infos) if info["true_acceptance"])   # 0-based step
    end = len(infos) - 1
    assert end == t0 + delay
    assert run["terminated"][end] and not run["truncated"][end] and run["reward"][end] == 1.0
    assert sum(run["reward"]) == 1.0
    # The held panel stayed accepted from the first acceptance to the sign-off.
    assert all(info["true_acceptance"] and info["accepted_ever"] for info in infos[t0:])
    assert not any(info["sensed_acceptance"] for info in infos[:end])
    assert infos[end]["is_success"] and infos[end]["sensed_acceptance"]


def test_certain_miss_runs_to_truncation(make_env):
    env = NoisyAcceptance(make_env(A, obs_mode="flat", max_episode_steps=140),
                          false_negative_rate=1.0)
    run = _rollout(env, seed=0, hold_after_acceptance=True)
    infos = run["info"][1:]
    assert len(infos) == 140 and run["truncated"][-1]
    assert not any(run["terminated"]) and sum(run["reward"]) == 0.0
    assert sum(i["true_acceptance"] for i in infos) > 20
    # Evaluation-side truth survives the missed signal: the panel is accepted at the end.
    assert infos[-1]["is_success"] and infos[-1]["accepted_ever"]
    assert not any(i["sensed_acceptance"] for i in infos)


def test_certain_false_positive_ends_the_first_step(make_env):
    env = NoisyAcceptance(make_env(A, obs_mode="flat"), false_positive_rate=1.0)
    env.reset(seed=0)
    obs, r, term, trunc, info = env.step(HOLD)
    assert r == 1.0 and term and not trunc
    assert info["sensed_acceptance"] and not info["true_acceptance"]
    assert info["is_success"] is False and info["accepted_ever"] is False


def test_sign_off_on_the_last_step_is_a_termination_only(make_env):
    # The step log's rule: exactly one of terminated / truncated ends an episode. A sign-off
    # on the time limit's last step is a termination (no bootstrap), not a truncation.
    env = NoisyAcceptance(make_env(A, obs_mode="flat", max_episode_steps=2), false_positive_rate=1.0)
    env.reset(seed=0)
    env.sensor.false_positive_rate = 0.0
    obs, r, term, trunc, info = env.step(HOLD)
    assert not (term or trunc)
    env.sensor.false_positive_rate = 1.0
    obs, r, term, trunc, info = env.step(HOLD)
    assert term and not trunc and r == 1.0


def test_divergence_truncates_even_with_a_certain_false_positive(make_env):
    env = NoisyAcceptance(make_env("WindowInstall-B-v0"), false_positive_rate=1.0)
    env.reset(seed=0)
    u = env.unwrapped
    a = u.scene.panel_dof_adr
    u.data.qvel[a:a + 3] = [1e4, -1e4, 1e4]
    obs, r, term, trunc, info = env.step(RELEASE)
    assert trunc and not term and r == 0.0
    assert info["sim_unstable"] and not info["sensed_acceptance"]


def test_false_positive_rate_on_random_actions(make_env):
    # Random actions never seat the panel: every reading is of a not-accepted state, so the
    # number of sign-offs over n steps is Binomial(n, p).
    n, p = 400, 0.05
    env = NoisyAcceptance(make_env(A, obs_mode="flat"), false_positive_rate=p)
    policy = RandomPolicy(env, seed=0)
    obs, _ = env.reset(seed=0)
    fires = true_acc = 0
    for _ in range(n):
        obs, r, term, trunc, info = env.step(policy.act(obs))
        fires += int(term)
        true_acc += int(info["true_acceptance"])
        assert r == float(term) and info["is_success"] is False
        if term or trunc:
            obs, _ = env.reset()
    assert true_acc == 0
    sd = np.sqrt(n * p * (1 - p))
    assert abs(fires - n * p) < 4 * sd, fires


def test_same_seed_same_noisy_signal(make_env):
    def signal(env, seed):
        policy = RandomPolicy(env, seed=seed)
        obs, _ = env.reset(seed=seed)
        ends = []
        steps = 0
        while len(ends) < 4:
            obs, r, term, trunc, info = env.step(policy.act(obs))
            steps += 1
            if term or trunc:
                ends.append((steps, r, term))
                steps = 0
                obs, _ = env.reset()          # unseeded: continues the seeded streams
        return ends

    env = NoisyAcceptance(make_env(A, obs_mode="flat"), false_positive_rate=0.15, seed=123)
    first = signal(env, 7)
    assert first == signal(env, 7)
    assert first != signal(env, 8)
    assert all(term and r == 1.0 for _, r, term in first)
