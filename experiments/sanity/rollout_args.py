"""The command-line checks the rollout diagnostics share (``chunk_replan.py``,
``failure_trace.py``, ``pixel_embedding_probe.py``): a registered env, a number of
development seeds, an output file that does not exist yet. Each returns the one-line
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


def out_errors(out: str) -> list[str]:
    return [f"--out {out} exists; choose another file"] if Path(out).exists() else []
