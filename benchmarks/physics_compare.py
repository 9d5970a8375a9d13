"""Physics comparison across MuJoCo builds and constraint-Jacobian settings.

Runs the scripted installer on seeded episodes and records, per episode, the outcome
(success, steps, failure mode, instability) and a SHA-256 of the whole trajectory (qpos and
qvel after every env step, as float64 bytes), plus the time spent in ``env.step``. Run it
once per interpreter (e.g. one with ``mujoco-core`` 4.0.0, one with 4.0.1) and compare the
JSON files with ``--compare``: equal hashes mean bit-identical dynamics.

Usage::

    OMP_NUM_THREADS=1 MUJOCO_GL=egl python benchmarks/physics_compare.py \\
        --env WindowInstall-A-v0 --episodes 10 --jacobian auto --out /tmp/a.json
    python benchmarks/physics_compare.py --compare /tmp/a.json /tmp/b.json
    python benchmarks/physics_compare.py --timing 20    # one line: CPU ms per env step, us per mj_step

``--timing N`` times (process CPU time) N blocks of 50 env steps (the installer's first 50
steps of seed 0, replayed) and N blocks of 1000 ``mj_step`` from the state after them, alternating, and
prints the medians; run it alternately under two interpreters to compare builds on a
shared machine.

``--jacobian`` overrides ``model.opt.jacobian`` after the env is built (``as-built`` keeps
the scene's own setting). MuJoCo resolves ``auto`` to dense for up to 60 dofs; our scene
has 13.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import window_bench  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text, provenance  # noqa: E402
from window_bench.installer.scripted import CONTROLLERS  # noqa: E402

JACOBIANS = {"dense": mujoco.mjtJacobian.mjJAC_DENSE, "sparse": mujoco.mjtJacobian.mjJAC_SPARSE,
             "auto": mujoco.mjtJacobian.mjJAC_AUTO}


def run(env_id: str, controller: str, episodes: int, seed: int, jacobian: str) -> dict:
    env = gym.make(env_id)
    u = env.unwrapped
    if jacobian != "as-built":
        u.model.opt.jacobian = JACOBIANS[jacobian]
    ctrl = CONTROLLERS[controller](env)
    rows = []
    from tqdm import tqdm
    for s in tqdm(range(seed, seed + episodes), desc=f"{controller} {env_id} {jacobian}",
                  unit="ep", file=sys.stderr):
        obs, info = env.reset(seed=s)
        ctrl.reset(seed=s)
        h = hashlib.sha256()
        step_time, steps = 0.0, 0
        while True:
            a = ctrl.act(obs)
            t0 = time.perf_counter()
            obs, reward, terminated, truncated, info = env.step(a)
            step_time += time.perf_counter() - t0
            steps += 1
            h.update(u.data.qpos.tobytes())
            h.update(u.data.qvel.tobytes())
            if terminated or truncated:
                break
        rows.append({"seed": s, "success": bool(terminated), "steps": steps,
                     "failure_mode": info["failure_mode"] or None,
                     "sim_unstable": bool(info["sim_unstable"]),
                     "suction_failures": int(info["suction_failures"]),
                     "trajectory_sha256": h.hexdigest(), "step_ms": 1e3 * step_time / steps})
    env.close()
    ms = [r["step_ms"] for r in rows]
    return {"env_id": env_id, "controller": controller, "jacobian": jacobian,
            "mujoco": mujoco.__version__, "opt_jacobian": int(u.model.opt.jacobian),
            "episodes": episodes, "seeds": [seed, seed + episodes - 1],
            "successes": sum(r["success"] for r in rows),
            "sim_unstable": sum(r["sim_unstable"] for r in rows),
            "median_step_ms": float(np.median(ms)), "rows": rows, "provenance": provenance()}


def timing(blocks: int) -> None:
    env = gym.make("WindowInstall-A-v0")
    u = env.unwrapped
    ctrl = CONTROLLERS["installer"](env)
    obs, _ = env.reset(seed=0)
    ctrl.reset(seed=0)
    actions = []
    for _ in range(50):
        actions.append(ctrl.act(obs))
        obs, *_ = env.step(actions[-1])
    m, d = u.model, mujoco.MjData(u.model)
    # CPU time of this process, not wall time: on a shared machine other processes stretch
    # wall time by whatever the load is, CPU time much less.
    clock = time.process_time
    env_ms, step_us = [], []
    for _ in range(blocks):
        env.reset(seed=0)
        t0 = clock()
        for a in actions:
            env.step(a)
        env_ms.append(1e3 * (clock() - t0) / len(actions))
        mujoco.mj_copyData(d, m, u.data)
        t0 = clock()
        mujoco.mj_step(m, d, 1000)
        step_us.append(1e6 * (clock() - t0) / 1000)
    print(f"mujoco {mujoco.__version__}: {np.median(env_ms):.3f} ms CPU per env step, "
          f"{np.median(step_us):.2f} us CPU per mj_step (medians of {blocks} blocks)")


def compare(paths: list[str]) -> None:
    runs = [json.load(open(p)) for p in paths]
    print("| file | mujoco | jacobian | episodes | successes | sim_unstable | median step ms |")
    print("|---|---|---|---|---|---|---|")
    for p, r in zip(paths, runs):
        print(f"| {os.path.basename(p)} | {r['mujoco']} | {r['jacobian']} | {r['episodes']} | "
              f"{r['successes']} | {r['sim_unstable']} | {r['median_step_ms']:.2f} |")
    ref = {row["seed"]: row for row in runs[0]["rows"]}
    for p, r in zip(paths[1:], runs[1:]):
        same = sum(ref.get(row["seed"], {}).get("trajectory_sha256") == row["trajectory_sha256"]
                   for row in r["rows"])
        print(f"{os.path.basename(p)}: {same}/{len(r['rows'])} trajectories bit-identical to "
              f"{os.path.basename(paths[0])}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--env", default="WindowInstall-A-v0", choices=window_bench.ENV_IDS,
                   help="registered env id")
    p.add_argument("--controller", default="installer", choices=sorted(CONTROLLERS),
                   help="reference controller")
    p.add_argument("--episodes", type=int, default=10, help="episodes (seeds seed..seed+N-1)")
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--jacobian", default="as-built", choices=["as-built", *JACOBIANS],
                   help="override model.opt.jacobian")
    p.add_argument("--out", help="JSON file to write (atomically)")
    p.add_argument("--compare", nargs="+", metavar="JSON",
                   help="compare result files instead of running (the first is the reference)")
    p.add_argument("--timing", type=int, metavar="N",
                   help="time N blocks instead of running episodes (see above)")
    a = p.parse_args(argv)
    if a.timing is not None:
        if a.timing < 1:
            p.error(f"--timing must be >= 1, got {a.timing}")
        timing(a.timing)
        return 0
    if a.compare:
        compare(a.compare)
        return 0
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if not a.out:
        p.error("--out is required when running")
    res = run(a.env, a.controller, a.episodes, a.seed, a.jacobian)
    atomic_write_text(a.out, json.dumps(res, indent=1))
    print(f"{res['mujoco']} {a.jacobian}: {res['successes']}/{a.episodes} seated, "
          f"{res['sim_unstable']} unstable, median {res['median_step_ms']:.2f} ms/step -> {a.out}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
