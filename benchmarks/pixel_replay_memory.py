"""Replay memory of ``cpu``-profile runs on the pixel track, measured from the storage.

Builds the harness's own replays (``ChunkReplay`` with and without ``half_obs``, the float16
feature storage of the pixel track) at a small capacity, reads the bytes per stored chunk
from the preallocated TorchRL storage, and multiplies by the capacities ``Run._make_replays``
preallocates for a ``cpu``-profile run: online ``budget // h + 2 x 600`` chunks, demo
``sum(ceil(T / h))`` over the 50 demonstrations (plus the whole budget for HIL-SERL, whose
takeovers join D_demo), at the 600-step bound and at a given mean demonstration length.
It also times ``sample(256)`` of h = 10 chunks from both replays (the float16 copy is
widened on sampling): medians of interleaved repeats.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/pixel_replay_memory.py [--mean-demo-steps 193]
        [--repeats 7] [--samples 10]

Results go to ``benchmarks/results/pixel_replay_memory.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from window_bench.data.replay import ChunkReplay
from window_bench.data.steplog import EpisodeLog
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.methods import PROFILES
from window_bench.pixels.encoder import FEATURE_VALUES, OBS_DIM

RUNS = (("qcfql-offline / qcfql (h = 10)", 10, False), ("qcfql-stepwise (h = 1)", 1, False),
        ("hil-serl (h = 1)", 1, True))


def pixel_replay(h: int, half: bool, T: int = 40, seed: int = 0) -> ChunkReplay:
    """One random episode of pixel observations (feature maps float16-exact, as
    ``PixelFeatures`` makes them) in a replay of the pixel track's layout."""
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((T + 1, OBS_DIM)).astype(np.float32)
    obs[:, :FEATURE_VALUES] = obs[:, :FEATURE_VALUES].astype(np.float16)
    rb = ChunkReplay(-(-T // h), h, 0.99, seed=seed, half_obs=FEATURE_VALUES if half else 0)
    rb.add_episode(EpisodeLog(
        observations=obs, actions=rng.uniform(-1, 1, (T, 7)), rewards=np.zeros(T),
        terminated=np.zeros(T, bool), truncated=np.r_[np.zeros(T - 1, bool), True],
        provenance=["policy"] * T, takeover_kind=[""] * T, chunk_horizon=h))
    return rb


def stored_bytes_per_chunk(rb: ChunkReplay) -> int:
    """Bytes of the preallocated storage divided by its capacity (every key, as stored)."""
    storage = rb._buffer.storage._storage
    return int(sum(v.nbytes for v in storage.values(include_nested=True, leaves_only=True))
               // rb.capacity)


def capacity(h: int, hil: bool, demo_steps: int) -> int:
    p = PROFILES["cpu"]
    online = p.budget_steps // h + 2 * p.max_episode_steps
    return online + p.n_demos * -(-demo_steps // h) + (p.budget_steps if hil else 0)


def sample_rate(rb: ChunkReplay, n: int, repeats: int) -> float:
    t0 = time.perf_counter()
    for _ in range(repeats):
        rb.sample(n)
    return repeats / (time.perf_counter() - t0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mean-demo-steps", type=int, default=193,
                    help="measured mean demonstration length on A (the bound is 600)")
    ap.add_argument("--samples", type=int, default=10, help="timed sample(256) calls per repeat")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default="benchmarks/results/pixel_replay_memory.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    per_chunk = {(h, half): stored_bytes_per_chunk(pixel_replay(h, half))
                 for h in (1, 10) for half in (False, True)}
    rows = []
    for label, h, hil in RUNS:
        for steps in (600, args.mean_demo_steps):
            n = capacity(h, hil, steps)
            rows.append({"run": label, "demo_steps": steps, "chunks": n,
                         "float32_GiB": round(n * per_chunk[h, False] / 2 ** 30, 2),
                         "float16_features_GiB": round(n * per_chunk[h, True] / 2 ** 30, 2)})
    # Interleaved repeats, medians: the machine is shared, slow phases hit both replays.
    replays = {"float32": pixel_replay(10, False, T=600),
               "float16_features": pixel_replay(10, True, T=600)}
    raw = {k: [] for k in replays}
    for _ in range(args.repeats):
        for k, rb in replays.items():
            raw[k].append(sample_rate(rb, 256, args.samples))
    rates = {k: float(np.median(v)) for k, v in raw.items()}
    result = {"bytes_per_chunk": {f"h={h}, {'float16_features' if half else 'float32'}": b
                                  for (h, half), b in per_chunk.items()},
              "cpu_profile_replay": rows, "sample256_per_s": rates,
              "sample_repeats": args.repeats, "samples_per_repeat": args.samples,
              "provenance": provenance()}
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "provenance"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
