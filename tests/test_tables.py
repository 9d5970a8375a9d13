"""bench tables: rows from raw results files, intervals across seeds, the paper beside ours,
and the committed Results pages equal to what bench tables regenerates from committed runs."""

import json
from pathlib import Path

import numpy as np
import pytest

from window_bench.harness.methods import METHODS, PROFILES
from window_bench.harness.results import DEFAULTS_REVISION
from window_bench.harness.tables import bootstrap_ci, build, iqm, load_paper, load_runs, \
    running_curves

REPO = Path(__file__).resolve().parents[1]


def _results(root: Path, method: str, env: str, seed: int, success: float, *, h=None,
             seed_set="test", M=100, overrides=None, episodes=None, cycle=25.0, track=None,
             operator=None, defaults=DEFAULTS_REVISION):
    """A results.json as bench run writes it (the fields bench tables reads); ``defaults=None``:
    a file from before the revisions of the defaults (revision 1)."""
    m = METHODS[method].as_dict()
    if h is not None:
        m["h"] = h
    k = round(success * M)
    fe = {"seed_set": seed_set, "episodes": M, "successes": k, "success_rate": k / M,
          "wilson95": [0.0, 1.0], "cycle_time_s": cycle, "pr_S": 1.0, "pr_I_given_S": 0.9,
          "pr_T_given_I": min(1.0, k / M / 0.9), "policy": "policies/final.safetensors"}
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
    if operator is not None:
        r["operator"] = operator
    if defaults is not None:
        r["defaults"] = defaults
    tag = ("".join(f"-{a}{b}" for a, b in (overrides or {}).items()) + (f"-{track}" if track else "")
           + (f"-{operator}" if operator else ""))
    tag += "" if defaults == DEFAULTS_REVISION else f"-d{defaults or 1}"
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
    row = next(ln for ln in t2.splitlines() if ln.startswith("| Ours (complete pipeline) |"))
    assert row.startswith("| Ours (complete pipeline) | 3 | **90** [80, 100] |")
    assert "100 [96, 100]" in row               # the paper's number and its Wilson interval
    assert "80 · 90 · 100" not in row           # a cell is mean [interval]; the seeds are below
    assert "    | Ours (complete pipeline) | 0 · 1 · 2 | 80 · 90 · 100 |" in t2
    dev = next(ln for ln in t2.splitlines() if "*dev*" in ln and ln.startswith("| Ours"))
    assert dev.startswith("| Ours (complete pipeline), M = 20, *dev* | 1 | **50** |")
    assert "Unless a row says otherwise: `state` track, `smoke` profile, final evaluation " \
           "with M = 100 on the held-out test seeds" in t2
    assert "development seeds" in t2
    t6 = pages["table6.md"]
    assert "| 5 |" in t6 and "| 20 |" in t6 and "82 [74, 88]" in t6
    assert "No runs for this table yet" in pages["table7.md"]


def test_overrides_are_their_own_row_without_a_paper_number(tmp_path):
    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.6, overrides={"policy_ema": 0.0})
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.7)
    t2 = build(runs, tmp_path / "out", figures=False)["table2.md"]
    row = next(ln for ln in t2.splitlines() if ln.startswith("| Ours (complete pipeline), variant"))
    assert row.startswith("| Ours (complete pipeline), variant 1 | 1 | **60** |")
    assert row.count("| – |") >= 3             # no paper numbers for our variant
    assert "policy_ema" not in row              # the overrides are a note, not the row's name
    assert "- Variant 1: `qcfql` with `policy_ema=0.0`.\n" in t2
    plain = next(ln for ln in t2.splitlines() if ln.startswith("| Ours (complete pipeline) |"))
    assert "| **70** | 100 [96, 100] |" in plain


def test_another_operator_is_its_own_row_named_in_its_note(tmp_path):
    runs = tmp_path / "runs"
    _results(runs, "qcfql-offline", "WindowInstall-B-v0", 0, 0.4, operator="attentive",
             overrides={"fine_pose_mm": 10.0})
    _results(runs, "qcfql-offline", "WindowInstall-B-v0", 0, 0.3, operator="attentive")
    _results(runs, "qcfql-offline", "WindowInstall-B-v0", 0, 0.1)    # the default operator
    t3 = build(runs, tmp_path / "out", figures=False)["table3.md"]
    rows = [ln for ln in t3.splitlines() if ln.startswith("| Ours (offline-only)")]
    assert len(rows) == 3
    plain = next(ln for ln in rows if ln.startswith("| Ours (offline-only) |"))
    assert "| **10** |" in plain and "| 75 |" in plain       # the paper's number stays here
    assert "- Variant 1: `qcfql-offline` with `fine_pose_mm=10.0`, `operator=\"attentive\"`.\n" in t3
    assert "- Variant 2: `qcfql-offline` with `operator=\"attentive\"`.\n" in t3
    assert all("| 75 |" not in ln for ln in rows if ", variant" in ln)


def test_a_variant_that_is_a_preset_is_named_by_it(tmp_path):
    from window_bench.harness.methods import get_preset

    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.1,
             overrides=get_preset("qcfql-as-published"))
    t2 = build(runs, tmp_path / "out", figures=False)["table2.md"]
    note = next(ln for ln in t2.splitlines() if ln.startswith("- Variant 1: `qcfql` with"))
    assert note.endswith(" (the preset `qcfql-as-published`).")


def test_row_names_say_only_what_differs_from_the_usual_run():
    from window_bench.harness.tables import RowKey, RowNames

    def key(**kw):
        base = dict(setting="A", method="qcfql", h=10, overrides=(), profile="cpu",
                    seed_set="test", M=100, track="state")
        return RowKey(**{**base, **kw})

    plain, pix, dev, smoke = key(), key(track="pixels"), key(seed_set="dev", M=20), \
        key(profile="smoke")
    variant = key(overrides=(("policy_ema", "0.0"),))
    names = RowNames([plain, plain, pix, dev, smoke, variant, key(method="sac", h=1)])
    assert names.usual == ("state", "cpu", "test", 100)
    assert [names.method(k) for k in (plain, pix, dev, smoke, variant)] == [
        "Ours (complete pipeline)", "Ours (complete pipeline), pixels",
        "Ours (complete pipeline), M = 20, *dev*", "Ours (complete pipeline), smoke profile",
        "Ours (complete pipeline), variant 1"]
    assert names.method(dev, markdown=False) == "Ours (complete pipeline), M = 20, dev"
    assert names.horizon(variant) == "10, variant 1"
    assert RowNames([dev]).method(dev) == "Ours (complete pipeline), *dev*"   # always marked


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
    for name in ("fig10.png", "fig10.svg", "fig11.png", "fig11.svg", "budget.png", "budget.svg"):
        assert (tmp_path / "out" / name).stat().st_size > 1000


def test_budget_figure_draws_each_profile_of_the_headline_methods(tmp_path, monkeypatch):
    """``budget.png``: one line per headline method and profile from the checkpoint
    evaluations, the final test-seed success as a dot at the line's end, the paper's final
    success as a star (online methods at 3.0 h, offline ones at 0); rows off the headline
    (pixels, variants, development-seed finals) are not drawn."""
    import matplotlib.axes
    import matplotlib.figure

    runs = tmp_path / "runs"
    for seed in (0, 1):
        for profile, top in (("smoke", 24_000), ("long", 108_000)):
            d = _results(tmp_path / profile, "qcfql", "WindowInstall-A-v0", seed, 0.5 + 0.1 * seed)
            (runs / "WindowInstall-A-v0").mkdir(parents=True, exist_ok=True)
            d = d.rename(runs / "WindowInstall-A-v0" / d.name.replace("smoke", profile))
            r = json.loads((d / "results.json").read_text())
            r["profile"] = {**r["profile"], "name": profile}
            r["checkpoints"] = [{"env_steps": s, "success_rate": s / top / 2,
                                 "wilson95": [0.0, 1.0]} for s in range(0, top + 1, top // 4)]
            (d / "results.json").write_text(json.dumps(r))
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.2, track="pixels")
    legends, legend = [], matplotlib.figure.Figure.legend
    monkeypatch.setattr(matplotlib.figure.Figure, "legend", lambda self, handles, labels, **kw:
                        legends.append(labels) or legend(self, handles, labels, **kw))
    stars, plot = [], matplotlib.axes.Axes.plot
    monkeypatch.setattr(matplotlib.axes.Axes, "plot", lambda self, x, y, *a, **kw: (
        stars.append((list(x), list(y))) if kw.get("marker") == "*" else None)
        or plot(self, x, y, *a, **kw))
    build(runs, tmp_path / "out")
    assert legends[-1] == ["Ours (complete pipeline), long", "Ours (complete pipeline), smoke"]
    assert (tmp_path / "out" / "budget.png").stat().st_size > 1000
    assert ([3.0], [100.0]) in stars and ([0.0], [78.0]) in stars   # complete; offline-only


def test_figure_legends_name_lines_as_the_table_names_rows(tmp_path, monkeypatch):
    import matplotlib.figure

    runs = tmp_path / "runs"
    eps = [{"steps": 300, "success": i > 5, "takeover_steps": 20} for i in range(30)]
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.9, episodes=eps)
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.2, episodes=eps, track="pixels")
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.1, episodes=eps,
             overrides={"policy_ema": 0.0, "prior_data": "replay"})
    legends, legend = [], matplotlib.figure.Figure.legend
    monkeypatch.setattr(matplotlib.figure.Figure, "legend", lambda self, handles, labels, **kw:
                        legends.append(labels) or legend(self, handles, labels, **kw))
    t2 = build(runs, tmp_path / "out")["table2.md"]
    assert legends[0] == ["Ours (complete pipeline)", "Ours (complete pipeline), pixels",
                          "Ours (complete pipeline), variant 1"]     # Fig. 11 (B) has no rows
    assert len(legends) == 1                  # the budget figure: no checkpoints, no legend
    for label in legends[0]:
        assert f"| {label} | 1 |" in t2


def test_tables_never_write_the_hand_written_results_index(tmp_path, monkeypatch):
    """docs/results/index.md is the hand-written overview: bench tables writes its list of
    tables to tables.md and leaves index.md alone, --force or not."""
    from window_bench.cli import main
    from window_bench.harness.tables import outputs

    monkeypatch.chdir(tmp_path)
    _results(tmp_path / "runs", "qcfql", "WindowInstall-A-v0", 0, 0.8)
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "index.md").write_text("hand-written overview")
    assert tmp_path / "o" / "index.md" not in outputs(tmp_path / "o")
    for force in ([], ["--force"], ["--force"]):
        assert main(["tables", "--runs", "runs", "--out", "o", "--no-figures", *force]) == 0
    assert (tmp_path / "o" / "index.md").read_text() == "hand-written overview"
    assert "[Table 2: Experiment A" in (tmp_path / "o" / "tables.md").read_text()


def test_committed_results_pages_equal_bench_tables(tmp_path, monkeypatch, capsys):
    """docs/results/*.md and README.md's headline are byte for byte what the documented
    command (``bench tables --runs leaderboard/runs --out docs/results --readme README.md
    --force``) makes of leaderboard/runs, here pointed at a copy."""
    from window_bench.cli import main

    monkeypatch.chdir(REPO)
    readme = tmp_path / "README.md"
    readme.write_bytes((REPO / "README.md").read_bytes())
    assert main(["tables", "--runs", "leaderboard/runs", "--out", str(tmp_path / "results"),
                 "--readme", str(readme), "--force"]) == 0
    assert "skipped" not in capsys.readouterr().err     # every committed raw file passes
    for name in [f"table{t}.md" for t in range(2, 8)] + ["tables.md"]:
        assert (REPO / "docs" / "results" / name).read_bytes() == \
            (tmp_path / "results" / name).read_bytes(), \
            f"docs/results/{name} differs from bench tables' output: run bench tables"
    assert readme.read_bytes() == (REPO / "README.md").read_bytes()


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
            "pr_T_given_I": min(1.0, k / 95)}))
    t7 = build(runs, tmp_path / "out", figures=False)["table7.md"]
    row = next(ln for ln in t7.splitlines() if ln.startswith("| B, 0.6x0.6 |"))
    assert "| 2 | **93** [90, 96] | 87 [79, 92] |" in row
    seeds = next(ln for ln in t7.splitlines() if ln.startswith("    | B, 0.6x0.6 |"))
    assert "| 0 · 1 | 90 · 96 |" in seeds


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
    assert state.startswith("| Ours (offline-only) | 2 | **80** [")
    assert pixels.startswith("| Ours (offline-only), pixels | 1 | **20** |")
    assert "Unless a row says otherwise: `state` track" in t2
    assert "`state` = privileged state" in t2 and "`pixels` = the paper's observation" in t2


def test_leaderboard_names_the_track_and_keeps_tracks_apart(tmp_path):
    from window_bench.harness.leaderboard import build as leaderboard, check_results, run_dest

    runs = tmp_path / "runs"
    d_state = _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.9)
    d_pix = _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.2, track="pixels")
    r_state, r_pix = (check_results(d / "results.json") for d in (d_state, d_pix))
    assert run_dest(r_state, "lb").name == "qcfql-offline-smoke-s0"
    assert run_dest(r_pix, "lb").name == "qcfql-offline-pixels-smoke-s0"
    # another chunk horizon or operator profile never lands on the default run's directory
    r_var = {**r_state, "method": {**r_state["method"], "h": 5}, "operator": "attentive"}
    assert run_dest(r_var, "lb").name == "qcfql-offline-h5-attentive-smoke-s0"
    # a pose read-out (pixels-seat) is named by its digest, in the directory and the row
    r_ro = {**r_pix, "encoder": {"pose_readout": {"sha256": "ab12" * 16}}}
    assert run_dest(r_ro, "lb").name == "qcfql-offline-pixels-readoutab12ab12-smoke-s0"
    r_odd = {**r_pix, "encoder": {"pose_readout": {"sha256": "../x"}}}
    assert run_dest(r_odd, "lb").name == "qcfql-offline-pixels-smoke-s0"
    # the operator and D_demo labels are named where they depart from the run's own revision
    r_cur = {**r_state, "operator": "average", "demo_actions": "executed"}
    assert run_dest(r_cur, "lb").name == "qcfql-offline-average-executed-smoke-s0"
    r_one = {k: v for k, v in r_cur.items() if k != "defaults"}           # revision 1
    assert run_dest(r_one, "lb").name == "qcfql-offline-smoke-s0"
    assert run_dest({**r_one, "operator": "attentive-flush", "demo_actions": "meant"},
                    "lb").name == "qcfql-offline-attentive-flush-meant-smoke-s0"
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


def test_headline_finds_the_published_agent_of_an_earlier_revision(tmp_path):
    """An earlier revision's run of the preset qcfql-as-published carries only the entries
    that made it the paper's agent then (later revisions' run defaults did not exist): the
    headline shows it, marked, and not a run that departs from the preset."""
    from window_bench.harness.methods import get_preset
    from window_bench.harness.tables import headline, load_paper, load_runs

    preset = get_preset("qcfql-as-published")
    then = {k: v for k, v in preset.items()
            if k in ("act_noise_scale", "td_noise_scale", "distill_noise_scale", "policy_ema",
                     "distill_from_ema", "prior_data")}
    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.06, overrides=then, operator="average",
             defaults=None)
    _results(runs, "qcfql", "WindowInstall-B-v0", 0, 0.5,
             overrides={**then, "policy_ema": 0.005}, operator="average", defaults=None)

    def published():
        text = headline(load_runs(runs), load_paper(), profile="smoke")
        return next(ln for ln in text.splitlines() if ln.startswith("| QC-FQL as published"))

    line = published()
    assert "| **6** (n = 1, defaults 1) | 100 [96, 100] | not run yet |" in line
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.3, overrides=preset)
    assert "| **30** (n = 1) | 100 [96, 100] |" in published()


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


# ---------------------------------------------------------------------------- hostile files
def _one_warning(err: str, path) -> str:
    """The single stderr line that names ``path``; no traceback."""
    lines = [ln for ln in err.splitlines() if str(path) in ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _edit(d: Path, edit) -> Path:
    p = d / "results.json"
    r = json.loads(p.read_text())
    edit(r)
    p.write_text(json.dumps(r))
    return p


@pytest.mark.parametrize("edit, reason", [
    (lambda r: r["final_eval"].update(success_rate=7.5), "final_eval.success_rate: 7.5 is greater"),
    (lambda r: r["final_eval"].update(episodes=-3), "final_eval.episodes: -3 is less than"),
    (lambda r: r["final_eval"].update(successes=130), "successes 130 > episodes 100"),
    (lambda r: r["final_eval"].update(success_rate=0.5), "success_rate 0.5 is not successes"),
    (lambda r: r["final_eval"].update(pr_S=-0.5), "final_eval.pr_S: -0.5"),
    (lambda r: r["final_eval"].update(seeds=[100000, 100099]), "seeds [100000, 100099] are not"),
    (lambda r: r["method"].update(label="<script>alert(1)</script>"), "method.label"),
    (lambda r: r["method"].update(h="<b>"), "method.h"),
    (lambda r: r["train_episodes"].append({"steps": 0, "success": True}), "steps: 0 is less"),
    (lambda r: (r.pop("final_eval"), r.update(checkpoints=[])), "no final_eval"),
])
def test_a_bad_results_file_is_skipped_with_one_line_and_not_rendered(tmp_path, capsys, edit,
                                                                      reason):
    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.8)
    bad = _edit(_results(runs, "qcfql", "WindowInstall-A-v0", 1, 0.9), edit)
    pages = build(runs, tmp_path / "out", figures=False)
    line = _one_warning(capsys.readouterr().err, bad)
    assert line.startswith(f"warning: skipped: {bad}: ") and reason in line
    row = next(ln for ln in pages["table2.md"].splitlines() if ln.startswith("| Ours (complete"))
    assert "| 1 |" in row and "**80**" in row            # the good seed alone
    assert "qcfql-smoke-test-s1" not in pages["table2.md"]
    text = "".join(pages.values())
    assert "750" not in text and "M = -3" not in text and "<script>" not in text


@pytest.mark.parametrize("raw, reason", [
    ('{"seed": NaN}', "NaN is not a number JSON allows"),
    ('{"seed": Infinity}', "Infinity is not a number JSON allows"),
    ('{"seed": 1e400}', "1e400 overflows a float"),
    ("not json", "not readable JSON"),
])
def test_nan_infinity_and_non_json_are_refused(tmp_path, capsys, raw, reason):
    runs = tmp_path / "runs"
    d = _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.8)
    (d / "results.json").write_text(raw)
    assert load_runs(runs) == {}
    assert reason in _one_warning(capsys.readouterr().err, d / "results.json")


def test_an_oversize_file_is_refused_before_it_is_read(tmp_path, capsys, monkeypatch):
    from window_bench.harness.schemas import MAX_JSON_BYTES

    runs = tmp_path / "runs"
    d = _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.8)
    with open(d / "results.json", "r+b") as f:       # sparse: no disk, no time
        f.truncate(MAX_JSON_BYTES + 1)
    monkeypatch.setattr(Path, "read_text", lambda *a, **k: pytest.fail("read whole"))
    monkeypatch.setattr(Path, "read_bytes", lambda *a, **k: pytest.fail("read whole"))
    assert load_runs(runs) == {}
    assert f"{MAX_JSON_BYTES + 1:,} bytes, over the" in _one_warning(capsys.readouterr().err,
                                                                     d / "results.json")


def test_a_directory_name_that_would_break_the_page_is_skipped(tmp_path, capsys):
    runs = tmp_path / "runs"
    d = _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.8)
    odd = d.rename(d.parent / "x`<img src=x>")
    assert load_runs(runs) == {}
    assert "is not one safe name" in _one_warning(capsys.readouterr().err, odd)


def _ood(runs: Path, train: Path, **fields) -> Path:
    env = "WindowInstall-B-Panel60x60-v0"
    (runs / env).mkdir(exist_ok=True)
    p = runs / env / f"{train.name}.json"
    p.write_text(json.dumps({"env_id": env, "method": "qcfql", "seed_set": "test",
                             "episodes": 100, "successes": 90, "success_rate": 0.9,
                             "wilson95": [0.8, 0.95], "cycle_time_s": 25.0, "pr_S": 1.0,
                             "pr_I_given_S": 0.95, "pr_T_given_I": 0.94,
                             "eval_seeds": [500000, 500099], **fields}))
    return p


@pytest.mark.parametrize("fields, reason", [
    ({"success_rate": 7.5}, "success_rate: 7.5 is greater than the maximum of 1"),
    ({"episodes": -3}, "episodes: -3 is less than the minimum of 1"),
    ({"successes": 900}, "successes 900 > episodes 100"),
    ({"cycle_time_s": -200.0}, "cycle_time_s: -200.0"),
    ({"env_id": "WindowInstall-B-Panel40x40-v0"}, "env_id 'WindowInstall-B-Panel40x40-v0'"),
    ({"method": "sac"}, "method 'sac', its training cell's is 'qcfql'"),
    ({"env_kwargs": {"clearance": 0.008}}, "is not a table entry"),
    ({"eval_seeds": [100000, 100099]}, "are not the 100 'test' seeds"),
    (None, "not readable JSON"),
    ("nan", "NaN is not a number JSON allows"),
])
def test_a_bad_table7_evaluation_is_skipped_with_one_line_and_not_rendered(tmp_path, capsys,
                                                                          fields, reason):
    runs = tmp_path / "runs"
    _ood(runs, _results(runs, "qcfql", "WindowInstall-B-v0", 0, 1.0))
    train = _results(runs, "qcfql", "WindowInstall-B-v0", 1, 1.0)
    bad = _ood(runs, train, **(fields if isinstance(fields, dict) else {}))
    if fields is None:
        bad.write_text("{not json")
    elif fields == "nan":
        bad.write_text(bad.read_text().replace('"cycle_time_s": 25.0', '"cycle_time_s": NaN'))
    t7 = build(runs, tmp_path / "out", figures=False)["table7.md"]
    line = _one_warning(capsys.readouterr().err, bad)
    assert line.startswith(f"warning: skipped: {bad}: ") and reason in line
    row = next(ln for ln in t7.splitlines() if ln.startswith("| B, 0.6x0.6 |"))
    assert "| 1 | **90** |" in row                        # seed 0's evaluation alone
    assert "750" not in t7 and "nan" not in t7 and "-200" not in t7


def test_strings_from_files_are_escaped_in_markdown():
    from window_bench.harness.schemas import md_text

    assert md_text("Ours (w/o warm-start)") == "Ours (w/o warm-start)"
    assert md_text("<script>a|b`c</script>\n[x](javascript:y) & z") == \
        ("&lt;script&gt;a&#124;b&#96;c&lt;/script&gt; &#91;x&#93;(javascript:y) &amp; z")


def test_the_leaderboard_skips_a_script_label_and_writes_only_where_told(tmp_path, capsys,
                                                                         monkeypatch):
    from window_bench.cli import main

    monkeypatch.chdir(tmp_path)
    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.8)
    bad = _edit(_results(runs, "qcfql", "WindowInstall-A-v0", 1, 0.9),
                lambda r: r["method"].update(label="<script>alert(1)</script>"))
    before = sorted(p for p in tmp_path.rglob("*"))
    assert main(["leaderboard", "--root", "runs"]) == 0
    out, err = capsys.readouterr()
    assert "<script>" not in out and "| 0 | 80 [" in out and "| 1 |" not in out
    assert _one_warning(err, "runs/WindowInstall-A-v0/qcfql-smoke-test-s1").startswith("skipped")
    assert sorted(tmp_path.rglob("*")) == before         # no README, no snippet by default
    assert bad.is_file()
    assert main(["leaderboard", "--root", "runs", "--readme", "lb/README.md",
                 "--snippet", "lb/snippet.md"]) == 0
    assert sorted(p.name for p in (tmp_path / "lb").iterdir()) == ["README.md", "snippet.md"]
    capsys.readouterr()
    assert main(["leaderboard", "--root", "runs", "--readme", "lb/README.md"]) == 2
    assert capsys.readouterr().err == "error: lb/README.md exists; pass --force to overwrite it\n"
    assert main(["leaderboard", "--root", "runs", "--readme", "lb/README.md", "--force"]) == 0


@pytest.mark.parametrize("argv, message", [
    (["leaderboard", "--root", "afile"], "argument --root: afile is a file, not a directory"),
    (["leaderboard", "--root", "afile/runs", "--add", "x"],
     "argument --root: afile/runs: afile is a file, not a directory"),
    (["leaderboard", "--root", "none"], "error: --root none: no such directory"),
    (["tables", "--runs", "afile", "--out", "o"], "argument --runs: afile is a file"),
    (["tables", "--runs", "runs", "--out", "afile"], "argument --out: afile: a file, not a dir"),
    (["tables", "--runs", "runs"], "the following arguments are required: --out"),
    (["tables", "--runs", "runs", "--out", "o", "--readme", "afile"],
     "error: --readme afile: not a file with the headline markers"),
    (["tables", "--runs", "runs", "--out", "o", "--readme", "none.md"],
     "error: --readme none.md: not a file with the headline markers"),
])
def test_bad_paths_of_leaderboard_and_tables_are_one_line_and_exit_2(tmp_path, capsys,
                                                                     monkeypatch, argv, message):
    from window_bench.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    _results(tmp_path / "runs", "qcfql", "WindowInstall-A-v0", 0, 0.8)
    before = sorted(tmp_path.rglob("*"))
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2 and message in err and err.count("\n") == 1, err
    assert sorted(tmp_path.rglob("*")) == before


def test_tables_write_only_under_out_and_never_overwrite_without_force(tmp_path, capsys,
                                                                      monkeypatch):
    from window_bench.cli import main
    from window_bench.harness.tables import HEADLINE_END, HEADLINE_START

    monkeypatch.chdir(tmp_path)
    _results(tmp_path / "runs", "qcfql", "WindowInstall-A-v0", 0, 0.8)
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{HEADLINE_START}\nold\n{HEADLINE_END}\n")
    assert main(["tables", "--runs", "runs", "--out", "o", "--no-figures"]) == 0
    assert readme.read_text().count("old") == 1       # no --readme: not touched
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")
                  if "runs" not in p.parts) == ["README.md", "o"] + \
        [f"o/{n}" for n in (*(f"table{t}.md" for t in range(2, 8)), "tables.md")]
    (tmp_path / "o" / "table2.md").write_text("mine")
    capsys.readouterr()
    assert main(["tables", "--runs", "runs", "--out", "o", "--no-figures"]) == 2
    assert capsys.readouterr().err.startswith("error: o/table")
    assert (tmp_path / "o" / "table2.md").read_text() == "mine"
    assert main(["tables", "--runs", "runs", "--out", "o2", "--no-figures", "--readme",
                 "README.md"]) == 2                     # the README is an existing file too
    assert not (tmp_path / "o2").exists() and "old" in readme.read_text()
    assert main(["tables", "--runs", "runs", "--out", "o", "--no-figures", "--readme",
                 "README.md", "--force"]) == 0
    assert (tmp_path / "o" / "table2.md").read_text() != "mine" and "old" not in readme.read_text()


def test_leaderboard_add_never_replaces_a_run_without_force(tmp_path, capsys, monkeypatch):
    from window_bench.cli import main

    monkeypatch.chdir(tmp_path)
    run = _results(tmp_path / "src", "qcfql", "WindowInstall-A-v0", 0, 0.8)
    assert main(["leaderboard", "--add", str(run), "--root", "lb"]) == 0
    dest = tmp_path / "lb" / "WindowInstall-A-v0" / "qcfql-smoke-s0" / "results.json"
    dest.write_text(dest.read_text().replace('"seed": 0', '"seed": 0 '))
    kept = dest.read_text()
    capsys.readouterr()
    assert main(["leaderboard", "--add", str(run), "--root", "lb"]) == 2
    assert capsys.readouterr().err == f"error: {dest.relative_to(tmp_path)} exists; pass " \
                                      f"--force to overwrite it\n"
    assert dest.read_text() == kept
    assert main(["leaderboard", "--add", str(run), "--root", "lb", "--force"]) == 0
    assert dest.read_text() == (run / "results.json").read_text()


def test_leaderboard_add_never_replaces_a_run_of_another_revision(tmp_path, capsys,
                                                                  monkeypatch):
    """Run names depart from each run's own revision's defaults, so a revision-2 run can have
    the name of a revision-1 run: ``--add --force`` refuses to replace it, in one line."""
    from window_bench.cli import main

    monkeypatch.chdir(tmp_path)
    old = _results(tmp_path / "old", "qcfql", "WindowInstall-A-v0", 0, 0.8, defaults=None)
    new = _results(tmp_path / "new", "qcfql", "WindowInstall-A-v0", 0, 0.5)
    assert main(["leaderboard", "--add", str(old), "--root", "lb"]) == 0
    dest = tmp_path / "lb" / "WindowInstall-A-v0" / "qcfql-smoke-s0" / "results.json"
    kept = dest.read_text()
    capsys.readouterr()
    assert main(["leaderboard", "--add", str(new), "--root", "lb", "--force"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {dest.relative_to(tmp_path)} holds a run made under "
                          f"revision 1 of the defaults, the new run revision "
                          f"{DEFAULTS_REVISION}") and err.count("\n") == 1
    assert dest.read_text() == kept
    dest.parent.rename(tmp_path / "lb" / "WindowInstall-A-v0" / "defaults-1")   # moved away
    assert main(["leaderboard", "--add", str(new), "--root", "lb"]) == 0
    assert dest.read_text() == (new / "results.json").read_text()


def test_the_leaderboard_marks_a_run_of_earlier_defaults(tmp_path):
    """Two runs of one name under different revisions must not read as the same run: the
    leaderboard marks the older one *defaults N*, as the tables do, and says what that means."""
    from window_bench.harness.leaderboard import build as leaderboard

    _results(tmp_path / "lb" / "defaults-1", "qcfql", "WindowInstall-B-v0", 1, 0.8, defaults=None)
    _results(tmp_path / "lb", "qcfql", "WindowInstall-B-v0", 1, 0.9)
    body = leaderboard(tmp_path / "lb")
    rows = [ln for ln in body.splitlines() if ln.startswith("| state | WindowInstall-B-v0")]
    assert len(rows) == 4                               # two runs, in both tables
    old = [ln for ln in rows if "*defaults 1*" in ln]
    assert len(old) == 2 and "| 80 [" in old[0]           # its results row
    assert not any(f"*defaults {DEFAULTS_REVISION}*" in ln for ln in rows)
    assert f"*defaults N*: run under revision N of the shipped defaults (now " \
           f"{DEFAULTS_REVISION})" in body


def test_a_row_of_earlier_defaults_is_marked_until_its_method_is_rerun(tmp_path):
    """A file without a defaults revision is revision 1: its departures are measured from
    revision 1's defaults (operator average, executed D_demo), its row is marked, and it
    leaves the table once its method has a row under the current defaults."""
    runs = tmp_path / "runs"
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.8, operator="average", defaults=None)
    _results(runs, "qcfql", "WindowInstall-A-v0", 0, 0.5, operator="attentive", defaults=None,
             overrides={"policy_ema": 0.0})
    _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.6, operator="average",
             defaults=None)
    _results(runs, "qcfql-offline", "WindowInstall-A-v0", 0, 0.9)
    t2 = build(runs, tmp_path / "out", figures=False)["table2.md"]
    rows = [ln for ln in t2.splitlines() if ln.startswith("| Ours")]
    assert any(ln.startswith("| Ours (complete pipeline), *defaults 1* | 1 | **80** | 100")
               for ln in rows)                      # average under revision 1: no variant
    assert any(ln.startswith("| Ours (complete pipeline), variant 1, *defaults 1* | 1 | **50**")
               for ln in rows)
    assert "- Variant 1: `qcfql` with `operator=\"attentive\"`, `policy_ema=0.0`.\n" in t2
    assert "Rows marked *defaults 1* were run under revision 1" in t2
    offline = [ln for ln in rows if ln.startswith("| Ours (offline-only)")]
    assert offline == [next(ln for ln in rows if ln.startswith("| Ours (offline-only) | 1 | **90**"))]
    # under the current defaults, average is a departure of its own
    _results(runs, "qcfql-offline", "WindowInstall-B-v0", 1, 0.2, operator="average")
    t3 = build(runs, tmp_path / "out2", figures=False)["table3.md"]
    assert "- Variant 1: `qcfql-offline` with `operator=\"average\"`.\n" in t3
