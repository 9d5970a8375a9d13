"""Episode videos (``bench video``): any policy file or reference controller, seen from the
wrist, side and overview cameras, written as MP4 with imageio's ffmpeg plugin.

The policy runs through the same :class:`~window_bench.installer.rollout.Rollout` loop and
the same flat-observation env as ``bench eval``; a wrapper renders the chosen cameras after
the reset and after every step and tiles them side by side (one frame per 0.1 s step, so
the default 10 fps is real time). Each episode is one file ``<env>_<policy>_seed<k>.mp4``,
written atomically; ``videos.json`` beside them records seed, outcome, failure mode, frame
count and provenance. Needs the ``video`` extra (``pip install "window-bench[video]"``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import gymnasium as gym
import numpy as np

from window_bench.envs.task import FAILURE_MODE_NAMES
from window_bench.gl import renderer

# Camera names in the scene, by the short names the command line uses, and the aspect
# (width / height) each is rendered at.
CAMERAS = {"wrist": ("robot0_wrist", 1.0), "side": ("side", 1.0), "overview": ("overview", 4 / 3)}
SIZE_RANGE = (64, 480)   # frame height in px; the scene's offscreen buffer is 640 x 480
FPS_RANGE = (1, 60)


def check_args(cameras: list[str], size: int, fps: int, policy: str = "installer") -> None:
    """One-line errors for bad arguments, before anything is built."""
    from window_bench.installer.scripted import CONTROLLERS

    if policy not in CONTROLLERS and not Path(policy).is_file():
        raise ValueError(f"policy {policy!r} is neither a controller ({', '.join(CONTROLLERS)}) "
                         "nor a policy file")
    bad = [c for c in cameras if c not in CAMERAS]
    if not cameras or bad:
        raise ValueError(f"cameras {bad or cameras!r}: choose one or more of {', '.join(CAMERAS)}")
    if not SIZE_RANGE[0] <= size <= SIZE_RANGE[1]:
        raise ValueError(f"size {size} px is outside [{SIZE_RANGE[0]}, {SIZE_RANGE[1]}]")
    if not FPS_RANGE[0] <= fps <= FPS_RANGE[1]:
        raise ValueError(f"fps {fps} is outside [{FPS_RANGE[0]}, {FPS_RANGE[1]}]")


class CameraRecorder(gym.Wrapper):
    """Renders ``cameras`` at height ``size`` after reset and every step into ``frames``
    (one RGB array per step, the views side by side, padded to multiples of 16 px for
    the H.264 encoder)."""

    def __init__(self, env: gym.Env, cameras: list[str], size: int):
        super().__init__(env)
        self.views = [(CAMERAS[c][0], size, int(round(size * CAMERAS[c][1] / 2)) * 2)
                      for c in cameras]
        self.renderers = {}
        self.frames: list[np.ndarray] = []

    def _frame(self) -> np.ndarray:
        u = self.env.unwrapped
        tiles = []
        for cam, h, w in self.views:
            r = self.renderers.get((h, w))
            if r is None:
                r = self.renderers[(h, w)] = renderer(u.model, h, w)
            r.update_scene(u.data, camera=cam)
            tiles.append(r.render())
        frame = np.concatenate(tiles, axis=1)
        pad_h, pad_w = -frame.shape[0] % 16, -frame.shape[1] % 16
        return np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)))

    def reset(self, **kwargs):
        out = self.env.reset(**kwargs)
        self.frames = [self._frame()]
        return out

    def step(self, action):
        out = self.env.step(action)
        self.frames.append(self._frame())
        return out

    def close(self):
        for r in self.renderers.values():
            r.close()
        self.renderers = {}
        super().close()


def make_policy(policy: str, env: gym.Env, seed: int):
    """A reference controller by name, or the frozen policy in a ``policies/*.safetensors``
    file (checked and read without pickle: a file cannot run code)."""
    from window_bench.installer.scripted import CONTROLLERS

    if policy in CONTROLLERS:
        return CONTROLLERS[policy](env, seed=seed)
    from window_bench.harness.run import AgentPolicy, load_policy_file

    agent_cls, state, _ = load_policy_file(policy)   # RunFileError (a ValueError) if not ours
    return AgentPolicy(agent_cls.from_policy_state_dict(state), deterministic=True)


def record(env_id: str, policy: str, seeds: list[int], out: str | os.PathLike,
           cameras: list[str] = list(CAMERAS), size: int = 240, fps: int = 10,
           progress: bool = True) -> list[dict]:
    """Record one MP4 per seed under ``out``; returns the rows written to ``videos.json``."""
    check_args(cameras, size, fps, policy)
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the MP4 writer imageio needs)
    except ImportError:
        raise ValueError('bench video needs the video extra: pip install "window-bench[video]"') from None
    from tqdm import tqdm

    from window_bench.harness.evaluation import atomic_write_text, provenance
    from window_bench.installer.rollout import Rollout

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    env = CameraRecorder(gym.make(env_id, obs_mode="flat"), cameras, size)
    pol = make_policy(policy, env, seeds[0])
    rollout = Rollout(env, pol, env_id=env_id)
    tag = Path(policy).stem if Path(policy).suffix else policy
    rows = []
    bar = tqdm(seeds, desc=f"video {env_id} {tag}", unit="ep", disable=not progress)
    try:
        for seed in bar:
            log = rollout.run(seed=seed, episode_id=seed)
            info = rollout.info
            path = out / f"{env_id}_{tag}_seed{seed}.mp4"
            tmp = path.with_name(f".{path.stem}.tmp.mp4")
            with imageio.get_writer(tmp, fps=fps, codec="libx264", quality=6,
                                    macro_block_size=16, ffmpeg_log_level="error") as w:
                for frame in env.frames:
                    w.append_data(frame)
            os.replace(tmp, path)
            rows.append({"seed": seed, "success": bool(log.terminated[-1]), "steps": log.T,
                         "failure_mode": FAILURE_MODE_NAMES[info["failure_code"]] or None,
                         "recoveries": getattr(pol, "recoveries", None),
                         "frames": len(env.frames), "file": path.name,
                         "bytes": path.stat().st_size})
            bar.set_postfix(seated=sum(r["success"] for r in rows), frames=len(env.frames))
    finally:
        env.close()
    atomic_write_text(out / "videos.json", json.dumps(
        {"env_id": env_id, "policy": policy, "cameras": cameras, "size": size, "fps": fps,
         "episodes": rows, "provenance": provenance()}, indent=1))
    return rows
