"""The env and our datasets through code that no one here wrote: copy/pickle, SB3's
subprocess vector env, Gymnasium's async vector env, RecordVideo and env checker, TorchRL's
batched GymEnv and a collector, Minari's load / recover / replay. Kept small (about two
minutes): each path is exercised for a few steps, not trained. Where the way a user's script
is laid out matters (spawned workers, no display), the recipe runs as a script of its own."""

import copy
import json
import os
import pickle
import subprocess
import sys
import textwrap

import cloudpickle
import gymnasium as gym
import numpy as np
import pytest

import window_bench  # noqa: F401  (registers the ids)
from window_bench.gl import choose_headless_backend
from window_bench.installer.scripted import ScriptedInstaller

# What a fresh shell on a machine without a display has: no backend chosen, no display.
HEADLESS_ENV = {k: v for k, v in os.environ.items()
                if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY", "WAYLAND_DISPLAY")}


def _run(tmp_path, args, env=None, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=timeout)


def _run_script(tmp_path, source: str, env=None) -> dict:
    """Run ``source`` as a user's script file; it prints one JSON line last."""
    (tmp_path / "script.py").write_text(textwrap.dedent(source))
    out = _run(tmp_path, ["script.py"], env=env)
    assert out.returncode == 0, out.stderr[-4000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


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


def test_info_codes_match_the_labels():
    from window_bench.envs.env import SUCTION_LOSS_NAMES
    from window_bench.envs.task import FAILURE_MODE_NAMES, STAGES

    env = gym.make("WindowInstall-B-v0", info_strings=True)
    _, info = env.reset(seed=0)
    assert (info["failure_code"], info["stage"], info["suction_loss_code"]) == (0, 0, 0)
    seen = set()
    for _ in range(20):   # vacuum never commanded: never_acquired
        _, _, _, _, info = env.step(np.zeros(7))
        assert FAILURE_MODE_NAMES[info["failure_code"]] == info["failure_mode"]
        assert SUCTION_LOSS_NAMES[info["suction_loss_code"]] == info["suction_loss"]
        seen.add(info["failure_mode"])
    assert seen == {"never_acquired"} and STAGES[info["stage"]] == "none"
    # The scripted installer reaches every stage; the codes follow.
    obs, info = env.reset(seed=1)
    ctrl = ScriptedInstaller(env)
    ctrl.reset(seed=1)
    stages = [info["stage"]]
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(ctrl.act(obs))
        stages.append(info["stage"])
        done = term or trunc
    assert stages == sorted(stages) and set(stages) == {0, 1, 2, 3} and info["failure_code"] == 0
    env.close()


def test_info_holds_numbers_unless_strings_are_asked_for():
    env = gym.make("WindowInstall-A-v0")
    _, info = env.reset(seed=0)
    infos = [info] + [env.step(env.action_space.sample())[4] for _ in range(3)]
    for i in infos:
        assert "failure_mode" not in i and "suction_loss" not in i
        assert all(isinstance(v, (bool, int, float)) for k, v in i.items() if k != "randomization")
    labelled = gym.make("WindowInstall-A-v0", info_strings=True)
    _, info = labelled.reset(seed=0)
    assert info["failure_mode"] == "" and info["suction_loss"] == ""
    assert set(info) == set(infos[0]) | {"failure_mode", "suction_loss"}
    with pytest.raises(ValueError, match="info_strings='no'"):
        gym.make("WindowInstall-A-v0", info_strings="no")
    env.close()
    labelled.close()


def test_torchrl_batched_gymenv_as_typed(tmp_path):
    """TorchRL's batched GymEnv records every info key, so every one must be a number: with
    no extra argument it builds, rolls out and feeds a collector with success and failure
    codes. Its workers are spawned, so the script imports window_bench at the top, as the
    recipe does."""
    pytest.importorskip("torchrl")
    r = _run_script(tmp_path, """
        import json
        import torch
        import window_bench
        from torchrl.collectors import Collector
        from torchrl.envs import GymEnv

        if __name__ == "__main__":
            torch.set_num_threads(1)
            env = GymEnv("WindowInstall-B-v0", num_envs=2)
            td = env.rollout(3)
            collector = Collector(env, policy=None, frames_per_batch=8, total_frames=16)
            batches = list(collector)
            collector.shutdown()
            env.close()
            print(json.dumps({
                "batch": list(env.batch_size), "rollout": list(td.batch_size),
                "stage": td["next", "stage"].tolist(),
                "batches": [list(b.batch_size) for b in batches],
                "success_dtype": str(batches[0]["next", "is_success"].dtype),
                "failure_codes": sorted({c for b in batches
                                         for c in b["next", "failure_code"].unique().tolist()})}))
        """)
    assert r["batch"] == [2] and r["rollout"] == [2, 3]
    assert r["stage"] == [[0, 0, 0], [0, 0, 0]]   # B: the panel starts on the ground
    assert r["batches"] == [[2, 4], [2, 4]] and r["success_dtype"] == "torch.bool"
    # Random actions in B: the vacuum engages only by chance, far from the panel.
    assert set(r["failure_codes"]) <= {1}


def test_torchrl_single_env_info_reader():
    torch = pytest.importorskip("torch")
    from torchrl.envs import GymEnv

    from window_bench.envs.interop import INFO_CODES, torchrl_info_reader

    torch.set_num_threads(1)
    env = GymEnv("window_bench:WindowInstall-A-v0")
    env.set_info_dict_reader(torchrl_info_reader())
    td = env.rollout(3)
    assert set(INFO_CODES) <= set(td["next"].keys())
    assert td["next", "stage"].tolist() == [1, 1, 1]   # A starts with the panel held
    env.close()


def test_minari_load_recover_and_replay(tmp_path, monkeypatch):
    """Our demo dataset through Minari alone: load, recover the env from the stored spec,
    replay the stored actions from the stored seeds: the same observations and return."""
    minari = pytest.importorskip("minari")
    from window_bench.installer.demos import collect_demos

    summary = collect_demos("WindowInstall-A-v0", 2, tmp_path, seed=0, progress=False)
    assert not (tmp_path / ".partial").exists(), "a finished collection leaves no checkpoints"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    ds = minari.load_dataset(summary["dataset_id"])
    meta = ds.storage.metadata
    assert meta["requirements"] == [f"window-bench=={window_bench.__version__}"]
    # No placeholders: the git identity, and a permalink only where git knows a remote.
    assert meta.get("author") != {"window-bench"}
    assert meta.get("code_permalink") is None or meta["code_permalink"].startswith("http")
    env = ds.recover_environment()
    assert env.spec.kwargs["obs_mode"] == "flat"
    assert env.observation_space == ds.observation_space and env.action_space == ds.action_space
    seeds = [int(m["seed"]) for m in ds.storage.get_episode_metadata(range(ds.total_episodes))]
    for ep, seed in zip(ds.iterate_episodes(), seeds):
        obs, _ = env.reset(seed=seed)
        assert np.array_equal(obs, ep.observations[0])
        ret = 0.0
        for t, a in enumerate(ep.actions):
            obs, r, term, trunc, _ = env.step(a)
            ret += r
            assert np.array_equal(obs, ep.observations[t + 1]), f"diverged at step {t}"
        assert ret == ep.rewards.sum() == 1.0 and term
    env.close()


def test_sb3_subproc_vec_env_whatever_the_import_placement(tmp_path):
    """Workers start in fresh interpreters (forkserver) that never run the script's
    ``__main__`` block, so only the ``window_bench:`` form of the id registers there."""
    r = _run_script(tmp_path, """
        import json
        import numpy as np
        from stable_baselines3.common.env_util import make_vec_env
        from stable_baselines3.common.vec_env import SubprocVecEnv

        if __name__ == "__main__":
            import window_bench  # noqa: F401  (too late for the workers)

            venv = make_vec_env("window_bench:WindowInstall-B-v0", n_envs=2, seed=0,
                                vec_env_cls=SubprocVecEnv,
                                env_kwargs={"obs_mode": "flat", "info_strings": True})
            obs = venv.reset()
            for _ in range(3):
                obs, rewards, dones, infos = venv.step(np.zeros((2, 7), np.float32))
            venv.close()
            print(json.dumps({"obs": list(obs.shape), "dtype": str(obs.dtype),
                              "rewards": list(rewards.shape),
                              "modes": [i["failure_mode"] for i in infos],
                              "same_obs": bool(np.array_equal(obs[0], obs[1]))}))
        """)
    assert r["obs"] == [2, 52] and r["dtype"] == "float32" and r["rewards"] == [2]
    assert r["modes"] == ["never_acquired"] * 2
    assert not r["same_obs"], "the two workers run different seeds: different panel poses"


def test_gymnasium_async_vector_env_and_record_video(tmp_path):
    pytest.importorskip("moviepy")
    envs = gym.vector.AsyncVectorEnv(
        [lambda: gym.make("window_bench:WindowInstall-A-v0", obs_mode="flat")] * 2)
    obs, infos = envs.reset(seed=[0, 1])
    assert obs.shape == (2, 52)
    obs, rewards, term, trunc, infos = envs.step(np.zeros((2, 7), np.float32))
    assert infos["failure_code"].dtype.kind == "i" and infos["stage"].tolist() == [1, 1]
    envs.close()

    env = gym.wrappers.RecordVideo(
        gym.make("WindowInstall-A-v0", render_mode="rgb_array", max_episode_steps=5),
        str(tmp_path), episode_trigger=lambda i: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, term, trunc, _ = env.step(np.zeros(7))
        done = term or trunc
    env.close()
    videos = list(tmp_path.glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 1000


def test_bench_video_writes_an_mp4_per_episode(tmp_path, capsys):
    imageio = pytest.importorskip("imageio.v2")
    pytest.importorskip("imageio_ffmpeg")
    import json

    from window_bench.cli import main

    assert main(["video", "--env", "WindowInstall-A-v0", "--seed", "3", "--size", "64",
                 "--cameras", "wrist", "overview", "--out", str(tmp_path)]) == 0
    assert "seed 3: seated after" in capsys.readouterr().out
    rows = json.loads((tmp_path / "videos.json").read_text())["episodes"]
    assert [r["seed"] for r in rows] == [3] and rows[0]["success"]
    # A comprehension, not list(): the reader's length is inf for a stream.
    frames = [f for f in imageio.get_reader(str(tmp_path / rows[0]["file"]), format="ffmpeg")]
    # One frame per step plus the reset; wrist 64 + overview 86 px wide, padded to 16s.
    assert len(frames) == rows[0]["steps"] + 1 == rows[0]["frames"]
    assert frames[0].shape == (64, 160, 3)
    fresh = str(tmp_path / "fresh")   # so that only the bad argument is wrong
    assert main(["video", "--size", "10", "--out", fresh]) == 2
    assert "size 10 px is outside [64, 480]" in capsys.readouterr().err
    # A file that is not a policy file (read without unpickling): one line, exit 2.
    assert main(["video", "--policy", str(tmp_path / "videos.json"), "--out", fresh]) == 2
    assert "videos.json: not a window-bench policy file" in capsys.readouterr().err
    assert main(["video", "--policy", "magic", "--out", fresh]) == 2
    assert "neither a controller" in capsys.readouterr().err


def test_headless_backend_is_chosen_only_when_unset():
    libs = {"EGL": "libEGL.so.1", "OSMesa": "libOSMesa.so.8"}
    for found, want in (({"EGL", "OSMesa"}, "egl"), ({"OSMesa"}, "osmesa"), (set(), None)):
        env = {}
        chosen = choose_headless_backend(env, lambda lib: libs[lib] if lib in found else None)
        assert chosen == want and env.get("MUJOCO_GL") == want
    for preset in ({"MUJOCO_GL": "osmesa"}, {"DISPLAY": ":0"}):
        env = dict(preset)
        assert choose_headless_backend(env, lambda lib: "found") is None and env == preset


def test_check_env_renders_without_mujoco_gl(tmp_path):
    """Gymnasium's env checker renders every declared render mode; on a machine without a
    display and with MUJOCO_GL unset that aborted the process before window_bench chose a
    headless backend on import."""
    r = _run_script(tmp_path, """
        import json, os
        import gymnasium as gym
        from gymnasium.utils.env_checker import check_env
        import window_bench

        for env_id in ("WindowInstall-A-v0", "WindowInstall-B-v0"):
            check_env(gym.make(env_id).unwrapped)
        print(json.dumps({"MUJOCO_GL": os.environ.get("MUJOCO_GL")}))
        """, env=HEADLESS_ENV)
    assert r["MUJOCO_GL"] in ("egl", "osmesa")


def test_bench_video_without_mujoco_gl(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    out = _run(tmp_path, ["-m", "window_bench.cli", "video", "--env", "WindowInstall-A-v0",
                          "--seed", "3", "--size", "64", "--cameras", "wrist",
                          "--out", str(tmp_path / "v")], env=HEADLESS_ENV)
    assert out.returncode == 0, out.stderr[-4000:]
    assert "seed 3: seated after" in out.stdout
    videos = list((tmp_path / "v").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 1000


def test_no_opengl_is_one_clear_error(tmp_path):
    """Neither EGL nor OSMesa installed and no display: one line and exit 2 (as encoder
    train and teleop), not an abort."""
    out = _run(tmp_path, ["-c", "import ctypes.util, sys; ctypes.util.find_library = "
                          "lambda name: None; from window_bench.cli import main; "
                          "sys.exit(main(sys.argv[1:]))", "video", "--size", "64",
                          "--cameras", "wrist", "--out", str(tmp_path / "v")],
               env=HEADLESS_ENV)
    assert out.returncode == 2, out.stderr[-4000:]
    # Above it only the progress bar.
    assert "Traceback" not in out.stderr and out.stderr.strip().splitlines()[-1] == (
        "error: cannot render: no display (DISPLAY is unset) and no EGL or OSMesa library "
        "was found (Debian: apt-get install libegl1 or libosmesa6), or set MUJOCO_GL to a "
        "backend that works here")
    assert not list((tmp_path / "v").glob("*.mp4"))
