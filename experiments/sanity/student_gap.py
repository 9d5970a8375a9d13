r"""Where does QC-FQL's one-step student part from its flow teacher, and is Q-guidance the
cause? Reads a Stage I cache entry (never writes it) and its demonstrations, and measures:

1. on every demonstration chunk state, the distance between the acting student's chunk
   ``mu(s, 0)`` and the teacher's ``a_xi(s, 0)``, and the size of the actor's Q-gradient
   ``|d Q / d u|`` there, split by stage (before the suction latches / while it holds);
2. four students on the dev seeds (z = 0, open-loop chunks, the harness's acting):
   ``cache`` (the averaged student the entry deploys), ``raw`` (the raw student: the
   averaging's share), ``distill`` (raw, then ``--steps`` updates of the distillation term
   alone) and ``full`` (raw, then ``--steps`` updates of the whole Eq. 9 loss: the matched
   control). ``distill`` against ``full`` isolates the Q-term. ``scratch``: a new student of
   ``--scratch-hidden`` sizes (e.g. the paper's 4 x 512) distilled alone from the same
   teacher for ``--scratch-steps`` updates: does capacity close the gap?

    python experiments/sanity/student_gap.py \
        leaderboard/runs/stage1_cache/421c1bfa....safetensors --env WindowInstall-B-v0 \
        --demos-dir leaderboard/runs/demos/WindowInstall-B-v0-average-n50-s0 --dev 20

Writes ``<out>/student_gap_<key[:8]>.json``.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from act_trainset import summarize  # noqa: E402
from bc_flow_eval import ChunkPolicy, save_result  # noqa: E402

from baselines.act import _harness_demos, _rollout  # noqa: E402
from baselines.qcfql import OneStepPolicy, QCFQLAgent  # noqa: E402
from window_bench.data.replay import ChunkReplay  # noqa: E402
from window_bench.harness.files import load_state, sha256_file  # noqa: E402
from window_bench.harness.seeds import eval_seeds  # noqa: E402

VACUUM_INDEX = 21   # robot0_vacuum in the flat state (7 q + 7 qd + 3 eef pos + 4 eef quat)
ARMS = ("cache", "raw", "distill", "full", "scratch")


def chunk_states(demos, h: int) -> np.ndarray:
    """The observations the learner decides at: every h-th step of every demonstration."""
    return np.concatenate([ep.observations[:ep.T:h] for ep in demos]).astype(np.float32)


def gap_by_stage(agent: QCFQLAgent, obs: np.ndarray) -> dict:
    """Student-teacher chunk distance and actor Q-gradient norm, before / after the latch."""
    o = agent.normalize(torch.as_tensor(obs))
    z = torch.zeros(len(o), agent.chunk_dim)
    with torch.no_grad():
        teacher = agent.teacher_actions(o, z)
        student = agent.ema_student(o, z).clamp(-1, 1)
    u = student.clone().requires_grad_(True)
    q = agent.critic(agent.critic_input(o, u), frozen=True).mean(0)
    (grad,) = torch.autograd.grad(q.sum(), u)
    out = {}
    latched = obs[:, VACUUM_INDEX] > 0.5
    for name, sel in (("before_latch", ~latched), ("latched", latched)):
        d = (student - teacher)[torch.as_tensor(sel)].norm(dim=-1).numpy()
        g = grad[torch.as_tensor(sel)].norm(dim=-1).numpy()
        out[name] = {"states": int(sel.sum()),
                     "student_teacher_l2_median": float(np.median(d)),
                     "student_teacher_l2_p90": float(np.percentile(d, 90)),
                     "q_grad_norm_median": float(np.median(g)),
                     "q_mean": float(q.detach()[torch.as_tensor(sel)].mean())}
    return out


def fine_tune(agent: QCFQLAgent, rb: ChunkReplay, steps: int, with_q: bool, batch: int,
              seed: int) -> QCFQLAgent:
    """A copy of ``agent`` whose raw student got ``steps`` more actor updates (distillation
    alone, or the whole Eq. 9 loss), critic and teacher frozen; it then acts raw."""
    a = copy.deepcopy(agent)
    opt = torch.optim.Adam(a.student.parameters(), lr=a.config.lr)
    torch.manual_seed(seed)
    for _ in range(steps):
        b = a.prepare(rb.sample(batch))
        parts = a.actor_loss(b)
        loss = parts["loss"] if with_q else a.config.alpha * parts["distill"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    a.ema_student.load_state_dict(a.student.state_dict())
    return a


def fresh_student(agent: QCFQLAgent, hidden: tuple[int, ...], seed: int) -> QCFQLAgent:
    """A copy of ``agent`` with a newly initialised student (and acting copy) of ``hidden``."""
    a = copy.deepcopy(agent)
    gen = torch.Generator().manual_seed(seed)
    a.student = OneStepPolicy(a.obs_dim, a.chunk_dim, hidden, gen, a.config.gelu_approximate)
    a.ema_student = copy.deepcopy(a.student).requires_grad_(False)
    return a


def main(argv=None) -> dict:
    torch.set_num_threads(1)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("entry", help="a Stage I cache entry (<key>.safetensors), read only")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--demos-dir", required=True, help="the Minari root the entry trained on")
    p.add_argument("--operator", default="average")
    p.add_argument("--demos", type=int, default=50)
    p.add_argument("--dev", type=int, default=20, help="dev seeds 100000..")
    p.add_argument("--steps", type=int, default=2000, help="fine-tuning updates per arm")
    p.add_argument("--arms", nargs="+", default=list(ARMS[:4]), choices=ARMS)
    p.add_argument("--scratch-hidden", type=int, nargs="+", default=[512, 512, 512, 512])
    p.add_argument("--scratch-steps", type=int, default=10000)
    p.add_argument("--out", default="experiments/sanity/results")
    a = p.parse_args(argv)
    entry = Path(a.entry)
    if not entry.is_file():
        p.error(f"{entry}: no such Stage I cache entry")
    if a.dev < 1 or a.steps < 0 or a.demos < 1 or a.scratch_steps < 0 or min(a.scratch_hidden) < 1:
        p.error(f"--dev {a.dev}, --demos {a.demos} and --scratch-hidden {a.scratch_hidden} must "
                f"be >= 1, --steps {a.steps} and --scratch-steps {a.scratch_steps} >= 0")
    material_path = entry.with_suffix(".json")
    material = json.loads(material_path.read_text()) if material_path.is_file() else {}
    tree, _ = load_state(entry, "stage1")
    agent = QCFQLAgent.from_state_dict(tree["agent"])
    seed = int(material.get("material", {}).get("seed", agent.seed))
    demos = _harness_demos(a.env, a.operator, a.demos_dir, a.demos, 1_000_000 + seed)
    rb = ChunkReplay(sum(-(-ep.T // agent.h) for ep in demos), agent.h, agent.gamma, seed=seed)
    for ep in demos:
        rb.add_episode(ep)
    obs = chunk_states(demos, agent.h)
    result = {"entry": str(entry), "entry_sha256": sha256_file(entry), "env": a.env,
              "num_updates": agent.num_updates, "alpha": agent.config.alpha,
              "fine_tune_steps": a.steps, "scratch_hidden": a.scratch_hidden,
              "scratch_steps": a.scratch_steps, "acting": f"z = 0, open-loop chunks of h = {agent.h}",
              "gap": {}, "arms": {}}
    seeds = list(eval_seeds("dev", a.dev))
    for arm in a.arms:
        t0 = time.perf_counter()
        if arm == "cache":
            arm_agent = agent
        elif arm == "scratch":
            arm_agent = fine_tune(fresh_student(agent, tuple(a.scratch_hidden), seed), rb,
                                  a.scratch_steps, False, agent.config.batch_size, seed)
        else:
            raw = copy.deepcopy(agent)
            raw.ema_student.load_state_dict(raw.student.state_dict())
            arm_agent = (raw if arm == "raw" else
                         fine_tune(raw, rb, a.steps, arm == "full", agent.config.batch_size, seed))
        result["gap"][arm] = gap_by_stage(arm_agent, obs)
        rows = _rollout(ChunkPolicy(arm_agent, "student"), a.env, seeds, None)
        s = {**summarize(rows), "seeds": [seeds[0], seeds[-1]], "rows": rows,
             "wall_s": round(time.perf_counter() - t0, 1)}
        result["arms"][arm] = s
        g = result["gap"][arm]
        print(f"{arm:8s} {s['successes']}/{s['episodes']} S {s['pr_s']} I|S {s['pr_i_given_s']} "
              f"T|I {s['pr_t_given_i']} {s['failure_modes']} | gap before latch "
              f"{g['before_latch']['student_teacher_l2_median']:.3f} latched "
              f"{g['latched']['student_teacher_l2_median']:.3f} | |dQ/du| "
              f"{g['before_latch']['q_grad_norm_median']:.4f} / "
              f"{g['latched']['q_grad_norm_median']:.4f} | {s['wall_s']} s", flush=True)
    tag = "" if a.arms != ["scratch"] else "_scratch" + "x".join(map(str, a.scratch_hidden))
    return save_result(result, Path(a.out) / f"student_gap_{entry.stem[:8]}{tag}.json")


if __name__ == "__main__":
    main()
