"""The command-line checks the rollout diagnostics share (``chunk_replan.py``,
``failure_trace.py``, ``pixel_embedding_probe.py``): a registered env, a number of
development seeds, an operator profile, an output file that does not exist yet; and a policy file loaded or
refused in one line (``pose_feedback.py``, ``pose_readout_trace.py``,
``state_policy_on_readout.py``). Each returns the one-line
messages of what is wrong (empty: all good), so a script reports every problem at once and
exits 2 before any work."""

from __future__ import annotations

from pathlib import Path

MAX_EPISODES = 500


def env_errors(env_id: str) -> list[str]:
    import window_bench

    if env_id in window_bench.ENV_IDS:
        return []
    return [f"--env {env_id!r}; allowed: {', '.join(window_bench.ENV_IDS)}"]


def episodes_errors(episodes: int) -> list[str]:
    if 1 <= episodes <= MAX_EPISODES:
        return []
    return [f"--episodes {episodes}; allowed: 1..{MAX_EPISODES}"]


def operator_errors(operator: str) -> list[str]:
    from window_bench.installer.operators import OPERATORS

    if operator in OPERATORS:
        return []
    return [f"--operator {operator!r}; allowed: {', '.join(sorted(OPERATORS))}"]


def out_errors(out: str) -> list[str]:
    return [f"--out {out} exists; choose another file"] if Path(out).exists() else []


def load_policy_or_exit(parser, path: str):
    """``load_policy_file(path)``, or the script's one-line error (exit 2) naming the file and
    what is wrong with it (missing, not a policy file, a kind no agent reads)."""
    from window_bench.harness.evaluation import load_policy_file

    try:
        return load_policy_file(path)
    except (OSError, ValueError) as e:
        parser.error(str(e))
