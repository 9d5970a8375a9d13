"""The matched-budget harness: ``bench run --method NAME`` (paper Sections 3.4-3.6, 4.2).

One run = one method on one env with one seed and one profile (:mod:`window_bench.harness.methods`):

* **Stage I - offline pretraining** on D_demo (``profile.offline_steps`` gradient steps);
* **Stage II - warm start**: the pretrained policy collects ``profile.warm_steps``
  transitions with no updates (and no takeovers);
* **Stage III - online fine-tuning**: ``profile.utd`` gradient steps per environment step on
  batches drawn 1:1 from D_demo and D_online, takeovers by the installer supervisor when the
  method has interventions, until ``profile.budget_steps`` environment steps (warm start
  included) have been used.

Every ``profile.checkpoint_every`` environment steps (and after Stage I) the frozen policy is
evaluated without interventions on M seeded rollouts (the same seeds at every checkpoint, for
every method), in worker processes: success (95 % Wilson interval), cycle time, Pr(S),
Pr(I|S), Pr(T|I), failure modes; training success and intervention rate over the last 20
episodes, takeover minutes, time-to-95 (raw success >= 95 % at J = 3 checkpoints in a row).
Progress is reported in simulated hours (environment steps / 36,000).

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
(its replay, where takeover steps go, its normaliser, its offline step count), never its kind;
what the observation track changes (the demonstrations, the training env, the supervisor) it
asks the track (:mod:`window_bench.harness.tracks`), never which track it is. Evaluation is
:mod:`window_bench.harness.evaluation`; the Stage I cache :mod:`window_bench.harness.stage1`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

import window_bench
from window_bench.data.steplog import (DEFAULT_DEMO_ACTIONS, STEP_DT, check_demo_actions,
                                       demo_actions as labelled)
from window_bench.harness.agent import check_agent_config, make_agent, takeover_segments
from window_bench.harness.evaluation import (FINAL_EVAL_KEYS, AgentPolicy, Evaluator,
                                             atomic_write_text, evaluate_policy_file, provenance,
                                             summarize_eval, time_to_threshold)
from window_bench.harness.files import STATE, RunDir, RunFileError
from window_bench.harness.methods import agent_class, get_method, get_profile
from window_bench.harness.results import (DEFAULTS_REVISION, LOSS_LOG_EVERY, RESULTS_SCHEMA,
                                          STEPS_PER_HOUR, Scalars, check_final_checkpoint,
                                          checkpoints_csv, chosen_checkpoint, plot_learning_curve)
from window_bench.harness.seeds import DEV_SEED0, MAX_SEED, eval_seeds
from window_bench.harness.stage1 import demos_sha256
from window_bench.harness.tracks import DEFAULT_TRACK, get_track
from window_bench.installer.rollout import Rollout
from window_bench.installer.operators import DEFAULT_OPERATOR, get_operator
# Where scripts have imported them from; they live in agent.py and evaluation.py.
from window_bench.harness.agent import obs_normalizer, parse_overrides  # noqa: F401
from window_bench.harness.evaluation import load_policy_file  # noqa: F401

EVAL_SEED0 = DEV_SEED0   # checkpoint evaluations use the development seeds (harness/seeds.py)
RATE_WINDOW = 20
DEMOS = "demos"         # where a run without --demos collects its own, inside --out


def _replay_from_state(sd: dict):
    from window_bench.data.replay import ChunkReplay

    rb = ChunkReplay(sd["capacity"], sd["h"], sd["gamma"], seed=sd["seed"],
                     half_obs=sd.get("half_obs", 0), stride=sd.get("stride"))
    rb.load_state_dict(sd)
    return rb


# ---------------------------------------------------------------------------- the run
class Run:
    """One training run; :meth:`train` executes (or resumes) it to the end."""

    def __init__(self, method: str, env_id: str, profile: str, seed: int, out: str | os.PathLike,
                 *, resume: bool = False, operator: str = DEFAULT_OPERATOR,
                 track: str = DEFAULT_TRACK, encoder_weights: str | os.PathLike | None = None,
                 demos: str | os.PathLike | None = None, progress: bool = True,
                 save_every_s: float = 60.0, acceptance_noise: dict | None = None,
                 agent_config: dict | None = None, h: int | None = None,
                 final_episodes: int | None = None, final_seed_set: str = "dev",
                 final_checkpoint: str = "last", stage1_cache: str | os.PathLike | None = None,
                 eval_workers: int | None = None, demo_actions: str = DEFAULT_DEMO_ACTIONS,
                 pixel_demos_cache: str | os.PathLike | None = None):
        self.method = get_method(method)
        if h is not None:    # Tables 5/6: replay, agent and chunking all follow method.h
            if not agent_class(self.method.agent).follows_method_h:
                raise ValueError(f"--h {h}: h is a run parameter of the QC-FQL methods, not of "
                                 f"{method!r} (agent {self.method.agent!r})")
            if isinstance(h, bool) or not isinstance(h, int) or not 1 <= h <= 100:
                raise ValueError(f"--h {h!r}; allowed: an integer in 1..100")
            self.method = dataclasses.replace(self.method, h=h)
        if final_episodes is not None:
            eval_seeds(final_seed_set, final_episodes)      # checks both before any work
        self.final_episodes, self.final_seed_set = final_episodes, final_seed_set
        self.final_checkpoint = check_final_checkpoint(final_checkpoint)
        self.stage1_cache, self.profile = stage1_cache, get_profile(profile)
        if eval_workers is not None:    # evaluation processes; results do not depend on it
            if isinstance(eval_workers, bool) or not isinstance(eval_workers, int) \
                    or not 1 <= eval_workers <= 64:
                raise ValueError(f"--eval-workers {eval_workers!r}; allowed: an integer in 1..64")
            self.profile = dataclasses.replace(self.profile, eval_workers=eval_workers)
        # The observation track runs its own agent for the method, and makes the run's
        # observation now: a wrong encoder weights file fails before any work.
        observed_on = get_track(track)
        self.track = observed_on.name
        self.method = dataclasses.replace(self.method,
                                          agent=observed_on.agent_kind(self.method.agent))
        self.agent_cls = agent_class(self.method.agent)
        self.observation = observed_on.for_run(encoder_weights)
        self.encoder = self.observation.record
        self._observed_demos = self._observed_demos_record = None
        if env_id not in window_bench.ENV_IDS:
            raise ValueError(f"unknown env {env_id!r}; registered: {', '.join(window_bench.ENV_IDS)}")
        get_operator(operator)
        self.demo_actions = check_demo_actions(demo_actions)
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
        # Where a track re-observes the demos (the pixel track); None: its place beside them.
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
        labelled(self._raw_demos or [], self.demo_actions)   # they record what is asked
        self.files = RunDir(self.out, {     # a run resumes only under the same defaults
            "method": self.method.name, "env_id": self.env_id, "profile": self.profile.name,
            "seed": self.seed, "operator": self.operator, "track": self.track, "h": self.method.h,
            "acceptance_noise": self.acceptance_noise, "agent_config": self.agent_config,
            **({"demo_actions": demo_actions} if demo_actions != "executed" else {}),
            "defaults": DEFAULTS_REVISION}, resume)
        if self._own_demos:
            from window_bench.installer.demos import demo_dataset_path

            try:
                self.files.check_listed(demo_dataset_path(DEMOS, self.env_id, self.operator))
                self._raw_demos = self._raw_demo_episodes(collect=False)
            except BaseException:
                self.files.close()
                raise
        self._stop_after_env_steps = None   # tests: simulate a kill (no state written)
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
        if self._observed_demos is None:   # once per Run: a track may render and encode
            self._observed_demos = labelled(self._observe_demos(eps), self.demo_actions)
        return self._observed_demos

    def _observe_demos(self, eps: list) -> list:
        """D_demo as the track observes it; a demo cache inside the run is listed, checked."""
        cache = self.observation.demos_cache(self.pixel_demos_cache, self.demos_root)
        inside = None
        if cache is not None and cache.resolve().is_relative_to(self.out.resolve()):
            inside = cache.resolve().relative_to(self.out.resolve()).as_posix()
            self.files.check_listed(inside)
        eps, self._observed_demos_record = self.observation.observe_demos(
            eps, self.env_id, cache, self.progress)
        if inside is not None:
            self.files.record(inside)
        return eps

    def _fresh(self) -> dict:
        torch.manual_seed(self.seed)
        demos = self._demos()
        self.agent = make_agent(self.method, self.profile, demos, self.seed, self.agent_config,
                                self.observation.front_end)
        self.observation.configure(self.agent)
        self.agent.attach_demos(demos)
        self._make_replays(demos)
        observed = self._observed_demos_record   # how the track re-observed them, if it did
        return {"stage": "offline", "offline_done": 0, "env_steps": 0, "episodes": [],
                "checkpoints": [], "grad_steps": 0, "update_credit": 0.0, "wall_clock_s": 0.0,
                "next_checkpoint": 0, "obs_dim": int(demos[0].observations.shape[1]),
                "h": self.method.h, "demos_sha256": demos_sha256(self._raw_demos),
                "pixel_demos": None if observed is None else [observed],
                "provenance_start": provenance()}

    def _make_replays(self, demos) -> None:
        """D_demo (with room for the takeover segments of agents that add them; windows every
        ``agent.demo_chunk_stride`` steps if set) and D_online, chunk replays on the grid."""
        from window_bench.data.replay import ChunkReplay

        h, p, gamma = self.method.h, self.profile, self.agent.gamma
        stride = self.agent.demo_chunk_stride or h    # D_demo's windows: the grid or denser
        demo_chunks = sum(-(-ep.T // stride) for ep in demos)
        if self.agent.takeovers_to_demo:
            demo_chunks += p.budget_steps
        half = self.observation.replay_half_obs   # e.g. feature maps stored as float16
        self.demo_rb = ChunkReplay(demo_chunks, h, gamma, self.seed, half, stride)
        for ep in demos:
            self.demo_rb.add_episode(ep)
        self.online_rb = ChunkReplay(p.budget_steps // h + 2 * p.max_episode_steps, h, gamma,
                                     seed=self.seed + 1, half_obs=half)

    def _save(self) -> None:
        self.files.write_run_state(STATE, {
            "counters": self.c, "agent": self.agent.state_dict(),
            "demo_rb": self.demo_rb.state_dict(), "online_rb": self.online_rb.state_dict(),
            "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(legacy=False)},
            "state")
        self._last_save = time.perf_counter()

    def _load(self) -> None:
        st = self.files.read_run_state(STATE, "state")
        self.c = st["counters"]
        if self.c.setdefault("h", self.method.h) != self.method.h:
            raise RunFileError(f"--resume: the saved run has h = {self.c['h']}, this command "
                               f"asks for h = {self.method.h}")
        demos = self._demos()   # a resume must read the demos the run began on
        digest = demos_sha256(self._raw_demos)
        if self.c.setdefault("demos_sha256", digest) != digest:
            raise RunFileError(f"--resume: the run in {self.out} began on other demonstrations "
                               f"than those in {self.demos_root} (sha256 "
                               f"{self.c['demos_sha256'][:12]}, not {digest[:12]}); pass the "
                               f"--demos it began with")
        self.agent = self.agent_cls.from_state_dict(st["agent"])
        self.agent.attach_demos(demos)
        if self._observed_demos_record is not None:   # one per start: cache key, hit, seconds
            self.c.setdefault("pixel_demos", []).append(self._observed_demos_record)
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
        self._tb = Scalars(self.out, self.loss_log_every)
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
        """Stage I, or the cached one of a run with the same agent, config, h, demos, seed."""
        if self.stage1_cache is None or not self.method.offline_pretrain:
            return self._stage_i_offline_pretraining()
        from window_bench.harness.stage1 import Stage1Cache, demos_sha256, key_material

        material = key_material(self.method.agent, self.track, self.agent.stage1_hyperparameters(),
                                self._offline_steps(), self.profile.batch_size,
                                demos_sha256(self._demos()), self.seed)
        self.c["stage1"] = Stage1Cache(self.stage1_cache).compute_or_load(
            material, self._stage_i_entry, self._restore_stage_i)

    def _stage_i_entry(self) -> dict:
        """Stage I computed here, as the cache keeps it."""
        self._stage_i_offline_pretraining()
        return {"agent": self.agent.state_dict(),
                "demo_rb_rng": self.demo_rb.state_dict()["rng_state"],
                "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(legacy=False),
                "offline_done": self.c["offline_done"], "grad_steps": self.c["grad_steps"]}

    def _restore_stage_i(self, tree: dict) -> None:
        """Stage I from a cache entry another run computed (this run's online settings)."""
        own, self.agent = self.agent, self.agent_cls.from_state_dict(tree["agent"])
        self.agent.take_online_settings(own)
        self.agent.attach_demos(self._demos())
        sd = self.demo_rb.state_dict()
        sd["rng_state"] = tree["demo_rb_rng"]
        self.demo_rb.load_state_dict(sd)
        torch.set_rng_state(tree["torch_rng"])
        np.random.set_state(tree["numpy_rng"])
        self.c.update(offline_done=tree["offline_done"], grad_steps=tree["grad_steps"],
                      stage="evaluate0")
        self._checkpoint_state()

    def _stage1_evaluator(self, evaluator):
        """Checkpoint 0 evaluates the Stage I result alone: with the cache, its rows are kept
        in the cache entry and reused by the runs that share it."""
        info = self.c.get("stage1")
        if info is None:
            return evaluator
        from window_bench.harness.stage1 import Stage1Cache

        what = {"env_id": self.env_id, "seeds": evaluator.seeds, "max_steps": evaluator.max_steps}
        evaluator, hit = Stage1Cache(self.stage1_cache).checkpoint0_evaluator(
            info["key"], evaluator, what)
        if hit is not None:
            info["eval0_cache_hit"] = hit
        return evaluator

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

        from window_bench.installer.supervisor import InstallerSupervisor

        m, p = self.method, self.profile
        # Training may see a noisy acceptance sensor; evaluation always uses true acceptance.
        env = self.observation.training_env(self.env_id, self.acceptance_noise,
                                            p.max_episode_steps, observe_every=int(self.agent.h))
        self.agent.begin_online()
        policy = AgentPolicy(self.agent, deterministic=False)
        budget = p.warm_steps if not m.online_updates else p.budget_steps
        sup = (self.observation.supervisor(InstallerSupervisor(self.operator))
               if m.interventions else None)
        if sup is not None and "supervisor" in self.c:   # what it carries between episodes
            sup.load_state_dict(self.c["supervisor"])
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
                    if rollout.supervisor is not None:
                        self.c["supervisor"] = rollout.supervisor.state_dict()
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
        self._tb.losses(metrics, self.c["grad_steps"] + n)
        return n

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
            for seg in takeover_segments(log):
                self.demo_rb.add_episode(seg)
        self.c["episodes"].append({
            "steps": log.T, "success": bool(rollout.info.get("is_success", log.terminated[-1])),
            "takeover_steps": int((log.provenance == "takeover").sum()),
            "takeovers": takeover_count(log),
            # the supervisor cue of each takeover, for the intervention-rate anatomy
            "takeover_cues": [cue for _, cue, _ in getattr(rollout.supervisor, "events", ())]})

    def _checkpoint_state(self) -> None:
        self.c["wall_clock_s"] = self._elapsed()
        self._t0 = time.perf_counter()
        self._save()

    def _evaluate(self) -> None:
        """Evaluate the frozen acting policy (M rollouts, interventions off), record the
        checkpoint row and write the policy file."""
        step = self.c["env_steps"]
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
        self._tb.checkpoint(cp)

    # ------------------------------------------------------------------ results
    def _final_eval(self) -> dict:
        """The final policy (the last checkpoint's, or the ``final_checkpoint`` choice's), its
        sha256, and its evaluation: M = ``final_episodes`` fresh rollouts on
        ``final_seed_set`` (test seeds for reported runs), or else its own dev evaluation."""
        from window_bench.harness.files import sha256_file
        cp = chosen_checkpoint(self.c["checkpoints"], self.final_checkpoint)
        path = next((self.out / "policies").glob(f"step_{cp['env_steps']:07d}.*"))
        out = {"env_steps": cp["env_steps"], "policy": path.relative_to(self.out).as_posix(),
               "policy_sha256": sha256_file(path), "checkpoint": self.final_checkpoint}
        if self.final_episodes is None:
            return {"seed_set": "dev", "seeds": [DEV_SEED0, DEV_SEED0 + cp["episodes"] - 1],
                    **out, **{k: cp[k] for k in FINAL_EVAL_KEYS if k in cp}}
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
            "schema_version": RESULTS_SCHEMA, "defaults": DEFAULTS_REVISION,
            "method": self.method.as_dict(),
            "env_id": self.env_id, "profile": self.profile.as_dict(), "seed": self.seed,
            "track": self.track, "encoder": self.encoder, "operator": self.operator,
            "operator_profile": get_operator(self.operator).as_dict(),   # its cues, as run
            "acceptance_noise": self.acceptance_noise, "demo_actions": self.demo_actions,
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
            "final_eval": final_eval, "stage1": self.c.get("stage1"),
            "pixel_demos": self.c.get("pixel_demos"),     # a track's re-observed demos
            "provenance": provenance(),                          # when the results were written
            "provenance_start": self.c.get("provenance_start"),  # the code the run started on
        }
        self.files.write("results.json", json.dumps(results, indent=1).encode())
        self.files.write("checkpoints.csv", checkpoints_csv(cps).encode())
        self.files.write("learning_curve.png", plot_learning_curve(results))
        return results
