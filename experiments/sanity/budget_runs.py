"""What a longer budget changed in a set of runs: per run, the final success, how many
development-seed checkpoints were at >= 95 %, time-to-95, takeover minutes, and the training
intervention rate (takeover steps / env steps) and the takeovers by cue over each third of
Stage III, the warm start left out, and which training episodes had a takeover
([the paper's 3.0 h on A](../../docs/results/diagnoses/budget-a.md)).

    python experiments/sanity/budget_runs.py leaderboard/runs/WindowInstall-A-v0/qcfql-cpu-s0 \\
        leaderboard/runs/WindowInstall-A-v0/qcfql-long-s0 --out OUT.json

Each RUN is a ``bench run`` directory; its ``results.json`` is checked against the results
schema before it is read. A bad argument is one line on stderr (exit 2) before anything is
written.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path


def _thirds(train_episodes: list[dict], warm_steps: int) -> list[list[dict]]:
    """Stage III's episodes in three parts: those that start at or after ``warm_steps`` env
    steps (the warm start has no takeovers), split where their cumulative steps cross a
    third of the total."""
    start, online = 0, []
    for e in train_episodes:
        if start >= warm_steps:
            online.append(e)
        start += e["steps"]
    total = sum(e["steps"] for e in online)
    thirds: list[list[dict]] = [[], [], []]
    done = 0
    for e in online:
        thirds[min(2, int(3 * done / total))].append(e)
        done += e["steps"]
    return thirds


def stage_iii_thirds(train_episodes: list[dict], warm_steps: int) -> list[float | None]:
    """The intervention rate (takeover steps / env steps) over each third of Stage III's env
    steps (:func:`_thirds`). ``None`` for a third without episodes."""
    return [round(sum(e["takeover_steps"] for e in t) / sum(e["steps"] for e in t), 3)
            if t else None for t in _thirds(train_episodes, warm_steps)]


def stage_iii_cues(train_episodes: list[dict], warm_steps: int) -> list[dict[str, int]]:
    """The takeovers of each third of Stage III (:func:`_thirds`), counted by cue
    (``coverage`` for the installer's deliberate ones)."""
    return [dict(sorted(Counter(c for e in t for c in e.get("takeover_cues", [])).items()))
            for t in _thirds(train_episodes, warm_steps)]


def takeover_episodes(train_episodes: list[dict], warm_steps: int) -> list[dict]:
    """Stage III's episodes with a takeover: their index among all training episodes (so
    runs with the same seed and env can be compared episode by episode: the same index is
    the same start state), third, takeover steps and cues."""
    thirds = _thirds(train_episodes, warm_steps)
    where = {id(e): k for k, t in enumerate(thirds) for e in t}
    return [{"episode": i, "third": where[id(e)] + 1, "takeover_steps": e["takeover_steps"],
             "cues": e.get("takeover_cues", [])}
            for i, e in enumerate(train_episodes) if id(e) in where and e["takeover_steps"]]


def describe(r: dict) -> dict:
    cps, final = r["checkpoints"], r["final"]
    return {"env_id": r["env_id"], "method": r["method"]["name"], "profile": r["profile"]["name"],
            "seed": r["seed"], "track": r["track"],
            "final_success": r["final_eval"]["success_rate"],
            "final_seed_set": r["final_eval"]["seed_set"],
            "final_episodes": r["final_eval"]["episodes"],
            "checkpoints_at_95": sum(c["success_rate"] >= 0.95 for c in cps),
            "checkpoints": len(cps),
            "time_to_95_sim_hours": final["time_to_95_sim_hours"],
            "takeover_minutes": round(final["takeover_minutes"], 1),
            "intervention_rate_stage_iii_thirds": stage_iii_thirds(
                r["train_episodes"], r["profile"]["warm_steps"]),
            "takeovers_stage_iii_thirds": stage_iii_cues(
                r["train_episodes"], r["profile"]["warm_steps"]),
            "takeover_episodes_stage_iii": takeover_episodes(
                r["train_episodes"], r["profile"]["warm_steps"])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="bench run directories")
    p.add_argument("--out", required=True, help="a new JSON file")
    args = p.parse_args(argv)
    from window_bench.harness.evaluation import provenance
    from window_bench.harness.schemas import check_results

    errs = [f"--out {args.out} exists; choose another file"] if Path(args.out).exists() else []
    results = []
    for run in args.runs:
        try:
            r = check_results(Path(run) / "results.json")
            if not (r.get("final_eval") or {}).get("seed_set") or not r["train_episodes"]:
                raise ValueError(f"{run}: not a finished online run (no final evaluation or "
                                 f"no training episodes)")
            results.append(r)
        except (OSError, ValueError) as e:
            errs.append(str(e).splitlines()[0])
    if errs:
        p.error("; ".join(errs))
    out = {"runs": {run: describe(r) for run, r in zip(args.runs, results)},
           "provenance": provenance()}
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    for run, d in out["runs"].items():
        print(json.dumps({"run": run, **d}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
