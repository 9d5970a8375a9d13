"""``bench tables``: the paper's Tables 2-7 and Figs. 10/11, regenerated from raw run files.

Inputs are only the raw files ``bench run`` / ``bench sweep`` wrote under a runs root:
``<env>/<run>/results.json`` of training cells and ``<ood env>/<run>.json`` (``bench eval``
output) of Table 7's evaluation-only cells, whose training cell is ``<env>/<run>``. Cells are
grouped into table rows by what was run (method, h, agent-config overrides, operator profile,
observation track, profile, evaluation seed set, M); within a row the seeds are the
samples, so a cell never mixes the privileged-state and the pixel track: each
row names its track where it differs from the table's usual one. Per cell we print our mean
over seeds with a 95 % bootstrap interval across seeds and the paper's number beside it
(:file:`paper_tables.csv`, transcribed from the paper), per row n, and below each table every
seed's values in a collapsed block.

The interval is the percentile bootstrap over seeds (10,000 resamples, fixed generator, so the
tables are byte-for-byte reproducible) from ``scipy.stats.bootstrap``. This is rliable's
stratified bootstrap with each table cell as its own stratum (one task per cell, runs
resampled with replacement); we call scipy instead of rliable because rliable would add
pandas, statsmodels, arch and seaborn to the install for this one function. With fewer than
two seeds there is no interval ("-"); with 3 seeds the bootstrap has only 10 distinct
resamples, so read the interval as a range of what the seeds did. The interquartile mean
(``scipy.stats.trim_mean(x, 0.25)``) is added where a row has at least 5 seeds.

Outputs (all written atomically, only under ``--out`` and to ``--readme``): one Markdown page
per table (``table2.md`` ... ``table7.md``), ``tables.md`` (their list and the seeds
protocol), and ``fig10.png/.svg`` (setting A) and ``fig11.png/.svg`` (setting B): running
averages over the last 20 training episodes of success, cycle time and intervention rate
against online hours, mean and interval over seeds; ``budget.png/.svg``: what the budget buys,
the headline methods' success against simulated hours for every profile that has runs.
``index.md``, the Results section's
hand-written overview, is never written. The committed Results pages and the README's
headline are regenerated with::

    bench tables --runs leaderboard/runs --out docs/results --readme README.md --force
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from window_bench.harness.evaluation import atomic_write, atomic_write_text
from window_bench.harness.methods import METHODS, agent_class, get_preset
from window_bench.harness.results import DEFAULTS_REVISION, departures, revision_of
from window_bench.harness.seeds import seed_set_of
from window_bench.harness.tracks import get_track

PAPER_CSV = Path(__file__).with_name("paper_tables.csv")
SETTINGS = {"A": "WindowInstall-A-v0", "B": "WindowInstall-B-v0"}
PANELS = {"Panel40x40": "0.4x0.4", "Panel60x60": "0.6x0.6", "Panel60x40": "0.6x0.4"}
N_BOOT = 10_000
RATE_WINDOW = 20
STEPS_PER_HOUR = 36_000
STEP_S = 0.1
#: The caption's sentence on rows of an earlier revision of the defaults (harness/results.py).
REVISION_NOTES = {1: ("were run under revision 1 of the defaults (the `average` installer, "
                      "D_demo as executed, QC-FQL without the fine pose and grasp features and "
                      "action companding; [revisions](tables.md#revisions-of-the-defaults)); "
                      "each leaves the table when its method is re-run under the current ones."),
                  2: ("were run under revision 2 of the defaults (QC-FQL fine-tuned online at "
                      "Stage I's learning rate; [revisions](tables.md#revisions-of-the-defaults)); "
                      "each leaves the table when its method is re-run under the current ones.")}


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
    #: (simulated hours, success) of every checkpoint evaluation (development seeds)
    checkpoints: list = field(default_factory=list)


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
    defaults: int = DEFAULTS_REVISION   # the revision of the defaults it was run under

    def superseded_by(self, other: "RowKey") -> bool:
        """A row of earlier defaults whose method (same setting, h, run and panel) has a row
        under the current defaults: it leaves the tables."""
        return self.defaults < other.defaults == DEFAULTS_REVISION and \
            dataclasses.replace(self, overrides=(), defaults=0) == \
            dataclasses.replace(other, overrides=(), defaults=0)


def _final(r: dict) -> tuple[dict, str, int]:
    """The final evaluation of a results file, its seed set and M. Runs from before the
    seeds protocol have only the last checkpoint, measured on the development seeds."""
    fe = r.get("final_eval")
    if fe:
        return fe, fe["seed_set"], fe["episodes"]
    return r["checkpoints"][-1], seed_set_of(r["eval_seeds"][0]), r["final"]["episodes"]


def _overrides(r: dict) -> tuple:
    """A row's departures from the defaults of the revision it was run under: its agent-config
    overrides, the operator profile of its demonstrations and takeovers and the D_demo labels
    where they are not the revision's, and a final checkpoint chosen on the dev seeds (cells
    that differ in any never share a row)."""
    pairs = {**(r.get("agent_config_overrides") or {}), **departures(r)}
    if (r.get("final_eval") or {}).get("checkpoint", "last") != "last":
        pairs["final_checkpoint"] = r["final_eval"]["checkpoint"]
    return tuple(sorted((k, json.dumps(v)) for k, v in pairs.items()))


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
                     _overrides(r), r["profile"]["name"], seed_set, M, r.get("track", "state"),
                     defaults=revision_of(r))
        m = r["method"]
        rows[key].append(Sample(
            r["seed"], fe["success_rate"], fe.get("cycle_time_s"), fe.get("pr_S"),
            fe.get("pr_I_given_S"), fe.get("pr_T_given_I"),
            time_to_95_h=f.get("time_to_95_sim_hours") if m["online_updates"] else None,
            takeover_min=f.get("takeover_minutes"),
            online_h=f["sim_hours"] if (m["online_updates"] or m["warm_start"]) else None,
            path=str(rel), episodes=r.get("train_episodes") or [],
            checkpoints=[(c["env_steps"] / STEPS_PER_HOUR, c["success_rate"])
                         for c in r.get("checkpoints") or []]))
        for panel_id, panel in PANELS.items():
            ood = r["env_id"].replace("-v0", f"-{panel_id}-v0")
            ev_path = path.parent.parent.parent / ood / f"{path.parent.name}.json"   # beside
            if not ev_path.is_file():
                continue
            try:
                ev = check_evaluation(ev_path, ood, m["name"])
            except ValueError as e:
                _skip(e)
                continue
            ekey = RowKey(key.setting, key.method, key.h, key.overrides, key.profile,
                          ev["seed_set"], ev["episodes"], key.track, panel, key.defaults)
            rows[ekey].append(Sample(r["seed"], ev["success_rate"], ev.get("cycle_time_s"),
                                     ev.get("pr_S"), ev.get("pr_I_given_S"),
                                     ev.get("pr_T_given_I"),
                                     path=str(ev_path.relative_to(root))))
    return {k: sorted(v, key=lambda s: s.seed) for k, v in rows.items()
            if not any(k.superseded_by(o) for o in rows)}


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


def cell(values, scale: float = 1.0, digits: int = 0) -> str:
    """``mean [lo, hi]`` over seeds (and the IQM with >= 5 seeds); ``(k of n)`` where only k
    seeds have a value. The values of each seed are :func:`per_seed`'s."""
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
    if len(vals) < len(values):
        out += f" ({len(vals)} of {len(values)})"
    return out


def per_seed(values, scale: float = 1.0, digits: int = 0) -> str:
    """The values in seed order, "–" for a seed without one."""
    return " · ".join(_num(v, scale, digits) for v in values)


def _paper(p: dict | None, key: str, digits: int = 0) -> str:
    if p is None or p.get(key) is None:
        return "–"
    v = p[key]
    text = f"{v:.{digits}f}"
    if key == "final_success_pct" and p.get("wilson_lo") is not None:
        text += f" [{p['wilson_lo']:.0f}, {p['wilson_hi']:.0f}]"
    return text


# ---------------------------------------------------------------------------- tables
@dataclass(frozen=True)
class Metric:
    """One measured quantity: its column head, the Sample field that holds it, how it is
    printed, and its column of :file:`paper_tables.csv`."""

    head: str
    attr: str
    scale: float
    digits: int
    paper_key: str
    paper_digits: int


SUCCESS = Metric("Success %", "success", 100, 0, "final_success_pct", 0)
TIME_TO_95 = Metric("Time-to-95 h", "time_to_95_h", 1, 2, "time_to_95_h", 2)
CYCLE = Metric("Cycle time s", "cycle_s", 1, 1, "cycle_s", 1)
TAKEOVER = Metric("Takeover min", "takeover_min", 1, 1, "human_effort_min", 0)
STAGES = (Metric("Pr(S) %", "pr_S", 100, 1, "pr_S", 1),
          Metric("Pr(I&#124;S) %", "pr_I_given_S", 100, 1, "pr_I_given_S", 1),
          Metric("Pr(T&#124;I) %", "pr_T_given_I", 100, 1, "pr_T_given_I", 1))


def _values(metric: Metric, samples) -> list:
    return [getattr(s, metric.attr) for s in samples]


def _ours(metric: Metric, key: "RowKey", samples) -> str:
    values = _values(metric, samples)
    if metric is TIME_TO_95:
        m = METHODS.get(key.method)
        if m is None or not m.online_updates:
            return "–"                           # no online phase, nothing to reach
        if all(v is None for v in values):
            return "not reached"
    return cell(values, metric.scale, metric.digits)


def _label(key: RowKey) -> str:
    m = METHODS.get(key.method)
    return m.label if m else f"`{key.method}`"


def _order(key: RowKey):
    names = list(METHODS)
    return (names.index(key.method) if key.method in names else 99, key.h, key.overrides,
            key.track != "state", key.profile, key.seed_set != "test", key.M)


def _run(key: RowKey) -> tuple[str, str, str, int]:
    return key.track, key.profile, key.seed_set, key.M


class RowNames:
    """Short names for the rows of one table: the method's label (or h), "variant N" for a
    row with agent-config overrides (spelled out in :meth:`notes`), and only those parts of
    the run (track, profile, M, seed set) where the row differs from the table's usual run,
    which the caption states once. A development-seed row is always marked *dev*."""

    def __init__(self, keys):
        runs = [_run(k) for k in keys]
        # per field the most common value; a tie goes to the state track, the test seeds, the
        # larger M, then the first in sorted order
        prefer = (lambda t: t == "state", lambda p: 0, lambda s: s == "test", lambda M: M)
        self.usual = tuple(max(sorted(set(f)), key=lambda v: (f.count(v), like(v)))
                           for f, like in zip(zip(*runs), prefer)) if runs \
            else ("state", "", "test", 0)
        self.variants: dict[tuple, int] = {}
        for k in keys:
            if k.overrides:
                self.variants.setdefault((k.method, k.overrides), len(self.variants) + 1)

    def tags(self, key: RowKey, markdown: bool = True) -> list[str]:
        track, profile, seed_set, M = self.usual
        out = []
        if key.track != track:
            out.append(key.track)
        if key.profile != profile:
            out.append(f"{key.profile} profile")
        if key.M != M:
            out.append(f"M = {key.M}")
        if key.seed_set == "dev":
            out.append("*dev*" if markdown else "dev")
        elif key.seed_set != seed_set:
            out.append(key.seed_set)
        if key.defaults < DEFAULTS_REVISION:
            out.append(f"*defaults {key.defaults}*" if markdown else f"defaults {key.defaults}")
        return out

    def _name(self, first: str, key: RowKey, markdown: bool) -> str:
        n = self.variants.get((key.method, key.overrides))
        return ", ".join([first] + ([f"variant {n}"] if n else []) + self.tags(key, markdown))

    def method(self, key: RowKey, markdown: bool = True) -> str:
        label = _label(key)
        return self._name(label if markdown else label.strip("`"), key, markdown)

    def horizon(self, key: RowKey) -> str:
        return self._name(str(key.h), key, True)

    def notes(self) -> str:
        """One line per variant: its method, agent-config overrides and preset name."""
        lines = []
        for (method, overrides), n in self.variants.items():
            preset = _preset_of(overrides)
            lines.append(f"- Variant {n}: `{method}` with "
                         + ", ".join(f"`{a}={b}`" for a, b in overrides)
                         + (f" (the preset `{preset}`)" if preset else "") + ".")
        return "\n".join(lines)


def _preset_of(overrides: tuple) -> str | None:
    """The name of the agent preset whose overrides these are, if any."""
    from window_bench.harness.methods import PRESETS

    return next((name for name in sorted(PRESETS)
                 if _overrides({"agent_config_overrides": PRESETS.lookup(name)}) == overrides),
                None)


# (column head, the row's text in it)
METHOD_COLUMN = ("Method", RowNames.method)
H_COLUMN = ("h", RowNames.horizon)
# one column, so that on a phone the row's setting and panel stay in view together
OOD_COLUMNS = (("Setting, panel (m)", lambda names, k: f"{k.setting}, {k.panel}"), METHOD_COLUMN)


def _paper_row(paper, table: int):
    """The paper's row of ``table`` for a key; none for our variants (agent-config overrides)."""
    return lambda k: None if k.overrides else paper.get((table, k.setting, k.method, k.h,
                                                         k.panel))


def _markdown_table(head: list[str], body: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
                     + ["| " + " | ".join(cells) + " |" for cells in body])


def _comparison(keys, rows, names, columns, metrics, paper_of, with_n: bool) -> str:
    """One Markdown table: the row's name, n, then ours beside the paper's per metric."""
    head = [c for c, _ in columns] + (["n"] if with_n else [])
    for m in metrics:
        head += [m.head, "paper"]
    body = []
    for k in keys:
        cells = [name(names, k) for _, name in columns] + ([str(len(rows[k]))] if with_n else [])
        for m in metrics:
            cells += [_ours(m, k, rows[k]), _paper(paper_of(k), m.paper_key, m.paper_digits)]
        body.append(cells)
    return _markdown_table(head, body)


def _per_seed_block(keys, rows, names, columns, metrics) -> str:
    """Every seed's value of every metric, in a block the reader opens."""
    table = _markdown_table(
        [c for c, _ in columns] + ["seeds"] + [m.head for m in metrics],
        [[name(names, k) for _, name in columns] + [" · ".join(str(s.seed) for s in rows[k])]
         + [per_seed(_values(m, rows[k]), m.scale, m.digits) for m in metrics] for k in keys])
    return '??? info "Per-seed values, in seed order"\n\n' + \
        "\n".join("    " + line for line in table.splitlines())


def _render(keys, rows, columns, groups, paper_of) -> str:
    """A table's body: one table per group of metrics (the first with n), the variants'
    overrides, the caption, and every seed's values in a collapsed block."""
    names = RowNames(keys)
    out = []
    for i, (title, metrics) in enumerate(groups):
        out += ([f"**{title}**", ""] if title else []) + \
            [_comparison(keys, rows, names, columns, metrics, paper_of, with_n=i == 0), ""]
    if names.variants:
        out += [names.notes(), ""]
    out += [_caption(keys), "",
            _per_seed_block(keys, rows, names, columns, [m for _, g in groups for m in g])]
    return "\n".join(out)


def _caption(keys) -> str:
    """The usual run of the table's rows, and the profile, budget, track, M and seed sets of
    all of them."""
    from window_bench.harness.methods import PROFILES

    track, profile, seed_set, M = RowNames(keys).usual
    parts = [f"Unless a row says otherwise: `{track}` track, `{profile}` profile, final "
             f"evaluation with M = {M} on the "
             f"{'held-out test' if seed_set == 'test' else 'development'} seeds"]
    for prof in sorted({k.profile for k in keys}):
        p = PROFILES.get(prof)
        if p is not None:
            parts.append(f"`{prof}` profile: budget {p.budget_steps:,} env steps "
                         f"({p.budget_steps / STEPS_PER_HOUR:.2f} simulated h; the paper's is "
                         f"3.0 h), {p.offline_steps:,} offline updates, UTD {p.utd:g}, "
                         f"MLPs {'x'.join(map(str, p.hidden))}; time-to-95 from the checkpoint "
                         f"evaluations (M = {p.eval_episodes} on the development seeds every "
                         f"{p.checkpoint_every:,} env steps, the profile's M; only the final "
                         f"checkpoint gets the row's M)")
    parts.append("Observation tracks: " + "; ".join(
        f"`{t}` = {_track_description(t)}" for t in sorted({k.track for k in keys})))
    text = ". ".join(parts) + "."
    if any(k.seed_set == "dev" for k in keys):
        text += (" Rows marked *dev* were measured on the development seeds 100000… that our "
                 "QC-FQL choices were tuned on: optimistic by construction, not comparable "
                 "with test-seed rows.")
    for rev in sorted({k.defaults for k in keys} - {DEFAULTS_REVISION}):
        text += f" Rows marked *defaults {rev}* {REVISION_NOTES[rev]}"
    return text


def _group_rows(rows, setting: str, only=None, panel: str = "0.5x0.5"):
    keys = [k for k in rows if k.setting == setting and k.panel == panel
            and (only is None or only(k))]
    return sorted(keys, key=_order)


def _track_description(name: str) -> str:
    """What a table's note says of an observation track: the track's own description."""
    try:
        return get_track(name).description
    except ValueError:     # a track no longer registered: its name
        return name


def _mark(key: RowKey) -> str:
    return (f"{key.track}, {key.profile}, M = {key.M}"
            + (", *dev*" if key.seed_set == "dev" else ""))


def _default_h(key: RowKey) -> bool:
    return key.method in METHODS and key.h == METHODS[key.method].h


def _table_main(rows, paper, table: int, setting: str) -> tuple[str, list]:
    keys = _group_rows(rows, setting, lambda k: _default_h(k) or k.method not in METHODS)
    return _render(keys, rows, [METHOD_COLUMN], [(None, (SUCCESS, TIME_TO_95, CYCLE, TAKEOVER))],
                   _paper_row(paper, table)), keys


STAGEWISE = "Stage-wise outcomes of the same rows"


def _table4(rows, paper) -> tuple[str, list]:
    keys = _group_rows(rows, "B", _default_h)
    return _render(keys, rows, [METHOD_COLUMN], [(None, (SUCCESS, *STAGES))],
                   _paper_row(paper, 3)), keys


def _table_h(rows, paper, table: int, setting: str) -> tuple[str, list]:
    keys = sorted(_group_rows(rows, setting, lambda k: k.method == "qcfql-no-intervention"),
                  key=lambda k: (k.h, _order(k)))
    groups = [(None, (SUCCESS, CYCLE))] + ([(STAGEWISE, STAGES)] if setting == "B" else [])
    return _render(keys, rows, [H_COLUMN], groups, _paper_row(paper, table)), keys


def _table7(rows, paper) -> tuple[str, list]:
    keys = sorted((k for k in rows if k.panel != "0.5x0.5"),
                  key=lambda k: (k.setting, list(PANELS.values()).index(k.panel), _order(k)))
    return _render(keys, rows, list(OOD_COLUMNS), [(None, (SUCCESS, CYCLE)), (STAGEWISE, STAGES)],
                   _paper_row(paper, 7)), keys


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


def plot_curves(rows, setting: str, path_png: Path, path_svg: Path,
                names: RowNames | None = None) -> list[RowKey]:
    """Fig. 10 (A) / Fig. 11 (B): one line per row with training episodes, mean and interval
    over seeds, named as the table names it (``names``, the table's :class:`RowNames`)."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in _group_rows(rows, setting, _default_h) if any(s.episodes for s in rows[k])]
    names = names or RowNames(keys)
    matplotlib.rcParams["svg.hashsalt"] = "window-bench"
    # drawn near the width the page shows it at, so that its text reads at the body's size
    fig, axes = plt.subplots(1, 3, figsize=(9.6, 3.4 + 0.2 * -(-len(keys) // 2)),
                             layout="constrained")
    ylabels = ["success (%)", "cycle time of successes (s)", "intervention rate (%)"]
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
            axes[a].plot(x, scales[a] * mean, color=f"C{i % 10}", ls=["-", "--"][i // 10 % 2],
                         label=names.method(k, markdown=False))
            axes[a].fill_between(x, scales[a] * lo, scales[a] * hi, color=f"C{i % 10}", alpha=0.2)
    for a, name in enumerate(ylabels):
        axes[a].set_ylabel(name, fontsize=9.5)
        axes[a].set_xlabel("online hours (simulated)", fontsize=9.5)
        axes[a].tick_params(labelsize=8.5)
        axes[a].grid(alpha=0.3)
    if keys:
        fig.legend(*axes[0].get_legend_handles_labels(), fontsize=9.5, loc="outside lower center",
                   ncol=2, frameon=False)
    fig.suptitle(f"Experiment {setting}: running average over the last {RATE_WINDOW} training "
                 f"episodes, mean and 95 % bootstrap interval over seeds", fontsize=10)
    atomic_write(path_png, lambda f: fig.savefig(f, format="png", dpi=100,
                                                 metadata={"Software": None}))
    atomic_write(path_svg, lambda f: fig.savefig(f, format="svg", metadata={"Date": None}))
    plt.close(fig)
    return keys


#: The file name (without extension) of :func:`plot_budget`'s figure.
BUDGET_FIGURE = "budget"
#: The paper's interaction budget (simulated hours), where its final numbers are.
PAPER_HOURS = 3.0


def plot_budget(rows, path_png: Path, path_svg: Path, paper: dict | None = None
                ) -> list[RowKey]:
    """What the budget buys: for each headline method (state track, held-out final
    evaluation), success against simulated hours on A and on B, one line per profile (mean
    over seeds of the checkpoint evaluations on the development seeds) ending in its final
    success on the test seeds (a marker with the interval over seeds); the paper's final
    success at its 3.0 h as a star (``paper``: :func:`load_paper`)."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    profiles = sorted({k.profile for k in rows}, key=lambda p: (p != "cpu", p))
    styles = ["-", "--", ":", "-."]
    matplotlib.rcParams["svg.hashsalt"] = "window-bench"
    fig, axes = plt.subplots(1, 2, figsize=(9.6, 4.2), layout="constrained", sharey=True)
    drawn = []
    for ax, setting in zip(axes, ("A", "B")):
        for i, (label, method, ours_row) in enumerate(_headline_rows()):
            p = (paper or {}).get((2 if setting == "A" else 3, setting, method,
                                   METHODS[method].h, "0.5x0.5"))
            if p and ours_row(()) and p.get("final_success_pct") is not None:
                at = PAPER_HOURS if METHODS[method].online_updates else 0.0   # offline: 0 h
                ax.plot([at], [float(p["final_success_pct"])], color=f"C{i}",
                        marker="*", ms=10, mfc="none", ls="none")
            for j, profile in enumerate(profiles):
                keys = _headline_keys(rows, setting, method, ours_row, profile)
                if not keys:
                    continue
                ss = [s for s in rows[keys[0]] if s.checkpoints]
                if not ss:
                    continue
                drawn.append(keys[0])
                top = max(s.checkpoints[-1][0] for s in ss)
                x = np.unique(np.concatenate([[h for h, _ in s.checkpoints] for s in ss]))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    y = np.nanmean([np.interp(x, *zip(*s.checkpoints), right=np.nan)
                                    for s in ss], axis=0)
                name = label.replace("`", "") + ("" if profile == "cpu" else f", {profile}")
                ax.plot(x, 100 * y, color=f"C{i}", ls=styles[j % 4], lw=1.4,
                        label=name if setting == "A" else None)
                final = [s.success for s in rows[keys[0]]]
                ci = bootstrap_ci(final, n_boot=2000)
                mean = 100 * float(np.mean(final))
                err = None if ci is None else [[mean - 100 * ci[0]], [100 * ci[1] - mean]]
                ax.errorbar([top], [mean], yerr=err, color=f"C{i}", marker="o", ms=5,
                            capsize=3, ls="none")
        ax.set_title(f"Experiment {setting}", fontsize=10)
        ax.set_xlabel("online hours (simulated)", fontsize=9.5)
        ax.tick_params(labelsize=8.5)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success (%)", fontsize=9.5)
    if drawn:
        fig.legend(*axes[0].get_legend_handles_labels(), fontsize=9, loc="outside lower center",
                   ncol=3, frameon=False)
    fig.suptitle("What the budget buys. Lines: checkpoint success (development seeds, mean "
                 "over seeds; solid: cpu profile);\ndots: final success (test seeds, 95 % "
                 f"interval); stars: the paper ({PAPER_HOURS:.1f} h online; offline methods "
                 "at 0)", fontsize=9.5)
    atomic_write(path_png, lambda f: fig.savefig(f, format="png", dpi=100,
                                                 metadata={"Software": None}))
    atomic_write(path_svg, lambda f: fig.savefig(f, format="svg", metadata={"Date": None}))
    plt.close(fig)
    return drawn


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
How to read a cell: **mean over seeds** [95 % bootstrap interval across seeds] (the IQM added
from 5 seeds; *(k of n)* where only k seeds have a value, e.g. a cycle time needs a success);
every seed's own value is under *Per-seed values*. *n* is the number of seeds. A row's name
adds only what differs from the table's usual run, stated under the table: the observation
track (`state`: privileged state; `pixels`: the paper's two camera views and
proprioception), the profile, the final evaluation's M, *dev* for development seeds; a
*variant N* runs the agent-config overrides listed under the table and has no paper
number. Success and the stage-wise rates are measured on the final checkpoint with
interventions off; *not reached* means no checkpoint of any seed reached 95 % success.
*paper* is the paper's number (its Wilson interval where it gives one), from
`window_bench/harness/paper_tables.csv`."""

PROTOCOL = """\
What our protocol differs in: the budget and network sizes of each row's profile (the
paper's is the `paper` profile: 3.0 simulated h, 4 x 512 MLPs, UTD 2); the observation track
(the paper's agents see pixels; a `state` row observes the privileged state, an easier
task); our QC-FQL departures (noise z = 0 for acting, bootstrapping and distillation, policy
averaging, the flow prior on accepted episodes without takeover steps; see [the QC-FQL
page](../qcfql.md)); and the evaluation seeds: reported numbers use the held-out test seeds
(see [the seeds protocol](tables.md#the-evaluation-seeds-protocol))."""


def _page(table: int, body: str, keys: list, rows, root_label: str, figure: str | None) -> str:
    ref, title, setting = TITLES[table]
    out = ["---", "hide:", "  - toc", "---", "",     # the tables get the page's width
           f"# {ref}: {title}", "",
           f"Generated by `bench tables` from the raw run files under `{root_label}`. "
           "Do not edit by hand.", ""]
    if keys:
        out += [body, ""]
    else:
        out += ["No runs for this table yet: run its grid "
                f"(`bench sweep experiments/table{table}.toml`) and regenerate.", ""]
    if figure:
        out += [f"![{figure.replace('fig', 'Fig. ')}: training curves of setting {setting}]"
                f"({figure}.png)", "",
                f"*{figure.replace('fig', 'Fig. ')} (setting {setting}): success, cycle time of "
                f"the successes and intervention rate, running averages over the last "
                f"{RATE_WINDOW} training episodes against simulated online hours; mean and 95 % "
                f"bootstrap interval over each row's seeds, lines named as the rows above.* "
                f"[SVG]({figure}.svg)", ""]
    out += [COLUMNS, "", PROTOCOL, ""]
    if keys:
        variants = RowNames(keys).variants
        out += ['??? note "Raw files of this table"', ""]
        for k in keys:
            n = variants.get((k.method, k.overrides))
            out += [f"    - {k.method}, h = {k.h}, {_mark(k)}{f', variant {n}' if n else ''}: "
                    + ", ".join(f"`{root_label}/{s.path}`" for s in rows[k])]
        out.append("")
    return "\n".join(out)


#: The generated list of tables and the seeds protocol. The Results section's index.md is the
#: hand-written overview, which bench tables never writes.
TABLES_NAME = "tables.md"
TABLES_PAGE = """\
# Tables 2-7

Generated by `bench tables` from the raw run files under `{root}`. Do not edit by hand.
What they add up to, claim by claim: [Results](index.md).

Each page regenerates one of the paper's tables with the paper's numbers beside ours:

{links}

Every row is on one observation track: `state` is the **privileged state** (the 52-float
simulator state, including the panel's exact pose relative to the seat), `pixels` the
paper's observation (two 128 x 128 RGB views through a frozen ResNet-10 and 18
proprioceptive values, [the pixel track](../pixels.md)). Under each table its usual track,
profile and evaluation are stated once, and a row names what differs. The two tracks never
share a row, and the paper's numbers are pixel-track numbers.

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

## Revisions of the defaults

Each results file records the revision of the shipped defaults it was run under
(`defaults`), and a row's variant names only its departures from its own revision's defaults.

| revision | installer (`--operator`) | D_demo labels (`--demo-actions`) | QC-FQL's run config |
|---|---|---|---|
| 1 | `average` | `executed` | the paper's observation and action units |
| 2 | `attentive-flush` | `meant` | `fine_pose_mm=10 fine_pose_deg=2 grasp_mm=10 action_power=2` ([QC-FQL](../qcfql.md)) |
| 3 (current) | `attentive-flush` | `meant` | revision 2's and `online_lr=3e-5` ([why](diagnoses/online-decline-a.md)) |

A row of an earlier revision stays in a table, marked *defaults 1* (or *2*), until its method is
re-run under the current defaults; then it leaves the table (its raw files stay in git).

Runs: {n_runs} training runs and {n_evals} evaluation-only cells. How the grids behind these
tables are run (Ray, resuming, the Stage I cache) and what it measured: [Running the
grids](sweep.md).
"""


#: The README's headline rows: (label, method, agent-config overrides). The paper's QC-FQL is
#: the preset ``qcfql-as-published`` (window_bench/catalog.py), the row Table 2/3's grids run
#: beside our default.
HEADLINE_START, HEADLINE_END = "<!-- bench tables: headline -->", "<!-- /bench tables -->"


def _headline_rows():
    """(label, method, a test of a row's overrides). The paper's QC-FQL is the preset
    ``qcfql-as-published``: its entries outside the agent's ``RUN_DEFAULTS`` make it the
    paper's agent in every revision; the others turn off run defaults that later revisions
    added, so an earlier revision's row of it carries only some of those."""
    run_defaults = getattr(agent_class(METHODS["qcfql"].agent), "RUN_DEFAULTS", {})
    paper = {(k, json.dumps(v)) for k, v in get_preset("qcfql-as-published").items()}
    core = {(k, v) for k, v in paper if k not in run_defaults}
    return (("Ours (complete pipeline)", "qcfql", lambda o: o == ()),
            ("QC-FQL as published (`PAPER_AGENT`)", "qcfql", lambda o: core <= set(o) <= paper),
            ("Ours (offline-only)", "qcfql-offline", lambda o: o == ()),
            ("HIL-SERL", "hil-serl", lambda o: o == ()), ("ACT", "act", lambda o: o == ()),
            ("SAC", "sac", lambda o: o == ()))


def _headline_keys(rows, setting: str, method: str, ours_row, profile: str) -> list:
    """The rows of a headline method on ``setting`` (state track, test seeds, the standard
    panel, the method's own h, ``ours_row`` of their overrides), newest revision first."""
    return sorted((k for k in rows if (k.setting, k.method, k.track, k.profile, k.seed_set,
                                       k.panel) ==
                   (setting, method, "state", profile, "test", "0.5x0.5")
                   and k.h == METHODS[method].h and ours_row(k.overrides)),
                  key=lambda k: -k.defaults)


def headline(rows, paper, profile: str = "cpu") -> str:
    """The README's headline table: final success of the key rows on A and B, ours (test
    seeds, M = 100, mean [interval] over seeds, n) beside the paper's."""
    lines = [f"| method | A: ours (state, {profile}) | A: paper | B: ours (state, {profile}) "
             "| B: paper |",
             "|---|---|---|---|---|"]
    for label, method, ours_row in _headline_rows():
        cols = []
        for table, setting in ((2, "A"), (3, "B")):
            keys = _headline_keys(rows, setting, method, ours_row, profile)
            ss = rows[keys[0]] if keys else []
            old = f", defaults {keys[0].defaults}" if keys and keys[0].defaults < \
                DEFAULTS_REVISION else ""
            ours = (f"{cell([s.success for s in ss], 100)} (n = {len(ss)}{old})"
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
    files = [out / f"table{t}.md" for t in TITLES] + [out / TABLES_NAME]
    if figures:
        files += [out / f"{fig}.{ext}" for fig in ("fig10", "fig11", BUDGET_FIGURE)
                  for ext in ("png", "svg")]
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
            plot_curves(rows, TITLES[table][2], out / f"{fig}.png", out / f"{fig}.svg",
                        RowNames(keys))
        pages[f"table{table}.md"] = _page(table, body, keys, rows, label, fig if figures else None)
    links = "\n".join(f"- [{TITLES[t][0]}: {TITLES[t][1]}](table{t}.md)" for t in TITLES)
    n_evals = sum(len(v) for k, v in rows.items() if k.panel != "0.5x0.5")
    pages[TABLES_NAME] = TABLES_PAGE.format(root=label, links=links, n_evals=n_evals,
                                            n_runs=sum(len(v) for k, v in rows.items()
                                                       if k.panel == "0.5x0.5"))
    if figures:
        plot_budget(rows, out / f"{BUDGET_FIGURE}.png", out / f"{BUDGET_FIGURE}.svg", paper)
    for name, text in pages.items():
        atomic_write_text(out / name, text)
    if readme is not None:
        update_readme(readme, headline(rows, paper))
    return pages
