"""Compute accounting of the grids: what the committed cells cost on this machine, what the
whole ``cpu`` grid and the ``long`` grid (the paper's 3.0 h on the ``cpu`` learner) cost, and
projections of the ``cpu`` grid under the ``paper`` profile and of the ``long`` grid on one
GPU.

    python benchmarks/compute_accounting.py [--runs leaderboard/runs] [--slots 2]

Measured: every finished cell's wall clock (``sweep-logs/<env>/<run>.json``, which includes
process start-up and waiting for a shared Stage I, and the run's own ``final.wall_clock_s``).
Projected, and labelled so:

* a whole grid on this machine: every cell of ``experiments/table{2,3,5,6,7}.toml`` (the
  ``cpu`` grid) or ``experiments/long.toml`` at the median wall clock of the finished cells
  of its method and profile (for the ``cpu`` grid, all finished ``cpu`` cells' median where a
  method has none yet; for the ``long`` grid, the ``long`` cells' median), divided by the
  number of cells that run at a time;
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
LONG_GRID = "long"
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


def update_cost(profile: str = "paper") -> dict:
    """FLOPs and aten ops of one QC-FQL update at ``profile``'s network size."""
    import logging

    logging.getLogger("torchrl").setLevel(logging.WARNING)   # its INFO lines go to stdout
    torch.set_num_threads(1)
    demo, online = make_replays(0)
    agent = QCFQLAgent(OBS_DIM, 7, QCFQLConfig(hidden=get_profile(profile).hidden), seed=0)
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
    by_key: dict[tuple[str, str], list[float]] = {}
    for c in cells:
        by_key.setdefault((c["method"], c["profile"]), []).append(wall(c))

    def projected(grids, fallback_profile):
        """Cells of ``grids``, training cells, and their summed median wall clock (s)."""
        pool_all = [wall(c) for c in cells if c["profile"] == fallback_profile]
        n, train, total = 0, 0, 0.0
        for g in grids:
            for cell in load_grid(Path("experiments") / f"{g}.toml").cells:
                n += 1
                if cell.on is not None:      # Table 7: one M = 100 evaluation, ~1/10 of a run
                    continue
                train += 1
                pool = by_key.get((cell.method, cell.profile)) or pool_all
                total += statistics.median(pool) if pool else float("nan")
        return n, train, total

    grid_cells, train_cells, projected_s = projected(GRIDS, "cpu")
    env = json.loads(Path("benchmarks/results/env_speed.json").read_text())
    env_step_s = 1.0 / env["results"]["state env steps/s, random actions"]["median"]
    eval_steps_per_episode = 0.8 * 250 + 0.2 * 600   # measured cpu runs: ~80 %, ~25 s cycles

    def gpu_run(profile: str, final_episodes: int = 0) -> dict:
        """One training cell of ``profile`` on one GPU (updates) and its host's CPU cores."""
        p = get_profile(profile)
        upd = update_cost(profile)
        updates = p.offline_steps + p.budget_steps * p.utd
        ms_update = max(upd["ms_flop_bound"], upd["ms_launch_bound"])
        checkpoints = p.budget_steps // p.checkpoint_every + 1
        eval_env_steps = (checkpoints * p.eval_episodes + final_episodes) * eval_steps_per_episode
        run_h = {"updates_gpu_h": updates * ms_update / 1000 / 3600,
                 "online_env_cpu_h": (p.budget_steps + p.warm_steps) * env_step_s / 3600,
                 "evaluation_env_cpu_h": eval_env_steps * env_step_s / GPU_HOST_CORES / 3600}
        return {"update": upd, "updates_per_run": updates, "ms_per_update": ms_update,
                "per_run_h": {k: round(v, 2) for k, v in run_h.items()},
                "run_h": round(sum(run_h.values()), 2)}

    paper_run = gpu_run("paper")
    long_grid = load_grid(Path("experiments") / f"{LONG_GRID}.toml")
    long_names = {cell.name for cell in long_grid.cells}
    long_cells = [c for c in cells if c["cell"] in long_names]
    long_n, long_train, long_s = projected((LONG_GRID,), LONG_GRID)
    long_run = gpu_run(LONG_GRID, final_episodes=long_grid.M)
    out = {"benchmark": "compute_accounting", "provenance": provenance(),
           "finished_cells": cells,
           "median_cell_wall_s_by_method_and_profile": {
               f"{m} {p}": statistics.median(v) for (m, p), v in by_key.items()},
           "grid": {"cells": grid_cells, "train_cells": train_cells, "slots": a.slots,
                    "projected_wall_h": projected_s / a.slots / 3600,
                    "finished": len(cells) - len(long_cells),
                    "measured_cell_h": round(sum(wall(c) for c in cells
                                                 if c["profile"] != LONG_GRID) / 3600, 1),
                    "measured_run_h": round(sum(c["run_wall_s"] for c in cells
                                                if c["profile"] != LONG_GRID) / 3600, 1)},
           "paper_profile_gpu_projection": {
               "assumptions": {"sustained_tflops": SUSTAINED_TFLOPS, "us_per_aten_op": US_PER_OP,
                               "gpu_host_cores_for_evaluation": GPU_HOST_CORES,
                               "eval_steps_per_episode": eval_steps_per_episode},
               **paper_run, "grid_h_one_gpu": round(paper_run["run_h"] * train_cells, 1)},
           "long_grid": {
               "cells": long_n, "finished": len(long_cells),
               "measured_cell_h": round(sum(wall(c) for c in long_cells) / 3600, 2),
               "projected_wall_h": (long_s / a.slots / 3600) if long_cells else None,
               "gpu_projection": {**long_run,
                                  "grid_h_one_gpu": round(long_run["run_h"] * long_train, 1)}}}
    atomic_write_text(a.out, json.dumps(out, indent=1))
    print(markdown(out))
    return out


def markdown(o: dict) -> str:
    g, p = o["grid"], o["paper_profile_gpu_projection"]
    lines = ["| method | profile | finished cells | median cell wall clock (min) |",
             "|---|---|---|---|"]
    counts: dict[str, int] = {}
    for c in o["finished_cells"]:
        key = f"{c['method']} {c['profile']}"
        counts[key] = counts.get(key, 0) + 1
    for key, s in sorted(o["median_cell_wall_s_by_method_and_profile"].items(),
                         key=lambda kv: (kv[0].split()[1] != "cpu", kv[0])):
        m, prof = key.split()
        lines.append(f"| `{m}` | `{prof}` | {counts[key]} | {s / 60:.1f} |")
    u = p["update"]
    lg = o["long_grid"]
    lr = lg["gpu_projection"]
    pace = ("the env steps, not the updates," if lr["per_run_h"]["online_env_cpu_h"]
            > lr["per_run_h"]["updates_gpu_h"] else "the updates, not the env steps,")
    mine = ("not yet projected (no finished `long` cell)" if lg["projected_wall_h"] is None
            else f"projected **{lg['projected_wall_h']:.1f} h** on this machine with {g['slots']} "
                 f"cells at a time")
    return "\n".join(lines) + f"""

**Measured.** The {g['finished']} finished cells outside the `long` grid logged
**{g['measured_cell_h']} cell-hours** from a cell's start to its end in the sweep record
({g['measured_run_h']} h in `bench run`'s own clock), about {g['measured_cell_h'] / g['slots']:.0f} h
of this machine at {g['slots']} cells at a time. A cell resumed after an interruption counts
only its last part, and most cells ran beside other jobs: this is the cost of the grid as it
was run, not on an idle machine (the projection below).

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
cells** one after the other on one GPU.

`long` grid (`experiments/long.toml`, {lg['cells']} cells): {lg['finished']} finished, measured
**{lg['measured_cell_h']} cell-hours**; the whole grid {mine}. On one GPU (projected): the
`cpu`-size update is {lr['update']['aten_ops']} aten ops, {lr['ms_per_update']} ms launch-bound;
{lr['updates_per_run']:,} updates ({lr['per_run_h']['updates_gpu_h']} h), the env steps on one
core ({lr['per_run_h']['online_env_cpu_h']} h) and the evaluations on
{p['assumptions']['gpu_host_cores_for_evaluation']} cores ({lr['per_run_h']['evaluation_env_cpu_h']} h):
about **{lr['run_h']} h per cell, {lr['grid_h_one_gpu']} h for the grid**: {pace} set its
pace."""


if __name__ == "__main__":
    main()
