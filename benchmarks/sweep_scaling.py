"""bench sweep with 1 and with 2 Ray workers on the same grid, back to back, and the Stage I
cache on and off on the same grid: wall clock of each sweep.

    python benchmarks/sweep_scaling.py scaling experiments/smoke.toml OUT [--repeats 1]
    python benchmarks/sweep_scaling.py cache experiments/stage1_cache.toml OUT [--repeats 1]

Every sweep starts from an empty runs root into which the grid's demonstrations were copied
beforehand (collected once, so demo collection is not part of what is compared); ``scaling``
runs without the Stage I cache so that the cells are independent. Writes OUT/<mode>.json
with every sweep's wall clock, the per-cell wall clocks, the load average before and after,
and the median ratio.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from window_bench.harness.sweep import demos_command, demos_dir, load_grid


def load() -> list[float]:
    return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]


def sweep(grid: str, out: Path, extra: list[str]) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
    t0 = time.perf_counter()
    rc = subprocess.call([sys.executable, "-m", "window_bench.cli", "sweep", grid, "--out",
                          str(out), "--no-progress", *extra], env=env,
                         stdout=open(out.parent / f"{out.name}.log", "w"), stderr=subprocess.STDOUT)
    wall = time.perf_counter() - t0
    summary = json.loads(next(out.glob("sweep-*.json")).read_text())
    return {"args": extra, "rc": rc, "wall_s": round(wall, 1),
            "cells_s": {k: round(v.get("wall_s", 0), 1) for k, v in summary["cells"].items()}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["scaling", "cache"])
    ap.add_argument("grid")
    ap.add_argument("out")
    ap.add_argument("--repeats", type=int, default=1)
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    demos = out / "demos-once"
    grid = load_grid(a.grid)
    for cell in grid.cells:   # the grid's demonstrations, collected once
        root = demos_dir(cell, grid, out / "once")
        if not (root / ".complete").exists():
            subprocess.check_call(demos_command(cell, grid, out / "once"),
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            (root / ".complete").write_text("")
    demos = out / "once" / "demos"
    variants = ({"1 worker": ["--workers", "1", "--no-stage1-cache"],
                 "2 workers": ["--workers", "2", "--no-stage1-cache"]} if a.mode == "scaling"
                else {"no cache": ["--workers", "2", "--no-stage1-cache"],
                      "cache": ["--workers", "2"]})
    runs = []
    for rep in range(a.repeats):
        order = list(variants) if rep % 2 == 0 else list(variants)[::-1]
        for name in order:
            root = out / f"{a.mode}-{name.replace(' ', '')}-r{rep}"
            shutil.rmtree(root, ignore_errors=True)
            shutil.copytree(demos, root / "demos")
            before = load()
            r = sweep(a.grid, root, variants[name])
            runs.append({"variant": name, "repeat": rep, "load_before": before,
                         "load_after": load(), **r})
            print(f"{name}: {r['wall_s']:.0f} s (rc {r['rc']}), load {before} -> {load()}",
                  flush=True)
    med = {n: statistics.median(r["wall_s"] for r in runs if r["variant"] == n) for n in variants}
    a_, b_ = list(variants)
    result = {"grid": a.grid, "mode": a.mode, "repeats": a.repeats, "cpus": os.cpu_count(),
              "runs": runs, "median_wall_s": med, "ratio": round(med[a_] / med[b_], 3)}
    (out / f"{a.mode}.json").write_text(json.dumps(result, indent=1))
    print(f"median {a_} {med[a_]:.0f} s, {b_} {med[b_]:.0f} s: ratio {result['ratio']:.2f}")


if __name__ == "__main__":
    main()
