"""Learner calls per second of every pixel learner (QC-FQL, HIL-SERL, SB3 SAC, ACT) against
the same learner on the state track, at the same network sizes (the ``cpu`` profile's: MLPs
256 x 256, batch 256; ACT: its ``cpu`` sizes and batch).

Each learner is built by the harness's own ``create`` from an ``AgentSpec`` on random
episodes (state: 52 values; pixels: 16,402 with float16-exact feature maps, as
``PixelFeatures`` makes them) and timed on ``learn``: QC-FQL (h = 10) and HIL-SERL (h = 1)
draw the harness's Stage III batch, ``mixed_batch`` of a demo and an online ``ChunkReplay``
1:1 (the pixel ones storing features as float16, as ``bench run --track pixels``), HIL-SERL
taking two critic steps and one actor step per call; SAC runs SB3's
``train(gradient_steps=1)`` on its own buffer; ACT draws its own batches from the demos (on
pixels: their cached float16 feature maps). Rows run interleaved in every repeat (the
machine is shared), MEDIANS over repeats are reported and each ratio is taken within a repeat,
both for wall-clock calls/s and for the process's CPU time per call (``time.process_time``:
on a shared machine it leaves out the time the process waited for a core).

``--baseline REV`` measures the code of another commit beside this tree's (or beside commit
``--current REV``), in one run: every repeat runs this script once (``--repeats 1``) in a
fresh process on each tree (a commit is ``git archive``-d to a temporary directory put first
on ``PYTHONPATH``), in alternating order, so both see the same machine load; a row the other
commit cannot build is left out.

Usage::

    OMP_NUM_THREADS=1 python benchmarks/pixel_learners_speed.py [--repeats 5] [--calls 5]
        [--baseline REV [--current REV]] [--methods qcfql hil-serl sac act]

Results go to ``benchmarks/results/pixel_learners_speed.json`` (written atomically).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from window_bench.data.replay import ChunkReplay, mixed_batch
from window_bench.data.steplog import EpisodeLog
from window_bench.harness.agent import AgentSpec
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.harness.methods import PROFILES, agent_class
from window_bench.pixels.encoder import FEATURE_VALUES, OBS_DIM

STATE_DIM = 52
#: method -> (state-track kind, pixel-track kind, chunk horizon h)
KINDS = {"qcfql": ("qcfql", "qcfql-pixels", 10), "hil-serl": ("hilserl", "hilserl-pixels", 1),
         "sac": ("sac", "sac-pixels", 1), "act": ("act", "act-pixels", 10)}
ROOT = Path(__file__).resolve().parents[1]


def episodes(obs_dim: int, n: int = 4, T: int = 100, seed: int = 0) -> list[EpisodeLog]:
    rng = np.random.default_rng(seed)
    out = []
    for e in range(n):
        obs = rng.standard_normal((T + 1, obs_dim)).astype(np.float32)
        if obs_dim == OBS_DIM:
            obs[:, :FEATURE_VALUES] = np.abs(obs[:, :FEATURE_VALUES]).astype(np.float16)
        out.append(EpisodeLog(
            observations=obs, actions=rng.uniform(-1, 1, (T, 7)), rewards=rng.uniform(-1, 0, T),
            terminated=np.zeros(T, bool), truncated=np.r_[np.zeros(T - 1, bool), True],
            provenance=["demo"] * T, takeover_kind=[""] * T, episode_id=e, seed=e))
    return out


def learner(kind: str, obs_dim: int, h: int):
    """A learner of ``kind`` and its ``learn`` argument (a sampler of 256-chunk batches)."""
    demos = episodes(obs_dim)
    obs = np.concatenate([ep.observations for ep in demos])
    profile = dataclasses.replace(PROFILES["cpu"], budget_steps=1_000)   # SAC's buffer size
    cls = agent_class(kind)
    mean, std = (None, None) if cls.own_normalizer else (obs.mean(0), obs.std(0))
    agent = cls.create(AgentSpec(obs_dim=obs_dim, action_dim=7, h=h, seed=0, profile=profile,
                                 demos=demos, obs_mean=mean, obs_std=std))
    agent.attach_demos(demos)
    replays = []
    for seed, eps in enumerate((demos, episodes(obs_dim, seed=1))):     # demo, online
        rb = ChunkReplay(sum(-(-ep.T // h) for ep in eps), h, agent.gamma, seed=seed,
                         half_obs=FEATURE_VALUES if obs_dim == OBS_DIM else 0)
        for ep in eps:
            rb.add_episode(ep)
        replays.append(rb)
    return agent, lambda: mixed_batch(*replays, profile.batch_size, 0.5)


def rate(agent, sample, calls: int) -> tuple[float, float]:
    """(calls/s wall clock, CPU ms per call) of ``calls`` learner calls."""
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(calls):
        agent.learn(sample)
    return calls / (time.perf_counter() - t0), (time.process_time() - c0) * 1e3 / calls


def measure(methods: list[str], repeats: int, calls: int) -> list[dict]:
    """Calls/s and CPU ms per call of every buildable row, ``repeats`` times, rows
    interleaved: one ``{row: (calls/s, CPU ms)}`` per repeat."""
    rows = {}
    for m in methods:
        state, pixels, h = KINDS[m]
        for track, kind in (("state", state), ("pixels", pixels)):
            try:
                rows[f"{m} {track}"] = learner(kind, OBS_DIM if track == "pixels" else STATE_DIM, h)
            except ValueError as err:          # e.g. a commit without this pixel learner
                print(f"{m} {track}: not measured ({err})", flush=True)
    for agent, sample in rows.values():                        # warm-up
        rate(agent, sample, 1)
    raw = []
    for r in range(repeats):
        raw.append({k: rate(a, s, calls) for k, (a, s) in rows.items()})
        print(f"repeat {r + 1}/{repeats}: "
              + ", ".join(f"{k} {v:.2f}/s {c:.1f} CPU ms" for k, (v, c) in raw[-1].items()),
              flush=True)
    return raw


def summary(raw: list[dict], methods: list[str]) -> dict:
    keys = raw[0].keys()
    both = [m for m in methods if f"{m} state" in keys and f"{m} pixels" in keys]

    def med(f) -> float:
        return float(np.median([f(x) for x in raw]))

    return {"learner_calls_per_s": {k: med(lambda x: x[k][0]) for k in keys},
            "learner_cpu_ms_per_call": {k: med(lambda x: x[k][1]) for k in keys},
            "pixel_call_cost_vs_state": {
                m: med(lambda x: x[f"{m} state"][0] / x[f"{m} pixels"][0]) for m in both},
            "pixel_call_cpu_cost_vs_state": {
                m: med(lambda x: x[f"{m} pixels"][1] / x[f"{m} state"][1]) for m in both}}


def child(tree: Path, methods: list[str], calls: int) -> list[dict]:
    """One repeat of this script in a fresh process on the code in ``tree``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.json"
        env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--repeats", "1",
                        "--calls", str(calls), "--out", str(out), "--methods", *methods],
                       cwd=tree, env=env, check=True)
        return json.loads(out.read_text())["raw"]


def _unpack(rev: str, into: Path) -> str:
    """Commit ``rev``'s files in ``into``; its full sha."""
    sha = subprocess.run(["git", "rev-parse", rev], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    into.mkdir()
    archive = subprocess.run(["git", "archive", sha], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return sha


def compare(rev: str, current: str | None, methods: list[str], repeats: int,
            calls: int) -> dict:
    """Commit ``rev`` against commit ``current`` (None: this tree), a fresh process per tree
    and repeat (see the module docstring)."""
    raw = {"baseline": [], "current": []}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"baseline": Path(tmp) / "baseline", "current": ROOT}
        sha = _unpack(rev, trees["baseline"])
        current_sha = "working tree"
        if current is not None:
            trees["current"] = Path(tmp) / "current"
            current_sha = _unpack(current, trees["current"])
        for r in range(repeats):
            order = ("baseline", "current") if r % 2 == 0 else ("current", "baseline")
            for name in order:
                print(f"repeat {r + 1}/{repeats}: {name}", flush=True)
                raw[name] += child(trees[name], methods, calls)
    out = {name: summary(rows, methods) for name, rows in raw.items()}
    pairs = list(zip(raw["baseline"], raw["current"]))
    rows = [k for k in raw["current"][0] if k in raw["baseline"][0]]
    speedup = {k: float(np.median([c[k][0] / b[k][0] for b, c in pairs])) for k in rows}
    cpu = {k: float(np.median([c[k][1] / b[k][1] for b, c in pairs])) for k in rows}
    return {"baseline_commit": sha, "current_commit": current_sha, **out,
            "current_vs_baseline_calls_per_s": speedup,
            "current_vs_baseline_cpu_ms_per_call": cpu, "raw": raw}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--calls", type=int, default=5, help="timed learner calls per row and repeat")
    ap.add_argument("--methods", nargs="+", default=list(KINDS), choices=list(KINDS))
    ap.add_argument("--baseline", default=None, metavar="REV",
                    help="also measure this commit's code, side by side (fresh processes)")
    ap.add_argument("--current", default=None, metavar="REV",
                    help="with --baseline: measure this commit instead of the working tree")
    ap.add_argument("--out", default="benchmarks/results/pixel_learners_speed.json")
    args = ap.parse_args(argv)
    for name in ("repeats", "calls"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    torch.set_num_threads(1)
    common = {"repeats": args.repeats, "calls": args.calls, "batch": 256, "hidden": [256, 256],
              "methods": args.methods}
    if args.baseline is None:
        raw = measure(args.methods, args.repeats, args.calls)
        result = {**summary(raw, args.methods), **common, "raw": raw}
        shown = ("learner_calls_per_s", "learner_cpu_ms_per_call", "pixel_call_cost_vs_state",
                 "pixel_call_cpu_cost_vs_state")
    else:
        result = {**compare(args.baseline, args.current, args.methods, args.repeats,
                            args.calls), **common}
        shown = ("baseline_commit", "current_commit", "baseline", "current",
                 "current_vs_baseline_calls_per_s", "current_vs_baseline_cpu_ms_per_call")
    result["provenance"] = provenance()
    atomic_write_text(args.out, json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in shown}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
