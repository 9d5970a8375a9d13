r"""Does distillation at the student's own states pull QC-FQL's student onto its teacher?

Reads a Stage I cache entry (never writes it) and the demonstrations it was trained on, rolls
the averaged student out deterministically on ``--collect`` training seeds (700000..), then
runs ``--updates`` distillation-only updates of the raw student toward the averaged teacher
(``z = 0``, Eq. 9 without the Q term, Adam at the agent's learning rate, the averaged copy
following at ``policy_ema`` as in the harness) on batches of 256 states:

* ``demo``: demonstration states only (the grid the teacher was trained on);
* ``own``: half demonstration states, half the student's own states (what the online phase
  does at the start: the replay is half D_demo, half the policy's episodes);
* ``own_seated`` / ``own_failed``: the same, with the own states of the seated / failed
  episodes only.

Then evaluates the averaged student on the dev seeds (z = 0, open-loop chunks).

    python experiments/sanity/distill_onpolicy.py CACHE/<key>.safetensors RUN/demos \
        --env WindowInstall-B-v0 --operator attentive --mode own --updates 3000 --dev 40

About one minute of updates and one of rollouts per mode on one core.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from act_trainset import summarize  # noqa: E402
from bc_flow_eval import ChunkPolicy  # noqa: E402

from baselines.act import _rollout  # noqa: E402
from baselines.qcfql import QCFQLAgent  # noqa: E402
from window_bench.harness.files import load_state  # noqa: E402
from window_bench.harness.seeds import eval_seeds  # noqa: E402

MODES = ("demo", "own", "own_seated", "own_failed")


def own_states(agent: QCFQLAgent, env_id: str, episodes: int, mode: str) -> np.ndarray:
    """The averaged student's observations at its chunk boundaries on training seeds
    700000.. (the episodes ``mode`` keeps), and how many of them seated."""
    import gymnasium as gym

    env = gym.make(env_id, obs_mode="flat")
    kept, seated = [], 0
    for i in range(episodes):
        obs, _ = env.reset(seed=700_000 + i)
        states, done, term = [], False, False
        while not done:
            states.append(np.asarray(obs, np.float32))
            for a in agent.act(obs, deterministic=True):
                obs, _, term, trunc, _ = env.step(a)
                done = term or trunc
                if done:
                    break
        seated += bool(term)
        if mode == "own" or (mode == "own_seated") == bool(term):
            kept.extend(states)
    env.close()
    print(f"own episodes: {seated} of {episodes} seated; {len(kept)} states kept", flush=True)
    return np.asarray(kept, np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("entry", help="a Stage I cache entry (<key>.safetensors), read only")
    p.add_argument("demos_dir", help="the Minari root of the demonstrations it was trained on")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--operator", default="attentive")
    p.add_argument("--mode", choices=MODES, default="own")
    p.add_argument("--updates", type=int, default=3000, help="distillation updates (1-100000)")
    p.add_argument("--collect", type=int, default=40, help="own episodes to collect (1-500)")
    p.add_argument("--dev", type=int, default=40, help="dev seeds to evaluate on (1-200)")
    a = p.parse_args(argv)
    for name, value, hi in (("updates", a.updates, 100_000), ("collect", a.collect, 500),
                            ("dev", a.dev, 200)):
        if not 1 <= value <= hi:
            p.error(f"--{name} {value}: allowed 1-{hi}")
    if not Path(a.entry).is_file():
        p.error(f"{a.entry}: no such Stage I cache entry")
    from window_bench.installer.demos import load_demos

    torch.set_num_threads(1)
    tree, _ = load_state(a.entry, "stage1")
    agent = QCFQLAgent.from_state_dict(tree["agent"])
    demos = load_demos(a.demos_dir, a.env, a.operator)
    demo = torch.from_numpy(np.concatenate([e.observations[:-1][::agent.h] for e in demos]))
    own = None if a.mode == "demo" else torch.from_numpy(
        own_states(agent, a.env, a.collect, a.mode))
    gen = torch.Generator().manual_seed(0)
    opt = torch.optim.Adam(agent.student.parameters(), lr=agent.config.lr)
    raw, avg = list(agent.student.parameters()), list(agent.ema_student.parameters())
    t0, losses = time.perf_counter(), []
    for k in range(a.updates):
        half = 256 if own is None else 128
        x = demo[torch.randint(len(demo), (half,), generator=gen)]
        if own is not None:
            x = torch.cat([x, own[torch.randint(len(own), (128,), generator=gen)]])
        obs = agent.normalize(x)
        z = torch.zeros(len(obs), agent.chunk_dim)
        loss = (agent.student(obs, z) - agent.teacher_actions(obs, z)).square().sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            torch._foreach_lerp_(avg, raw, agent.config.policy_ema)
        losses.append(loss.item())
        if k % 1000 == 0 or k == a.updates - 1:
            print(f"update {k}: distillation loss {np.mean(losses[-1000:]):.4f}", flush=True)
    s = summarize(_rollout(ChunkPolicy(agent, "student"), a.env, list(eval_seeds("dev", a.dev))))
    print(f"{a.mode}, {a.updates} updates: seated {s['successes']} of {s['episodes']} "
          f"(Wilson {s['wilson95'][0]:.2f}-{s['wilson95'][1]:.2f}), Pr(S) {s['pr_s']}, "
          f"Pr(T|I) {s['pr_t_given_i']:.2f}, {s['failure_modes']}, "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
