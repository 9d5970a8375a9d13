"""The matched-budget harness: ``bench run --method NAME`` (paper Sections 3.4-3.6, 4.2).

One run = one method on one env with one seed and one profile (:mod:`window_bench.harness.methods`):

* **Stage I - offline pretraining** on D_demo (``profile.offline_steps`` gradient steps);
* **Stage II - warm start**: the pretrained policy collects ``profile.warm_steps``
  transitions with no updates (and no takeovers);
* **Stage III - online fine-tuning**: ``profile.utd`` gradient steps per environment step on
  batches drawn 1:1 from D_demo and D_online, takeovers by the installer supervisor when the
  method has interventions, until ``profile.budget_steps`` environment steps (warm start
  included) have been used.

Every ``profile.checkpoint_every`` environment steps (and once after Stage I) the policy is
frozen and evaluated with interventions off over M seeded rollouts (the same seeds at every
checkpoint and for every method), in parallel worker processes: success with a 95 % Wilson
interval, cycle time over successes, stage-wise Pr(S), Pr(I|S), Pr(T|I) and the failure-mode
histogram. Training metrics: running success and intervention rate over the last 20 training
episodes, cumulative takeover minutes, and time-to-95 (the first checkpoint where raw success
>= 95 % holds for J = 3 consecutive checkpoints). Progress is reported in simulated hours
(environment steps / 36,000) and in compute wall-clock.

Outputs in ``--out``: ``results.json`` (schema-versioned: method, env, profile, seed,
hyperparameters, versions, git commit, every checkpoint), ``checkpoints.csv``,
``learning_curve.png``, TensorBoard scalars under ``tb/``, the frozen policy of every
checkpoint under ``policies/`` (acting weights only; ``bench eval`` reads them), and
``state.safetensors``, the atomic training state (agent, optimizer, replay, RNGs, counters)
written at episode boundaries, from which ``--resume`` continues a killed run exactly where
the state was saved. The directory is owned through :class:`~window_bench.harness.files.RunDir`:
locked while the run writes, every file in ``manifest.json`` with its sha256 and verified when
it is read back, nothing pickled; the whole configuration is checked before any of it.

The harness runs every method through one loop: it holds an
:class:`~window_bench.harness.agent.Agent` built from the registry
(:data:`~window_bench.harness.methods.AGENTS`) and reads the agent's declared capabilities
(its replay, where takeover steps go, its normaliser, its offline step count), never its kind.
"""

from __future__ import annotations

import csv
import io
import json
import multiprocessing as mp
import os
import time
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from window_bench.harness.agent import Agent, AgentSpec
from window_bench.harness.evaluation import atomic_write_text, provenance, wilson_interval
from window_bench.harness.files import (STATE, RunDir, RunFileError, find_run_dir, load_state,
                                        verify_files)
from window_bench.harness.seeds import DEV_SEED0, MAX_SEED, SEED_SETS, eval_seeds
from window_bench.harness.methods import Method, Profile, agent_class, get_method, get_profile
from window_bench.installer.rollout import Rollout
from window_bench.data.steplog import ACTION_DIM, STEP_DT
from window_bench.envs.task import FAILURE_MODE_NAMES, FAILURE_MODES

RESULTS_SCHEMA = 1
STEPS_PER_HOUR = 36_000            # 10 Hz
EVAL_SEED0 = DEV_SEED0   # checkpoint evaluations use the development seeds (harness/seeds.py)
TIME_TO_95_J = 3
RATE_WINDOW = 20
LOSS_LOG_EVERY = 500    # learner calls averaged into one TensorBoard point (loss/...)
DEMOS = "demos"         # where a run without --demos collects its own, inside --out
MAX_OVERRIDE_INT = 1_000_000   # --agent-config counts and sizes (the paper's Stage I: 1e6)
MAX_OVERRIDE_WIDTH = 8192      # --agent-config layer widths (the paper's MLPs: 512)


# ---------------------------------------------------------------------------- agents
def make_agent(method: Method, profile: Profile, demos: list, seed: int,
               overrides: dict | None = None) -> Agent:
    """A fresh learner for ``method`` (its class from the registry) with the profile's sizes;
    ``overrides`` replace fields of the agent's config (``bench run --agent-config KEY=VALUE``)."""
    cls = agent_class(method.agent)
    obs = np.concatenate([ep.observations for ep in demos])
    mean, std = (None, None) if cls.own_normalizer else obs_normalizer(obs)
    return cls.create(AgentSpec(obs_dim=int(obs.shape[1]), action_dim=ACTION_DIM, h=method.h,
                                seed=seed, profile=profile, demos=demos, obs_mean=mean,
                                obs_std=std, overrides=dict(overrides or {})))


def parse_overrides(items: list[str] | None) -> dict:
    """``["alpha=100", "act_noise_scale=0"]`` -> ``{"alpha": 100, "act_noise_scale": 0}``
    (values parsed as JSON where possible: numbers, booleans, lists)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--agent-config {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
        if isinstance(out[key], list):
            out[key] = tuple(out[key])
    return out


def _fits(value, tp) -> bool:
    """``value`` (parsed from JSON, lists as tuples) has the annotated type ``tp``."""
    import types
    import typing

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in args)
    if origin is tuple:
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(v, args[0]) for v in value)
        return len(value) == len(args) and all(_fits(v, a) for v, a in zip(value, args))
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is str:
        return isinstance(value, str)
    return True   # a type the configs do not use: their own checks decide


def _type_name(tp) -> str:
    import types
    import typing

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_type_name(args[0]).removeprefix('an ').removeprefix('a ')}s"
        return f"a list [{', '.join(_type_name(a) for a in args)}]"
    return {type(None): "null", bool: "true or false", int: "an integer", float: "a number",
            str: "a string"}.get(tp, getattr(tp, "__name__", str(tp)))


def check_agent_config(agent_cls: type, h: int, profile: Profile, overrides: dict):
    """The agent's config with ``--agent-config`` applied, or a one-line ``ValueError``: each
    value must have its field's declared type (read from the config dataclass) and be finite;
    the config's own checks then hold the ranges (positive sizes, rates in [0, 1] ...)."""
    import dataclasses
    import math
    import typing

    try:   # the config's own checks first: their messages name the allowed range
        config, error = agent_cls.make_config(h, profile, overrides), None
    except TypeError as e:   # a value of a type its checks did not expect
        config, error = None, e
    default = agent_cls.make_config(h, profile, {})
    if dataclasses.is_dataclass(default):
        name, hints = type(default).__name__, typing.get_type_hints(type(default))
        for key, value in overrides.items():
            if key in hints and not _fits(value, hints[key]):
                raise ValueError(f"{name}.{key} = {value!r} is not allowed: it must be "
                                 f"{_type_name(hints[key])}")
    if error is not None:   # still one line, naming the values
        raise ValueError(f"--agent-config {overrides}: {str(error).splitlines()[0]}")
    for key, value in overrides.items():
        # sizes the configs bound only from below: a width or a count that exhausts memory
        # would stop the run after its directory was made
        most = MAX_OVERRIDE_WIDTH if isinstance(value, tuple) else MAX_OVERRIDE_INT
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{type(config).__name__}.{key} = {value!r} is not allowed: "
                                 f"it must be finite")
            if isinstance(v, int) and not isinstance(v, bool) and v > most:
                raise ValueError(f"{type(config).__name__}.{key} = {value!r} is not allowed: "
                                 f"{'each entry' if isinstance(value, tuple) else 'it'} must "
                                 f"be at most {most}")
    return config


def obs_normalizer(obs: np.ndarray, floor: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std of the demonstrations' observations, for the agents' fixed z-scoring.

    A feature constant in the demonstrations (the vacuum flag in A, which never drops in a
    good demonstration) keeps scale 1: it is only centred, because flooring its std would
    blow a value seen only online (the flag at 0) up to ``1 / floor`` units. Other stds are
    floored at ``floor``; the agents also clip normalised inputs (QC-FQL: +-10).
    """
    mean, std = obs.mean(0), obs.std(0)
    std = np.where(std < 1e-6, 1.0, np.maximum(std, floor))
    return mean.astype(np.float32), std.astype(np.float32)


class AgentPolicy:
    """Adapts an agent (``act(obs, deterministic)`` -> (h, 7)) to the rollout's policy API."""

    def __init__(self, agent, deterministic: bool):
        self.agent, self.deterministic = agent, deterministic
        self.h = int(agent.h)

    def reset(self, seed=None):
        self.agent.reset()   # e.g. ACT's temporal-ensembling history

    def act(self, obs):
        return self.agent.act(obs, deterministic=self.deterministic)


# ---------------------------------------------------------------------------- evaluation
def _eval_rollout(agent_cls: type, policy_state: dict, env_id: str, max_steps: int,
                  env_kwargs: dict | None = None):
    """A deterministic rollout of the policy in the env of its observation track
    (``env_kwargs``: constructor arguments of the env, e.g. ``{"clearance": 0.005}``)."""
    import window_bench  # noqa: F401  (registers the envs in a spawned worker)
    from window_bench.pixels.track import make_track_env

    agent = agent_cls.from_policy_state_dict(policy_state)
    # The policy's observation track: a pixel agent names its encoder weights in its state.
    # Pixels are rendered and encoded only where the policy reads them (its chunk grid).
    env = make_track_env(env_id, getattr(agent_cls, "track", "state"),
                         weights=policy_state.get("encoder_weights"), max_episode_steps=max_steps,
                         observe_every=int(agent.h), **(env_kwargs or {}))
    return Rollout(env, AgentPolicy(agent, deterministic=True), env_id=env_id), env


def _eval_episode(rollout: Rollout, seed: int) -> dict:
    """One evaluation episode from the reset seed ``seed``; its row."""
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
        torch.set_num_threads(1)
        if _WORKER_ROLLOUT:
            _WORKER_ROLLOUT[2].close()
        _WORKER_ROLLOUT[:] = [token, *_eval_rollout(agent_cls, policy_state, env_id, max_steps,
                                                    env_kwargs)]
    return _eval_episode(_WORKER_ROLLOUT[1], seed)


def summarize_eval(rows: list[dict]) -> dict:
    """Checkpoint metrics from evaluation rows: success, Wilson, cycle time, stage-wise."""
    n = len(rows)
    k = sum(r["success"] for r in rows)
    s = sum(r["suction_acquired"] for r in rows)
    i = sum(r["insertion_entered"] and r["suction_acquired"] for r in rows)
    t = sum(r["success"] and r["insertion_entered"] for r in rows)
    lo, hi = wilson_interval(k, n)
    cycles = [r["cycle_time_s"] for r in rows if r["success"]]
    modes = Counter(r["failure_mode"] for r in rows if not r["success"])
    ratio = lambda a, b: (a / b) if b else None  # noqa: E731
    # Rows written before the env reported the cause of a suction loss count as neither.
    broke = [r.get("grip_breaks", 0) > 0 for r in rows]
    released = [r.get("commanded_releases", 0) > 0 for r in rows]
    lost = [r["failure_mode"] == "suction_lost" and not r["success"] for r in rows]
    return {"episodes": n, "successes": k, "success_rate": k / n, "wilson95": [lo, hi],
            "cycle_time_s": float(np.mean(cycles)) if cycles else None,
            "pr_S": ratio(s, n), "pr_I_given_S": ratio(i, s), "pr_T_given_I": ratio(t, i),
            "failure_modes": {m: modes[m] for m in FAILURE_MODES if modes.get(m)},
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


def _replay_from_state(sd: dict):
    from window_bench.data.replay import ChunkReplay

    rb = ChunkReplay(sd["capacity"], sd["h"], sd["gamma"], seed=sd["seed"],
                     half_obs=sd.get("half_obs", 0))
    rb.load_state_dict(sd)
    return rb


# ---------------------------------------------------------------------------- files
def _checkpoints_csv(checkpoints: list[dict]) -> str:
    cols = ["env_steps", "sim_hours", "wall_clock_s", "episodes", "successes", "success_rate",
            "wilson_lo", "wilson_hi", "cycle_time_s", "pr_S", "pr_I_given_S", "pr_T_given_I",
            "takeover_minutes", "train_success_rate", "train_intervention_rate",
            "failure_modes"]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(cols)
    for c in checkpoints:
        row = {**c, "wilson_lo": c["wilson95"][0], "wilson_hi": c["wilson95"][1],
               "failure_modes": json.dumps(c["failure_modes"])}
        w.writerow(["" if row.get(k) is None else row.get(k) for k in cols])
    return buf.getvalue()


def plot_learning_curve(results: dict) -> bytes:
    """Success with its Wilson band and the training intervention rate vs simulated hours
    (the layout of the paper's Figs. 10 and 11), as PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cps = results["checkpoints"]
    x = [c["sim_hours"] for c in cps]
    y = [100 * c["success_rate"] for c in cps]
    lo = [100 * c["wilson95"][0] for c in cps]
    hi = [100 * c["wilson95"][1] for c in cps]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6.4, 5.6), sharex=True)
    a1.fill_between(x, lo, hi, alpha=0.25, label="95 % Wilson")
    a1.plot(x, y, "o-", label=f"{results['method']['label']}")
    a1.axhline(95, ls=":", c="gray")
    a1.set_ylabel("success (%)")
    a1.set_ylim(-2, 102)
    a1.legend(loc="lower right")
    a1.set_title(f"{results['method']['name']} on {results['env_id']} "
                 f"({results['profile']['name']} profile, seed {results['seed']})")
    ir = [100 * (c["train_intervention_rate"] or 0) for c in cps]
    a2.plot(x, ir, "s-", c="C3")
    a2.set_ylabel("intervention rate,\nlast 20 episodes (%)")
    a2.set_xlabel("online interaction (simulated hours, warm start included)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


# ---------------------------------------------------------------------------- the run
class Run:
    """One training run; :meth:`train` executes (or resumes) it to the end."""

    def __init__(self, method: str, env_id: str, profile: str, seed: int, out: str | os.PathLike,
                 *, resume: bool = False, operator: str = "average",
                 track: str = "state", encoder_weights: str | os.PathLike | None = None,
                 demos: str | os.PathLike | None = None, progress: bool = True,
                 save_every_s: float = 60.0, acceptance_noise: dict | None = None,
                 agent_config: dict | None = None, h: int | None = None,
                 final_episodes: int | None = None, final_seed_set: str = "dev",
                 stage1_cache: str | os.PathLike | None = None,
                 eval_workers: int | None = None,
                 pixel_demos_cache: str | os.PathLike | None = None):
        self.method = get_method(method)
        if h is not None:    # Tables 5/6: replay, agent and chunking all follow method.h
            if not agent_class(self.method.agent).follows_method_h:
                raise ValueError(f"--h {h}: h is a run parameter of the QC-FQL methods, not of "
                                 f"{method!r} (agent {self.method.agent!r})")
            if isinstance(h, bool) or not isinstance(h, int) or not 1 <= h <= 100:
                raise ValueError(f"--h {h!r}; allowed: an integer in 1..100")
            import dataclasses

            self.method = dataclasses.replace(self.method, h=h)
        if final_episodes is not None:
            eval_seeds(final_seed_set, final_episodes)      # checks both before any work
        self.final_episodes, self.final_seed_set = final_episodes, final_seed_set
        self.stage1_cache = stage1_cache
        self.profile = get_profile(profile)
        if eval_workers is not None:    # evaluation processes; results do not depend on it
            if isinstance(eval_workers, bool) or not isinstance(eval_workers, int) \
                    or not 1 <= eval_workers <= 64:
                raise ValueError(f"--eval-workers {eval_workers!r}; allowed: an integer in 1..64")
            import dataclasses

            self.profile = dataclasses.replace(self.profile, eval_workers=eval_workers)
        self.agent_cls = agent_class(self.method.agent)
        self._init_track(track, encoder_weights)
        import window_bench

        if env_id not in window_bench.ENV_IDS:
            raise ValueError(f"unknown env {env_id!r}; registered: {', '.join(window_bench.ENV_IDS)}")
        from window_bench.installer.operators import get_operator

        get_operator(operator)
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
            raise ValueError(f"--seed {seed!r}; allowed: an integer in 0..{MAX_SEED}")
        self.env_id, self.seed, self.operator = env_id, seed, operator
        if acceptance_noise is not None:
            from window_bench.envs.wrappers import AcceptanceSensor

            AcceptanceSensor(**acceptance_noise)     # validates the rates and the delay
        self.acceptance_noise = acceptance_noise
        self.agent_config = dict(agent_config or {})
        # A bad --agent-config stops the run here, before any demo is collected.
        check_agent_config(self.agent_cls, self.method.h, self.profile, self.agent_config)
        self.out = Path(out)
        self.demos_root = Path(demos) if demos is not None else self.out / DEMOS
        # The pixel track's re-observed demos (pixels/demo_cache.py); None: beside the demos.
        self.pixel_demos_cache = Path(pixel_demos_cache) if pixel_demos_cache is not None \
            else None
        self._check_dirs(stage1_cache)
        self.progress, self.save_every_s = progress, float(save_every_s)
        h = self.agent_config.get("h", self.method.h)
        if h != self.method.h:
            raise ValueError(f"--agent-config h = {h!r}: the method {self.method.name} has h = "
                             f"{self.method.h} (Table 1); choose the method with the chunk "
                             f"horizon you want")
        # Demos elsewhere that exist are read now: one that cannot be read stops the run
        # before any file. The run's own demos are read once checked against its manifest.
        self._raw_demos = None if self._own_demos else self._raw_demo_episodes(collect=False)
        self.files = RunDir(self.out, {
            "method": self.method.name, "env_id": self.env_id, "profile": self.profile.name,
            "seed": self.seed, "operator": self.operator, "track": self.track, "h": self.method.h,
            "acceptance_noise": self.acceptance_noise, "agent_config": self.agent_config},
            resume)
        if self._own_demos:
            from window_bench.installer.demos import demo_dataset_path

            try:
                self.files.check_listed(demo_dataset_path(DEMOS, self.env_id, self.operator))
                self._raw_demos = self._raw_demo_episodes(collect=False)
            except BaseException:
                self.files.close()
                raise
        self._stop_after_env_steps = None   # tests: simulate a kill (no state written)
        self._tb, self._loss_acc = None, []
        self.loss_log_every = LOSS_LOG_EVERY

    def _check_dirs(self, stage1_cache) -> None:
        """The directories the run writes besides ``out`` are usable (a file in the way is
        refused now, not after Stage I); demos inside ``out`` are its own ``demos/``."""
        from window_bench.harness.files import check_out_dir

        for option, path in (("--stage1-cache", stage1_cache),
                             ("--pixel-demos-cache", self.pixel_demos_cache)):
            if path is not None:
                check_out_dir(path, option)
        if not self.demos_root.is_dir():   # collected there
            check_out_dir(self.demos_root, "--demos")
        out, demos = self.out.resolve(), self.demos_root.resolve()
        self._own_demos = demos == out / DEMOS
        if demos.is_relative_to(out) and not self._own_demos:
            raise ValueError(f"--demos {self.demos_root}: inside the run directory {self.out}; "
                             f"use its own {DEMOS}/ (the default) or a directory outside it")

    def _init_track(self, track: str, encoder_weights) -> None:
        """The observation track (docs/pixels.md): ``state`` (the privileged 52-float state)
        or ``pixels`` (two views through the frozen ResNet-10 + proprioception). The pixel
        track runs the method's pixel agent kind and resolves the backbone now, so a wrong
        weights file fails before any work."""
        import dataclasses

        from window_bench.pixels.track import TRACK_LABELS, check_track, track_agent_kind

        self.track = check_track(track)
        self.backbone, self.encoder_weights, self._pixel_demos = None, None, None
        self.replay_half_obs = 0
        self.encoder = {"track_label": TRACK_LABELS[self.track]}
        if self.track == "pixels":
            from window_bench.harness.files import sha256_file
            from window_bench.pixels.encoder import FEATURE_VALUES
            from window_bench.pixels.weights import DEFAULT_WEIGHTS, resolve_backbone, weights_record

            self.replay_half_obs = FEATURE_VALUES   # both views' maps, float16-exact
            kind = track_agent_kind(self.method.agent, self.track)
            self.method = dataclasses.replace(self.method, agent=kind)
            self.agent_cls = agent_class(kind)
            if encoder_weights is not None:
                encoder_weights = str(Path(encoder_weights).resolve())
            self.backbone, label = resolve_backbone(encoder_weights)
            self.encoder_weights = encoder_weights
            path = DEFAULT_WEIGHTS if encoder_weights is None else Path(encoder_weights)
            record = weights_record(path)
            self.encoder.update(weights=label, sha256=sha256_file(path),
                                **{k: record[k] for k in ("command", "heldout_quality")
                                   if k in record})

    # ------------------------------------------------------------------ setup
    def _raw_demo_episodes(self, collect: bool):
        """D_demo as recorded: read, or (``collect``) collected first where there is no
        dataset - never over one that exists and cannot be read."""
        from window_bench.installer.demos import demo_dataset_path, load_or_collect_demos

        missing = not demo_dataset_path(self.demos_root, self.env_id, self.operator).exists()
        if missing and not collect:
            return None
        eps = load_or_collect_demos(self.demos_root, self.env_id, self.operator,
                                    self.profile.n_demos, seed=1_000_000 + self.seed,
                                    progress=self.progress)
        if missing and self._own_demos:
            self.files.record(DEMOS)   # collected into the run: listed, verified on resume
        if len(eps) < self.profile.n_demos:
            raise ValueError(f"{self.demos_root}: {len(eps)} demonstrations, the profile needs "
                             f"{self.profile.n_demos}")
        return eps[: self.profile.n_demos]

    def _demos(self):
        eps = self._raw_demos
        if eps is None:
            eps = self._raw_demos = self._raw_demo_episodes(collect=True)
        if self.track == "pixels":   # re-observed once per Run: it renders and encodes
            if self._pixel_demos is None:
                from window_bench.pixels.demo_cache import DEFAULT_SUBDIR, cached_pixel_demos

                cache = self.pixel_demos_cache or self.demos_root / DEFAULT_SUBDIR
                # a cache inside the run is the run's: listed, and checked before it is read
                out, where = self.out.resolve(), cache.resolve()
                inside = where.relative_to(out).as_posix() if where.is_relative_to(out) else None
                if inside is not None:
                    self.files.check_listed(inside)
                self._pixel_demos, self._pixel_demos_record = cached_pixel_demos(
                    eps, self.env_id, self.backbone, cache, self.progress)
                if inside is not None:
                    self.files.record(inside)
            return self._pixel_demos
        return eps

    def _demos_sha256(self) -> str:
        """The recorded demonstrations' digest: a resume must read the ones the run began on."""
        from window_bench.harness.stage1 import demos_sha256

        return demos_sha256(self._raw_demos)

    def _fresh(self) -> dict:
        torch.manual_seed(self.seed)
        demos = self._demos()
        self.agent = make_agent(self.method, self.profile, demos, self.seed, self.agent_config)
        if self.track == "pixels":
            self.agent.encoder_weights = self.encoder_weights
        self.agent.attach_demos(demos)
        self._make_replays(demos)
        return {"stage": "offline", "offline_done": 0, "env_steps": 0, "episodes": [],
                "checkpoints": [], "grad_steps": 0, "update_credit": 0.0, "wall_clock_s": 0.0,
                "next_checkpoint": 0, "obs_dim": int(demos[0].observations.shape[1]),
                "h": self.method.h, "demos_sha256": self._demos_sha256(),
                "pixel_demos": [self._pixel_demos_record] if self.track == "pixels" else None,
                "provenance_start": provenance()}

    def _make_replays(self, demos) -> None:
        """D_demo (with room for the takeover segments of agents that add them) and D_online,
        as chunk replays on the method's grid."""
        from window_bench.data.replay import ChunkReplay

        h, p, gamma = self.method.h, self.profile, self.agent.gamma
        demo_chunks = sum(-(-ep.T // h) for ep in demos)
        if self.agent.takeovers_to_demo:
            demo_chunks += p.budget_steps
        half = self.replay_half_obs   # pixel track: feature maps stored as float16
        self.demo_rb = ChunkReplay(demo_chunks, h, gamma, seed=self.seed, half_obs=half)
        for ep in demos:
            self.demo_rb.add_episode(ep)
        self.online_rb = ChunkReplay(p.budget_steps // h + 2 * p.max_episode_steps, h, gamma,
                                     seed=self.seed + 1, half_obs=half)

    def _save(self) -> None:
        self.files.write_state(STATE, {
            "counters": self.c, "agent": self.agent.state_dict(),
            "demo_rb": self.demo_rb.state_dict(), "online_rb": self.online_rb.state_dict(),
            "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(legacy=False)},
            "state", self.files.identity)
        self._last_save = time.perf_counter()

    def _load(self) -> None:
        st, saved = self.files.read_state(STATE, "state")
        # RunDir matched this command to the manifest; the manifest must match the run that
        # saved the state (a manifest edited to another seed would relabel this run)
        run, saved = self.files.manifest["run"], saved if isinstance(saved, dict) else {}
        for key in sorted(set(saved) | set(run)):
            if saved.get(key) != run.get(key):
                raise RunFileError(f"{self.out / 'manifest.json'}: records {key} = "
                                   f"{run.get(key)!r}, the run's {STATE} was saved with "
                                   f"{saved.get(key)!r} (edited, or another run's manifest); "
                                   f"restore it from a copy or start a new run")
        self.c = st["counters"]
        if self.c.setdefault("h", self.method.h) != self.method.h:
            raise RunFileError(f"--resume: the saved run has h = {self.c['h']}, this command "
                               f"asks for h = {self.method.h}")
        demos, digest = self._demos(), self._demos_sha256()
        if self.c.setdefault("demos_sha256", digest) != digest:
            raise RunFileError(f"--resume: the run in {self.out} began on other demonstrations "
                               f"than those in {self.demos_root} (sha256 "
                               f"{self.c['demos_sha256'][:12]}, not {digest[:12]}); pass the "
                               f"--demos it began with")
        self.agent = self.agent_cls.from_state_dict(st["agent"])
        self.agent.attach_demos(demos)
        if self.track == "pixels":   # one record per start: cache key, hit, seconds
            self.c.setdefault("pixel_demos", []).append(self._pixel_demos_record)
        self.demo_rb, self.online_rb = (_replay_from_state(st[k]) for k in ("demo_rb", "online_rb"))
        # After the agent: building one may seed the global RNGs (SB3 does).
        torch.set_rng_state(st["torch_rng"])
        np.random.set_state(st["numpy_rng"])

    # ------------------------------------------------------------------ the run, top to bottom
    def train(self) -> dict:
        """Stage I, the first checkpoint, Stages II-III; a resumed run skips what is done."""
        try:
            return self._train()
        finally:
            self.files.close()   # the lock; the OS releases it too if the process dies

    def _train(self) -> dict:
        torch.set_num_threads(1)
        self._t0 = self._last_save = time.perf_counter()
        if self.files.has(STATE):
            self._load()
        else:
            self.c = self._fresh()
            self._save()
        p = self.profile
        self._tb = self._tensorboard()
        self._evaluator = Evaluator(self.env_id, p.eval_episodes, p.eval_workers,
                                    p.max_episode_steps, progress=self.progress)
        try:
            if self.c["stage"] == "offline":
                self._stage_i_cached()
            if self.c["stage"] == "evaluate0":
                self._first_checkpoint()
            if self.c["stage"] in ("warm", "online"):
                self._stages_ii_iii_interaction()
        finally:
            self._evaluator.close()
            if self._tb is not None:
                self._tb.close()
        return self._finish()

    def _stage_i_offline_pretraining(self) -> None:
        """``offline_steps`` learner calls on D_demo batches (none without Stage I)."""
        from tqdm import tqdm

        p = self.profile
        if self.method.offline_pretrain:
            with tqdm(total=self._offline_steps(), initial=self.c["offline_done"],
                      desc="Stage I  offline", unit="upd", disable=not self.progress) as bar:
                while self.c["offline_done"] < self._offline_steps():
                    n = self._learn(lambda: self.demo_rb.sample(p.batch_size))
                    self.c["offline_done"] += n
                    self.c["grad_steps"] += n
                    bar.update(n)
                    if time.perf_counter() - self._last_save > self.save_every_s:
                        self._checkpoint_state()
        self.c["stage"] = "evaluate0"
        self._checkpoint_state()

    def _stage_i_cached(self) -> None:
        """Stage I, or its cached result when ``stage1_cache`` is set and a run with the same
        agent, config, h, demonstrations and seed computed it (harness/stage1.py)."""
        if self.stage1_cache is None or not self.method.offline_pretrain:
            return self._stage_i_offline_pretraining()
        from window_bench.harness.stage1 import Stage1Cache, demos_sha256, key_material, \
            stage1_key

        cache = Stage1Cache(self.stage1_cache)
        demos = self._demos()
        material = key_material(self.method.agent, self.agent.hyperparameters(),
                                self._offline_steps(), self.profile.batch_size,
                                demos_sha256(demos), self.seed)
        key = stage1_key(material)
        t0 = time.perf_counter()
        with cache.lock(key):
            waited = time.perf_counter() - t0
            entry = cache.load(key)
            if entry is None:
                self._stage_i_offline_pretraining()
                wall = time.perf_counter() - t0 - waited
                cache.store(key, {"agent": self.agent.state_dict(),
                                  "demo_rb_rng": self.demo_rb.state_dict()["rng_state"],
                                  "torch_rng": torch.get_rng_state(),
                                  "numpy_rng": np.random.get_state(legacy=False),
                                  "offline_done": self.c["offline_done"],
                                  "grad_steps": self.c["grad_steps"]}, material, wall)
            else:
                tree, meta = entry
                self.agent = self.agent_cls.from_state_dict(tree["agent"])
                self.agent.attach_demos(demos)
                sd = self.demo_rb.state_dict()
                sd["rng_state"] = tree["demo_rb_rng"]
                self.demo_rb.load_state_dict(sd)
                torch.set_rng_state(tree["torch_rng"])
                np.random.set_state(tree["numpy_rng"])
                self.c.update(offline_done=tree["offline_done"], grad_steps=tree["grad_steps"],
                              stage="evaluate0")
                wall = meta["stage1_wall_clock_s"]
                self._checkpoint_state()
        self.c["stage1"] = {"key": key, "cache_hit": entry is not None,
                            "stage1_wall_clock_s": round(wall, 2),
                            "lock_wait_s": round(waited, 2),
                            "load_s": round(time.perf_counter() - t0 - waited, 2)
                            if entry is not None else None}

    def _stage1_evaluator(self, evaluator):
        """Checkpoint 0 evaluates the Stage I result alone: with the cache, its rows are kept
        in the cache entry and reused by the runs that share it."""
        info = self.c.get("stage1")
        if info is None:
            return evaluator
        from window_bench.harness.stage1 import Stage1Cache

        cache = Stage1Cache(self.stage1_cache)
        entry = cache.load(info["key"])
        if entry is None:
            return evaluator
        tree, meta = entry
        what = {"env_id": self.env_id, "seeds": evaluator.seeds, "max_steps": evaluator.max_steps}
        if tree.get("eval0", {}).get("what") == what:
            info["eval0_cache_hit"] = True
            return lambda agent_cls, state: tree["eval0"]["rows"]

        def evaluate_and_keep(agent_cls, state):
            rows = evaluator(agent_cls, state)
            cache.store(info["key"], {**tree, "eval0": {"what": what, "rows": rows}}, None,
                        meta["stage1_wall_clock_s"])
            return rows
        info["eval0_cache_hit"] = False
        return evaluate_and_keep

    def _first_checkpoint(self) -> None:
        """The pretrained (or initial) policy's checkpoint at 0 environment steps."""
        m = self.method
        evaluator = self._evaluator
        self._evaluator = self._stage1_evaluator(evaluator)
        try:
            self._evaluate()
        finally:
            self._evaluator = evaluator
        if self.c.get("stage1"):   # bench sweep starts the runs that share it on this file
            atomic_write_text(self.out / "stage1.json", json.dumps(self.c["stage1"], indent=1))
        self.c["next_checkpoint"] = self.profile.checkpoint_every
        self.c["stage"] = "warm" if m.warm_start else "online"
        if not m.warm_start and not m.online_updates:
            self.c["stage"] = "done"
        self._checkpoint_state()

    def _stages_ii_iii_interaction(self) -> None:
        """The warm start (no updates, no takeovers), then online fine-tuning: UTD learner
        calls per environment step on 1:1 batches, takeovers when the method has them, a
        checkpoint every ``checkpoint_every`` steps, until the budget is spent."""
        from tqdm import tqdm

        from window_bench.envs.wrappers import make_training_env
        from window_bench.installer.supervisor import InstallerSupervisor

        m, p = self.method, self.profile
        # Training may see a noisy acceptance sensor; evaluation always uses true acceptance.
        env = make_training_env(self.env_id, self.acceptance_noise,
                                obs_mode="flat" if self.track == "state" else "pixels",
                                max_episode_steps=p.max_episode_steps)
        if self.track == "pixels":
            from window_bench.pixels.features import PixelFeatures

            # Rendered and encoded only on the chunk grid: the replay's chunked transitions
            # and the policy read nothing else (h = 1 learners: every step).
            env = PixelFeatures(env, self.backbone, observe_every=int(self.agent.h))
        policy = AgentPolicy(self.agent, deterministic=False)
        budget = p.warm_steps if not m.online_updates else p.budget_steps
        sup = InstallerSupervisor(self.operator) if m.interventions else None
        if sup is not None and self.track == "pixels":   # the installer sees the scene
            from window_bench.pixels.track import StateSupervisor

            sup = StateSupervisor(sup)
        with tqdm(total=budget, initial=self.c["env_steps"], desc="Stage II/III env", unit="step",
                  disable=not self.progress) as bar:
            while self.c["env_steps"] < budget:
                warm = m.warm_start and self.c["env_steps"] < p.warm_steps
                self.c["stage"] = "warm" if warm else "online"
                rollout = Rollout(env, policy, supervisor=None if warm else sup,
                                  env_id=self.env_id, operator=self.operator if sup else "")
                ep_id = len(self.c["episodes"])
                rollout.reset(seed=self.seed * 1_000_003 + ep_id, episode_id=ep_id)
                while not rollout.done:
                    rollout.step()
                    self.c["env_steps"] += 1
                    bar.update(1)
                    if (self._stop_after_env_steps is not None
                            and self.c["env_steps"] >= self._stop_after_env_steps):
                        raise KeyboardInterrupt("simulated kill")
                    if not warm and m.online_updates:
                        self.c["update_credit"] += p.utd
                        while self.c["update_credit"] >= 1.0:
                            n = self._learn(self._batch)
                            self.c["update_credit"] -= n
                            self.c["grad_steps"] += n
                    if self.c["env_steps"] >= self.c["next_checkpoint"]:
                        self._evaluate()
                        self.c["next_checkpoint"] += p.checkpoint_every
                        last = self.c["checkpoints"][-1]
                        bar.set_postfix(success=f"{100 * last['success_rate']:.0f}%",
                                        takeover_min=f"{last['takeover_minutes']:.1f}")
                    if self.c["env_steps"] >= budget:
                        break
                if rollout.done:
                    self._store_episode(rollout)
                if time.perf_counter() - self._last_save > self.save_every_s or not rollout.done:
                    self._checkpoint_state()
        env.close()
        if self.c["checkpoints"][-1]["env_steps"] != self.c["env_steps"]:
            self._evaluate()
        self.c["stage"] = "done"
        self._checkpoint_state()

    # ------------------------------------------------------------------ the steps of a stage
    def _elapsed(self) -> float:
        return self.c["wall_clock_s"] + (time.perf_counter() - self._t0)

    def _offline_steps(self) -> int:
        own = self.agent.offline_steps   # e.g. ACT's own count (batch 8; docs/act.md)
        return self.profile.offline_steps if own is None else own

    def _batch(self):
        from window_bench.data.replay import mixed_batch

        return mixed_batch(self.demo_rb, self.online_rb, self.profile.batch_size, 0.5)

    def _learn(self, sample) -> int:
        """One learner call on batches from ``sample()``; returns its gradient steps."""
        metrics, n = self.agent.learn(sample)
        self._log_losses(metrics, n)
        return n

    def _log_losses(self, metrics: dict, n: int) -> None:
        """Average the learner's metrics over ``loss_log_every`` calls into TensorBoard
        (``loss/<name>`` against gradient steps); nothing is kept in the resume state."""
        self._loss_acc.append(metrics)
        if len(self._loss_acc) < self.loss_log_every:
            return
        if self._tb is not None:
            step = self.c["grad_steps"] + n
            for key in self._loss_acc[0]:
                vals = [m[key] for m in self._loss_acc if isinstance(m.get(key), (int, float))]
                if vals:
                    self._tb.add_scalar(f"loss/{key}", float(np.mean(vals)), step)
        self._loss_acc = []

    def _store_episode(self, rollout) -> None:
        """A finished training episode: into the agent's own replay or D_online (and its
        takeover segments into D_demo for agents that learn from them as demonstrations),
        and into the training-episode rows."""
        from window_bench.data.effort import takeover_count

        log = rollout.episode_log()
        if self.agent.own_replay:
            self.agent.add_episode(log)
        else:
            self.online_rb.add_episode(log)
        if self.agent.takeovers_to_demo:
            from baselines.hilserl import takeover_segments

            for seg in takeover_segments(log):
                self.demo_rb.add_episode(seg)
        self.c["episodes"].append({
            "steps": log.T, "success": bool(rollout.info.get("is_success", log.terminated[-1])),
            "takeover_steps": int((log.provenance == "takeover").sum()),
            "takeovers": takeover_count(log),
            # what triggered each takeover (supervisor cue: suction_lost, wedging, stall,
            # reinsertion, no_progress, coverage), for the intervention-rate anatomy
            "takeover_cues": [cue for _, cue, _ in getattr(rollout.supervisor, "events", ())]})

    def _checkpoint_state(self) -> None:
        self.c["wall_clock_s"] = self._elapsed()
        self._t0 = time.perf_counter()
        self._save()

    def _evaluate(self) -> None:
        """Evaluate the frozen acting policy (M rollouts, interventions off), record the
        checkpoint row and write the policy file."""
        step, tb = self.c["env_steps"], self._tb
        state = self.agent.policy_state_dict()
        s = summarize_eval(self._evaluator(self.agent_cls, state))
        eps = self.c["episodes"]
        recent = eps[-RATE_WINDOW:]
        take_steps = sum(e["takeover_steps"] for e in recent)
        cp = {"env_steps": step, "sim_hours": step / STEPS_PER_HOUR,
              "wall_clock_s": round(self._elapsed(), 1), **s,
              "takeover_minutes": sum(e["takeover_steps"] for e in eps) * STEP_DT / 60,
              "train_episodes": len(eps),
              "train_success_rate": (np.mean([e["success"] for e in recent]) if recent else None),
              "train_intervention_rate": (take_steps / sum(e["steps"] for e in recent)
                                          if recent else None),
              "grad_steps": self.c["grad_steps"]}
        cp = {k: (float(v) if isinstance(v, np.floating) else v) for k, v in cp.items()}
        self.c["checkpoints"].append(cp)
        self.files.write_state(f"policies/step_{step:07d}.safetensors", state, "policy", {
            "agent_kind": self.method.agent, "method": self.method.name, "env_id": self.env_id,
            "profile": self.profile.name, "seed": self.seed, "track": self.track,
            "env_steps": step})
        if tb is not None:
            for key in ("success_rate", "takeover_minutes", "train_intervention_rate",
                        "train_success_rate", "wall_clock_s"):
                if cp.get(key) is not None:
                    tb.add_scalar(f"eval/{key}" if key == "success_rate" else f"train/{key}",
                                  cp[key], step)
            tb.flush()

    def _tensorboard(self):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:   # tensorboard not installed: scalars are still in the CSV/JSON
            return None
        return SummaryWriter(str(self.out / "tb"))

    # ------------------------------------------------------------------ results
    def _final_eval(self) -> dict:
        """The final checkpoint's policy file, its sha256, and its evaluation: M =
        ``final_episodes`` fresh rollouts on ``final_seed_set`` (the test seeds for reported
        runs), or else the last checkpoint's own evaluation on the development seeds."""
        from window_bench.harness.files import sha256_file

        last = self.c["checkpoints"][-1]
        path = next((self.out / "policies").glob(f"step_{last['env_steps']:07d}.*"))
        out = {"env_steps": last["env_steps"], "policy": path.relative_to(self.out).as_posix(),
               "policy_sha256": sha256_file(path)}
        if self.final_episodes is None:
            return {"seed_set": "dev", "seeds": [DEV_SEED0, DEV_SEED0 + last["episodes"] - 1],
                    **out, **{k: last[k] for k in FINAL_EVAL_KEYS if k in last}}
        r = evaluate_policy_file(path, self.final_episodes, self.profile.eval_workers,
                                 seed_set=self.final_seed_set,
                                 max_steps=self.profile.max_episode_steps,
                                 progress=self.progress)
        return {"seeds": r["eval_seeds"], **out,
                **{k: r[k] for k in (*FINAL_EVAL_KEYS, "seed_set")}}

    def _finish(self) -> dict:
        cps = self.c["checkpoints"]
        rates = [c["success_rate"] for c in cps]
        steps = [c["env_steps"] for c in cps]
        t95 = time_to_threshold(rates, steps) if self.method.online_updates else None
        final = cps[-1]
        final_eval = self._final_eval()
        results = {
            "schema_version": RESULTS_SCHEMA, "method": self.method.as_dict(),
            "env_id": self.env_id, "profile": self.profile.as_dict(), "seed": self.seed,
            "track": self.track, "encoder": self.encoder,
            "operator": self.operator, "acceptance_noise": self.acceptance_noise,
            "agent_config_overrides": self.agent_config,
            "hyperparameters": self.agent.hyperparameters(),
            "final": {"success_rate": final["success_rate"], "wilson95": final["wilson95"],
                      "episodes": final["episodes"], "cycle_time_s": final["cycle_time_s"],
                      "time_to_95_env_steps": t95,
                      "time_to_95_sim_hours": None if t95 is None else t95 / STEPS_PER_HOUR,
                      "takeover_minutes": final["takeover_minutes"],
                      "env_steps": self.c["env_steps"],
                      "sim_hours": self.c["env_steps"] / STEPS_PER_HOUR,
                      "grad_steps": self.c["grad_steps"],
                      "wall_clock_s": round(self.c["wall_clock_s"], 1)},
            "checkpoints": cps,
            "train_episodes": self.c["episodes"],
            "eval_seed_set": "dev",                             # the checkpoints' seeds
            "eval_seeds": [EVAL_SEED0, EVAL_SEED0 + self.profile.eval_episodes - 1],
            "final_eval": final_eval,
            "stage1": self.c.get("stage1"),
            "pixel_demos": self.c.get("pixel_demos"),            # pixel track: demo cache
            "provenance": provenance(),                          # when the results were written
            "provenance_start": self.c.get("provenance_start"),  # the code the run started on
        }
        self.files.write("results.json", json.dumps(results, indent=1).encode())
        self.files.write("checkpoints.csv", _checkpoints_csv(cps).encode())
        self.files.write("learning_curve.png", plot_learning_curve(results))
        return results


def load_policy_file(path: str | os.PathLike) -> tuple[type, dict, dict]:
    """``(agent class, policy state, metadata)`` of a frozen policy file, checked before
    anything runs: against its run's ``manifest.json`` when it lies in a run directory,
    against its own sha256 always, and rebuilt once; :class:`RunFileError` otherwise."""
    import window_bench

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
