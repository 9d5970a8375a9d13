"""Demonstration collection (D_demo) and supervision measurements, behind ``bench demos`` /
``bench supervise``.

:func:`collect_demos` runs the human-like demonstrator (:class:`HumanlikeInstaller` with an
operator profile) through the same 7-D action interface and the same :class:`Rollout` logging
as every policy, keeps the successful episodes (the paper's D_demo is 50 successful
teleoperated trajectories) and writes them as a Minari dataset. Finished episodes are
checkpointed one file each under ``<out>/.partial``, so a killed collection resumes where it
stopped and gives the same dataset; a collection that finishes removes its checkpoints.

:func:`measure_supervision` lets an operator profile supervise a reference controller
(random actions, the straight push) and counts takeovers and installer minutes.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np

from window_bench.data.dataset import load_episodes, save_episodes
from window_bench.data.effort import effort_minutes, takeover_count
from window_bench.harness.evaluation import atomic_write_text, provenance
from window_bench.installer.operators import DEFAULT_OPERATOR, HumanlikeInstaller, get_operator
from window_bench.installer.rollout import Rollout
from window_bench.data.steplog import STEP_DT, EpisodeLog
from window_bench.envs.task import FAILURE_MODE_NAMES


def demo_dataset_id(env_id: str, operator: str) -> str:
    """Minari id of a demo set, e.g. ``window-bench/demos-a-average-v0``."""
    tag = env_id.removeprefix("WindowInstall-").rsplit("-v", 1)[0].lower()
    return f"window-bench/demos-{tag}-{operator}-v0"


def demo_dataset_path(out: str | os.PathLike, env_id: str, operator: str) -> Path:
    """Where :func:`collect_demos` writes that dataset (Minari: ``<root>/<namespace>/<name>``)."""
    return Path(out) / demo_dataset_id(env_id, operator)


def load_or_collect_demos(out: str | os.PathLike, env_id: str, operator: str, n: int,
                          seed: int, progress: bool = True) -> list[EpisodeLog]:
    """The demonstrations under ``out``, collected first only if that dataset does not
    exist: one that exists but cannot be read is an error, never replaced."""
    if not demo_dataset_path(out, env_id, operator).exists():
        collect_demos(env_id, n, out, operator=operator, seed=seed, progress=progress)
    try:
        return load_demos(out, env_id, operator)
    except ValueError as e:
        raise ValueError(f"{e}; it was not replaced: repair or remove it, or pass another "
                         f"--demos") from None


def _save_partial(path: Path, log: EpisodeLog, row: dict) -> None:
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, observations=log.observations, actions=log.actions, rewards=log.rewards,
             terminated=log.terminated, truncated=log.truncated, provenance=log.provenance,
             takeover_kind=log.takeover_kind, policy_chunk_start=log.policy_chunk_start,
             stage_flags=log.stage_flags, row=json.dumps(row),
             **({} if log.meant_actions is None else {"meant_actions": log.meant_actions}),
             randomization=json.dumps(log.randomization))
    os.replace(tmp, path)


def _load_partial(path: Path, env_id: str, operator: str) -> tuple[EpisodeLog | None, dict]:
    """A finished episode's checkpoint (no pickle: numpy refuses object arrays); one that is
    not what :func:`_save_partial` wrote is a one-line ``ValueError`` naming it."""
    try:
        return _read_partial(path, env_id, operator)
    except (OSError, ValueError, KeyError, TypeError, AttributeError, EOFError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{path}: not a demonstration checkpoint of this collection ({msg}); "
                         f"remove it to run that episode again") from None


def _read_partial(path: Path, env_id: str, operator: str) -> tuple[EpisodeLog | None, dict]:
    with np.load(path) as z:
        row = json.loads(str(z["row"]))
        missing = {"episode_id", "seed", "success", "seconds", "recoveries",
                   "failure_mode"} - set(row)
        if missing:
            raise ValueError(f"its row lacks {', '.join(sorted(missing))}")
        if not row["success"]:
            return None, row
        log = EpisodeLog(observations=z["observations"], actions=z["actions"],
                         rewards=z["rewards"], terminated=z["terminated"],
                         truncated=z["truncated"], provenance=z["provenance"],
                         takeover_kind=z["takeover_kind"], episode_id=row["episode_id"],
                         env_id=env_id, seed=row["seed"],
                         policy_chunk_start=z["policy_chunk_start"],
                         stage_flags=z["stage_flags"],
                         randomization=json.loads(str(z["randomization"])), operator=operator,
                         meant_actions=z["meant_actions"] if "meant_actions" in z else None)
    log.validate()
    return log, row


def collect_demos(env_id: str, n: int, out: str | os.PathLike, *, operator: str = DEFAULT_OPERATOR,
                  seed: int = 0, max_attempts: int | None = None, progress: bool = True) -> dict:
    """Collect ``n`` successful demonstrations into ``out`` (a Minari datasets root).

    Episode ``i`` uses seed ``seed + i`` for the env and the demonstrator. Stops after
    ``max_attempts`` episodes (default ``2 * n``) even if fewer succeeded. Returns the summary
    that is also written to ``out/<dataset>.json``.
    """
    from tqdm import tqdm

    if n < 1:
        raise ValueError(f"n = {n} demonstrations: must be >= 1")
    profile = get_operator(operator)
    max_attempts = 2 * n if max_attempts is None else max_attempts
    if max_attempts < n:
        raise ValueError(f"max_attempts = {max_attempts} is below n = {n}")
    out = Path(out)
    if demo_dataset_path(out, env_id, profile.name).exists():
        try:   # a dataset that is there stays there: resumed when readable, else an error
            load_demos(out, env_id, profile.name)
        except ValueError as e:
            raise ValueError(f"{e}; it was not replaced: repair or remove it, or collect into "
                             f"another --out") from None
    partial = out / ".partial" / demo_dataset_id(env_id, profile.name).replace("/", "__")
    partial.mkdir(parents=True, exist_ok=True)
    env = gym.make(env_id, obs_mode="flat")
    demonstrator = HumanlikeInstaller(env, profile)
    rollout = Rollout(env, demonstrator, provenance="demo", operator=profile.name, env_id=env_id)
    kept: list[EpisodeLog] = []
    rows: list[dict] = []
    t0, c0 = time.perf_counter(), time.process_time()
    bar = tqdm(total=n, desc=f"demos {env_id} ({profile.name})", unit="demo", disable=not progress)
    i = 0
    while len(kept) < n and i < max_attempts:
        path = partial / f"{i:05d}.npz"
        if path.exists():
            log, row = _load_partial(path, env_id, profile.name)
        else:
            log = rollout.run(seed=seed + i, episode_id=i)
            row = {"episode_id": i, "seed": seed + i, "success": bool(log.terminated[-1]),
                   "steps": log.T, "seconds": round(log.T * STEP_DT, 1),
                   "recoveries": int(demonstrator.recoveries),
                   "hesitations": int(demonstrator.hesitations),
                   "failure_mode": FAILURE_MODE_NAMES[rollout.info["failure_code"]]}
            _save_partial(path, log, row)
        rows.append(row)
        if row["success"]:
            kept.append(log)
            bar.update(1)
        bar.set_postfix(attempts=i + 1, success=f"{len(kept)}/{i + 1}")
        i += 1
    bar.close()
    env.close()
    if not kept:
        raise RuntimeError(f"no successful demonstration in {i} attempts on {env_id}")
    dataset_id = demo_dataset_id(env_id, profile.name)
    for j, log in enumerate(kept):
        log.episode_id = j
    lengths = np.array([r["seconds"] for r in rows if r["success"]])
    summary = {
        "dataset_id": dataset_id, "env_id": env_id, "operator": profile.as_dict(),
        "requested": n, "kept": len(kept), "attempts": i,
        "success_rate": len(kept) / i,
        "episode_seconds_mean": float(lengths.mean()), "episode_seconds_min": float(lengths.min()),
        "episode_seconds_max": float(lengths.max()),
        "simulated_minutes_all_attempts": sum(r["seconds"] for r in rows) / 60.0,
        "recoveries_mean": float(np.mean([r["recoveries"] for r in rows if r["success"]])),
        "failure_modes": dict(Counter(r["failure_mode"] for r in rows if not r["success"])),
        "wall_clock_s": round(time.perf_counter() - t0, 1),
        "cpu_time_s": round(time.process_time() - c0, 1), "seed": seed,
        "episodes": rows, "provenance": provenance(),
    }
    save_episodes(kept, dataset_id, env_id=env_id, obs_dim=kept[0].observations.shape[1],
                  data_path=out, metadata={"operator": profile.name, "seed": seed,
                                           "attempts": i}, overwrite=True)
    atomic_write_text(out / f"{dataset_id.replace('/', '__')}.json", json.dumps(summary, indent=1))
    # The dataset and its summary are in place: the resume checkpoints have done their job.
    shutil.rmtree(partial)
    with contextlib.suppress(OSError):   # other collections may still be resuming there
        partial.parent.rmdir()
    return summary


def load_demos(out: str | os.PathLike, env_id: str,
               operator: str = DEFAULT_OPERATOR) -> list[EpisodeLog]:
    """The demonstrations :func:`collect_demos` wrote for ``env_id`` and ``operator``."""
    return load_episodes(demo_dataset_id(env_id, operator), data_path=out)


def measure_supervision(env_id: str, controller: str, operator: str, episodes: int, *,
                        seed: int = 0, h: int = 10, progress: bool = True) -> dict:
    """An operator profile supervising a reference controller: takeovers and minutes."""
    from tqdm import tqdm

    from window_bench.installer.scripted import CONTROLLERS
    from window_bench.installer.supervisor import InstallerSupervisor

    if controller not in CONTROLLERS:
        raise ValueError(f"unknown controller {controller!r}; choose from {sorted(CONTROLLERS)}")
    profile = get_operator(operator)
    env = gym.make(env_id, obs_mode="flat")
    policy = CONTROLLERS[controller](env, seed=seed)
    sup = InstallerSupervisor(profile)
    rollout = Rollout(env, policy, supervisor=sup, h=h, operator=profile.name, env_id=env_id)
    logs, cues, kinds = [], Counter(), Counter()
    t0 = time.perf_counter()
    for i in tqdm(range(episodes), desc=f"{profile.name} supervising {controller}",
                  unit="ep", disable=not progress):
        logs.append(rollout.run(seed=seed + i, episode_id=i))
        cues.update(c for _, c, k in sup.events if k == "safety")
        kinds.update(k for _, _, k in sup.events)
    env.close()
    steps = sum(log.T for log in logs)
    takeover_steps = sum(int((log.provenance == "takeover").sum()) for log in logs)
    return {
        "env_id": env_id, "controller": controller, "operator": profile.name, "episodes": episodes,
        "seed": seed, "h": h, "successes": int(sum(bool(log.terminated[-1]) for log in logs)),
        "takeovers": sum(takeover_count(log) for log in logs),
        "takeovers_per_episode": sum(takeover_count(log) for log in logs) / episodes,
        "safety_takeovers": kinds.get("safety", 0), "coverage_interventions": kinds.get("coverage", 0),
        "safety_cues": dict(cues), "takeover_minutes": effort_minutes(logs),
        "takeover_fraction": takeover_steps / steps, "simulated_minutes": steps * STEP_DT / 60,
        "wall_clock_s": round(time.perf_counter() - t0, 1), "provenance": provenance(),
    }
