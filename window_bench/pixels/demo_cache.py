"""The pixel-demo cache: the state-track demonstrations re-observed on the pixel track once,
then read from disk by every run (and every resume) that needs them.

:func:`~window_bench.pixels.track.pixel_demos` replays each demonstration's actions from its
seed under :class:`~window_bench.pixels.features.PixelFeatures`: two renders and a ResNet-10
pass per step, about half an hour for the 50 demonstrations of a ``cpu`` run on two loaded
cores. Its result is fully determined by

* the demonstrations (:func:`~window_bench.harness.stage1.demos_sha256` over their
  observations and actions, plus their seeds, rewards and terminations, which the replay
  starts from and checks),
* the env id and the code of the environment (every module of :mod:`window_bench.envs`: the
  scene's cameras, the physics the replay runs, the proprioception),
* the frozen backbone (a sha256 over its tensors, whatever file or seed they came from),
* the pixel observation layout (views, image size, float16 feature maps) and the code that
  renders and encodes (``features.py``, ``encoder.py``, ``track.py``),
* the MuJoCo and torch versions and ``MUJOCO_GL`` (renderer and convolution numerics),

and the cache key is the sha256 of exactly that (:func:`key_material`). An entry
``<key>.safetensors`` holds every observation of every episode, the feature maps as float16
(lossless: ``PixelFeatures`` rounds them to float16) and the 18 proprioceptive values as
float32, in the code-free state format of :mod:`window_bench.harness.files` (a sha256 over
its content, no pickle), written atomically; ``<key>.json`` records what the key hashes,
the size and how long the re-observation took. Two runs that miss the same entry take an
``fcntl`` lock on ``<key>.lock``: the first computes, the second waits and then loads. An
entry that does not load or does not fit the demonstrations (cut, corrupt, edited, another
episode count) is reported on one line and recomputed, never used.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import time

import numpy as np

from window_bench.harness.evaluation import atomic_write, atomic_write_text
from window_bench.harness.stage1 import Stage1Cache

KIND = "pixel_demos"
#: Bump when what an entry holds, or how it is laid out, changes.
FORMAT_VERSION = 1
#: The cache's directory inside the demonstrations' directory (``--demos``, or the run's
#: ``demos/``) unless a run is given another one.
DEFAULT_SUBDIR = "pixel_cache"
_CODE = ("window_bench.pixels.features", "window_bench.pixels.encoder",
         "window_bench.pixels.cameras", "window_bench.pixels.track", "window_bench.envs.env",
         "window_bench.envs.scene", "window_bench.envs.task", "window_bench.envs.controller",
         "window_bench.envs.wrappers")


def backbone_sha256(backbone) -> str:
    """sha256 over the backbone's tensors (names, dtypes, shapes, bytes), buffers included."""
    import torch

    h = hashlib.sha256()
    for name, t in sorted(backbone.state_dict().items()):
        t = t.detach().cpu().contiguous()
        h.update(f"{name}:{t.dtype}:{list(t.shape)}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def _replay_sha256(demos) -> str:
    """What the replay starts from and checks besides observations and actions."""
    h = hashlib.sha256()
    for ep in demos:
        h.update(f"{int(ep.seed)}:{ep.T}\0".encode())
        for arr in (ep.rewards, ep.terminated):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    return h.hexdigest()


def key_material(demos, env_id: str, backbone, cameras: str = "paper") -> dict:
    """Everything the re-observed observations depend on (see the module docstring)."""
    from window_bench.pixels.cameras import camera_names

    import mujoco
    import torch

    from window_bench.harness.stage1 import _source_sha256, demos_sha256
    from window_bench.pixels.encoder import FEATURE_VALUES, IMAGE_SIZE, OBS_DIM, PROPRIO_DIM, VIEWS

    return {"format_version": FORMAT_VERSION, "env_id": env_id, "episodes": len(demos),
            "demos_sha256": demos_sha256(demos), "replay_sha256": _replay_sha256(demos),
            "encoder_sha256": backbone_sha256(backbone),
            "layout": {"views": list(VIEWS), "cameras": list(camera_names(cameras)),
                       "image_size": IMAGE_SIZE, "obs_dim": OBS_DIM,
                       "feature_values": FEATURE_VALUES, "feature_dtype": "float16",
                       "proprio_dim": PROPRIO_DIM, "proprio_dtype": "float32"},
            "code_sha256": _source_sha256(*_CODE), "mujoco": mujoco.__version__,
            "torch": torch.__version__, "mujoco_gl": os.environ.get("MUJOCO_GL")}


def cache_key(material: dict) -> str:
    return hashlib.sha256(json.dumps(material, sort_keys=True).encode()).hexdigest()


def _pack(pixel_eps: list) -> dict:
    """The observations of ``pixel_eps`` as one entry; refuses feature maps that float16
    would change (PixelFeatures rounds them, so this means the features code changed)."""
    from window_bench.pixels.encoder import FEATURE_VALUES

    features, proprio = [], []
    for ep in pixel_eps:
        obs = np.asarray(ep.observations, np.float32)
        features.append(obs[:, :FEATURE_VALUES].astype(np.float16))
        if not np.array_equal(features[-1].astype(np.float32).view(np.uint32),
                              obs[:, :FEATURE_VALUES].view(np.uint32)):
            raise RuntimeError("pixel demos: feature maps are not float16-exact, so the cache "
                               "would not return them bit for bit (PixelFeatures changed?)")
        proprio.append(obs[:, FEATURE_VALUES:])
    return {"features": np.concatenate(features), "proprio": np.concatenate(proprio),
            "lengths": np.array([len(ep.observations) for ep in pixel_eps], np.int64),
            "episode_ids": [int(ep.episode_id) for ep in pixel_eps],
            "seeds": [int(ep.seed) for ep in pixel_eps]}


def _unpack(tree: dict, demos: list) -> list:
    """The episodes ``pixel_demos(demos, ...)`` returns, rebuilt from an entry;
    ``ValueError`` when the entry does not belong to ``demos``."""
    from window_bench.pixels.encoder import FEATURE_VALUES, PROPRIO_DIM

    lengths = [int(n) for n in tree["lengths"]]
    features, proprio = tree["features"], tree["proprio"]
    expected = [ep.T + 1 for ep in demos]
    if lengths != expected or tree["seeds"] != [int(ep.seed) for ep in demos] \
            or tree["episode_ids"] != [int(ep.episode_id) for ep in demos]:
        raise ValueError(f"holds {len(lengths)} episodes of {sum(lengths)} observations, the "
                         f"demonstrations have {len(expected)} of {sum(expected)}")
    n = sum(lengths)
    if features.shape != (n, FEATURE_VALUES) or features.dtype != np.float16 \
            or proprio.shape != (n, PROPRIO_DIM) or proprio.dtype != np.float32:
        raise ValueError(f"arrays {features.dtype}{features.shape} and "
                         f"{proprio.dtype}{proprio.shape} do not have the pixel layout")
    out, start = [], 0
    for ep, length in zip(demos, lengths):
        stop = start + length
        obs = np.concatenate([features[start:stop].astype(np.float32), proprio[start:stop]], 1)
        out.append(dataclasses.replace(ep, observations=obs))
        start = stop
    return out


class PixelDemoCache(Stage1Cache):
    """A directory of re-observed demonstrations, ``<key>.safetensors`` + ``<key>.json``: the
    Stage I cache's layout and ``<key>.lock``, with entries of its own kind."""

    def load(self, key: str, demos: list):
        """The re-observed ``demos`` of entry ``key``; ``None`` when there is none, or when it
        cannot be used (said on stderr in one line: it is then recomputed)."""
        from window_bench.harness.files import RunFileError, load_state

        path = self.path(key)
        if not path.is_file():
            return None
        try:
            tree, meta = load_state(path, KIND)
            if meta.get("key") != key:
                raise ValueError(f"it is the entry of key {str(meta.get('key'))[:12]}")
            return _unpack(tree, demos)
        except (RunFileError, ValueError, KeyError, TypeError, AttributeError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            print(f"pixel demo cache: {path} cannot be used ({msg}); recomputing it",
                  file=sys.stderr)
            return None

    def store(self, key: str, pixel_eps: list, material: dict, wall_clock_s: float) -> int:
        """Write entry ``key`` (atomically); returns its size in bytes."""
        from window_bench.harness.files import dump_state

        meta = {"key": key, "reobserve_wall_clock_s": round(float(wall_clock_s), 2)}
        data = dump_state(_pack(pixel_eps), KIND, meta)
        atomic_write(self.path(key), lambda f: f.write(data))
        atomic_write_text(self.root / f"{key}.json", json.dumps(
            {**meta, "bytes": len(data), "material": material}, indent=1, sort_keys=True))
        return len(data)


def cached_pixel_demos(demos: list, env_id: str, backbone, cache_dir: str | os.PathLike,
                       progress: bool = False, cameras: str = "paper") -> tuple[list, dict]:
    """``pixel_demos(demos, env_id, backbone)`` through the cache in ``cache_dir``, and the
    record a results file keeps: the key, whether it was a hit, and the seconds it took
    (``lock_wait_s``: waiting for another run computing the same entry). ``cameras``: the
    camera set (:mod:`window_bench.pixels.cameras`), part of the key."""
    from window_bench.pixels import track   # looked up at call time: tests replace it

    t0 = time.perf_counter()
    material = key_material(demos, env_id, backbone, cameras)
    extra = {} if cameras == "paper" else {"cameras": cameras}
    key = cache_key(material)
    try:
        cache = PixelDemoCache(cache_dir)
        writable = os.access(cache.root, os.W_OK)
    except OSError:
        writable = False
    if not writable:   # e.g. a read-only demos directory: the run goes on, uncached
        print(f"pixel demo cache: {cache_dir} cannot be written; re-observing the demos "
              f"without a cache", file=sys.stderr)
        out = track.pixel_demos(demos, env_id, backbone, progress, **extra)
        return out, {"key": key, "cache_hit": False, "cache_dir": None,
                     "wall_clock_s": round(time.perf_counter() - t0, 2), "lock_wait_s": 0.0}
    t_lock = time.perf_counter()
    with cache.lock(key):
        waited = time.perf_counter() - t_lock
        out = cache.load(key, demos)
        hit = out is not None
        if not hit:
            out = track.pixel_demos(demos, env_id, backbone, progress, **extra)
            cache.store(key, out, material, time.perf_counter() - t0 - waited)
    wall = time.perf_counter() - t0 - waited
    if progress and hit:
        print(f"pixel demos: {len(out)} from the cache {cache.path(key)} ({wall:.1f} s)",
              file=sys.stderr)
    return out, {"key": key, "cache_hit": hit, "cache_dir": str(cache.root),
                 "wall_clock_s": round(wall, 2), "lock_wait_s": round(waited, 2)}
