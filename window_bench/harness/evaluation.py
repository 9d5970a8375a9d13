"""Rolling out a controller or a frozen policy, the statistics we report, and their files.

* Reference controllers (``bench install`` / ``bench calibrate``): :func:`evaluate` runs
  seeded episodes; per-episode rows are appended to a JSONL file as they finish, so a
  calibration killed at any moment resumes where it stopped; :func:`summarize`.
* Frozen policies (a training run's checkpoints, ``bench eval``): :class:`Evaluator` rolls
  the policy out deterministically, interventions off, on seeds of a seed set, in spawned
  worker processes, in the env of the policy's observation track; :func:`summarize_eval`
  gives success with its Wilson interval, cycle time, the stage-wise rates and the failure
  modes; :func:`evaluate_policy_file` checks a policy file before anything runs.

Every results file carries the provenance the project promises: env id, controller, seeds,
versions of window-bench / mujoco / numpy / gymnasium and the git commit; summaries are
written to a temporary file and renamed into place.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
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

from window_bench.data.steplog import STEP_DT
from window_bench.envs.scene import TORQUE_LIMITS
from window_bench.envs.task import FAILURE_MODE_NAMES, FAILURE_MODES
from window_bench.harness.methods import agent_class
from window_bench.harness.seeds import eval_seeds
from window_bench.harness.tracks import DEFAULT_TRACK, get_track
from window_bench.installer.scripted import CONTROLLERS

TIME_TO_95_J = 3


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
    # The interval holds p; rounding must not put 100/100 outside it (1 - 1e-16).
    return min(max(0.0, centre - half), p), max(min(1.0, centre + half), p)


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


def _successes(rows: list[dict]) -> dict:
    """Episodes, successes, success rate and its 95 % Wilson interval of episode rows."""
    n = len(rows)
    k = sum(r["success"] for r in rows)
    return {"episodes": n, "successes": k, "success_rate": k / n,
            "wilson95": list(wilson_interval(k, n))}


def _failure_modes(rows: list[dict]) -> dict[str, int]:
    """How many failed episodes ended in each failure mode (the ones that occur)."""
    modes = Counter(r["failure_mode"] for r in rows if not r["success"])
    return {m: modes[m] for m in FAILURE_MODES if modes.get(m)}


def summarize(rows: list[dict]) -> dict:
    n = len(rows)
    k = sum(r["success"] for r in rows)
    cycle = [r["cycle_time_s"] for r in rows if r["success"]]
    return {
        **_successes(rows),
        "cycle_time_s_mean": float(np.mean(cycle)) if cycle else None,
        "cycle_time_s_median": float(np.median(cycle)) if cycle else None,
        "failure_modes": _failure_modes(rows),
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


# ---------------------------------------------------------------------------- frozen policies
class AgentPolicy:
    """Adapts an agent (``act(obs, deterministic)`` -> (h, 7)) to the rollout's policy API."""

    def __init__(self, agent, deterministic: bool):
        self.agent, self.deterministic = agent, deterministic
        self.h = int(agent.h)

    def reset(self, seed=None):
        self.agent.reset()   # e.g. ACT's temporal-ensembling history

    def act(self, obs):
        return self.agent.act(obs, deterministic=self.deterministic)


def _eval_rollout(agent_cls: type, policy_state: dict, env_id: str, max_steps: int,
                  env_kwargs: dict | None = None):
    """A deterministic rollout of the policy in the env of its observation track, observed
    on the policy's chunk grid (``env_kwargs``: constructor arguments of the env, e.g.
    ``{"clearance": 0.005}``)."""
    from window_bench.installer.rollout import Rollout

    agent = agent_cls.from_policy_state_dict(policy_state)
    track = get_track(getattr(agent_cls, "track", DEFAULT_TRACK))
    env = track.eval_env(env_id, policy_state, observe_every=int(agent.h),
                         max_episode_steps=max_steps, **(env_kwargs or {}))
    return Rollout(env, AgentPolicy(agent, deterministic=True), env_id=env_id), env


def _eval_episode(rollout, seed: int) -> dict:
    """One evaluation episode of a :class:`~window_bench.installer.rollout.Rollout` from the
    reset seed ``seed``; its row."""
    log = rollout.run(seed=seed, episode_id=seed)
    info = rollout.info
    return {"seed": int(seed), "success": bool(log.terminated[-1]),
            "cycle_time_s": round(log.T * STEP_DT, 1),
            "suction_acquired": bool(info["suction_acquired"]),
            "insertion_entered": bool(info["insertion_entered"]),
            "failure_mode": "" if log.terminated[-1]
            else (FAILURE_MODE_NAMES[info["failure_code"]] or "timeout"),
            # suction lost by a vacuum-off command vs grips broken at the holding limit
            "commanded_releases": int(info["suction_releases"]),
            "grip_breaks": int(info["suction_failures"]),
            # the acceptance test's centring error on the last step (accepted: < 2 mm)
            "final_position_error_mm": round(1000.0 * float(info["position_error"]), 2)}


#: A pool worker's rollout for the evaluation in progress: (token, rollout, env).
_WORKER_ROLLOUT: list = []


def _eval_worker(task) -> dict:
    """One episode in a pool worker. The worker builds the agent and env once per
    evaluation (``token``) and keeps them for that evaluation's next episodes."""
    token, agent_cls, policy_state, env_id, seed, max_steps, env_kwargs = task
    if not _WORKER_ROLLOUT or _WORKER_ROLLOUT[0] != token:
        import torch

        torch.set_num_threads(1)
        if _WORKER_ROLLOUT:
            _WORKER_ROLLOUT[2].close()
        _WORKER_ROLLOUT[:] = [token, *_eval_rollout(agent_cls, policy_state, env_id, max_steps,
                                                    env_kwargs)]
    return _eval_episode(_WORKER_ROLLOUT[1], seed)


def summarize_eval(rows: list[dict]) -> dict:
    """Checkpoint metrics from evaluation rows: success, Wilson, cycle time, stage-wise."""
    n = len(rows)
    s = sum(r["suction_acquired"] for r in rows)
    i = sum(r["insertion_entered"] and r["suction_acquired"] for r in rows)
    t = sum(r["success"] and r["insertion_entered"] for r in rows)
    cycles = [r["cycle_time_s"] for r in rows if r["success"]]
    ratio = lambda a, b: (a / b) if b else None  # noqa: E731
    # Rows written before the env reported the cause of a suction loss count as neither.
    broke = [r.get("grip_breaks", 0) > 0 for r in rows]
    released = [r.get("commanded_releases", 0) > 0 for r in rows]
    lost = [r["failure_mode"] == "suction_lost" and not r["success"] for r in rows]
    return {**_successes(rows),
            "cycle_time_s": float(np.mean(cycles)) if cycles else None,
            "pr_S": ratio(s, n), "pr_I_given_S": ratio(i, s), "pr_T_given_I": ratio(t, i),
            "failure_modes": _failure_modes(rows),
            "episodes_with_commanded_release": sum(released),
            "episodes_with_grip_break": sum(broke),
            # suction_lost failures by cause: any grip break, else commanded releases only
            "suction_lost_by": {"grip_break": sum(x and b for x, b in zip(lost, broke)),
                                "commanded": sum(x and c and not b
                                                 for x, c, b in zip(lost, released, broke))}}


#: What a results file's ``final_eval`` keeps of :func:`summarize_eval` (besides seeds, policy
#: and its hash): success, stage-wise rates, failure modes and why suction was lost.
FINAL_EVAL_KEYS = ("episodes", "successes", "success_rate", "wilson95", "cycle_time_s", "pr_S",
                   "pr_I_given_S", "pr_T_given_I", "failure_modes",
                   "episodes_with_commanded_release", "episodes_with_grip_break",
                   "suction_lost_by")


def time_to_threshold(rates: list[float], steps: list[int], threshold: float = 0.95,
                      J: int = TIME_TO_95_J) -> int | None:
    """First checkpoint step from which raw success >= threshold for J consecutive
    checkpoints; None if never."""
    if J < 1:
        raise ValueError(f"J = {J} must be >= 1")
    run = 0
    for idx, r in enumerate(rates):
        run = run + 1 if r >= threshold else 0
        if run >= J:
            return steps[idx - J + 1]
    return None


class Evaluator:
    """Frozen-policy evaluation, in spawned worker processes when ``workers`` > 1, with a
    progress bar over the episodes (rate and ETA) when ``progress``. Each episode depends
    only on its seed, so the rows do not depend on the number of workers or on which worker
    ran which episode."""

    def __init__(self, env_id: str, episodes: int, workers: int, max_steps: int,
                 seed_set: str = "dev", progress: bool = False, env_kwargs: dict | None = None):
        self.env_id, self.episodes, self.max_steps = env_id, episodes, max_steps
        self.env_kwargs = dict(env_kwargs or {})
        self.seed_set, self.progress = seed_set, progress
        self.seeds = eval_seeds(seed_set, episodes)
        self.workers = max(1, min(workers, episodes))
        self.pool = None

    def __call__(self, agent_cls: type, policy_state: dict) -> list[dict]:
        """Rows of the M evaluation rollouts of ``agent_cls.from_policy_state_dict(policy_state)``."""
        from tqdm import tqdm

        rows = []
        with tqdm(total=len(self.seeds), desc=f"evaluate ({self.seed_set} seeds)", unit="ep",
                  disable=not self.progress, leave=False) as bar:
            if self.workers == 1:
                rollout, env = _eval_rollout(agent_cls, policy_state, self.env_id,
                                             self.max_steps, self.env_kwargs)
                try:
                    for seed in self.seeds:
                        rows.append(_eval_episode(rollout, seed))
                        bar.update(1)
                finally:
                    env.close()
            else:
                if self.pool is None:
                    self.pool = mp.get_context("spawn").Pool(self.workers)
                token = os.urandom(8).hex()
                tasks = [(token, agent_cls, policy_state, self.env_id, seed, self.max_steps,
                          self.env_kwargs) for seed in self.seeds]
                for row in self.pool.imap_unordered(_eval_worker, tasks):
                    rows.append(row)
                    bar.update(1)
        return sorted(rows, key=lambda r: r["seed"])

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close()
            self.pool.join()
            self.pool = None


def load_policy_file(path: str | os.PathLike) -> tuple[type, dict, dict]:
    """``(agent class, policy state, metadata)`` of a frozen policy file, checked before
    anything runs: against its run's ``manifest.json`` when it lies in a run directory,
    against its own sha256 always, and rebuilt once (its agent kind looked up in the agents
    registry); :class:`~window_bench.harness.files.RunFileError` otherwise."""
    import window_bench
    from window_bench.harness.files import RunFileError, find_run_dir, load_state, verify_files

    path = Path(path)
    run_dir = find_run_dir(path)
    if run_dir is not None:
        verify_files(run_dir, [path.resolve().relative_to(run_dir).as_posix()])
    policy, meta = load_state(path, "policy")
    try:
        agent_cls = agent_class(meta["agent_kind"])
        if meta["env_id"] not in window_bench.ENV_IDS:
            raise ValueError(f"env {meta['env_id']!r} is not registered")
        agent_cls.from_policy_state_dict(policy)   # here, not in a worker's traceback
    except (KeyError, ValueError, TypeError, RuntimeError) as e:
        raise RunFileError(f"{path}: does not hold a policy this window-bench can run "
                           f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})"
                           ) from None
    return agent_cls, policy, meta


def evaluate_policy_file(path: str | os.PathLike, episodes: int, workers: int = 2,
                         env_id: str | None = None, seed_set: str = "dev",
                         max_steps: int = 600, progress: bool = False,
                         clearance: float | None = None) -> dict:
    """``bench eval``: evaluate a frozen policy file from ``policies/`` (interventions off),
    after :func:`load_policy_file` checked it. ``clearance`` (m per side, the scene's range
    [0.0005, 0.02]; None: the env id's own, 0.002) rebuilds the opening with another
    clearance: a tolerance-sensitivity check, not a registered task, so its rows are not
    comparable with the tables and the summary records it in ``env_kwargs``."""
    from window_bench.envs.scene import SceneConfig

    env_kwargs = {}
    if clearance is not None:
        SceneConfig(clearance=float(clearance))      # the scene's range check, before any work
        env_kwargs["clearance"] = float(clearance)
    agent_cls, policy, meta = load_policy_file(path)
    env_id = env_id or meta["env_id"]
    ev = Evaluator(env_id, episodes, workers, max_steps, seed_set, progress, env_kwargs)
    try:
        rows = ev(agent_cls, policy)
    finally:
        ev.close()
    return {"policy": str(path), "method": meta["method"], "env_id": env_id,
            "trained_env_steps": meta["env_steps"], **summarize_eval(rows),
            "seed_set": seed_set, "eval_seeds": [ev.seeds[0], ev.seeds[-1]],
            "env_kwargs": env_kwargs, "rows": rows, "provenance": provenance()}
