"""The matched-budget harness: metrics on hand-checkable cases, the methods registry, a smoke
run through ``bench run`` and an exact resume after a simulated kill."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from window_bench.cli import main
from window_bench.data.dataset import load_episodes
from window_bench.harness.evaluation import wilson_interval
from window_bench.harness.run import Run, summarize_eval, time_to_threshold
from window_bench.harness.methods import METHODS, PROFILES, get_method, get_profile, methods_table
from window_bench.installer.operators import DEFAULT_OPERATOR
from window_bench.harness.results import DEFAULTS_REVISION


# ---------------------------------------------------------------- metrics
def _wilson_by_inversion(k, n, z=1.96):
    """Independent: the Wilson interval is {p : |k/n - p| <= z sqrt(p(1-p)/n)}; find its
    ends by bisection on the score statistic."""
    phat = k / n

    def inside(p):
        return abs(phat - p) <= z * math.sqrt(p * (1 - p) / n) + 1e-15

    def edge(lo, hi):   # lo inside, hi outside (or vice versa); bisect the boundary
        for _ in range(200):
            mid = (lo + hi) / 2
            if inside(mid) == inside(lo):
                lo = mid
            else:
                hi = mid
        return (lo + hi) / 2

    lower = 0.0 if inside(0.0) else edge(phat, 0.0)
    upper = 1.0 if inside(1.0) else edge(phat, 1.0)
    return lower, upper


@pytest.mark.parametrize("k,n", [(0, 10), (1, 10), (5, 10), (9, 10), (10, 10), (95, 100),
                                 (62, 100), (0, 1), (3, 7)])
def test_wilson_matches_an_independent_inversion(k, n):
    lo, hi = wilson_interval(k, n)
    ref = _wilson_by_inversion(k, n)
    assert lo == pytest.approx(ref[0], abs=1e-9) and hi == pytest.approx(ref[1], abs=1e-9)


@pytest.mark.parametrize("n", [20, 100, 7])
def test_wilson_holds_the_rate_at_the_ends_exactly(n):
    """100 / 100 once gave an upper bound of 1 - 1e-16, which the results check refused."""
    assert wilson_interval(n, n)[1] == 1.0 and wilson_interval(0, n)[0] == 0.0
    for k in range(n + 1):
        lo, hi = wilson_interval(k, n)
        assert lo <= k / n <= hi


def test_time_to_95_needs_three_consecutive_checkpoints():
    steps = [0, 3000, 6000, 9000, 12000, 15000, 18000]
    assert time_to_threshold([0.5, 0.96, 0.97, 0.90, 0.95, 0.99, 1.0], steps) == 12000
    assert time_to_threshold([0.96, 0.97, 0.95, 0.2, 0.2, 0.2, 0.2], steps) == 0
    assert time_to_threshold([0.96, 0.97, 0.2, 0.96, 0.97, 0.2, 0.99], steps) is None
    assert time_to_threshold([0.949] * 7, steps) is None
    assert time_to_threshold([0.2, 0.96], steps[:2], J=1) == 3000
    with pytest.raises(ValueError, match="J = 0"):
        time_to_threshold([1.0], [0], J=0)


def test_stagewise_rates():
    row = lambda s, i, ok, fm="": {"seed": 0, "success": ok, "cycle_time_s": 20.0,  # noqa: E731
                                   "suction_acquired": s, "insertion_entered": i,
                                   "failure_mode": fm}
    rows = ([row(True, True, True)] * 6 + [row(True, True, False, "mid_depth_jamming")] * 2
            + [row(True, False, False, "approach_failed")] + [row(False, False, False, "never_acquired")])
    s = summarize_eval(rows)
    assert s["success_rate"] == 0.6 and s["pr_S"] == 0.9
    assert s["pr_I_given_S"] == pytest.approx(8 / 9) and s["pr_T_given_I"] == 0.75
    assert s["failure_modes"] == {"never_acquired": 1, "approach_failed": 1, "mid_depth_jamming": 2}
    assert s["cycle_time_s"] == 20.0


# ---------------------------------------------------------------- registry
def test_registry_has_the_table_1_rows():
    assert set(METHODS) >= {"qcfql", "qcfql-no-intervention", "qcfql-no-warmstart",
                            "qcfql-offline", "qcfql-offline-warmstart", "qcfql-stepwise",
                            "qcfql-stepwise-intervention"}
    m = METHODS
    assert m["qcfql"].interventions and m["qcfql"].warm_start and m["qcfql"].h == 10
    assert not m["qcfql-no-intervention"].interventions
    assert not m["qcfql-no-warmstart"].warm_start and m["qcfql-no-warmstart"].interventions
    assert not m["qcfql-offline"].online_updates and not m["qcfql-offline"].warm_start
    assert m["qcfql-offline-warmstart"].warm_start and not m["qcfql-offline-warmstart"].online_updates
    assert m["qcfql-stepwise"].h == 1 and not m["qcfql-stepwise"].interventions
    assert m["qcfql-stepwise-intervention"].h == 1 and m["qcfql-stepwise-intervention"].interventions
    # The external baselines' rows of Table 1.
    assert len(METHODS) == 10
    act, sac, hil = m["act"], m["sac"], m["hil-serl"]
    assert act.chunking and not (act.online_updates or act.interventions or act.warm_start)
    assert sac.online_updates and not (sac.interventions or sac.warm_start or sac.chunking)
    assert not sac.offline_pretrain
    assert hil.online_updates and hil.interventions and hil.warm_start and not hil.chunking
    table = methods_table()
    assert "| Ours (complete pipeline) | `qcfql` | ✓ | ✓ | ✓ | ✓ | ✓ (10) |" in table
    assert "| ACT (offline IL) | `act` | ✓ | × | × | × | ✓ (10) |" in table
    with pytest.raises(ValueError, match="unknown method 'qcfq'; choose from act, sac, hil-serl, .*, qcfql$"):
        get_method("qcfq")
    assert PROFILES["paper"].budget_steps == 108_000 and PROFILES["paper"].warm_steps == 10_000
    assert PROFILES["paper"].utd == 2 and PROFILES["paper"].checkpoint_every == 3_000


def test_the_long_profile_is_the_papers_budget_with_the_cpu_learner():
    from window_bench.harness.methods import AGENTS
    long, cpu, paper = PROFILES["long"], PROFILES["cpu"], PROFILES["paper"]
    assert (long.budget_steps, long.warm_steps) == (paper.budget_steps, paper.warm_steps)
    assert long.budget_steps / 36_000 == 3.0 and long.checkpoint_every / 36_000 == 0.1
    assert (long.hidden, long.utd, long.offline_steps, long.batch_size) == (
        cpu.hidden, cpu.utd, cpu.offline_steps, cpu.batch_size)
    assert len(long.reductions) >= 3
    # every agent kind builds its config for every profile (none is keyed to a missing name)
    for kind in AGENTS:
        cls = AGENTS.lookup(kind)
        for profile in PROFILES.values():
            cls.make_config(10, profile, {})
        assert cls.make_config(10, long, {}) == cls.make_config(10, cpu, {})


def test_cli_rejects_unknown_names(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--method", "nope", "--out", "x"])
    assert "unknown method 'nope'; choose from act, sac, hil-serl, qcfql-stepwise" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["run", "--method", "qcfql", "--profile", "huge", "--out", "x"])
    assert "unknown profile 'huge'" in capsys.readouterr().err


# ---------------------------------------------------------------- runs
def test_smoke_run_through_the_cli_and_eval(tmp_path, demos_root, capsys):
    out = tmp_path / "run"
    assert main(["run", "--method", "qcfql", "--profile", "smoke", "--seed", "0", "--out",
                 str(out), "--demos", str(demos_root)]) == 0
    r = json.loads((out / "results.json").read_text())
    assert r["schema_version"] == 1 and r["method"]["name"] == "qcfql" and r["seed"] == 0
    assert r["profile"]["name"] == "smoke" and r["hyperparameters"]["h"] == 10
    assert r["operator"] == DEFAULT_OPERATOR and r["operator_profile"]["wedge_steps"] == 10
    assert r["defaults"] == DEFAULTS_REVISION and r["demo_actions"] == "meant"
    assert r["provenance"]["git_commit"] and "mujoco" in json.dumps(r["provenance"])
    steps = [c["env_steps"] for c in r["checkpoints"]]
    assert steps == [0, 200, 400]            # after Stage I, then every 200 steps
    for c in r["checkpoints"]:
        assert c["episodes"] == 2 and 0 <= c["wilson95"][0] <= c["success_rate"] <= c["wilson95"][1]
    assert r["final"]["env_steps"] == 400
    assert r["final"]["grad_steps"] == 20 + round(0.05 * 300)   # offline + UTD x online steps
    assert (out / "checkpoints.csv").read_text().count("\n") == 4
    assert (out / "learning_curve.png").stat().st_size > 1000
    assert list((out / "tb").iterdir())
    # Every training episode is accounted for (takeover steps only after the warm start).
    assert sum(e["steps"] for e in r["train_episodes"]) <= 400
    # Each takeover's cue is recorded, from the supervisor's vocabulary (two takeovers can
    # merge into one takeover segment across the hold-still steps to a chunk boundary).
    from window_bench.installer.supervisor import CUES

    for e in r["train_episodes"]:
        assert len(e["takeover_cues"]) >= e["takeovers"] and bool(e["takeover_cues"]) == bool(e["takeovers"])
        assert set(e["takeover_cues"]) <= set(CUES) | {"coverage"}
    capsys.readouterr()
    assert main(["eval", str(out / "policies" / "step_0000400.safetensors"), "--episodes", "2"]) == 0
    assert "qcfql (400 env steps) on WindowInstall-A-v0: " in capsys.readouterr().out
    # ... and at another clearance: the opening is rebuilt, the summary says so.
    assert main(["eval", str(out / "policies" / "step_0000400.safetensors"), "--episodes", "1",
                 "--eval-workers", "1", "--clearance", "8", "--out", str(tmp_path / "c.json")]) == 0
    assert "on WindowInstall-A-v0 at 8 mm clearance: " in capsys.readouterr().out
    assert json.loads((tmp_path / "c.json").read_text())["env_kwargs"] == {"clearance": 0.008}
    # The leaderboard is regenerated from the raw run files.
    from window_bench.harness.leaderboard import add_run, build

    dest = add_run(out, tmp_path / "lb")
    assert sorted(p.name for p in dest.iterdir()) == ["checkpoints.csv", "learning_curve.png",
                                                       "manifest.json", "policies", "results.json"]
    # the final policy comes along, listed in the copy's manifest, so tools verify it there
    final = json.loads((dest / "results.json").read_text())["final_eval"]["policy"]
    assert [p.name for p in (dest / "policies").iterdir()] == [final.split("/")[1]]
    from window_bench.harness.files import verify_files

    verify_files(dest, [final])
    # a policy changed after the run wrote it is refused, and nothing is copied
    import shutil as _sh

    bad = tmp_path / "tampered"
    _sh.copytree(out, bad)
    (bad / final).write_bytes(b"not the run's policy")
    with pytest.raises(Exception, match="sha256 does not match"):
        add_run(bad, tmp_path / "lb2")
    assert not (tmp_path / "lb2").exists()
    body = build(tmp_path / "lb", readme=tmp_path / "LB.md", snippet=None)
    assert "| WindowInstall-A-v0 | Ours (complete pipeline) (`qcfql`) | smoke | 0 |" in body
    assert body in (tmp_path / "LB.md").read_text()
    # The run directory is not silently reused.
    with pytest.raises(ValueError, match="already holds a run .* pass --resume"):
        Run("qcfql", "WindowInstall-A-v0", "smoke", 0, out)


class _Still:
    """An agent that holds the arm still (zero pose command, vacuum on)."""
    h, track = 1, "state"

    @classmethod
    def from_policy_state_dict(cls, state):
        return cls()

    def reset(self):
        pass

    def act(self, obs, deterministic=True):
        return np.array([[0, 0, 0, 0, 0, 0, 1]], np.float32)


def test_eval_env_kwargs_rebuild_the_opening():
    """``Evaluator(..., env_kwargs)`` builds its env with them (the clearance check of
    ``bench eval --clearance``), and the scene's range check refuses a bad one."""
    from window_bench.harness.evaluation import Evaluator, _eval_rollout

    _, env = _eval_rollout(_Still, {}, "WindowInstall-A-v0", 5, {"clearance": 0.01})
    try:
        assert env.unwrapped.cfg.clearance == 0.01
        assert np.allclose(env.unwrapped.cfg.opening, (0.52, 0.52))
    finally:
        env.close()
    rows = Evaluator("WindowInstall-A-v0", 1, 1, 3, env_kwargs={"clearance": 0.01})(_Still, {})
    assert [r["seed"] for r in rows] == [100_000] and not rows[0]["success"]
    assert rows[0]["final_position_error_mm"] > 100.0        # the panel is still on the rack
    with pytest.raises(ValueError, match=r"clearance=0.05 is outside the supported range"):
        Evaluator("WindowInstall-A-v0", 1, 1, 3, env_kwargs={"clearance": 0.05})(_Still, {})


def _assert_same(a, b, path="state"):
    """Equal nested states: tensors and arrays bit for bit, everything else by value."""
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b), path
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=path)
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


@pytest.mark.parametrize("method", ["qcfql-no-intervention", "qcfql", "sac"])
def test_resume_after_a_kill_reproduces_the_run(tmp_path, demos_root, method):
    """Killed at 250 env steps (no state written after the last episode end) and resumed:
    the same checkpoints, training episodes and final agent state as a run never killed.
    SB3 SAC resumes from its plain state_dict (networks, optimisers, replay arrays); the
    installer supervisor from the count it carries between episodes."""
    def run(out, kill_at=None):
        r = Run(method, "WindowInstall-A-v0", "smoke", 3, out,
                demos=demos_root, progress=False, save_every_s=0.0)
        r._stop_after_env_steps = kill_at
        return r

    whole = run(tmp_path / "whole").train()
    killed = run(tmp_path / "killed", kill_at=250)
    with pytest.raises(KeyboardInterrupt):
        killed.train()
    resumed = Run(method, "WindowInstall-A-v0", "smoke", 3, tmp_path / "killed",
                  resume=True, demos=demos_root, progress=False, save_every_s=0.0).train()
    strip = lambda cps: [{k: v for k, v in c.items() if k != "wall_clock_s"} for c in cps]  # noqa: E731
    assert strip(resumed["checkpoints"]) == strip(whole["checkpoints"])
    assert resumed["train_episodes"] == whole["train_episodes"]
    from window_bench.harness.files import load_state

    a, _ = load_state(tmp_path / "whole" / "state.safetensors", "state")
    b, _ = load_state(tmp_path / "killed" / "state.safetensors", "state")
    _assert_same(a["agent"], b["agent"])
    _assert_same(a["online_rb"], b["online_rb"])
    assert a["counters"].get("supervisor") == b["counters"].get("supervisor")
    assert ("supervisor" in a["counters"]) == (method == "qcfql")
    with pytest.raises(ValueError, match="seed = 3"):
        Run(method, "WindowInstall-A-v0", "smoke", 4, tmp_path / "killed",
            resume=True, demos=demos_root).train()


def test_learner_losses_reach_tensorboard(tmp_path, demos_root):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = Run("qcfql-offline", "WindowInstall-A-v0", "smoke", 0, tmp_path / "run",
              demos=demos_root, progress=False)
    run.loss_log_every = 5
    run.train()
    ea = EventAccumulator(str(tmp_path / "run" / "tb"))
    ea.Reload()
    tags = ea.Tags()["scalars"]
    assert {"loss/critic_loss", "loss/flow_loss", "loss/distill_loss", "loss/q_loss"} <= set(tags)
    points = ea.Scalars("loss/flow_loss")
    assert [p.step for p in points] == [5, 10, 15, 20]   # 20 offline updates, 5 per point
    assert all(np.isfinite(p.value) and p.value > 0 for p in points)


def test_offline_only_method_never_touches_the_env(tmp_path, demos_root):
    r = Run("qcfql-offline", "WindowInstall-A-v0", "smoke", 0, tmp_path / "off",
            demos=demos_root, progress=False).train()
    assert [c["env_steps"] for c in r["checkpoints"]] == [0]
    assert r["final"]["env_steps"] == 0 and r["train_episodes"] == []
    assert r["final"]["time_to_95_env_steps"] is None
    assert np.isfinite(r["final"]["success_rate"])


def test_acceptance_noise_is_validated(tmp_path, capsys):
    with pytest.raises(ValueError, match="false_positive_rate"):
        Run("qcfql", "WindowInstall-A-v0", "smoke", 0, tmp_path / "n",
            acceptance_noise={"false_positive_rate": 1.5})
    assert main(["run", "--method", "qcfql", "--out", str(tmp_path / "m"),
                 "--acceptance-noise", "0.01", "x", "3"]) == 2
    assert "error:" in capsys.readouterr().err


def test_methods_snippet_in_the_docs_is_current():
    from pathlib import Path

    snippet = Path(__file__).resolve().parents[1] / "docs" / "snippets" / "methods_table.md"
    assert snippet.read_text().strip() == methods_table().strip(), (
        "regenerate it: python -c 'from window_bench.harness.methods import methods_table; "
        "print(methods_table())' > docs/snippets/methods_table.md")


def test_chosen_checkpoint_reads_dev_success_and_prefers_the_later_on_ties():
    from window_bench.harness.results import chosen_checkpoint

    cps = [{"env_steps": s, "success_rate": r} for s, r in ((0, .1), (10, .9), (20, .9), (30, .2))]
    assert chosen_checkpoint(cps, "last")["env_steps"] == 30
    assert chosen_checkpoint(cps, "best-dev")["env_steps"] == 20
    with pytest.raises(ValueError, match="--final-checkpoint 'best'; allowed: last, best-dev"):
        chosen_checkpoint(cps, "best")


def test_a_best_dev_run_evaluates_the_checkpoint_best_on_the_dev_seeds(tmp_path, demos_root,
                                                                      monkeypatch):
    """The final evaluation runs the policy file of the checkpoint with the best dev success
    (here made the middle one), records the choice, and the tables keep it apart."""
    import window_bench.harness.run as run_mod
    from window_bench.harness.evaluation import wilson_interval
    from window_bench.harness.files import sha256_file
    from window_bench.harness.schemas import check_results
    from window_bench.harness.tables import _overrides

    rates, real = iter([0.0, 1.0, 0.5]), run_mod.summarize_eval
    def summarize(rows):        # checkpoint evaluations of 2 episodes: 0, 2, 1 successes
        s, rate = real(rows), next(rates)
        k = int(rate * s["episodes"])
        return {**s, "success_rate": rate, "successes": k,
                "wilson95": list(wilson_interval(k, s["episodes"]))}

    monkeypatch.setattr(run_mod, "summarize_eval", summarize)
    with pytest.raises(ValueError, match="--final-checkpoint 'first'; allowed"):
        Run("sac", "WindowInstall-A-v0", "smoke", 0, tmp_path / "bad", demos=demos_root,
            final_checkpoint="first")
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "sac"
    r = Run("sac", "WindowInstall-A-v0", "smoke", 0, out, demos=demos_root, progress=False,
            final_episodes=2, final_checkpoint="best-dev").train()
    fe = r["final_eval"]
    assert (fe["checkpoint"], fe["env_steps"], fe["policy"]) == \
        ("best-dev", 200, "policies/step_0000200.safetensors")
    assert fe["policy_sha256"] == sha256_file(out / fe["policy"]) and fe["episodes"] == 2
    assert r["final"]["env_steps"] == 400       # trained to the end all the same
    check_results(out / "results.json")     # the schema knows the field
    assert ("final_checkpoint", '"best-dev"') in _overrides(r)


@pytest.mark.parametrize("method", ["hil-serl", "sac", "act"])
def test_baselines_run_through_the_harness(tmp_path, demos_root, method):
    """Each external baseline trains for a few steps in the smoke profile and evaluates at
    the same checkpoints as QC-FQL (ACT: offline only, one evaluation)."""
    r = Run(method, "WindowInstall-A-v0", "smoke", 0, tmp_path / method, demos=demos_root,
            progress=False).train()
    if method == "act":
        assert [c["env_steps"] for c in r["checkpoints"]] == [0]
        assert r["final"]["grad_steps"] == 100 and r["train_episodes"] == []
        assert r["hyperparameters"]["chunk"] == 10 and r["checkpoints"][0]["episodes"] == 2
        return
    assert [c["env_steps"] for c in r["checkpoints"]] == [0, 200, 400]
    assert r["final"]["env_steps"] == 400 and r["final"]["grad_steps"] > 0
    assert r["method"]["h"] == 1 and r["hyperparameters"]
    assert sum(e["steps"] for e in r["train_episodes"]) <= 400
    if method == "sac":
        demos = load_episodes(f"window-bench/demos-a-{DEFAULT_OPERATOR}-v0", data_path=demos_root)
        assert r["hyperparameters"]["demo_transitions"] == sum(ep.T for ep in demos)


def test_demo_chunk_stride_puts_a_window_at_every_demonstrated_step(tmp_path, monkeypatch,
                                                                     demos_root):
    """QC-FQL's ``demo_chunk_stride = 1`` (the reference's window sampling): D_demo holds one
    chunk window per demonstrated step instead of one per ``h``; the online replay stays on
    the grid; a resumed run rebuilds the same buffer; a stride outside 1..h stops the run in
    one line before any file is written."""
    import dataclasses

    from window_bench.harness import methods

    monkeypatch.setitem(methods.PROFILES, "smoke", dataclasses.replace(
        methods.PROFILES["smoke"], eval_episodes=1, max_episode_steps=20))
    run = Run("qcfql-offline", "WindowInstall-A-v0", "smoke", 0, tmp_path / "r",
              demos=demos_root, agent_config={"demo_chunk_stride": 1}, progress=False,
              eval_workers=1)
    run.train()
    steps = sum(ep.T for ep in run._demos())
    assert run.demo_rb.stride == 1 and len(run.demo_rb) == steps
    assert run.online_rb.stride == run.method.h == 10
    starts = run.demo_rb.sample(512)["chunk_start"]
    assert (starts % 10 != 0).any()          # windows off the grid
    again = Run("qcfql-offline", "WindowInstall-A-v0", "smoke", 0, tmp_path / "r",
                demos=demos_root, agent_config={"demo_chunk_stride": 1}, progress=False,
                resume=True)
    again._load()
    assert again.demo_rb.stride == 1 and len(again.demo_rb) == steps
    again.files.close()
    with pytest.raises(ValueError, match=r"demo_chunk_stride = 11 is not allowed: .* 1\.\.h = 10"):
        Run("qcfql", "WindowInstall-A-v0", "smoke", 0, tmp_path / "bad", demos=demos_root,
            agent_config={"demo_chunk_stride": 11})
    assert not (tmp_path / "bad").exists()


def test_qcfql_offline_steps_sets_stage_i_and_its_cache_key(tmp_path, demos_root):
    """``--agent-config offline_steps=N`` runs N Stage I updates instead of the profile's (a
    weak start), names a Stage I of its own in the cache, and is refused out of range before
    any file is written."""
    def run(out, **config):
        return Run("qcfql", "WindowInstall-A-v0", "smoke", 0, tmp_path / out, demos=demos_root,
                   progress=False, save_every_s=0.0, stage1_cache=tmp_path / "cache",
                   agent_config=config or None)

    short, plain_run = run("short", offline_steps=3), run("plain")
    a, b = short.train(), plain_run.train()
    assert short.c["offline_done"] == 3
    assert plain_run.c["offline_done"] == get_profile("smoke").offline_steps != 3
    assert a["stage1"]["key"] != b["stage1"]["key"] and not b["stage1"]["cache_hit"]
    assert a["agent_config_overrides"] == {"offline_steps": 3}
    with pytest.raises(ValueError, match=r"offline_steps = -1 is not allowed: .*\[0, 10000000\]"):
        run("bad", offline_steps=-1)
    assert not (tmp_path / "bad").exists()


def test_online_lr_acts_from_stage_ii_and_shares_stage_i(tmp_path, demos_root):
    """``online_lr`` is a setting of the online phase: Adam steps at it from Stage II on (and
    after a resume), and a run that differs only there loads the other's Stage I."""
    def run(out, **config):
        return Run("qcfql", "WindowInstall-A-v0", "smoke", 0, tmp_path / out, demos=demos_root,
                   progress=False, save_every_s=0.0, stage1_cache=tmp_path / "cache",
                   agent_config=config or None)

    plain_run, slow = run("plain", online_lr=None), run("slow", online_lr=1e-5)
    a, b = plain_run.train(), slow.train()
    assert a["stage1"]["key"] == b["stage1"]["key"]
    from window_bench.harness.stage1 import demos_sha256
    assert a["stage1"]["demos_sha256"] == b["stage1"]["demos_sha256"] == \
        demos_sha256(plain_run._demos())   # the demos Stage I trained on (as labelled)
    assert (a["stage1"]["cache_hit"], b["stage1"]["cache_hit"]) == (False, True)
    assert [g["lr"] for g in plain_run.agent.optimizer.param_groups] == [3e-4]
    assert [g["lr"] for g in slow.agent.optimizer.param_groups] == [1e-5]
    assert a["checkpoints"][0]["successes"] == b["checkpoints"][0]["successes"]
    assert b["agent_config_overrides"] == {"online_lr": 1e-5}
    from baselines.qcfql import QCFQLAgent
    from window_bench.harness.methods import get_profile
    assert QCFQLAgent.make_config(10, get_profile("smoke"), {}).online_lr == 3e-5  # bench run's
    with pytest.raises(ValueError, match="online_lr = 0"):
        run("bad", online_lr=0).train()
