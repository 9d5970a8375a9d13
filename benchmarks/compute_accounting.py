"""Compute accounting of the grid (issue 17): what the committed cells cost on this machine,
what the whole grid costs, and a projection of the same grid under the ``paper`` profile on
one GPU.

    python benchmarks/compute_accounting.py [--runs leaderboard/runs] [--slots 2]

Measured: every finished cell's wall clock (``sweep-logs/<env>/<run>.json``, which includes
process start-up and waiting for a shared Stage I, and the run's own ``final.wall_clock_s``).
Projected, and labelled so:

* the whole grid on this machine: every cell of ``experiments/table{2,3,5,6,7}.toml`` at the
  median wall clock of the finished cells of its method (all finished cells' median where a
  method has none yet), divided by the number of cells that run at a time;
* the ``paper`` profile on one GPU. No GPU was lent to the sessions that wrote this, so
  nothing was timed on one. An update's time is bounded below by its work and by its kernel
  count: ``max(FLOPs / sustained rate, aten ops * per-op cost)``, where the FLOPs and the
  number of aten ops of one ``paper``-size QC-FQL update are counted here (torch's
  ``FlopCounterMode`` and a dispatch-mode counter; every aten op is taken as one kernel
  launch) and the two rates are the stated assumptions below. Env steps stay on the CPU: their
  cost is ``benchmarks/results/env_speed.json``'s measured step time, with the evaluation
  rollouts spread over the GPU machine's cores.

Writes ``benchmarks/results/compute_accounting.json`` and prints the Markdown that
``docs/snippets/compute_measured.md`` holds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from update_speed import BATCH, OBS_DIM, make_replays  # noqa: E402

from baselines.qcfql import QCFQLAgent, QCFQLConfig  # noqa: E402
from window_bench.data.replay import mixed_batch  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text, provenance  # noqa: E402
from window_bench.harness.methods import get_profile  # noqa: E402
from window_bench.harness.sweep import load_grid  # noqa: E402

GRIDS = ("table2", "table3", "table5", "table6", "table7")
#: Assumptions of the GPU projection (one H200, PyTorch eager, float32 with TF32 matmuls).
SUSTAINED_TFLOPS = 100.0      # small (256-row) matmuls reach a fraction of the ~495 TF32 peak
US_PER_OP = 10.0              # eager dispatch + launch per aten op, CPU-bound on the host
GPU_HOST_CORES = 16           # the lent GPU machine's cores, for evaluation rollouts


class OpCounter(TorchDispatchMode):
    """Counts aten ops below autograd (forward and backward): a proxy for kernel launches."""

    def __init__(self):
        super().__init__()
        self.ops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        return func(*args, **(kwargs or {}))


def paper_update_cost() -> dict:
    torch.set_num_threads(1)
    demo, online = make_replays(0)
    agent = QCFQLAgent(OBS_DIM, 7, QCFQLConfig(hidden=get_profile("paper").hidden), seed=0)
    batch = mixed_batch(demo, online, BATCH)
    agent.update(batch)                                  # first-call allocations
    with FlopCounterMode(display=False) as flops:
        agent.update(batch)
    with OpCounter() as ops:
        agent.update(batch)
    gflop = flops.get_total_flops() / 1e9
    return {"gflop": round(gflop, 3), "aten_ops": ops.ops,
            "ms_flop_bound": round(gflop / SUSTAINED_TFLOPS, 3),
            "ms_launch_bound": round(ops.ops * US_PER_OP / 1000, 3)}


def finished_cells(runs: Path) -> list[dict]:
    cells = []
    for res in sorted(runs.glob("WindowInstall-*/*/results.json")):
        r = json.loads(res.read_text())
        if not (r.get("final_eval") or {}).get("policy"):
            continue
        log = runs / "sweep-logs" / res.parent.parent.name / f"{res.parent.name}.json"
        sweep = json.loads(log.read_text()) if log.exists() else {}
        cells.append({"cell": f"{res.parent.parent.name}/{res.parent.name}",
                      "method": r["method"]["name"], "profile": r["profile"]["name"],
                      "run_wall_s": r["final"]["wall_clock_s"],
                      "cell_wall_s": sweep.get("wall_s"),
                      "final_eval_s": (r.get("final_eval") or {}).get("wall_clock_s")})
    return cells


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", default="leaderboard/runs")
    ap.add_argument("--slots", type=int, default=2, help="cells at a time on this machine")
    ap.add_argument("--out", default="benchmarks/results/compute_accounting.json")
    a = ap.parse_args(argv)
    cells = finished_cells(Path(a.runs))
    wall = lambda c: c["cell_wall_s"] or c["run_wall_s"]  # noqa: E731
    by_method: dict[str, list[float]] = {}
    for c in cells:
        by_method.setdefault(c["method"], []).append(wall(c))
    everything = [wall(c) for c in cells]
    grid_cells, projected_s = 0, 0.0
    for g in GRIDS:
        for cell in load_grid(Path("experiments") / f"{g}.toml").cells:
            grid_cells += 1
            if cell.on is not None:          # Table 7: one M = 100 evaluation, ~1/10 of a run
                continue
            pool = by_method.get(cell.method) or everything
            projected_s += statistics.median(pool) if pool else float("nan")
    env = json.loads(Path("benchmarks/results/env_speed.json").read_text())
    env_step_s = 1.0 / env["results"]["state env steps/s, random actions"]["median"]
    paper = get_profile("paper")
    upd = paper_update_cost()
    updates = paper.offline_steps + paper.budget_steps * paper.utd
    ms_update = max(upd["ms_flop_bound"], upd["ms_launch_bound"])
    checkpoints = paper.budget_steps // paper.checkpoint_every + 1
    eval_steps_per_episode = 0.8 * 250 + 0.2 * 600   # measured cpu runs: ~80 %, ~25 s cycles
    eval_env_steps = checkpoints * paper.eval_episodes * eval_steps_per_episode
    run_h = {"updates_gpu_h": updates * ms_update / 1000 / 3600,
             "online_env_cpu_h": (paper.budget_steps + paper.warm_steps) * env_step_s / 3600,
             "evaluation_env_cpu_h": eval_env_steps * env_step_s / GPU_HOST_CORES / 3600}
    train_cells = sum(1 for g in GRIDS for c in load_grid(Path("experiments") / f"{g}.toml").cells
                      if c.on is None)
    out = {"benchmark": "compute_accounting", "provenance": provenance(),
           "finished_cells": cells,
           "median_cell_wall_s_by_method": {m: statistics.median(v) for m, v in by_method.items()},
           "grid": {"cells": grid_cells, "train_cells": train_cells, "slots": a.slots,
                    "projected_wall_h": projected_s / a.slots / 3600,
                    "finished": len(cells)},
           "paper_profile_gpu_projection": {
               "assumptions": {"sustained_tflops": SUSTAINED_TFLOPS, "us_per_aten_op": US_PER_OP,
                               "gpu_host_cores_for_evaluation": GPU_HOST_CORES,
                               "eval_steps_per_episode": eval_steps_per_episode},
               "update": upd, "updates_per_run": updates, "ms_per_update": ms_update,
               "per_run_h": {k: round(v, 2) for k, v in run_h.items()},
               "run_h": round(sum(run_h.values()), 2),
               "grid_h_one_gpu": round(sum(run_h.values()) * train_cells, 1)}}
    atomic_write_text(a.out, json.dumps(out, indent=1))
    print(markdown(out))
    return out


def markdown(o: dict) -> str:
    g, p = o["grid"], o["paper_profile_gpu_projection"]
    lines = ["| method | finished cells | median cell wall clock (min) |", "|---|---|---|"]
    counts: dict[str, int] = {}
    for c in o["finished_cells"]:
        counts[c["method"]] = counts.get(c["method"], 0) + 1
    for m, s in sorted(o["median_cell_wall_s_by_method"].items()):
        lines.append(f"| `{m}` | {counts[m]} | {s / 60:.1f} |")
    u = p["update"]
    return "\n".join(lines) + f"""

Whole grid (Tables 2-7, {g['cells']} cells of which {g['train_cells']} train): projected
**{g['projected_wall_h']:.1f} h** on this machine with {g['slots']} cells at a time, from the
{g['finished']} finished cells above (a projection, not a measurement).

`paper` profile on one GPU (projected; no GPU was timed): one update is {u['gflop']} GFLOP and
{u['aten_ops']} aten ops, so {u['ms_flop_bound']} ms at {p['assumptions']['sustained_tflops']:.0f}
sustained TFLOPS and {u['ms_launch_bound']} ms at {p['assumptions']['us_per_aten_op']:.0f} µs per op:
launch-bound, {p['ms_per_update']} ms per update. A run is {p['updates_per_run']:,} updates
({p['per_run_h']['updates_gpu_h']} h), the online env steps on one CPU core
({p['per_run_h']['online_env_cpu_h']} h) and the M = 100 evaluations spread over
{p['assumptions']['gpu_host_cores_for_evaluation']} cores ({p['per_run_h']['evaluation_env_cpu_h']} h):
about **{p['run_h']} h per run, {p['grid_h_one_gpu']} h for the {g['train_cells']} training
cells** one after the other on one GPU."""


if __name__ == "__main__":
    main()
