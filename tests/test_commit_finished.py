"""experiments/commit_finished.py commits a finished cell's raw files and nothing else."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]
SCRIPT = REPO / "experiments" / "commit_finished.py"


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True,
                          text=True).stdout


def _cell(root: Path, name: str, finished: bool) -> Path:
    run = root / "WindowInstall-A-v0" / name
    (run / "policies").mkdir(parents=True)
    (run / "tb").mkdir()
    for step in (0, 3000, 6000):
        (run / "policies" / f"step_{step:07d}.safetensors").write_bytes(b"w" * 16)
    (run / "state.safetensors").write_bytes(b"s" * 16)
    (run / "tb" / "events").write_text("e")
    for f in ("checkpoints.csv", "manifest.json", "learning_curve.png", "stage1.json"):
        (run / f).write_text(f)
    fe = {"policy": "policies/step_0006000.safetensors", "episodes": 100} if finished else None
    (run / "results.json").write_text(json.dumps({"final_eval": fe}))
    logs = root / "sweep-logs" / "WindowInstall-A-v0"
    logs.mkdir(parents=True, exist_ok=True)
    (logs / f"{name}.json").write_text("{}")
    (logs / f"{name}.log").write_text("log")
    return run


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_only_the_final_policy_and_the_raw_files_are_committed(tmp_path):
    shutil.copy(REPO / ".gitignore", tmp_path / ".gitignore")
    _git(tmp_path, "init", "-q")
    _git(tmp_path, "config", "user.email", "t@example.com")
    _git(tmp_path, "config", "user.name", "t")
    _git(tmp_path, "add", ".gitignore")
    _git(tmp_path, "commit", "-qm", "init")
    root = tmp_path / "leaderboard" / "runs"
    _cell(root, "qcfql-cpu-s0", finished=True)
    _cell(root, "qcfql-cpu-s1", finished=False)
    (root / "sweep-table2.json").write_text("{}")

    def run():
        return subprocess.run([sys.executable, str(SCRIPT)], cwd=tmp_path,
                              capture_output=True, text=True)

    p = run()
    assert p.returncode == 0, p.stderr
    assert "grid: raw files of WindowInstall-A-v0/qcfql-cpu-s0" in p.stdout
    cell = "leaderboard/runs/WindowInstall-A-v0/qcfql-cpu-s0/"
    assert set(_git(tmp_path, "ls-files").split()) == {
        ".gitignore", "leaderboard/runs/sweep-table2.json",
        "leaderboard/runs/sweep-logs/WindowInstall-A-v0/qcfql-cpu-s0.json",
        *(cell + f for f in ("results.json", "checkpoints.csv", "manifest.json",
                             "learning_curve.png", "stage1.json",
                             "policies/step_0006000.safetensors"))}

    # nothing new: no commit; a changed results file: one commit of that file
    head = _git(tmp_path, "rev-parse", "HEAD")
    assert run().returncode == 0 and _git(tmp_path, "rev-parse", "HEAD") == head
    (root / "WindowInstall-A-v0" / "qcfql-cpu-s0" / "checkpoints.csv").write_text("changed")
    assert run().returncode == 0
    assert _git(tmp_path, "show", "--name-only", "--format=", "HEAD").split() == [
        cell + "checkpoints.csv"]


def test_a_missing_sweep_root_is_a_one_line_error(tmp_path):
    p = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "nowhere")], cwd=tmp_path,
                       capture_output=True, text=True)
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and "nowhere is not a directory" in p.stderr
