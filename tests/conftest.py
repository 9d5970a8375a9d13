"""Shared test setup.

``MUJOCO_GL`` is left as the user has it: ``import window_bench`` (below, before any test
module imports mujoco) picks a headless backend where there is no display, as it does for
users, so the suite renders the way a user's script does.
"""

import os

# These machines have 2 cores: one BLAS/torch thread per process.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import window_bench  # noqa: E402,F401  (registers the ids)
from window_bench.installer.operators import DEFAULT_OPERATOR  # noqa: E402


@pytest.fixture
def make_env():
    """``make_env(id, **kwargs)`` -> unwrapped-or-not env that is closed after the test."""
    envs = []

    def _make(env_id, **kwargs):
        env = gym.make(env_id, **kwargs)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()


def tcp_action(env, target_pos, g=0.0, gain=1.0):
    """Pose-increment action that moves the TCP toward ``target_pos`` (world frame).

    The action is the increment in the current TCP frame at 0.025 m per unit, so a world
    displacement d maps to R.T @ d / 0.025, clipped to the box.
    """
    from window_bench.envs.env import POS_SCALE

    p, R = env.unwrapped.tcp_pose()
    a = np.zeros(7)
    a[:3] = np.clip(gain * R.T @ (np.asarray(target_pos) - p) / POS_SCALE, -1.0, 1.0)
    a[6] = g
    return a


def drive_tcp(env, target_pos, g=0.0, max_steps=40, tol=5e-4):
    """Step until the TCP is within ``tol`` of ``target_pos``; returns the last step tuple."""
    out = None
    for _ in range(max_steps):
        p, _ = env.unwrapped.tcp_pose()
        if np.linalg.norm(np.asarray(target_pos) - p) < tol:
            break
        out = env.step(tcp_action(env, target_pos, g))
        assert not (out[2] or out[3]), f"episode ended while driving the TCP: {out[4]}"
    return out


@pytest.fixture(scope="session")
def demos_root(tmp_path_factory):
    """Two ``average``-operator demonstrations on WindowInstall-A-v0 (the smoke profile's
    D_demo), collected once for every test module that runs the harness."""
    from window_bench.installer.demos import collect_demos

    root = tmp_path_factory.mktemp("demos")
    collect_demos("WindowInstall-A-v0", 2, root, operator=DEFAULT_OPERATOR, seed=0,
                  progress=False)
    return root
