"""Rolling out a controller, the statistics we report, and the run files they go into.

Every results file carries the provenance the project promises: env id, controller, seeds,
versions of window-bench / mujoco / numpy / gymnasium and the git commit. Per-episode rows
are appended to a JSONL file as they finish, so a calibration killed at any moment resumes
where it stopped; summaries are written to a temporary file and renamed into place.
"""

from __future__ import annotations

import json
import math
import os
import platform
import secrets
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np

from window_bench.installer.scripted import CONTROLLERS
from window_bench.envs.scene import TORQUE_LIMITS
from window_bench.envs.task import FAILURE_MODE_NAMES, FAILURE_MODES


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval for a binomial proportion (the paper's convention)."""
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    if not (0 <= successes <= n):
        raise ValueError(f"successes={successes} must lie in [0, n={n}]")
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).resolve().parent, timeout=5)
        commit = out.stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5,
                               cwd=Path(__file__).resolve().parent).stdout.strip()
        return commit + ("-dirty" if dirty else "") if commit else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def provenance() -> dict:
    import mujoco

    from window_bench import __version__
    return {
        "window_bench": __version__, "mujoco": mujoco.__version__, "numpy": np.__version__,
        "gymnasium": gym.__version__, "python": platform.python_version(),
        "machine": platform.machine(), "git_commit": git_commit(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        # Learning libraries, when the caller has loaded them (importing torch is slow).
        **{name: sys.modules[name].__version__ for name in
           ("torch", "torchrl", "tensordict", "stable_baselines3") if name in sys.modules},
    }


def atomic_write(path: str | os.PathLike, write, binary: bool = True) -> None:
    """``write(fileobj)`` into a temporary file next to ``path``, fsync, then rename it into
    place: readers see the old file or the new one, never half of one. The file gets the
    mode the user's umask gives a new file (``mkstemp`` would make it 0600)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write(path, lambda f: f.write(text), binary=False)


def run_episode(env, controller, seed: int) -> dict:
    """One seeded episode; returns the row we log (stage event times in seconds)."""
    obs, info = env.reset(seed=seed)
    controller.reset(seed=seed)
    events = {"suction_acquired": 0.0 if info["suction_acquired"] else None,
              "insertion_entered": None, "seated": None}
    steps = 0
    u = env.unwrapped
    hold = np.zeros(7)
    while True:
        obs, reward, terminated, truncated, info = env.step(controller.act(obs))
        steps += 1
        np.maximum(hold, np.abs(u.holding_torque()), out=hold)
        for k in events:
            if info[k] and events[k] is None:
                events[k] = round(info["cycle_time_s"], 1)
        if terminated or truncated:
            break
    return {
        "seed": seed, "success": bool(terminated), "steps": steps,
        "cycle_time_s": round(info["cycle_time_s"], 1),
        "failure_mode": FAILURE_MODE_NAMES[info["failure_code"]] or None,
        "sim_unstable": bool(info["sim_unstable"]),
        **{f"t_{k}": v for k, v in events.items()},
        "recoveries": getattr(controller, "recoveries", None),
        "suction_failures": info["suction_failures"],
        # Max over the episode, as a fraction of each joint's torque limit (Table 10).
        "holding_torque_frac": np.round(hold / TORQUE_LIMITS, 3).tolist(),
        "peak_torque_frac": np.round(u.osc.max_abs_tau / TORQUE_LIMITS, 3).tolist(),
        "randomization": {k: round(v, 6) for k, v in env.unwrapped._randomization.items()},
    }


#: What :func:`summarize` reads of a row; a resumed row without them is refused.
ROW_KEYS = frozenset({"seed", "success", "cycle_time_s", "failure_mode", "t_suction_acquired",
                      "t_insertion_entered"})


def summarize(rows: list[dict]) -> dict:
    n = len(rows)
    k = sum(r["success"] for r in rows)
    lo, hi = wilson_interval(k, n)
    cycle = [r["cycle_time_s"] for r in rows if r["success"]]
    modes = Counter(r["failure_mode"] for r in rows if not r["success"])
    return {
        "episodes": n, "successes": k, "success_rate": k / n, "wilson95": [lo, hi],
        "cycle_time_s_mean": float(np.mean(cycle)) if cycle else None,
        "cycle_time_s_median": float(np.median(cycle)) if cycle else None,
        "failure_modes": {m: modes.get(m, 0) for m in FAILURE_MODES if modes.get(m, 0)},
        "seeds": [min(r["seed"] for r in rows), max(r["seed"] for r in rows)],
        "holding_torque_frac_max": np.max([r["holding_torque_frac"] for r in rows], axis=0).round(3).tolist()
        if all("holding_torque_frac" in r for r in rows) else None,
        "suction_failures": sum(r.get("suction_failures", 0) for r in rows),
        "stage_rates": {
            "suction_acquired": sum(r["t_suction_acquired"] is not None for r in rows) / n,
            "insertion_entered": sum(r["t_insertion_entered"] is not None for r in rows) / n,
            "seated": k / n,
        },
    }


def read_rows(rows_path: str | os.PathLike) -> dict[int, dict]:
    """The rows a killed :func:`evaluate` already wrote to ``rows_path``, by seed (none when
    there is no file); a line that parses but is not such a row is a one-line ``ValueError``."""
    done: dict[int, dict] = {}
    if not Path(rows_path).exists():
        return done
    for i, line in enumerate(Path(rows_path).read_text().splitlines(), 1):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a kill: that episode is simply run again
        if not (isinstance(row, dict) and ROW_KEYS <= set(row)
                and type(row["seed"]) is int and type(row["success"]) is bool):
            raise ValueError(f"{rows_path}:{i}: not an episode row of this command; remove "
                             f"the line, or the file, to run that episode again")
        done[row["seed"]] = row
    return done


def evaluate(env_id: str, controller: str, episodes: int, seed: int = 0,
             rows_path: str | os.PathLike | None = None, progress: bool = True,
             env_kwargs: dict | None = None) -> list[dict]:
    """Run ``episodes`` seeded episodes (seeds ``seed .. seed+episodes-1``).

    With ``rows_path`` each finished episode is appended to that JSONL file at once, and
    episodes already in it are skipped: a killed run resumes."""
    if controller not in CONTROLLERS:
        raise ValueError(f"controller={controller!r}; allowed: {sorted(CONTROLLERS)}")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    done = read_rows(rows_path) if rows_path is not None else {}
    env = gym.make(env_id, **(env_kwargs or {}))
    ctrl = CONTROLLERS[controller](env)
    commit = git_commit()
    seeds = [s for s in range(seed, seed + episodes) if s not in done]
    rows = [done[s] for s in range(seed, seed + episodes) if s in done]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=episodes, initial=len(rows), desc=f"{controller} {env_id}",
                   unit="ep", dynamic_ncols=True)
    f = None
    if rows_path is not None:
        Path(rows_path).parent.mkdir(parents=True, exist_ok=True)
        cut = Path(rows_path).exists() and not Path(rows_path).read_bytes().endswith(b"\n") \
            and Path(rows_path).stat().st_size > 0
        f = open(rows_path, "a")
        if cut:
            f.write("\n")  # end the line a kill cut short, so the next row starts clean
    try:
        for s in seeds:
            row = run_episode(env, ctrl, s)
            row["git_commit"] = commit   # a resumed run may span commits: each row says
            rows.append(row)
            if f is not None:
                f.write(json.dumps(row) + "\n")
                f.flush()
                os.fsync(f.fileno())
            if bar is not None:
                k = sum(r["success"] for r in rows)
                bar.set_postfix(success=f"{k}/{len(rows)}")
                bar.update(1)
    finally:
        if f is not None:
            f.close()
        if bar is not None:
            bar.close()
        env.close()
    return sorted(rows, key=lambda r: r["seed"])
