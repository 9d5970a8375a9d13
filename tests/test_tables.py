"""bench tables: rows from raw results files, intervals across seeds, the paper beside ours,
and the committed Results pages equal to what bench tables regenerates from committed runs."""

import json
from pathlib import Path

import numpy as np
import pytest

from window_bench.harness.methods import METHODS, PROFILES
from window_bench.harness.tables import bootstrap_ci, build, iqm, load_paper, load_runs, \
    running_curves

REPO = Path(__file__).resolve().parents[1]


def _results(root: Path, method: str, env: str, seed: int, success: float, *, h=None,
             seed_set="test", M=100, overrides=None, episodes=None, cycle=25.0, track=None):
    """A results.json as bench run writes it (the fields bench tables reads)."""
    m = METHODS[method].as_dict()
    if h is not None:
        m["h"] = h
    k = round(success * M)
    fe = {"seed_set": seed_set, "episodes": M, "successes": k, "success_rate": k / M,
          "wilson95": [0.0, 1.0], "cycle_time_s": cycle, "pr_S": 1.0, "pr_I_given_S": 0.9,
          "pr_T_given_I": k / M / 0.9, "policy": "policies/final.safetensors"}
    r = {"schema_version": 1, "method": m, "env_id": env, "profile": PROFILES["smoke"].as_dict(),
         "seed": seed, "agent_config_overrides": overrides or {},
         "final": {"success_rate": k / M, "wilson95": [0, 1], "episodes": M,
                   "cycle_time_s": cycle, "time_to_95_sim_hours": None,
                   "takeover_minutes": 3.0, "sim_hours": 0.01, "wall_clock_s": 10.0},
         "checkpoints": [], "train_episodes": episodes or [],
         "eval_seeds": [500000, 500000 + M - 1], "final_eval": fe,
         "provenance": {"git_commit": "unknown"}}
    if track is not None:           # files from before the track setting have none: state
        r["track"] = track
    tag = "".join(f"-{a}{b}" for a, b in (overrides or {}).items()) + (f"-{track}" if track else "")
    d = root / env / f"{method}{'' if h is None else f'-h{h}'}{tag}-smoke-{seed_set}-s{seed}"
    d.mkdir(parents=True)
    (d / "results.json").write_text(json.dumps(r))
    return d


def test_bootstrap_interval_and_iqm():
    assert bootstrap_ci([0.8]) is None                     # one seed: no interval
    assert bootstrap_ci([0.5, 0.5, 0.5]) == (0.5, 0.5)
    lo, hi = bootstrap_ci([0.6, 0.8, 1.0])
    assert 0.6 <= lo < 0.8 < hi <= 1.0
    assert bootstrap_ci([0.6, 0.8, 1.0]) == (lo, hi)        # fixed generator: reproducible
    assert iqm([1, 2, 3, 4]) is None                        # fewer than 5 seeds
    assert iqm([0, 1, 2, 3, 100]) == pytest.approx(2.0)     # the outlier is trimmed


def test_paper_numbers_are_the_papers():
    p = load_paper()
    assert p[(2, "A", "qcfql", 10, "0.5x0.5")]["final_success_pct"] == 100
    assert p[(3, "B", "hil-serl", 1, "0.5x0.5")]["pr_T_given_I"] == 91.1
    assert p[(5, "A", "qcfql-no-intervention", 5, "0.5x0.5")]["wilson_lo"] == 60.7
    assert p[(7, "B", "qcfql", 10, "0.6x0.6")]["cycle_s"] == 25.8


def test_rows_group_seeds_and_put_the_paper_beside_ours(tmp_path):
    runs = tmp_path / "runs"
    for seed, s in enumerate([0.80, 0.90, 1.00]):
        _results(runs, "qcfql", "WindowInstall-A-v0", seed, s)
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.5, seed_set="dev", M=20)
    for h in (5, 20):
        _results(runs, "qcfql-no-intervention", "WindowInstall-B-v0", 0, 0.7, h=h)
    rows = load_runs(runs)
    assert len(rows) == 4                       # test and dev seeds never share a row
    pages = build(runs, tmp_path / "out", figures=False)
    t2 = pages["table2.md"]
    row = next(ln for ln in t2.splitlines() if ln.startswith("| Ours (complete pipeline)")
               and "*dev*" not in ln)
    assert "| 3 |" in row and "**90**" in row and "80 · 90 · 100" in row
    assert "100 [96, 100]" in row               # the paper's number and its Wilson interval
    dev = next(ln for ln in t2.splitlines() if "*dev*" in ln and ln.startswith("| Ours"))
    assert "**50**" in dev and "M = 20" in dev
    assert "development seeds" in t2
    t6 = pages["table6.md"]
    assert "| 5 |" in t6 and "| 20 |" in t6 and "82 [74, 88]" in t6
    assert "No runs for this table yet" in pages["table7.md"]


def test_overrides_are_their_own_row_without_a_paper_number(tmp_path):
    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.6, overrides={"policy_ema": 0.0})
    t2 = build(runs, tmp_path / "out", figures=False)["table2.md"]
    row = next(ln for ln in t2.splitlines() if "policy_ema" in ln and ln.startswith("|"))
    assert row.count("| – |") >= 3             # no paper numbers for our variant


def test_running_curves_window_and_rates():
    eps = [{"steps": 100, "success": i % 2 == 0, "takeover_steps": 10 * (i % 2)}
           for i in range(40)]
    x = np.array([0.0, 100 / 36000, 40 * 100 / 36000])
    c = running_curves(eps, x)
    assert np.isnan(c[0, 0])                    # no episode finished yet
    assert c[0, 1] == 1.0 and c[1, 1] == pytest.approx(10.0) and c[2, 1] == 0.0
    assert c[0, 2] == 0.5 and c[2, 2] == pytest.approx(10 * 10 / 2000)


def test_figures_written(tmp_path):
    runs = tmp_path / "runs"
    eps = [{"steps": 300, "success": i > 5, "takeover_steps": 20} for i in range(30)]
    for seed in (0, 1):
        _results(runs, "qcfql", "WindowInstall-A-v0", seed, 0.9, episodes=eps)
    build(runs, tmp_path / "out")
    for name in ("fig10.png", "fig10.svg", "fig11.png", "fig11.svg"):
        assert (tmp_path / "out" / name).stat().st_size > 1000


def test_committed_results_pages_equal_bench_tables(tmp_path, monkeypatch):
    """docs/results/*.md are byte for byte what bench tables makes of leaderboard/runs."""
    monkeypatch.chdir(REPO)
    pages = build("leaderboard/runs", tmp_path, figures=True)
    for name in pages:
        assert (REPO / "docs" / "results" / name).read_bytes() == (tmp_path / name).read_bytes(), \
            f"docs/results/{name} differs from bench tables' output: run bench tables"


def test_table7_from_evaluation_cells(tmp_path):
    """bench eval outputs at <ood env>/<run>.json join their training cell <env>/<run>."""
    runs = tmp_path / "runs"
    for seed, k in enumerate([90, 96]):
        d = _results(runs, "qcfql", "WindowInstall-B-v0", seed, 1.0)
        ood = runs / "WindowInstall-B-Panel60x60-v0"
        ood.mkdir(exist_ok=True)
        (ood / f"{d.name}.json").write_text(json.dumps({
            "env_id": "WindowInstall-B-Panel60x60-v0", "seed_set": "test", "episodes": 100,
            "success_rate": k / 100, "cycle_time_s": 25.0, "pr_S": 1.0, "pr_I_given_S": 0.95,
            "pr_T_given_I": k / 95}))
    t7 = build(runs, tmp_path / "out", figures=False)["table7.md"]
    row = next(ln for ln in t7.splitlines() if ln.startswith("| B | 0.6x0.6"))
    assert "**93**" in row and "90 · 96" in row and "| 87 [79, 92] |" in row


def test_state_and_pixel_runs_of_one_method_are_different_rows(tmp_path):
    """The track is part of a row's identity: a state and a pixel run of the same method,
    seed and profile never share a cell, each row names its track, and the caption spells
    the state track out as privileged state."""
    runs = tmp_path / "runs"
    _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.9)            # no field: state
    _results(runs, "qcfql-offline", "WindowInstall-A-v0", 1, 0.7, track="state")
    _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.2, track="pixels")
    rows = load_runs(runs)
    assert sorted((k.track, [s.seed for s in v]) for k, v in rows.items()) == \
        [("pixels", [0]), ("state", [0, 1])]
    t2 = build(runs, tmp_path / "out", figures=False)["table2.md"]
    lines = [ln for ln in t2.splitlines() if ln.startswith("| Ours (offline-only)")]
    assert len(lines) == 2
    state, pixels = lines                       # the state row first
    assert "| state, smoke, M = 100 | 2 |" in state and "**80**" in state
    assert "| pixels, smoke, M = 100 | 1 |" in pixels and "**20**" in pixels
    assert "`state` = privileged state" in t2 and "`pixels` = the paper's observation" in t2


def test_leaderboard_names_the_track_and_keeps_tracks_apart(tmp_path):
    from window_bench.harness.leaderboard import build as leaderboard, check_results, run_dest

    runs = tmp_path / "runs"
    d_state = _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.9)
    d_pix = _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.2, track="pixels")
    r_state, r_pix = (check_results(d / "results.json") for d in (d_state, d_pix))
    assert run_dest(r_state, "lb").name == "qcfql-offline-smoke-s0"
    assert run_dest(r_pix, "lb").name == "qcfql-offline-pixels-smoke-s0"
    body = leaderboard(runs, readme=None, snippet=None)
    rows = [ln for ln in body.splitlines() if "(`qcfql-offline`)" in ln]
    assert rows[0].startswith("| state | WindowInstall-A-v0 |") and "| 90 [" in rows[0]
    assert rows[1].startswith("| pixels | WindowInstall-A-v0 |") and "| 20 [" in rows[1]
    assert "`state` = privileged state" in body
    bad = json.loads((d_pix / "results.json").read_text())
    bad["track"] = "depth"
    (d_pix / "results.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="track: 'depth' is not one of"):
        check_results(d_pix / "results.json")


def test_readme_headline_block_is_replaced_between_its_markers_only(tmp_path):
    from window_bench.harness.tables import HEADLINE_END, HEADLINE_START, update_readme

    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{HEADLINE_START}\nold table\n{HEADLINE_END}\noutro\n")
    assert update_readme(readme, "| new |")
    assert readme.read_text() == f"intro\n{HEADLINE_START}\n| new |\n{HEADLINE_END}\noutro\n"
    plain = tmp_path / "OTHER.md"
    plain.write_text("no markers\n")
    assert not update_readme(plain, "| new |") and plain.read_text() == "no markers\n"
    assert not update_readme(tmp_path / "missing.md", "| new |")


def test_headline_rows_come_from_test_seed_runs_only(tmp_path):
    from window_bench.harness.tables import headline, load_paper, load_runs

    runs = tmp_path / "runs"
    for seed, rate in enumerate([0.6, 0.8]):
        _results(runs, "qcfql-offline", "WindowInstall-A-v0", seed, rate)
    text = headline(load_runs(runs), load_paper(), profile="smoke")
    offline = next(line for line in text.splitlines() if "offline-only" in line)
    complete = next(line for line in text.splitlines() if "complete pipeline" in line)
    assert "**70**" in offline and "(n = 2)" in offline and "| 78 |" in offline
    assert complete.count("not run yet") == 2


def test_committed_readme_headline_equals_bench_tables():
    """README.md's headline block is what bench tables makes of leaderboard/runs."""
    from window_bench.harness.tables import HEADLINE_END, HEADLINE_START, headline, \
        load_paper, load_runs

    block = (REPO / "README.md").read_text().split(HEADLINE_START)[1].split(HEADLINE_END)[0]
    assert block.strip() == headline(load_runs(REPO / "leaderboard" / "runs"), load_paper())


def test_committed_leaderboard_equals_bench_leaderboard(tmp_path, monkeypatch):
    """leaderboard/README.md and the docs' leaderboard table are what bench leaderboard makes
    of leaderboard/runs (rebuild them when a cell is committed)."""
    from window_bench.harness.leaderboard import build as build_leaderboard

    monkeypatch.chdir(REPO)
    build_leaderboard("leaderboard/runs", readme=tmp_path / "README.md",
                      snippet=tmp_path / "leaderboard.md")
    assert (REPO / "leaderboard" / "README.md").read_bytes() == \
        (tmp_path / "README.md").read_bytes(), "leaderboard/README.md: run bench leaderboard"
    assert (REPO / "docs" / "snippets" / "leaderboard.md").read_bytes() == \
        (tmp_path / "leaderboard.md").read_bytes(), \
        "docs/snippets/leaderboard.md: run bench leaderboard"
