"""``bench tables``: the paper's Tables 2-7 and Figs. 10/11, regenerated from raw run files.

Inputs are only the raw files ``bench run`` / ``bench sweep`` wrote under a runs root:
``<env>/<run>/results.json`` of training cells and ``<ood env>/<run>.json`` (``bench eval``
output) of Table 7's evaluation-only cells, whose training cell is ``<env>/<run>``. Cells are grouped into table rows by what was run (method,
h, agent-config overrides, observation track, profile, evaluation seed set, M); within a row the
seeds are the samples, so a cell never mixes the privileged-state and the pixel track: each
row's *run* column names its track. Per cell we print our mean over seeds with a 95 % bootstrap interval across seeds,
the per-seed values, n, and the paper's number beside it
(:file:`paper_tables.csv`, transcribed from the paper).

The interval is the percentile bootstrap over seeds (10,000 resamples, fixed generator, so the
tables are byte-for-byte reproducible) from ``scipy.stats.bootstrap``. This is rliable's
stratified bootstrap with each table cell as its own stratum (one task per cell, runs
resampled with replacement); we call scipy instead of rliable because rliable would add
pandas, statsmodels, arch and seaborn to the install for this one function. With fewer than
two seeds there is no interval ("-"); with 3 seeds the bootstrap has only 10 distinct
resamples, so read the interval as a range of what the seeds did. The interquartile mean
(``scipy.stats.trim_mean(x, 0.25)``) is added where a row has at least 5 seeds.

Outputs (all written atomically, only under ``--out`` and to ``--readme``): one Markdown page
per table (``table2.md`` ... ``table7.md``, ``index.md``), and ``fig10.png/.svg`` (setting A)
and ``fig11.png/.svg`` (setting B): running averages over the last 20 training episodes of
success, cycle time and intervention rate against online hours, mean and interval over seeds.
The committed Results pages and the README's headline are regenerated with::

    bench tables --runs leaderboard/runs --out docs/results --readme README.md --force
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from window_bench.harness.evaluation import atomic_write, atomic_write_text
from window_bench.harness.methods import METHODS
from window_bench.harness.seeds import seed_set_of
from window_bench.pixels.track import TRACK_LABELS

PAPER_CSV = Path(__file__).with_name("paper_tables.csv")
SETTINGS = {"A": "WindowInstall-A-v0", "B": "WindowInstall-B-v0"}
PANELS = {"Panel40x40": "0.4x0.4", "Panel60x60": "0.6x0.6", "Panel60x40": "0.6x0.4"}
N_BOOT = 10_000
RATE_WINDOW = 20
STEPS_PER_HOUR = 36_000
STEP_S = 0.1


# ---------------------------------------------------------------------------- raw files
@dataclass
class Sample:
    """One seed's numbers for one cell (a training run, or an evaluation of its policy)."""

    seed: int
    success: float
    cycle_s: float | None
    pr_S: float | None
    pr_I_given_S: float | None
    pr_T_given_I: float | None
    time_to_95_h: float | None = None
    takeover_min: float | None = None
    online_h: float | None = None
    path: str = ""
    episodes: list = field(default_factory=list)


@dataclass(frozen=True)
class RowKey:
    setting: str                 # "A" / "B"
    method: str
    h: int
    overrides: tuple
    profile: str
    seed_set: str
    M: int
    track: str
    panel: str = "0.5x0.5"


def _final(r: dict) -> tuple[dict, str, int]:
    """The final evaluation of a results file, its seed set and M. Runs from before the
    seeds protocol have only the last checkpoint, measured on the development seeds."""
    fe = r.get("final_eval")
    if fe:
        return fe, fe["seed_set"], fe["episodes"]
    return r["checkpoints"][-1], seed_set_of(r["eval_seeds"][0]), r["final"]["episodes"]


def _overrides(r: dict) -> tuple:
    return tuple(sorted((k, json.dumps(v)) for k, v in (r.get("agent_config_overrides") or {}).items()))


def _skip(e: Exception) -> None:
    """The leaderboard's rule: a bad file is named and skipped, never rendered."""
    print(f"warning: skipped: {e}", file=sys.stderr)


def load_runs(root: str | os.PathLike) -> dict[RowKey, list[Sample]]:
    """Every cell under ``root`` as ``{row: [one Sample per seed]}``; results files and
    evaluation summaries are checked (:mod:`window_bench.harness.schemas`) and a bad one is
    skipped with a warning."""
    from window_bench.harness.schemas import SAFE_NAME, check_evaluation, check_results

    root = Path(root)
    rows: dict[RowKey, list[Sample]] = defaultdict(list)
    setting_of = {v: k for k, v in SETTINGS.items()}
    for path in sorted(root.rglob("results.json")):
        rel = path.parent.relative_to(root)
        try:
            bad = [p for p in rel.parts if not SAFE_NAME.match(p)]
            if bad:     # the directory is printed in the table's list of raw files
                raise ValueError(f"{path}: directory name {bad[0]!r} is not one safe name")
            r = check_results(path)
        except (ValueError, FileNotFoundError) as e:
            _skip(e)
            continue
        if r["env_id"] not in setting_of:
            continue
        fe, seed_set, M = _final(r)
        f = r["final"]
        key = RowKey(setting_of[r["env_id"]], r["method"]["name"], r["method"]["h"],
                     _overrides(r), r["profile"]["name"], seed_set, M, r.get("track", "state"))
        m = r["method"]
        rows[key].append(Sample(
            r["seed"], fe["success_rate"], fe.get("cycle_time_s"), fe.get("pr_S"),
            fe.get("pr_I_given_S"), fe.get("pr_T_given_I"),
            time_to_95_h=f.get("time_to_95_sim_hours") if m["online_updates"] else None,
            takeover_min=f.get("takeover_minutes"),
            online_h=f["sim_hours"] if (m["online_updates"] or m["warm_start"]) else None,
            path=str(rel), episodes=r.get("train_episodes") or []))
        for panel_id, panel in PANELS.items():
            ood = r["env_id"].replace("-v0", f"-{panel_id}-v0")
            ev_path = root / ood / f"{path.parent.name}.json"
            if not ev_path.is_file():
                continue
            try:
                ev = check_evaluation(ev_path, ood, m["name"])
            except ValueError as e:
                _skip(e)
                continue
            ekey = RowKey(key.setting, key.method, key.h, key.overrides, key.profile,
                          ev["seed_set"], ev["episodes"], key.track, panel)
            rows[ekey].append(Sample(r["seed"], ev["success_rate"], ev.get("cycle_time_s"),
                                     ev.get("pr_S"), ev.get("pr_I_given_S"),
                                     ev.get("pr_T_given_I"),
                                     path=str(ev_path.relative_to(root))))
    return {k: sorted(v, key=lambda s: s.seed) for k, v in rows.items()}


def load_paper(path: str | os.PathLike = PAPER_CSV) -> dict[tuple, dict]:
    """``{(table, setting, method, h, panel): row}`` from the transcribed paper numbers."""
    lines = [ln.removeprefix("# ") for ln in Path(path).read_text().splitlines()
             if not ln.startswith("# ") or ln.startswith("# table,")]   # the header is "# table,..."
    out = {}
    for row in csv.DictReader(io.StringIO("\n".join(lines))):
        out[(int(row["table"]), row["setting"], row["method"], int(row["h"]), row["panel"])] = {
            k: (float(v) if v not in ("", None) else None) for k, v in row.items()
            if k not in ("table", "setting", "method", "h", "panel")}
    return out


# ---------------------------------------------------------------------------- statistics
def bootstrap_ci(values, n_boot: int = N_BOOT, seed: int = 0) -> tuple[float, float] | None:
    """95 % percentile bootstrap interval of the mean across seeds; None below 2 seeds."""
    from scipy.stats import bootstrap

    x = np.asarray([v for v in values if v is not None], dtype=float)
    if len(x) < 2:
        return None
    if np.all(x == x[0]):
        return float(x[0]), float(x[0])
    res = bootstrap((x,), np.mean, n_resamples=n_boot, confidence_level=0.95,
                    method="percentile", rng=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def iqm(values) -> float | None:
    from scipy.stats import trim_mean

    x = [v for v in values if v is not None]
    return float(trim_mean(x, 0.25)) if len(x) >= 5 else None


def _num(x, scale: float = 1.0, digits: int = 0) -> str:
    return "–" if x is None else f"{scale * x:.{digits}f}"


def cell(values, scale: float = 1.0, digits: int = 0, per_seed: bool = True) -> str:
    """``mean [lo, hi]`` over seeds, then the per-seed values (and IQM with >= 5 seeds)."""
    vals = [v for v in values if v is not None]
    if not vals:
        return "–"
    out = f"**{_num(float(np.mean(vals)), scale, digits)}**"
    ci = bootstrap_ci(vals)
    if ci is not None:
        out += f" [{_num(ci[0], scale, digits)}, {_num(ci[1], scale, digits)}]"
    q = iqm(vals)
    if q is not None:
        out += f" IQM {_num(q, scale, digits)}"
    if per_seed and len(values) > 1:
        out += "<br>" + " · ".join(_num(v, scale, digits) for v in values)
    if len(vals) < len(values):
        out += f" ({len(vals)} of {len(values)})"
    return out


def _paper(p: dict | None, key: str, digits: int = 0) -> str:
    if p is None or p.get(key) is None:
        return "–"
    v = p[key]
    text = f"{v:.{digits}f}"
    if key == "final_success_pct" and p.get("wilson_lo") is not None:
        text += f" [{p['wilson_lo']:.0f}, {p['wilson_hi']:.0f}]"
    return text


# ---------------------------------------------------------------------------- tables
def _label(key: RowKey) -> str:
    m = METHODS.get(key.method)
    text = f"{m.label if m else key.method} (`{key.method}`)"
    if key.overrides:
        text += "<br>" + ", ".join(f"{k}={v}" for k, v in key.overrides)
    return text


def _order(key: RowKey):
    names = list(METHODS)
    return (names.index(key.method) if key.method in names else 99, key.h, key.overrides,
            key.track != "state", key.profile, key.seed_set != "test", key.M)


def _caption(keys, rows) -> str:
    """Profile, budget, track, M and seed sets of the rows in a table."""
    from window_bench.harness.methods import PROFILES

    parts = []
    for prof in sorted({k.profile for k in keys}):
        p = PROFILES.get(prof)
        if p is not None:
            parts.append(f"`{prof}` profile: budget {p.budget_steps:,} env steps "
                         f"({p.budget_steps / STEPS_PER_HOUR:.2f} simulated h; the paper's is "
                         f"3.0 h), {p.offline_steps:,} offline updates, UTD {p.utd:g}, "
                         f"MLPs {'x'.join(map(str, p.hidden))}; time-to-95 from the checkpoint "
                         f"evaluations (M = {p.eval_episodes} on the development seeds every "
                         f"{p.checkpoint_every:,} env steps, the profile's M; only the final "
                         f"checkpoint gets the M of the *run* column)")
    sets = sorted({(k.seed_set, k.M) for k in keys})
    parts.append("final evaluation: " + "; ".join(
        f"M = {M} on the {'held-out test' if s == 'test' else 'development'} seeds"
        for s, M in sets))
    parts.append("observation track (the *run* column's first word): " + "; ".join(
        f"`{t}` = {TRACK_DESCRIPTIONS.get(t, t)}" for t in sorted({k.track for k in keys})))
    dev = [k for k in keys if k.seed_set == "dev"]
    text = ". ".join(parts) + "."
    if dev:
        text += (" Rows marked *dev* were measured on the development seeds 100000… that our "
                 "QC-FQL choices were tuned on: optimistic by construction, not comparable "
                 "with test-seed rows.")
    return text


def _group_rows(rows, setting: str, only=None, panel: str = "0.5x0.5"):
    keys = [k for k in rows if k.setting == setting and k.panel == panel
            and (only is None or only(k))]
    return sorted(keys, key=_order)


TRACK_DESCRIPTIONS = {
    "state": f"{TRACK_LABELS['state']} (the 52-float simulator state, with the panel's exact "
             "pose relative to the seat: not what the paper's agents observe)",
    "pixels": "the paper's observation: wrist and side RGB views (128 x 128) through the frozen "
              "ResNet-10, and 18 proprioceptive values (see [the pixel track](../pixels.md))"}


def _mark(key: RowKey) -> str:
    return (f"{key.track}, {key.profile}, M = {key.M}"
            + (", *dev*" if key.seed_set == "dev" else ""))


def _table_main(rows, paper, table: int, setting: str) -> tuple[str, list]:
    keys = _group_rows(rows, setting, lambda k: k.h == METHODS.get(k.method, k).h
                       if k.method in METHODS else True)
    head = ("| Method | run | n | Final success % (ours) | paper | Time-to-95 h (ours) | paper "
            "| Cycle time s (ours) | paper | Takeover min (ours) | paper |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for k in keys:
        ss = rows[k]
        p = paper.get((table, setting, k.method, k.h, "0.5x0.5")) if not k.overrides else None
        t95 = [s.time_to_95_h for s in ss]
        reached = sum(v is not None for v in t95)
        t95_text = ("–" if not METHODS.get(k.method) or not METHODS[k.method].online_updates
                    else cell(t95, digits=2) if reached else f"not reached (0 of {len(ss)})")
        lines.append(f"| {_label(k)} | {_mark(k)} | {len(ss)} | "
                     f"{cell([s.success for s in ss], 100)} | {_paper(p, 'final_success_pct')} | "
                     f"{t95_text} | {_paper(p, 'time_to_95_h', 2)} | "
                     f"{cell([s.cycle_s for s in ss], digits=1)} | {_paper(p, 'cycle_s', 1)} | "
                     f"{cell([s.takeover_min for s in ss], digits=1)} | "
                     f"{_paper(p, 'human_effort_min')} |")
    return "\n".join(lines), keys


def _stagewise_cols(ss, p) -> str:
    return (f"{cell([s.pr_S for s in ss], 100, 1)} | {_paper(p, 'pr_S', 1)} | "
            f"{cell([s.pr_I_given_S for s in ss], 100, 1)} | {_paper(p, 'pr_I_given_S', 1)} | "
            f"{cell([s.pr_T_given_I for s in ss], 100, 1)} | {_paper(p, 'pr_T_given_I', 1)}")


_STAGE_HEAD = "Pr(S) % (ours) | paper | Pr(I&#124;S) % (ours) | paper | Pr(T&#124;I) % (ours) | paper"


def _table4(rows, paper) -> tuple[str, list]:
    keys = _group_rows(rows, "B", lambda k: k.method in METHODS and k.h == METHODS[k.method].h)
    lines = [f"| Method | run | n | Success % (ours) | paper | {_STAGE_HEAD} |",
             "|---" * 10 + "|"]
    for k in keys:
        ss = rows[k]
        p = paper.get((3, "B", k.method, k.h, "0.5x0.5")) if not k.overrides else None
        lines.append(f"| {_label(k)} | {_mark(k)} | {len(ss)} | "
                     f"{cell([s.success for s in ss], 100)} | {_paper(p, 'final_success_pct')} | "
                     f"{_stagewise_cols(ss, p)} |")
    return "\n".join(lines), keys


def _table_h(rows, paper, table: int, setting: str) -> tuple[str, list]:
    keys = _group_rows(rows, setting, lambda k: k.method == "qcfql-no-intervention")
    stage = setting == "B"
    head = "| h | run | n | Success % (ours) | paper | Cycle time s (ours) | paper |"
    lines = [head + (f" {_STAGE_HEAD} |" if stage else ""),
             "|---" * (7 + 6 * stage) + "|"]
    for k in sorted(keys, key=lambda k: (k.h, _order(k))):
        ss = rows[k]
        p = paper.get((table, setting, k.method, k.h, "0.5x0.5")) if not k.overrides else None
        h = f"{k.h}" + ("<br>" + ", ".join(f"{a}={b}" for a, b in k.overrides) if k.overrides else "")
        lines.append(f"| {h} | {_mark(k)} | {len(ss)} | {cell([s.success for s in ss], 100)} | "
                     f"{_paper(p, 'final_success_pct')} | {cell([s.cycle_s for s in ss], digits=1)}"
                     f" | {_paper(p, 'cycle_s', 1)} |"
                     + (f" {_stagewise_cols(ss, p)} |" if stage else ""))
    return "\n".join(lines), keys


def _table7(rows, paper) -> tuple[str, list]:
    keys = sorted((k for k in rows if k.panel != "0.5x0.5"),
                  key=lambda k: (k.setting, list(PANELS.values()).index(k.panel), _order(k)))
    lines = [f"| Setting | Panel (m) | Method | run | n | Success % (ours) | paper | "
             f"Cycle time s (ours) | paper | {_STAGE_HEAD} |", "|---" * 15 + "|"]
    for k in keys:
        ss = rows[k]
        p = paper.get((7, k.setting, k.method, k.h, k.panel)) if not k.overrides else None
        lines.append(f"| {k.setting} | {k.panel} | {_label(k)} | {_mark(k)} | {len(ss)} | "
                     f"{cell([s.success for s in ss], 100)} | {_paper(p, 'final_success_pct')} | "
                     f"{cell([s.cycle_s for s in ss], digits=1)} | {_paper(p, 'cycle_s', 1)} | "
                     f"{_stagewise_cols(ss, p)} |")
    return "\n".join(lines), keys


# ---------------------------------------------------------------------------- figures
def running_curves(episodes: list[dict], grid_h: np.ndarray) -> np.ndarray:
    """(3, len(grid_h)): success, cycle time (s, successes) and intervention rate over the
    last ``RATE_WINDOW`` training episodes finished by each point of ``grid_h`` (hours)."""
    out = np.full((3, len(grid_h)), np.nan)
    if not episodes:
        return out
    steps = np.array([e["steps"] for e in episodes], dtype=float)
    ends = np.cumsum(steps) / STEPS_PER_HOUR
    succ = np.array([e["success"] for e in episodes], dtype=float)
    take = np.array([e.get("takeover_steps", 0) for e in episodes], dtype=float)
    for j, x in enumerate(grid_h):
        n = int(np.searchsorted(ends, x, side="right"))
        if n == 0:
            continue
        w = slice(max(0, n - RATE_WINDOW), n)
        out[0, j] = succ[w].mean()
        ok = succ[w] > 0
        out[1, j] = (steps[w][ok] * STEP_S).mean() if ok.any() else np.nan
        out[2, j] = take[w].sum() / steps[w].sum()
    return out


def _band(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds (axis 0) and the bootstrap interval at each point."""
    mean = np.nanmean(curves, axis=0)
    lo, hi = mean.copy(), mean.copy()
    for j in range(curves.shape[1]):
        ci = bootstrap_ci([v for v in curves[:, j] if np.isfinite(v)], n_boot=2000)
        if ci is not None:
            lo[j], hi[j] = ci
    return mean, lo, hi


def plot_curves(rows, setting: str, path_png: Path, path_svg: Path) -> list[RowKey]:
    """Fig. 10 (A) / Fig. 11 (B): one line per method, mean and interval over seeds."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in _group_rows(rows, setting, lambda k: k.method in METHODS
                                   and k.h == METHODS[k.method].h)
            if any(s.episodes for s in rows[k])]
    matplotlib.rcParams["svg.hashsalt"] = "window-bench"
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    names = ["success (%)", "cycle time of successes (s)", "intervention rate (%)"]
    scales = [100, 1, 100]
    for i, k in enumerate(keys):
        ss = [s for s in rows[k] if s.episodes]
        top = max(sum(e["steps"] for e in s.episodes) for s in ss) / STEPS_PER_HOUR
        x = np.linspace(0, top, 60)
        curves = np.stack([running_curves(s.episodes, x) for s in ss])
        for a in range(3):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN early points
                mean, lo, hi = _band(curves[:, a])
            label = (f"{METHODS[k.method].label}"
                     f"{''.join(f', {a}={b}' for a, b in k.overrides)} ({k.track}, {k.profile}, "
                     f"n={len(ss)}{', dev' if k.seed_set == 'dev' else ''})")
            axes[a].plot(x, scales[a] * mean, color=f"C{i}", label=label)
            axes[a].fill_between(x, scales[a] * lo, scales[a] * hi, color=f"C{i}", alpha=0.2)
    for a, name in enumerate(names):
        axes[a].set_ylabel(name)
        axes[a].set_xlabel("online interaction (simulated h)")
        axes[a].grid(alpha=0.3)
    if keys:
        fig.legend(*axes[0].get_legend_handles_labels(), fontsize=7, loc="lower center",
                   ncol=2, frameon=False)
    fig.suptitle(f"Experiment {setting}: running average over the last {RATE_WINDOW} training "
                 f"episodes, mean and 95 % bootstrap interval over seeds", fontsize=10)
    fig.tight_layout(rect=(0, 0.06 * -(-len(keys) // 2), 1, 1))
    atomic_write(path_png, lambda f: fig.savefig(f, format="png", dpi=100,
                                                 metadata={"Software": None}))
    atomic_write(path_svg, lambda f: fig.savefig(f, format="svg", metadata={"Date": None}))
    plt.close(fig)
    return keys


# ---------------------------------------------------------------------------- pages
TITLES = {
    2: ("Table 2", "Experiment A: sample efficiency and supervision burden", "A"),
    3: ("Table 3", "Experiment B: sample efficiency and supervision burden", "B"),
    4: ("Table 4", "Experiment B: stage-wise outcomes", "B"),
    5: ("Table 5", "Chunk-horizon sensitivity of Ours (w/o intervention), Experiment A", "A"),
    6: ("Table 6", "Chunk-horizon sensitivity of Ours (w/o intervention), Experiment B", "B"),
    7: ("Table 7", "Zero-shot out-of-distribution panels", None),
}

COLUMNS = """\
How to read a cell: **mean over seeds** [95 % bootstrap interval across seeds], then the
per-seed values in seed order (IQM added from 5 seeds). *n* is the number of seeds. *run*
names the observation track (`state`: privileged state; `pixels`: the paper's two camera
views and proprioception), the profile and the final evaluation's M. Success and the stage-wise rates are measured
on the final checkpoint with interventions off. *paper* is the paper's number (its Wilson
interval where it gives one), from `window_bench/harness/paper_tables.csv`; a row with agent-config
overrides is our variant and has no paper number."""

PROTOCOL = """\
What our protocol differs in: the budget and network sizes of the profile named in each
row (the paper's is the `paper` profile: 3.0 simulated h, 4 x 512 MLPs, UTD 2); the
observation track each row names (the paper's agents see pixels; a `state` row observes the
privileged state, an easier task); our QC-FQL departures (noise z = 0 for acting,
bootstrapping and distillation, policy averaging, the flow prior on accepted episodes without
takeover steps; see [the QC-FQL page](../qcfql.md)); and the evaluation seeds: reported numbers
use the held-out test seeds (see [Results](index.md))."""


def _page(table: int, body: str, keys: list, rows, root_label: str, figure: str | None) -> str:
    ref, title, _ = TITLES[table]
    out = ["---", "hide:", "  - toc", "---", "",     # the wide tables need the page's width
           f"# {ref}: {title}", "",
           f"Generated by `bench tables` from the raw run files under `{root_label}`. "
           "Do not edit by hand.", ""]
    if keys:
        out += [body, "", _caption(keys, rows), ""]
    else:
        out += ["No runs for this table yet: run its grid "
                f"(`bench sweep experiments/table{table}.toml`) and regenerate.", ""]
    if figure:
        out += [f"![{figure}]({figure}.png)", "",
                f"{figure.replace('fig', 'Fig. ')}: [SVG]({figure}.svg).", ""]
    out += [COLUMNS, "", PROTOCOL, ""]
    if keys:
        out += ["Raw files of this table:", ""]
        for k in keys:
            out += [f"- {k.method}, h = {k.h}, {_mark(k)}: " +
                    ", ".join(f"`{root_label}/{s.path}`" for s in rows[k])]
        out.append("")
    return "\n".join(out)


INDEX = """\
# Results

Generated by `bench tables` from the raw run files under `{root}`. Do not edit by hand.

Each page regenerates one of the paper's tables with the paper's numbers beside ours:

{links}

Every row names its observation track in its *run* column: `state` is the **privileged
state** (the 52-float simulator state, including the panel's exact pose relative to the
seat), `pixels` the paper's observation (two 128 x 128 RGB views through a frozen ResNet-10
and 18 proprioceptive values, [the pixel track](../pixels.md)). The two tracks never share a
row, and the paper's numbers are pixel-track numbers.

## The evaluation seeds protocol

Our QC-FQL's design choices were tuned on evaluation episodes seeded 100000, 100001, …
(the **development** seeds). A number measured there is optimistic by construction, so
reported numbers are measured on a disjoint **test** set, seeds 500000, 500001, …, that no
tuning run ever evaluated on (`window_bench/harness/seeds.py`). The rule:

- tuning and development (`bench run`'s checkpoint evaluations, `bench eval` by default) use
  the development seeds;
- every reported run evaluates its final checkpoint with M = 100 on the test seeds
  (`bench sweep` grids, `--final-seed-set test`), and Table 7's out-of-distribution cells do
  the same;
- nothing is ever chosen by looking at test-seed numbers: a design choice is made on the
  development seeds, and a change after a test number was published is a new row, not a
  retune of the old one;
- every results file says which set it used (`final_eval.seed_set`; files from before the
  protocol record only `eval_seeds`, which start at 100000: development seeds), and every
  table row says so too (*dev* marks development-seed rows).

Runs: {n_runs} training runs and {n_evals} evaluation-only cells. How the grids behind these
tables are run (Ray, resuming, the Stage I cache) and what it measured: [Running the
grids](sweep.md).
"""


#: The README's headline rows: (label, method, agent-config overrides). The paper's QC-FQL is
#: ``baselines.qcfql.PAPER_AGENT``, the row Table 2/3's grids run beside our default.
HEADLINE_START, HEADLINE_END = "<!-- bench tables: headline -->", "<!-- /bench tables -->"


def _headline_rows():
    from baselines.qcfql import PAPER_AGENT

    paper_agent = tuple(sorted((k, json.dumps(v)) for k, v in PAPER_AGENT.items()))
    return (("Ours (complete pipeline)", "qcfql", ()),
            ("QC-FQL as published (`PAPER_AGENT`)", "qcfql", paper_agent),
            ("Ours (offline-only)", "qcfql-offline", ()),
            ("HIL-SERL", "hil-serl", ()), ("ACT", "act", ()), ("SAC", "sac", ()))


def headline(rows, paper, profile: str = "cpu") -> str:
    """The README's headline table: final success of the key rows on A and B, ours (test
    seeds, M = 100, mean [interval] over seeds, n) beside the paper's."""
    lines = [f"| method | A: ours (state, {profile}) | A: paper | B: ours (state, {profile}) "
             "| B: paper |",
             "|---|---|---|---|---|"]
    for label, method, overrides in _headline_rows():
        cols = []
        for table, setting in ((2, "A"), (3, "B")):
            keys = [k for k in rows if (k.setting, k.method, k.overrides, k.track, k.profile,
                                        k.seed_set, k.panel) ==
                    (setting, method, overrides, "state", profile, "test", "0.5x0.5")
                    and k.h == METHODS[method].h]
            ss = rows[keys[0]] if keys else []
            ours = (f"{cell([s.success for s in ss], 100, per_seed=False)} (n = {len(ss)})"
                    if ss else "not run yet")
            p = paper.get((table, setting, method, METHODS[method].h, "0.5x0.5"))
            cols += [ours, _paper(p, "final_success_pct")]   # the paper ran one QC-FQL
        lines.append(f"| {label} | " + " | ".join(cols) + " |")
    return "\n".join(lines)


def update_readme(path: str | os.PathLike, text: str) -> bool:
    """Replace the block between the headline markers of ``path``; False (nothing written)
    where the file or its markers are missing."""
    path = Path(path)
    if not path.is_file():
        return False
    old = path.read_text()
    if HEADLINE_START not in old or HEADLINE_END not in old:
        return False
    head, rest = old.split(HEADLINE_START, 1)
    tail = rest.split(HEADLINE_END, 1)[1]
    new = f"{head}{HEADLINE_START}\n{text}\n{HEADLINE_END}{tail}"
    if new != old:
        atomic_write_text(path, new)
    return True


def outputs(out: str | os.PathLike, figures: bool = True,
            readme: str | os.PathLike | None = None) -> list[Path]:
    """Every file :func:`build` writes, and nothing else (``bench tables`` refuses to
    overwrite them without ``--force``)."""
    out = Path(out)
    files = [out / f"table{t}.md" for t in TITLES] + [out / "index.md"]
    if figures:
        files += [out / f"{fig}.{ext}" for fig in ("fig10", "fig11") for ext in ("png", "svg")]
    return files + ([Path(readme)] if readme is not None else [])


def build(root: str | os.PathLike, out: str | os.PathLike, figures: bool = True,
          readme: str | os.PathLike | None = None) -> dict[str, str]:
    """Regenerate every page (and figure) from ``root`` into ``out``, and the headline block
    of ``readme`` when given; returns ``{file name: text}``. It writes :func:`outputs` only."""
    root, out = Path(root), Path(out)
    rows = load_runs(root)
    paper = load_paper()
    label = root.as_posix()
    pages = {}
    specs = {2: (_table_main(rows, paper, 2, "A"), "fig10"),
             3: (_table_main(rows, paper, 3, "B"), "fig11"),
             4: (_table4(rows, paper), None),
             5: (_table_h(rows, paper, 5, "A"), None),
             6: (_table_h(rows, paper, 6, "B"), None),
             7: (_table7(rows, paper), None)}
    for table, ((body, keys), fig) in specs.items():
        if fig and figures:
            plot_curves(rows, TITLES[table][2], out / f"{fig}.png", out / f"{fig}.svg")
        pages[f"table{table}.md"] = _page(table, body, keys, rows, label, fig if figures else None)
    links = "\n".join(f"- [{TITLES[t][0]}: {TITLES[t][1]}](table{t}.md)" for t in TITLES)
    n_evals = sum(len(v) for k, v in rows.items() if k.panel != "0.5x0.5")
    pages["index.md"] = INDEX.format(root=label, links=links, n_evals=n_evals,
                                     n_runs=sum(len(v) for k, v in rows.items()
                                                if k.panel == "0.5x0.5"))
    for name, text in pages.items():
        atomic_write_text(out / name, text)
    if readme is not None:
        update_readme(readme, headline(rows, paper))
    return pages
