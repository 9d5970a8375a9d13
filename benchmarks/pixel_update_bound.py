"""How close to the state track can a pixel learner call get, whatever the aggregation head
costs? The pixel learners of ``pixel_learners_speed.py`` (the same builders, batches and
``learn`` calls, ``cpu`` sizes) timed with three versions of the per-view trainable head
(``ViewAggregation.forward``), rows interleaved in every repeat:

* ``fp32`` - the head as it is (one folded 8,192 -> 32 GEMM per view, float32);
* ``free`` - the head replaced by a stand-in of next to no cost with the same output shape and
  a gradient path (LayerNorm and tanh of 32 of the map values plus the bottleneck bias): the
  call's cost without the head, i.e. a LOWER BOUND on any implementation of the head that keeps
  the rest of the learner (its replay draws, its MLPs, its number of passes);
* ``bf16`` - the GEMM in bfloat16 (inputs and folded weight cast per call, float32 result);
  this machine's CPU has AMX-BF16, where a bfloat16 GEMM of this shape is about 4x faster.

The issue's target is a pixel call within 2x of the state call. If ``free`` is already at or
above 2x, no head implementation reaches it.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/pixel_update_bound.py [--methods sac hil-serl] [--repeats 5]

Results: ``benchmarks/results/pixel_update_bound.json`` (CPU ms per call, medians over repeats,
ratios to the state call of the same repeat).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pixel_learners_speed as P  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text, provenance  # noqa: E402
from window_bench.pixels import encoder as E  # noqa: E402

FP32 = E.ViewAggregation.forward


def free(self, fmap, weight=None):
    """A stand-in head of next to no cost: 32 map values, the bias, LayerNorm, tanh."""
    return torch.tanh(self.norm(fmap.flatten(1)[:, :E.EMBED_DIM] + self.bottleneck.bias))


def bf16(self, fmap, weight=None):
    """The folded GEMM in bfloat16, result widened to float32."""
    weight = self.folded_weight() if weight is None else weight
    z = F.linear(fmap.flatten(1).to(torch.bfloat16), weight.to(torch.bfloat16)).float()
    return torch.tanh(self.norm(z + self.bottleneck.bias))


HEADS = {"fp32": FP32, "free": free, "bf16": bf16}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", nargs="+", default=["sac", "hil-serl"], choices=list(P.KINDS))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--calls", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results/pixel_update_bound.json")
    a = ap.parse_args(argv)
    if a.repeats < 1 or a.calls < 1:
        ap.error(f"--repeats {a.repeats} and --calls {a.calls} must be >= 1")
    torch.set_num_threads(1)
    rows = {}
    for m in a.methods:
        state, pixels, h = P.KINDS[m]
        rows[(m, "state")] = P.learner(state, P.STATE_DIM, h)
        rows[(m, "pixels")] = P.learner(pixels, P.OBS_DIM, h)
    raw: list[dict] = []
    try:
        for r in range(a.repeats):
            rep = {}
            for head, fwd in HEADS.items():
                E.ViewAggregation.forward = fwd
                for (m, track), (agent, sample) in rows.items():
                    if track == "state" and head != "fp32":
                        continue             # the state learners have no head
                    P.rate(agent, sample, 1)                              # warm-up
                    rep[f"{m} {track}" + (f" {head}" if track == "pixels" else "")] = \
                        P.rate(agent, sample, a.calls)[1]
            raw.append(rep)
            print(f"repeat {r + 1}/{a.repeats}: "
                  + ", ".join(f"{k} {v:.1f}" for k, v in rep.items()) + " CPU ms", flush=True)
    finally:
        E.ViewAggregation.forward = FP32
    med = {k: float(np.median([x[k] for x in raw])) for k in raw[0]}
    ratio = {m: {head: float(np.median([x[f"{m} pixels {head}"] / x[f"{m} state"] for x in raw]))
                 for head in HEADS} for m in a.methods}
    for m in a.methods:
        print(f"{m}: state {med[f'{m} state']:.1f} CPU ms; pixel / state: "
              + ", ".join(f"{h} {v:.2f}x" for h, v in ratio[m].items()))
    atomic_write_text(a.out, json.dumps({"cpu_ms_per_call_median": med,
                                         "pixel_vs_state_cpu_cost": ratio, "repeats": a.repeats,
                                         "calls": a.calls, "raw": raw,
                                         "provenance": provenance()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
