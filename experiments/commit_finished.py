"""Commit every finished cell's raw files under a sweep root, so a long grid loses nothing
when the session running it is cut off (the cells themselves resume with ``bench sweep``).

    python experiments/commit_finished.py [ROOT]          # default leaderboard/runs
    while sleep 300; do python experiments/commit_finished.py; done   # beside a sweep

A training cell is finished when its ``results.json`` has a final evaluation. What is
committed: ``results.json``, ``checkpoints.csv``, ``learning_curve.png``, ``manifest.json``, ``stage1.json`` (where Stage I came from: computed or the cache, and its wall clock),
the final policy (acting weights only, with its sha256 in the manifest and in
``final_eval.policy_sha256``) and the sweep's ``sweep-logs/<cell>.json`` (exit code, wall
clock). Never the training state, replay, TensorBoard events or intermediate policies
(``.gitignore``). An evaluation cell (Table 7) is its ``<env>/<run>.json`` and its sweep record; each sweep's summary
``sweep-<grid>.json`` goes along.
"""

import json
import subprocess
import sys
import time
from pathlib import Path

KEEP = ("results.json", "checkpoints.csv", "learning_curve.png", "manifest.json", "stage1.json")


def finished_files(root: Path) -> list[Path]:
    files = []
    for res in sorted(root.glob("WindowInstall-*/*/results.json")):
        run = res.parent
        try:
            r = json.loads(res.read_text())
        except ValueError:
            continue
        fe = r.get("final_eval") or {}
        if not fe.get("policy"):
            continue
        files += [run / n for n in KEEP if (run / n).exists()] + [run / fe["policy"]]
        log = root / "sweep-logs" / f"{run.parent.name}" / f"{run.name}.json"
        files += [log] if log.exists() else []
    for ev in sorted(root.glob("WindowInstall-*/*.json")):          # evaluation-only cells (Table 7)
        log = root / "sweep-logs" / ev.parent.name / ev.name
        files += [ev] + ([log] if log.exists() else [])
    files += sorted(root.glob("sweep-*.json"))                       # each sweep's summary
    return files


def git(*args: str) -> subprocess.CompletedProcess:
    for attempt in range(20):          # another process may hold .git/index.lock briefly
        p = subprocess.run(["git", *args], capture_output=True, text=True)
        if "index.lock" not in p.stderr:
            return p
        time.sleep(3)
    return p


def main() -> int:
    root = Path(sys.argv[1] if len(sys.argv) > 1 else "leaderboard/runs")
    if not root.is_dir():
        print(f"error: sweep root {root} is not a directory (default leaderboard/runs, "
              "relative to the repository root)", file=sys.stderr)
        return 2
    files = [str(f) for f in finished_files(root)]
    if not files:
        return 0
    # Add exactly these files. (`git status --ignored` names an ignored directory, not its
    # files: adding what it printed committed every intermediate policy of policies/.)
    p = git("add", "-f", "--", *files)
    if p.returncode:
        print(p.stderr, file=sys.stderr)
        return 1
    paths = git("diff", "--cached", "--name-only", "--", *files).stdout.split()
    if not paths:
        return 0
    n = len(root.parts)
    cells = sorted({"/".join(Path(x).parts[n:n + 2]).removesuffix(".json") for x in paths
                    if "sweep-logs" not in x})
    msg = "grid: raw files of " + ", ".join(cells)
    p = git("commit", "-q", "-m", msg, "--", *paths)
    print(p.stdout + p.stderr if p.returncode else msg)
    return p.returncode


if __name__ == "__main__":
    sys.exit(main())
