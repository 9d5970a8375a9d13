r"""Does a QC-FQL policy change with more demo-only updates? Stage I continued on D_demo.

Loads a Stage I cache entry (``bench run --stage1-cache DIR`` writes one), continues the same
demo-only updates for ``--extra`` more gradient steps and evaluates the averaged student
(deterministic, no takeovers) on the development seeds every ``--every`` updates,
rewriting ``--out`` after each evaluation (``finished`` false until the last). It
separates what more updates on the 50 demonstrations do from what the online data does
([the online phase on B](../../docs/results/diagnoses/b-online.md)).

    python experiments/sanity/offline_continuation.py CACHE/<key>.safetensors RUN/demos \
        --env WindowInstall-A-v0 --operator attentive-flush --extra 24000 --every 6000 \
        --out experiments/sanity/results/offline_continuation_A_s1.json

RUN/demos holds the run's demonstrations of ``--env`` by ``--operator``. ``--set KEY=VALUE``
(repeatable) changes an agent setting for the continued updates only (``lr``, ``alpha``,
``policy_ema`` ...), as a later phase of a run would; ``--policy teacher`` (or ``both``)
evaluates the averaged flow teacher as well as the student. One process, one thread; about 20 minutes for 24,000 updates and five evaluations of 20 episodes on A.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_args import env_errors, episodes_errors, operator_errors, out_errors  # noqa: E402

MAX_UPDATES = 200_000


def main(argv=None) -> int:
    from window_bench.installer.operators import DEFAULT_OPERATOR

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cache", help="a Stage I cache entry (.safetensors) of a qcfql run")
    p.add_argument("demos", help="the run's demonstrations directory (RUN/demos)")
    p.add_argument("--env", default="WindowInstall-B-v0")
    p.add_argument("--operator", default=DEFAULT_OPERATOR, help="who demonstrated")
    p.add_argument("--extra", type=int, default=24000, help=f"more updates (1-{MAX_UPDATES})")
    p.add_argument("--every", type=int, default=6000, help="updates between evaluations")
    p.add_argument("--episodes", type=int, default=20, help="dev seeds 100000.. (1-500)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="an agent setting for the continued updates (repeatable)")
    p.add_argument("--policy", choices=("student", "teacher", "both"), default="student",
                   help="which averaged network acts in the evaluations")
    p.add_argument("--out", required=True, help="JSON file to write (not overwritten)")
    args = p.parse_args(argv)
    errs = (env_errors(args.env) + episodes_errors(args.episodes) + out_errors(args.out)
            + operator_errors(args.operator))
    if not 1 <= args.extra <= MAX_UPDATES:
        errs.append(f"--extra {args.extra}; allowed: 1..{MAX_UPDATES}")
    if not 1 <= args.every <= args.extra:
        errs.append(f"--every {args.every}; allowed: 1..--extra ({args.extra})")
    from baselines.qcfql import QCFQLAgent, QCFQLConfig
    from window_bench.harness.agent import parse_overrides, with_overrides

    try:
        overrides = parse_overrides(args.set)
        with_overrides(QCFQLConfig(), overrides)
    except (TypeError, ValueError) as e:
        errs.append(f"--set: {e}")
    if errs:
        print("error: " + "; ".join(errs), file=sys.stderr)
        return 2

    from window_bench.data.replay import ChunkReplay
    from window_bench.envs.wrappers import make_training_env
    from window_bench.harness.evaluation import AgentPolicy, provenance
    from window_bench.harness.files import load_state
    from window_bench.harness.seeds import DEV_SEED0
    from window_bench.installer.demos import load_demos
    from window_bench.installer.rollout import Rollout

    torch.set_num_threads(1)
    try:
        tree, _ = load_state(args.cache, "stage1")
    except (OSError, ValueError) as e:
        print(f"error: {args.cache}: {e}", file=sys.stderr)
        return 2
    agent = QCFQLAgent.from_state_dict(tree["agent"])
    try:   # the continued phase's settings; the optimizer's rate follows ``lr``
        agent.config = with_overrides(agent.config, overrides)
    except (TypeError, ValueError) as e:
        print(f"error: --set: {e}", file=sys.stderr)
        return 2
    for group in agent.optimizer.param_groups:
        group["lr"] = agent.config.lr
    torch.set_rng_state(tree["torch_rng"])
    demos = load_demos(args.demos, args.env, args.operator)
    h = agent.config.h
    rb = ChunkReplay(sum(-(-e.T // h) for e in demos) + h, h, agent.config.gamma, seed=123)
    for e in demos:
        rb.add_episode(e)
    env = make_training_env(args.env, None, obs_mode="flat", max_episode_steps=600)

    class Acting(AgentPolicy):   # the averaged teacher or student, deterministic
        def __init__(self, which: str):
            super().__init__(agent, True)
            self.which = which

        def act(self, obs):
            return self.agent.act(obs, deterministic=True, policy=self.which)

    policies = ("student", "teacher") if args.policy == "both" else (args.policy,)

    def evaluate(done: int) -> dict:
        row = {"extra_updates": done}
        for which in policies:
            rollout = Rollout(env, Acting(which), env_id=args.env)
            row["successes" if which == "student" else "teacher_successes"] = sum(
                bool(rollout.run(seed=DEV_SEED0 + i, episode_id=i).terminated[-1])
                for i in range(args.episodes))
        return row

    def write(rows: list[dict], finished: bool) -> None:   # after every evaluation
        out = {"cache": Path(args.cache).name, "env_id": args.env, "operator": args.operator,
               "episodes": args.episodes, "dev_seed0": DEV_SEED0, "settings": overrides,
               "extra": args.extra, "finished": finished, "curve": rows,
               "provenance": provenance()}
        for key in ("successes", "teacher_successes"):
            if key in rows[0]:
                out[key] = [r[key] for r in rows]
                out[key.replace("successes", "success_rate")] = [
                    float(np.round(r[key] / args.episodes, 3)) for r in rows]
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(args.out + ".tmp")
        tmp.write_text(json.dumps(out, indent=1) + "\n")
        tmp.replace(args.out)

    rows = [evaluate(0)]
    print(json.dumps(rows[-1]), flush=True)
    write(rows, False)
    done = 0
    while done < args.extra:
        n = min(args.every, args.extra - done)
        for _ in range(n):
            agent.update(rb.sample(agent.config.batch_size))
        done += n
        rows.append(evaluate(done))
        print(json.dumps(rows[-1]), flush=True)
        write(rows, done >= args.extra)
    env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
