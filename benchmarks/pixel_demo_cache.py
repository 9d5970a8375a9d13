"""The pixel-demo cache, miss against hit: what a pixel-track run (or resume) pays to get its
re-observed demonstrations with and without an entry on disk.

Collects ``--n`` demonstrations of the ``average`` operator (seed 1,000,000, as ``bench run``
seed 0 does) into a temporary directory, then calls
:func:`window_bench.pixels.demo_cache.cached_pixel_demos` with the shipped encoder: once on an
empty cache (a miss: replay, render, encode, write) and ``--repeats`` times on the entry it
wrote (hits), checking every hit bit for bit against the miss. Reports the miss, the median
hit, the entry's size and the per-step size.

Usage::

    OMP_NUM_THREADS=1 MUJOCO_GL=egl python benchmarks/pixel_demo_cache.py [--n 2] [--repeats 5]

Results go to ``benchmarks/results/pixel_demo_cache.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.installer.demos import collect_demos, load_demos
from window_bench.pixels.demo_cache import cached_pixel_demos
from window_bench.pixels.weights import resolve_backbone

ENV = "WindowInstall-A-v0"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2, help="demonstrations (a cpu run has 50)")
    ap.add_argument("--repeats", type=int, default=5, help="hits to time")
    ap.add_argument("--out", default="benchmarks/results/pixel_demo_cache.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
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
