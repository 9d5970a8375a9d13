"""The leaderboard: tables regenerated from raw run files, never typed by hand.

``bench leaderboard`` reads every ``results.json`` under ``leaderboard/runs`` (copied there
from ``bench run`` output directories with :func:`add_run`), checks it, prints the table and
writes it only where told (``--readme leaderboard/README.md --snippet
docs/snippets/leaderboard.md --force`` regenerates the committed ones): one row per run in
the layout of the paper's Tables 2 and 3, led by the run's observation track (``state``: the
privileged state; ``pixels``: the paper's camera views; runs of different tracks are sorted
apart and never share a directory name) (final success with its Wilson interval, online interaction
time, time-to-95, cycle time, takeover minutes) plus the profile and the compute wall clock,
so that a ``cpu``-profile number is never mistaken for a ``paper`` one.

Nothing is copied or tabulated before it is checked: :func:`check_results`
(:mod:`window_bench.harness.schemas`) validates a ``results.json`` against
:func:`results_schema` (types, rates in [0, 1], counts that agree, method, env and profile ids
from the registries, no path separators in anything that names a directory, a size cap) and
the run's ``manifest.json`` sha256 when the run has one. :func:`build` skips (and reports) a
bad file in ``root`` instead of failing on it.
"""

from __future__ import annotations

import json
import re
import os
import shutil
import sys
from pathlib import Path

from window_bench.harness.evaluation import atomic_write_text
from window_bench.harness.files import MANIFEST, read_manifest
from window_bench.harness.methods import METHODS
from window_bench.harness.tracks import DEFAULT_TRACK
from window_bench.harness.results import DEFAULTS_REVISION, departures, revision_of
from window_bench.harness.schemas import RUN_FILES, SAFE_NAME, check_results, md_text, \
    results_schema  # noqa: F401  (results_schema: the leaderboard's schema, documented here)


def override_tag(items) -> str:
    """``-<key><value>`` for each agent-config override ``(key, value)``, in order; a list value
    joins its items with ``x`` (``-student_hidden512x512``), so that a run's name stays one
    safe directory name. ``bench sweep`` names its cells with the same tags."""
    return "".join(f"-{k}{'x'.join(map(str, v)) if isinstance(v, (list, tuple)) else v}"
                   for k, v in items)


def _own_h(results: dict) -> int | None:
    """The run's chunk horizon where it is not its method's (Tables 5/6), else None."""
    m = results["method"]
    default = METHODS[m["name"]].h if m["name"] in METHODS else None
    return m["h"] if default is not None and m.get("h", default) != default else None


def _pose_readout(results: dict) -> str | None:
    """The first 12 hex digits of the pose read-out a pixel run's agents saw, or None."""
    readout = (results.get("encoder") or {}).get("pose_readout")
    sha = readout.get("sha256") if isinstance(readout, dict) else None
    return sha[:12] if isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha) else None


def _operator(results: dict) -> str | None:
    """The run's operator profile where it is not its revision's default, else None."""
    return departures(results).get("operator")


def run_dest(results: dict, root: str | os.PathLike) -> Path:
    """``root/<env>/<method>[-h<h>]<overrides>[-<track>][-readout<sha>][-<operator>]
    [-best-dev][-<demo actions>]-<profile>-s<seed>``, checked to stay inside ``root``: a run with another
    chunk horizon, track, pose read-out, operator profile, final checkpoint or demo actions
    never lands on
    the default run of the same method and seed (named as ``bench sweep`` names its cells)."""
    method = results["method"]["name"]
    h, operator = _own_h(results), _operator(results)
    tag = "" if h is None else f"-h{h}"
    tag += override_tag((results.get("agent_config_overrides") or {}).items())
    if _track(results) != DEFAULT_TRACK:
        tag += f"-{_track(results)}"
    if _pose_readout(results) is not None:
        tag += f"-readout{_pose_readout(results)[:8]}"
    if operator is not None:
        tag += f"-{operator}"
    choice = (results.get("final_eval") or {}).get("checkpoint", "last")
    tag += "" if choice == "last" else f"-{choice}"     # --final-checkpoint best-dev
    demo = departures(results).get("demo_actions")                      # --demo-actions
    tag += "" if demo is None else f"-{demo}"
    name = f"{method}{tag}-{results['profile']['name']}-s{results['seed']}"
    dest = Path(root) / results["env_id"] / name
    if not SAFE_NAME.match(name) or not dest.resolve().is_relative_to(Path(root).resolve()):
        raise ValueError(f"leaderboard entry name {name!r} is not one safe directory name")
    return dest


def add_run(run_dir: str | os.PathLike, root: str | os.PathLike = "leaderboard/runs") -> Path:
    """Copy a finished run's raw files into ``root/<env>/<method>-<profile>-s<seed>`` (after
    :func:`check_results`), with a manifest of what was copied: the files of
    :data:`RUN_FILES` and, where the run has one, the final evaluation's policy (the acting
    weights behind its number; :func:`check_results` holds its name to
    ``policies/<name>.safetensors``; its sha256 must be the one the results and the run's
    manifest record, else ``ValueError``)."""
    from window_bench.harness.files import sha256_file, verify_files

    run_dir = Path(run_dir)
    results = check_results(run_dir / "results.json")
    dest = run_dest(results, root)
    source = read_manifest(run_dir) if (run_dir / MANIFEST).is_file() else None
    names = [n for n in RUN_FILES if (run_dir / n).exists()]
    final = results.get("final_eval") or {}
    policy = final.get("policy")
    if policy is not None and source is not None and (run_dir / policy).is_file():
        verify_files(run_dir, [policy], source)
        if sha256_file(run_dir / policy) != final.get("policy_sha256"):
            raise ValueError(f"{run_dir / policy}: sha256 differs from final_eval.policy_sha256 "
                             f"in {run_dir / 'results.json'}")
        names.append(policy)
    dest.mkdir(parents=True, exist_ok=True)
    for name in names:
        (dest / name).parent.mkdir(exist_ok=True)
        tmp = dest / (name + ".tmp")
        shutil.copyfile(run_dir / name, tmp)
        os.replace(tmp, dest / name)
    if source is not None:
        atomic_write_text(dest / MANIFEST, json.dumps(
            {**source, "files": {n: source["files"][n] for n in names}}, indent=1,
            sort_keys=True))
    return dest


def _track(results: dict) -> str:
    """The run's observation track; results files from before the setting are ``state``."""
    return results.get("track", DEFAULT_TRACK)


def _pct(x) -> str:
    return "–" if x is None else f"{100 * x:.0f}"


def table(results: list[dict]) -> str:
    """Two tables that each fit a 1280 px page: the results (nine narrow columns; the final
    success comes from the results' final evaluation, with its M and seed set), then where and
    when each run was measured. Runs from before the seeds protocol were evaluated on the
    development seeds (``dev``)."""
    from window_bench.harness.seeds import seed_set_of

    order = {name: i for i, name in enumerate(METHODS)}
    rows = sorted(results, key=lambda r: (_track(r) != DEFAULT_TRACK, r["env_id"],
                                         r["profile"]["name"],
                                         order.get(r["method"]["name"], 99), r["seed"]))
    lines = ["| track ³ | env | method | profile | seed | final success (%) [95 % Wilson] | "
             "M, seeds ² | time-to-95 (sim. h) | cycle time (s) | takeover (min) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    runs = ["| track ³ | env | method | profile | seed | online interaction (sim. h) | "
            "wall clock (h) | commit ¹ |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        f, m = r["final"], r["method"]
        fe = r.get("final_eval") or {**f, "seed_set": seed_set_of(r["eval_seeds"][0])}
        lo, hi = fe["wilson95"]
        online = f["sim_hours"] if m["online_updates"] or m["warm_start"] else None
        t95 = f.get("time_to_95_sim_hours")
        cyc = fe.get("cycle_time_s")
        h = "" if _own_h(r) is None else f", h={_own_h(r)}"
        extra = "".join(f", {k}={v}" for k, v in (r.get("agent_config_overrides") or {}).items())
        if _operator(r) is not None:
            extra += f", operator {md_text(_operator(r))}"
        demo = departures(r).get("demo_actions")
        if demo is not None:
            extra += f", {md_text(demo)} demo actions"
        if _pose_readout(r) is not None:
            extra += f", pose read-out {_pose_readout(r)}"
        if revision_of(r) != DEFAULTS_REVISION:     # as the tables mark it
            extra += f", *defaults {revision_of(r)}*"
        who = (f"| {_track(r)} | {r['env_id']} | {md_text(m['label'])} (`{m['name']}`{h}"
               f"{extra}) | {r['profile']['name']} | {r['seed']} |")
        lines.append(
            f"{who} {_pct(fe['success_rate'])} [{_pct(lo)}, {_pct(hi)}] | "
            f"{fe['episodes']}, {fe['seed_set']} | {'–' if t95 is None else f'{t95:.2f}'} | "
            f"{'–' if cyc is None else f'{cyc:.1f}'} | {f['takeover_minutes']:.1f} |")
        runs.append(
            f"{who} {'–' if online is None else f'{online:.2f}'} | "
            f"{f['wall_clock_s'] / 3600:.2f} | "
            f"{(r.get('provenance_start') or r['provenance'])['git_commit'][:12]} |")
    return "\n".join(lines) + "\n\nWhere and when each run was measured:\n\n" + "\n".join(runs)


def build(root: str | os.PathLike = "leaderboard/runs", readme: str | os.PathLike | None = None,
          snippet: str | os.PathLike | None = None) -> str:
    """The table of the runs under ``root``, also written to ``readme`` (the page) and
    ``snippet`` (the table alone, for the docs) where given; returns the table."""
    results = []
    for path in sorted(Path(root).rglob("results.json")):
        try:
            results.append(check_results(path))
        except (ValueError, FileNotFoundError) as e:   # RunFileError is a ValueError
            print(f"skipped {e}", file=sys.stderr)
    body = (table(results) + "\n\n¹ The commit the run started on; for runs that predate "
            "that record, the commit that wrote their results.\n"
            "² M rollouts on the final checkpoint, interventions off, on the `dev` seeds "
            "(100000…, the seeds our QC-FQL choices were tuned on: optimistic by "
            "construction) or the held-out `test` seeds (500000…); see "
            "`window_bench/harness/seeds.py`.\n"
            f"*defaults N*: run under revision N of the shipped defaults (now "
            f"{DEFAULTS_REVISION}); a run's options name only its departures from its own "
            "revision's defaults (docs/results/tables.md, revisions of the defaults).\n"
            "³ Observation track: `state` = privileged state (the 52-float simulator state, "
            "with the panel's exact pose relative to the seat); `pixels` = the paper's wrist "
            "and side RGB views through a frozen ResNet-10 plus 18 proprioceptive values; "
            "`pixels-seat` = the same with two cameras on the opening's corners in place of "
            "the wrist and side views (docs/pixels.md).") if results else "No runs yet."
    if snippet is not None:
        atomic_write_text(snippet, body + "\n")
    if readme is not None:
        atomic_write_text(readme, "# Leaderboard\n\n"
                          "Generated by `bench leaderboard` from the raw run files under "
                          f"`{Path(root).as_posix()}/` (each: `results.json`, `checkpoints.csv`, "
                          "`learning_curve.png`, exactly as `bench run` wrote them, and the final "
                          "policy). Do not "
                          "edit by hand.\n\n" + body + "\n\n"
                          "Success is over M autonomous rollouts with interventions off, "
                          "on the final checkpoint. Online interaction "
                          "includes the warm start; the paper's budget is 3.0 simulated "
                          "hours (`paper` profile). `cpu`-profile runs use the reductions "
                          "listed in each results file.\n")
    return body
