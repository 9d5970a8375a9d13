"""The pixel-demo cache, miss against hit: what a pixel-track run (or resume) pays to get its
re-observed demonstrations with and without an entry on disk.

Collects ``--n`` demonstrations of the ``average`` operator (seed 1,000,000, as ``bench run``
seed 0 does) into a temporary directory, then calls
:func:`window_bench.pixels.demo_cache.cached_pixel_demos` with the shipped encoder: once on an
empty cache (a miss: replay, render, encode, write) and ``--repeats`` times on the entry it
wrote (hits), checking every hit bit for bit against the miss. Reports the miss, the median
hit, the entry's size and the per-step size.

``--cpu-scale`` instead times the write and the hits of an entry the size of a ``cpu`` run's
(50 demonstrations of ``--steps`` steps each, 193 the measured mean) with random feature maps
(float16-exact) in place of re-observed ones: what a hit costs does not depend on what the
features are, and re-observing 50 demonstrations takes about half an hour.

Usage::

    OMP_NUM_THREADS=1 MUJOCO_GL=egl python benchmarks/pixel_demo_cache.py [--n 2] [--repeats 5]
    OMP_NUM_THREADS=1 python benchmarks/pixel_demo_cache.py --cpu-scale [--steps 193]

Results go to ``benchmarks/results/pixel_demo_cache.json`` (``pixel_demo_cache_cpu_scale.json``
with ``--cpu-scale``), written atomically.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.installer.demos import collect_demos, load_demos
from window_bench.pixels.demo_cache import (PixelDemoCache, cache_key, cached_pixel_demos,
                                            key_material)
from window_bench.pixels.weights import resolve_backbone

ENV = "WindowInstall-A-v0"


def cpu_scale(steps: int, repeats: int, out: str) -> None:
    """Write and hit an entry of 50 synthetic demonstrations of ``steps`` steps."""
    import numpy as np

    from window_bench.data.steplog import EpisodeLog
    from window_bench.pixels.encoder import FEATURE_VALUES, OBS_DIM

    rng = np.random.default_rng(0)
    demos, pixel = [], []
    for i in range(50):
        obs = rng.standard_normal((steps + 1, OBS_DIM)).astype(np.float32)
        obs[:, :FEATURE_VALUES] = obs[:, :FEATURE_VALUES].astype(np.float16)
        ep = EpisodeLog(observations=rng.standard_normal((steps + 1, 52)).astype(np.float32),
                        actions=np.zeros((steps, 7), np.float32), rewards=np.zeros(steps),
                        terminated=np.zeros(steps, bool), truncated=np.zeros(steps, bool),
                        provenance=np.full(steps, "demo"), takeover_kind=np.full(steps, "none"),
                        episode_id=i, seed=1_000_000 + i)
        demos.append(ep)
        pixel.append(dataclasses.replace(ep, observations=obs))
    backbone, label = resolve_backbone(None)
    material = key_material(demos, ENV, backbone)
    key = cache_key(material)
    with tempfile.TemporaryDirectory() as tmp:
        cache = PixelDemoCache(tmp)
        t = time.perf_counter()
        cache.store(key, pixel, material, 0.0)
        write_s = time.perf_counter() - t
        hits = []
        for _ in range(repeats):
            t = time.perf_counter()
            got, rec = cached_pixel_demos(demos, ENV, backbone, tmp)
            hits.append(time.perf_counter() - t)
            assert rec["cache_hit"] and all(a.observations.tobytes() == b.observations.tobytes()
                                            for a, b in zip(got, pixel))
        size = cache.path(key).stat().st_size
    result = {"what": "cpu-scale entry, random float16-exact feature maps", "demos": 50,
              "steps": 50 * steps, "observations": 50 * (steps + 1), "write_s": round(write_s, 2),
              "hit_median_s": round(statistics.median(hits), 2),
              "hits_s": [round(h, 2) for h in hits], "entry_bytes": size,
              "provenance": provenance()}
    atomic_write_text(out, json.dumps(result, indent=1))
    print(f"cpu scale, 50 x {steps} steps: write {write_s:.1f} s, hit median "
          f"{statistics.median(hits):.2f} s over {repeats}; entry {size / 2**20:.0f} MiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2, help="demonstrations (a cpu run has 50)")
    ap.add_argument("--repeats", type=int, default=5, help="hits to time")
    ap.add_argument("--cpu-scale", action="store_true", help="a cpu run's entry, synthetic")
    ap.add_argument("--steps", type=int, default=193, help="--cpu-scale: steps per demo")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.cpu_scale:
        return cpu_scale(args.steps, args.repeats, args.out or
                         "benchmarks/results/pixel_demo_cache_cpu_scale.json")
    args.out = args.out or "benchmarks/results/pixel_demo_cache.json"
    backbone, label = resolve_backbone(None)
    with tempfile.TemporaryDirectory() as tmp:
        collect_demos(ENV, args.n, tmp, operator="average", seed=1_000_000, progress=False)
        demos = load_demos(tmp, ENV, "average")
        cache = Path(tmp) / "pixel_cache"
        t = time.perf_counter()
        ref, miss = cached_pixel_demos(demos, ENV, backbone, cache, progress=True)
        miss_s = time.perf_counter() - t
        assert not miss["cache_hit"]
        hits = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            got, rec = cached_pixel_demos(demos, ENV, backbone, cache)
            hits.append(time.perf_counter() - t)
            assert rec["cache_hit"] and all(a.observations.tobytes() == b.observations.tobytes()
                                            for a, b in zip(got, ref))
        size = (cache / f"{miss['key']}.safetensors").stat().st_size
    steps = sum(ep.T for ep in demos)
    obs = steps + len(demos)
    result = {
        "env_id": ENV, "encoder": label, "demos": len(demos), "steps": steps,
        "observations": obs, "miss_s": round(miss_s, 2),
        "hit_median_s": round(statistics.median(hits), 3), "hits_s": [round(h, 3) for h in hits],
        "speedup": round(miss_s / statistics.median(hits), 1),
        "entry_bytes": size, "bytes_per_observation": round(size / obs, 1),
        "float32_bytes_per_observation": ref[0].observations.shape[1] * 4,
        "provenance": provenance()}
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(f"{len(demos)} demos ({steps} steps): miss {miss_s:.1f} s, hit median "
          f"{statistics.median(hits):.3f} s over {args.repeats} ({result['speedup']}x); entry "
          f"{size / 2**20:.1f} MiB, {size / obs / 1024:.1f} KiB per observation")


if __name__ == "__main__":
    main()
