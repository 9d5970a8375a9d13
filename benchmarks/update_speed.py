"""QC-FQL update speed on one CPU thread, and where the time of one update goes.

Every block below runs in every repeat, one after the other, so slow phases of a shared
machine hit all rows alike; MEDIANS over repeats are reported.

For each profile (``paper``: 4 x 512, the paper's sizes; ``cpu``: 2 x 256), with batch 256,
h = 10, obs 52, 2 critics, K = 10 Euler steps:

(a) ``updates/s``: the harness's loop, ``agent.update(mixed_batch(demo, online, 256))``
    (1:1 demo/online sampling included), and ``update()`` alone on pre-sampled batches.
(b) the breakdown: the same work cut into its parts and timed part by part in one loop
    (replay sampling, batch preparation, TD target = student on s' + target critics, critic
    forward, critic backward, flow BC forward, flow BC backward, teacher K-step Euler
    sampling, student + frozen-critic forward, student backward, fused Adam step, Polyak).
    Their sum is compared with (a).
(c) variants of the full update, for the record: exact-erf GELU (``gelu_approximate="none"``,
    a config option) and the whole update under ``torch.autocast("cpu", torch.bfloat16)``
    (an experiment the agent does not offer).
(d) FLOPs: the matmul FLOPs of one update (``torch.utils.flop_counter``), against this
    thread's current rate for a plain (256 x 512) @ (512 x 512) matmul measured in every
    repeat: how close the update is to the machine's compute bound.
(e) the critic ensemble layout (forward + backward of 2 critics on a batch): members with
    their own ``F.linear`` calls (what the agent does), the members' weights stacked for
    ``torch.baddbmm``, and ``torch.vmap`` over stacked parameters.

The JAX reference (``qc``, agent ``acfql``) does 3-6 updates/s at 4 x 512, batch 256, h 10 on
a 2-core CPU of this kind (``/work/shared/reference/algorithms.md``); the ratio to it is
reported for the ``paper`` profile.

Usage::

    python benchmarks/update_speed.py [--repeats 5] [--updates 30] [--profiles paper cpu]

Results go to ``benchmarks/results/update_speed.json`` (written atomically, with provenance).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # baselines/ from a checkout

from baselines.qcfql import QCFQLAgent, QCFQLConfig  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text, provenance  # noqa: E402
from window_bench.data.replay import ChunkReplay, mixed_batch  # noqa: E402
from window_bench.data.steplog import EpisodeLog  # noqa: E402

PROFILES = {"paper": (512, 512, 512, 512), "cpu": (256, 256)}
OBS_DIM, BATCH, H = 52, 256, 10
#: updates/s of the JAX reference on this kind of machine (algorithms.md), low and high
JAX_REFERENCE_UPDATES_PER_S = (3.0, 6.0)
BREAKDOWN_PARTS = ("replay_sampling", "prepare", "td_target", "critic_fwd", "critic_bwd",
                   "flow_bc_fwd", "flow_bc_bwd", "teacher_sampling", "student_fwd",
                   "student_bwd", "optimizer_step", "polyak")


def synthetic_episode(rng: np.random.Generator, episode_id: int, provenance: str) -> EpisodeLog:
    """A 600-step episode with random observations and actions (timing needs no physics)."""
    T = int(rng.integers(300, 601))
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    (term if rng.random() < 0.5 else trunc)[-1] = True
    rewards = np.zeros(T, np.float32)
    rewards[-1] = float(term[-1])
    return EpisodeLog(observations=rng.normal(size=(T + 1, OBS_DIM)).astype(np.float32),
                      actions=rng.uniform(-1, 1, (T, 7)).astype(np.float32), rewards=rewards,
                      terminated=term, truncated=trunc, provenance=[provenance] * T,
                      takeover_kind=[""] * T, episode_id=episode_id)


def make_replays(seed: int) -> tuple[ChunkReplay, ChunkReplay]:
    rng = np.random.default_rng(seed)
    demo = ChunkReplay(capacity=20_000, h=H, gamma=0.99, seed=seed)
    online = ChunkReplay(capacity=200_000, h=H, gamma=0.99, seed=seed + 1)
    for e in range(50):
        demo.add_episode(synthetic_episode(rng, e, "demo"))
    for e in range(50, 150):
        online.add_episode(synthetic_episode(rng, e, "policy"))
    return demo, online


def sgemm_gflops(n: int = 40) -> float:
    """This thread's current matmul rate: (256 x 512) @ (512 x 512) float32, GFLOP/s."""
    x, w = torch.randn(256, 512), torch.randn(512, 512)
    x @ w
    return 2 * 256 * 512 * 512 / timed(lambda: x @ w, n) / 1e9


def timed(fn, n: int) -> float:
    """Seconds per call of ``fn`` over ``n`` calls."""
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


def breakdown_once(agent: QCFQLAgent, demo, online, acc: dict[str, float]) -> None:
    """One update done part by part; adds each part's seconds to ``acc``."""
    clock = time.perf_counter
    t = clock()
    batch = mixed_batch(demo, online, BATCH)
    t, acc["replay_sampling"] = clock(), acc["replay_sampling"] + clock() - t
    b = agent.prepare(batch)
    t, acc["prepare"] = clock(), acc["prepare"] + clock() - t
    agent.optimizer.zero_grad(set_to_none=True)
    y = agent.td_target(b)
    t, acc["td_target"] = clock(), acc["td_target"] + clock() - t
    critic_loss, _ = agent.critic_loss(b, y)
    t, acc["critic_fwd"] = clock(), acc["critic_fwd"] + clock() - t
    critic_loss.backward()
    t, acc["critic_bwd"] = clock(), acc["critic_bwd"] + clock() - t
    flow_loss = agent.flow_loss(b)
    t, acc["flow_bc_fwd"] = clock(), acc["flow_bc_fwd"] + clock() - t
    flow_loss.backward()
    t, acc["flow_bc_bwd"] = clock(), acc["flow_bc_bwd"] + clock() - t
    z = agent._noise(BATCH)
    target = agent.teacher_actions(b["obs"], z)
    t, acc["teacher_sampling"] = clock(), acc["teacher_sampling"] + clock() - t
    actor = agent.actor_loss(b, z=z, target=target)
    t, acc["student_fwd"] = clock(), acc["student_fwd"] + clock() - t
    actor["loss"].backward()
    t, acc["student_bwd"] = clock(), acc["student_bwd"] + clock() - t
    agent.optimizer.step()
    t, acc["optimizer_step"] = clock(), acc["optimizer_step"] + clock() - t
    agent.polyak()
    acc["polyak"] += clock() - t


# ---------------------------------------------------------------- ensemble layouts (e)

def _critic_params(hidden, num, gen):
    dims = (OBS_DIM + H * 7, *hidden, 1)
    layers = []
    for d_in, d_out in zip(dims[:-1], dims[1:]):
        bound = float(np.sqrt(6.0 / (d_in + d_out)))
        w = (torch.rand(num, d_in, d_out, generator=gen) * 2 - 1) * bound
        layers.append((w.requires_grad_(), torch.zeros(num, 1, d_out, requires_grad=True)))
    norms = [(torch.ones(num, 1, d, requires_grad=True), torch.zeros(num, 1, d,
                                                                    requires_grad=True))
             for d in hidden]
    return layers, norms


def _stacked_forward(layers, norms, x):
    """All members at once: one ``baddbmm`` per layer on (num, B, width) activations."""
    y = x.expand(layers[0][0].shape[0], *x.shape)
    for i, (w, b) in enumerate(layers):
        y = torch.baddbmm(b, y, w)
        if i < len(norms):
            y = F.layer_norm(F.gelu(y, approximate="tanh"), y.shape[-1:], eps=1e-6)
            y = torch.addcmul(norms[i][1], y, norms[i][0])
    return y.squeeze(-1)


def _single_forward(layers, norms, x):
    """One member from its own slices of the stacked parameters (for ``torch.vmap``)."""
    y = x
    for i, (w, b) in enumerate(layers):
        y = torch.addmm(b, y, w)
        if i < len(norms):
            y = F.layer_norm(F.gelu(y, approximate="tanh"), y.shape[-1:], norms[i][0][0],
                             norms[i][1][0], eps=1e-6)
    return y.squeeze(-1)


def ensemble_layouts(hidden, repeats: int, n: int) -> dict:
    agent = QCFQLAgent(OBS_DIM, 7, QCFQLConfig(hidden=hidden), seed=0)
    layers, norms = _critic_params(hidden, 2, torch.Generator().manual_seed(0))
    x = torch.randn(BATCH, OBS_DIM + H * 7)
    vmapped = torch.vmap(_single_forward, in_dims=(0, 0, None))
    variants = {
        "per_member_linear": lambda: agent.critic(x).sum().backward(),
        "stacked_baddbmm": lambda: _stacked_forward(layers, norms, x).sum().backward(),
        "vmap": lambda: vmapped(layers, norms, x).sum().backward(),
    }
    times = {k: [] for k in variants}
    for fn in variants.values():
        fn()
    for _ in range(repeats):
        for key, fn in variants.items():
            times[key].append(timed(fn, n) * 1e3)
    return {key: {"median_ms": statistics.median(v), "all_ms": v} for key, v in times.items()}


# ---------------------------------------------------------------- main

def run_profile(name: str, hidden, repeats: int, n: int, seed: int) -> dict:
    demo, online = make_replays(seed)
    make = lambda **kw: QCFQLAgent(OBS_DIM, 7, QCFQLConfig(hidden=hidden, **kw), seed=seed)  # noqa: E731
    agent, parts_agent, bf16_agent = make(), make(), make()
    exact_agent = make(gelu_approximate="none")
    fixed = [mixed_batch(demo, online, BATCH) for _ in range(n)]

    def loop_with_sampling():
        agent.update(mixed_batch(demo, online, BATCH))

    it = {"i": 0}

    def update_only():
        agent.update(fixed[it["i"] % n])
        it["i"] += 1

    def exact_gelu():
        exact_agent.update(fixed[it["i"] % n])
        it["i"] += 1

    def bf16():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            bf16_agent.update(fixed[it["i"] % n])
        it["i"] += 1

    rows = {"update_with_sampling": loop_with_sampling, "update_only": update_only,
            "gelu_exact": exact_gelu, "bf16_autocast": bf16}
    for fn in rows.values():  # warm-up: first-call allocations
        fn()
    parts = {p: 0.0 for p in BREAKDOWN_PARTS}
    breakdown_once(parts_agent, demo, online, parts)
    with FlopCounterMode(display=False) as counter:  # matmul FLOPs of one update
        make().update(fixed[0])
    gflop = counter.get_total_flops() / 1e9

    per_s = {k: [] for k in rows}
    parts_ms = {p: [] for p in BREAKDOWN_PARTS}
    loads, sgemm = [], []
    for r in range(repeats):
        loads.append(os.getloadavg()[0])
        sgemm.append(sgemm_gflops())
        for key, fn in rows.items():
            per_s[key].append(1.0 / timed(fn, n))
        acc = {p: 0.0 for p in BREAKDOWN_PARTS}
        for _ in range(n):
            breakdown_once(parts_agent, demo, online, acc)
        for p in BREAKDOWN_PARTS:
            parts_ms[p].append(acc[p] / n * 1e3)
        print(f"  [{name}] repeat {r + 1}/{repeats}: "
              f"{per_s['update_with_sampling'][-1]:.2f} updates/s (load {loads[-1]:.1f})",
              flush=True)

    med_parts = {p: statistics.median(v) for p, v in parts_ms.items()}
    parts_total = sum(med_parts.values())
    out = {
        "hidden": list(hidden), "batch": BATCH, "h": H, "obs_dim": OBS_DIM, "num_critics": 2,
        "flow_steps": 10, "parameters": sum(p.numel() for p in agent._params),
        "updates_per_s": {k: {"median": statistics.median(v), "min": min(v), "max": max(v),
                              "all": v} for k, v in per_s.items()},
        "breakdown_ms": {p: {"median": med_parts[p], "share": med_parts[p] / parts_total,
                             "all": parts_ms[p]} for p in BREAKDOWN_PARTS},
        "breakdown_total_ms": parts_total,
        "update_with_sampling_ms": 1e3 / statistics.median(per_s["update_with_sampling"]),
        "matmul_gflop_per_update": gflop,
        "sgemm_gflops": {"median": statistics.median(sgemm), "all": sgemm},
        "achieved_gflops": gflop * statistics.median(per_s["update_only"]),
        "loadavg_1min": loads,
    }
    out["matmul_efficiency"] = out["achieved_gflops"] / out["sgemm_gflops"]["median"]
    if name == "paper":
        med = out["updates_per_s"]["update_with_sampling"]["median"]
        out["ratio_to_jax_reference"] = {"jax_updates_per_s": list(JAX_REFERENCE_UPDATES_PER_S),
                                         "low": med / JAX_REFERENCE_UPDATES_PER_S[1],
                                         "high": med / JAX_REFERENCE_UPDATES_PER_S[0]}
    return out


def print_profile(name: str, res: dict) -> None:
    ups = res["updates_per_s"]
    print(f"\n== {name}: hidden {res['hidden']}, batch {res['batch']}, h {res['h']}, "
          f"{res['parameters']:,} parameters")
    for key, v in ups.items():
        print(f"  {key:22s} {v['median']:7.2f} updates/s  (min {v['min']:.2f}, "
              f"max {v['max']:.2f})")
    print(f"  {res['matmul_gflop_per_update']:.2f} GFLOP of matmuls per update: "
          f"{res['achieved_gflops']:.1f} GFLOP/s achieved vs {res['sgemm_gflops']['median']:.1f} "
          f"GFLOP/s for a plain 256x512x512 matmul now ({100 * res['matmul_efficiency']:.0f} %)")
    if "ratio_to_jax_reference" in res:
        r = res["ratio_to_jax_reference"]
        print(f"  vs JAX reference (3-6 updates/s): {r['low']:.2f}x - {r['high']:.2f}x")
    print(f"  breakdown (median ms per update; sum {res['breakdown_total_ms']:.1f} ms vs "
          f"{res['update_with_sampling_ms']:.1f} ms for the whole update):")
    for part, v in res["breakdown_ms"].items():
        print(f"    {part:18s} {v['median']:8.2f} ms  {100 * v['share']:5.1f} %")
    if "ensemble_layouts" in res:
        print("  critic ensemble fwd+bwd (median ms):", {
            k: round(v["median_ms"], 2) for k, v in res["ensemble_layouts"].items()})


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--updates", type=int, default=30, help="updates per timed block")
    parser.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=list(PROFILES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"
                                              / "update_speed.json"))
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.updates < 1:
        parser.error(f"--repeats {args.repeats} and --updates {args.updates} must be >= 1")
    torch.set_num_threads(1)

    results = {}
    for name in args.profiles:
        print(f"profile {name} ...", flush=True)
        results[name] = run_profile(name, PROFILES[name], args.repeats, args.updates, args.seed)
        results[name]["ensemble_layouts"] = ensemble_layouts(PROFILES[name], args.repeats,
                                                             max(5, args.updates // 3))
        print_profile(name, results[name])

    import tensordict
    import torchrl
    record = {
        "benchmark": "update_speed", "args": vars(args), "provenance": provenance(),
        "versions": {"torch": torch.__version__, "torchrl": torchrl.__version__,
                     "tensordict": tensordict.__version__},
        "hardware": {"cpu_model": _cpu_model(), "cpu_count": os.cpu_count(),
                     "torch_threads": torch.get_num_threads(),
                     "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
                     "os": platform.platform()},
        "profiles": results,
    }
    atomic_write_text(args.out, json.dumps(record, indent=2) + "\n")
    print(f"\nwrote {args.out}")
    return record


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


if __name__ == "__main__":
    main()
