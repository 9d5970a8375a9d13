"""Where a pixel learner call's time goes: ``torch.profiler`` over learner calls of the pixel
and the state learner of one method, each operator's self CPU time assigned to a part of the
pixel front end by its operator and input shapes (the 16,384 feature-map values of a stored
row, the 8,192 of a view, the aggregation's 512 channels and 4,096 spatial embeddings), the
rest left to the learner behind it.

The learners and batches are those of ``benchmarks/pixel_learners_speed.py`` (``cpu`` sizes,
the harness's Stage III ``mixed_batch`` for QC-FQL and HIL-SERL, SB3's own buffer for SAC).
The profiler adds a fixed cost per operator, which weighs most on the state learner's many
small operators: read the shares of a pixel call, and take speed ratios from
``pixel_learners_speed.py``.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/pixel_update_profile.py [--methods hil-serl sac]
        [--calls 5]

Results go to ``benchmarks/results/pixel_update_profile.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pixel_learners_speed import KINDS, STATE_DIM, learner  # noqa: E402

from window_bench.harness.evaluation import atomic_write_text, provenance  # noqa: E402
from window_bench.pixels.encoder import OBS_DIM  # noqa: E402

#: (part, operator names or None for any, a substring of the input shapes), first match wins.
PARTS = (
    ("replay: gather the stored float16 rows", ("aten::index_select", "aten::index"), "16384"),
    ("replay: widen float16 -> float32 into the batch", ("aten::copy_",), "16384"),
    ("aggregation: forward GEMM (8,192 -> 32 per view)", ("aten::addmm", "aten::mm"),
     "[8192, 32]"),
    ("aggregation: weight gradient GEMM", ("aten::mm",), "[256, 8192]"),
    ("aggregation: Adam and Polyak steps of its weights", None, "4096"),
    ("aggregation: Adam and Polyak steps of its weights", None, "[512, 4, 4, 8]"),
    ("aggregation: folding kernels and bottleneck (and back)", None, "512"),
)
REST = "the learner behind the front end (MLPs, losses, its optimisers), LayerNorm/tanh, glue"


def part_of(name: str, shapes: str) -> str:
    for part, ops, shape in PARTS:
        if (ops is None or name in ops) and shape in shapes:
            return part
    return REST


def profiled(kind: str, obs_dim: int, h: int, calls: int) -> dict:
    agent, sample = learner(kind, obs_dim, h)
    agent.learn(sample)                                              # warm-up
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        for _ in range(calls):
            agent.learn(sample)
    parts: dict[str, float] = {}
    for ev in prof.key_averages(group_by_input_shape=True):
        part = part_of(ev.key, str(ev.input_shapes))
        parts[part] = parts.get(part, 0.0) + ev.self_cpu_time_total / 1e3 / calls
    return {"ms_per_call": sum(parts.values()),
            "parts_ms_per_call": dict(sorted(parts.items(), key=lambda kv: -kv[1]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", nargs="+", default=["hil-serl", "sac"], choices=list(KINDS))
    ap.add_argument("--calls", type=int, default=5, help="profiled learner calls per learner")
    ap.add_argument("--out", default="benchmarks/results/pixel_update_profile.json")
    args = ap.parse_args(argv)
    if args.calls < 1:
        ap.error(f"--calls must be >= 1, got {args.calls}")
    torch.set_num_threads(1)
    result = {"calls": args.calls, "batch": 256, "hidden": [256, 256], "methods": {}}
    for m in args.methods:
        state, pixels, h = KINDS[m]
        row = {"state": profiled(state, STATE_DIM, h, args.calls),
               "pixels": profiled(pixels, OBS_DIM, h, args.calls)}
        result["methods"][m] = row
        total = row["pixels"]["ms_per_call"]
        print(f"\n{m}: profiled pixel call {total:.1f} ms, state call "
              f"{row['state']['ms_per_call']:.1f} ms (self CPU time under the profiler)")
        for part, ms in row["pixels"]["parts_ms_per_call"].items():
            print(f"  {ms:7.1f} ms  {100 * ms / total:5.1f} %  {part}")
    result["provenance"] = provenance()
    atomic_write_text(args.out, json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
