"""The checkpoint rows of a ``bench run`` directory, also of a run stopped before its end.

``checkpoints.csv`` and ``results.json`` are written when a run finishes; a run stopped at a
reduced budget (the controlled ``hil-serl`` changes in docs/baselines.md stop at 12,000
env steps) has its rows only in ``state.safetensors``. This prints them (success, Wilson
interval, Pr(S), Pr(I|S), Pr(T|I), failure modes, commanded releases and grip breaks, the
installer's share of the last training episodes) and writes them as JSON.

    python experiments/sanity/hilserl_checkpoints.py /tmp/hs_clip \\
        --json experiments/sanity/results/hilserl_clip_checkpoints.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from window_bench.harness.evaluation import atomic_write_text
from window_bench.harness.files import load_state, verify_files

KEYS = ("env_steps", "grad_steps", "episodes", "successes", "wilson95", "pr_S",
        "pr_I_given_S", "pr_T_given_I", "failure_modes", "episodes_with_commanded_release",
        "episodes_with_grip_break", "train_episodes", "train_success_rate",
        "train_intervention_rate", "wall_clock_s")


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    verify_files(a.run_dir, ["state.safetensors"])
    state, _ = load_state(a.run_dir / "state.safetensors", "state")
    c = state["counters"]
    rows = [{k: cp.get(k) for k in KEYS} for cp in c["checkpoints"]]
    out = {"run_dir": str(a.run_dir), "env_steps": c["env_steps"],
           "grad_steps": c["grad_steps"], "train_episodes_accepted":
               sum(bool(e["success"]) for e in c["episodes"]),
           "train_episodes": len(c["episodes"]), "checkpoints": rows}
    for r in rows:
        print(json.dumps(r))
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.json, json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
