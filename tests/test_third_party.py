"""The env and our datasets through code that no one here wrote: copy/pickle, SB3's
subprocess vector env, Gymnasium's async vector env and RecordVideo, TorchRL's batched
GymEnv and a collector, Minari's load / recover / replay. Kept small (about a minute):
each path is exercised for a few steps, not trained."""

import copy
import pickle

import cloudpickle
import gymnasium as gym
import numpy as np
import pytest

import window_bench  # noqa: F401  (registers the ids)
from window_bench.installer.scripted import ScriptedInstaller


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return bool(np.array_equal(np.asarray(a), np.asarray(b)))


COPIERS = {
    "deepcopy": copy.deepcopy,
    "pickle": lambda e: pickle.loads(pickle.dumps(e)),
    "cloudpickle": lambda e: cloudpickle.loads(cloudpickle.dumps(e)),
}


@pytest.mark.parametrize("wrapped", [True, False], ids=["gym.make", "unwrapped"])
@pytest.mark.parametrize("how", sorted(COPIERS))
def test_copy_mid_episode_continues_bit_identically(how, wrapped):
    """Copied mid-episode (panel held, on its way to the opening, after a recovery-free
    approach), the copy and the original seat the panel along the same trajectory."""
    env = gym.make("WindowInstall-A-v0")
    env = env if wrapped else env.unwrapped
    ctrl = ScriptedInstaller(env)
    obs, _ = env.reset(seed=7)
    ctrl.reset(seed=7)
    for _ in range(30):
        obs, *_ = env.step(ctrl.act(obs))
    twin = COPIERS[how](env)
    assert type(twin) is type(env) and twin.unwrapped.model is not env.unwrapped.model
    steps, done = 0, False
    while not done:
        a = ctrl.act(obs)
        out, out_twin = env.step(a), twin.step(a)
        assert _same(out[0], out_twin[0]), f"observations differ {steps} steps after the copy"
        assert out[1:4] == out_twin[1:4]
        assert {k: v for k, v in out[4].items() if k != "randomization"} == \
            {k: v for k, v in out_twin[4].items() if k != "randomization"}
        obs, done = out[0], out[2] or out[3]
        steps += 1
    assert out[2], "the scripted installer seats this panel"
    # Both reset to the same episode afterwards, and the copy renders (fresh GL context).
    assert _same(env.reset(seed=3)[0], twin.reset(seed=3)[0])
    env.close()
    twin.close()


def test_copy_before_reset_and_of_pixel_env():
    env = gym.make("WindowInstall-B-v0", obs_mode="pixels", image_size=32)
    twin = copy.deepcopy(env)
    o1, _ = env.reset(seed=1)
    o2, _ = twin.reset(seed=1)
    assert _same(o1, o2) and o1["wrist_rgb"].shape == (32, 32, 3)
    env.close()
    twin.close()
