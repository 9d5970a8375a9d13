"""The JSON files ``bench tables``, ``bench leaderboard`` and ``bench sweep`` read, and how they
are read without trusting them.

* :func:`read_json`: a file over :data:`MAX_JSON_BYTES` is refused before it is read, and
  NaN, Infinity and numbers too large for a float are refused (Python's ``json`` accepts them).
* :func:`results_schema` (``bench run``'s ``results.json``: its final evaluation, checkpoint
  rows and training episodes) and :func:`evaluation_schema` (a ``bench eval`` summary, Table
  7's cells): types, rates in [0, 1], non-negative integer counts, ids from the registries, no
  path separator in anything that names a file or directory. :func:`check_counts` adds what
  a schema cannot say: successes <= episodes, success_rate = successes / episodes, the rate
  inside its Wilson interval, the seed range matching its seed set and M.
* :func:`md_text`: a string from a file, escaped for a Markdown table cell.

Every refusal is a one-line ``ValueError`` that names the file, the field and why.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

from window_bench.harness.files import MANIFEST, read_manifest, verify_files
from window_bench.harness.results import RESULTS_SCHEMA
from window_bench.harness.seeds import MAX_EPISODES, SEED_SETS, seed_set_of

#: Real results files are tens of kB and a ``bench eval`` summary with every row of M = 10,000
#: episodes about 3 MB; anything larger is not one of ours and is not read.
MAX_JSON_BYTES = 8 << 20
RUN_FILES = ("results.json", "checkpoints.csv", "learning_curve.png")
#: One directory or file name: no separator, never ``.``/``..`` (the first character).
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+=-]*$")
#: A method label as the registry writes them ("Ours (w/o warm-start)").
LABEL = r"^[A-Za-z0-9][A-Za-z0-9 ()/,.+'-]*$"
#: Identifier names of agent-config fields; no leading underscore, so no dunder.
FIELD_NAME = r"^[A-Za-z][A-Za-z0-9_]*$"
#: ``final_eval.policy``: a file of the run's own ``policies/``.
POLICY_FILE = r"^policies/[A-Za-z0-9_-]+\.safetensors$"
RATE_TOLERANCE = 1e-9


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def _finite_float(text: str) -> float:
    x = float(text)
    if not math.isfinite(x):
        raise ValueError(f"{text} overflows a float")
    return x


def read_json(path: str | os.PathLike, limit: int = MAX_JSON_BYTES):
    """The parsed JSON of ``path``: a regular file of at most ``limit`` bytes, strict JSON
    (no NaN or Infinity, every number finite); else a one-line ``ValueError``."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: not a regular file")
    if path.stat().st_size > limit:
        raise ValueError(f"{path}: {path.stat().st_size:,} bytes, over the {limit:,}-byte limit "
                         f"for a run file; not read")
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)        # a file that grew after the stat is cut off here
    except OSError as e:
        raise ValueError(f"{path}: cannot be read ({e.strerror})") from None
    if len(data) > limit:
        raise ValueError(f"{path}: over the {limit:,}-byte limit for a run file; not read")
    try:
        return json.loads(data.decode("utf-8"), parse_constant=_reject_constant,
                          parse_float=_finite_float)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{path}: not readable JSON ({msg})") from None


def md_text(value) -> str:
    """``value`` as text that stays inside one Markdown table cell and renders as itself:
    no HTML, code span, link or cell break."""
    text = " ".join(str(value).splitlines())
    for char, entity in (("&", "&amp;"), ("<", "&lt;"), (">", "&gt;"), ("|", "&#124;"),
                         ("`", "&#96;"), ("[", "&#91;"), ("]", "&#93;")):
        text = text.replace(char, entity)
    return text


# ---------------------------------------------------------------------------- schemas
def _opt(s: dict) -> dict:
    return {"anyOf": [s, {"type": "null"}]}


RATE = {"type": "number", "minimum": 0, "maximum": 1}
NONNEG = {"type": "number", "minimum": 0}
COUNT = {"type": "integer", "minimum": 0, "maximum": 10**15}   # k / n stays a float
INTERVAL = {"type": "array", "items": RATE, "minItems": 2, "maxItems": 2}
SEED_RANGE = {"type": "array", "items": COUNT, "minItems": 2, "maxItems": 2}


def _summary(required: list[str]) -> dict:
    """An evaluation's summary (``summarize_eval``): a checkpoint row, ``final_eval``, or a
    ``bench eval`` output."""
    return {"type": "object", "required": required, "properties": {
        "episodes": {"type": "integer", "minimum": 1, "maximum": MAX_EPISODES},
        "successes": COUNT, "success_rate": RATE, "wilson95": INTERVAL,
        "cycle_time_s": _opt(NONNEG), "pr_S": _opt(RATE), "pr_I_given_S": _opt(RATE),
        "pr_T_given_I": _opt(RATE),
        "failure_modes": {"type": "object", "propertyNames": {"pattern": FIELD_NAME},
                          "additionalProperties": COUNT},
        "episodes_with_commanded_release": COUNT, "episodes_with_grip_break": COUNT,
        "suction_lost_by": {"type": "object", "additionalProperties": COUNT},
        "seed_set": {"enum": list(SEED_SETS)}}}


def _with(schema: dict, **properties) -> dict:
    return {**schema, "properties": {**schema["properties"], **properties}}


def results_schema() -> dict:
    """JSON Schema of every ``results.json`` field ``bench tables`` / ``bench leaderboard``
    read."""
    import window_bench
    from window_bench.harness.methods import METHODS, PROFILES
    from window_bench.harness.results import FINAL_CHECKPOINTS, REVISION_DEFAULTS
    from window_bench.data.steplog import DEMO_ACTIONS
    from window_bench.installer.operators import OPERATORS
    from window_bench.harness.tracks import TRACKS

    commit = {"type": "object", "required": ["git_commit"], "properties": {
        "git_commit": {"type": "string", "pattern": r"^([0-9a-f]{7,40}(-dirty)?|unknown)$"}}}
    safe = {"type": "string", "pattern": SAFE_NAME.pattern}
    return {
        "type": "object",
        "required": ["schema_version", "method", "env_id", "profile", "seed", "final",
                     "checkpoints", "provenance"],
        "properties": {
            "schema_version": {"const": RESULTS_SCHEMA},
            "defaults": {"enum": list(REVISION_DEFAULTS)},
            "operator": {"enum": sorted(OPERATORS)},
            "demo_actions": {"enum": list(DEMO_ACTIONS)},
            "method": {"type": "object", "required": ["name", "label", "h", "online_updates",
                                                      "warm_start"],
                       "properties": {"name": {"enum": list(METHODS)},
                                      "label": {"type": "string", "pattern": LABEL,
                                                "maxLength": 80},
                                      "h": {"type": "integer", "minimum": 1, "maximum": 100},
                                      "online_updates": {"type": "boolean"},
                                      "warm_start": {"type": "boolean"}}},
            "env_id": {"enum": list(window_bench.ENV_IDS)},
            "profile": {"type": "object", "required": ["name"],
                        "properties": {"name": {"enum": list(PROFILES)}}},
            "seed": COUNT,
            "track": {"enum": list(TRACKS)},
            "agent_config_overrides": _opt({
                "type": "object", "propertyNames": {"pattern": FIELD_NAME},
                "additionalProperties": {"anyOf": [{"type": ["number", "boolean", "null"]}, safe,
                                                   {"type": "array", "items": {"anyOf": [
                                                       {"type": "number"}, safe]}}]}}),
            "final": {"type": "object",
                      "required": ["success_rate", "wilson95", "episodes", "takeover_minutes",
                                   "sim_hours", "wall_clock_s"],
                      "properties": {"success_rate": RATE, "wilson95": INTERVAL,
                                     "episodes": {"type": "integer", "minimum": 1},
                                     "cycle_time_s": _opt(NONNEG),
                                     "time_to_95_sim_hours": _opt(NONNEG),
                                     "takeover_minutes": NONNEG, "sim_hours": NONNEG,
                                     "wall_clock_s": NONNEG, "env_steps": COUNT}},
            "final_eval": _with(
                _summary(["seed_set", "episodes", "successes", "success_rate", "wilson95"]),
                seeds=SEED_RANGE, env_steps=COUNT, checkpoint={"enum": list(FINAL_CHECKPOINTS)},
                policy={"type": "string", "pattern": POLICY_FILE},
                policy_sha256={"type": "string", "pattern": r"^[0-9a-f]{64}$"}),
            "checkpoints": {"type": "array", "items": _with(
                _summary(["env_steps", "success_rate", "wilson95"]), env_steps=COUNT,
                sim_hours=NONNEG, wall_clock_s=NONNEG, takeover_minutes=NONNEG,
                train_episodes=COUNT, grad_steps=COUNT, train_success_rate=_opt(RATE),
                train_intervention_rate=_opt(RATE))},
            "train_episodes": {"type": "array", "items": {
                "type": "object", "required": ["steps", "success"],
                "properties": {"steps": {"type": "integer", "minimum": 1},
                               "success": {"type": "boolean"}, "takeover_steps": COUNT,
                               "takeovers": COUNT}}},
            "eval_seeds": SEED_RANGE,
            "provenance": commit,
            "provenance_start": _opt(commit),
        },
    }


def evaluation_schema() -> dict:
    """JSON Schema of a ``bench eval`` summary as Table 7 reads it (``<ood env>/<run>.json``)."""
    import window_bench
    from window_bench.harness.methods import METHODS

    return _with(_summary(["env_id", "seed_set", "episodes", "success_rate"]),
                 env_id={"enum": list(window_bench.ENV_IDS)}, method={"enum": list(METHODS)},
                 trained_env_steps=COUNT, eval_seeds=SEED_RANGE, env_kwargs={"type": "object"},
                 rows={"type": "array"})


def _validate(path, doc, schema: dict) -> None:
    import jsonschema

    err = jsonschema.exceptions.best_match(
        jsonschema.Draft202012Validator(schema).iter_errors(doc))
    if err is not None:
        where = ".".join(map(str, err.absolute_path)) or "(top level)"
        raise ValueError(f"{path}: {where}: {err.message}")


def check_counts(path, where: str, s: dict, seeds_key: str | None = None) -> None:
    """What the schema cannot say about an evaluation summary ``s`` (one-line ``ValueError``
    naming ``path`` and ``where``): its counts, rate, interval and seed range agree."""
    def fail(msg):
        raise ValueError(f"{path}: {where}: {msg}")

    n, k, rate = s.get("episodes"), s.get("successes"), s["success_rate"]
    if k is not None and n is not None:
        if k > n:
            fail(f"successes {k} > episodes {n}")
        if abs(rate - k / n) > RATE_TOLERANCE:
            fail(f"success_rate {rate} is not successes / episodes = {k}/{n}")
    if s.get("wilson95") is not None:
        lo, hi = s["wilson95"]
        # tolerant of rounding: files written before the fix hold 100/100's bound as 1 - 1e-16
        if not lo - RATE_TOLERANCE <= rate <= hi + RATE_TOLERANCE:
            fail(f"success_rate {rate} lies outside its wilson95 [{lo}, {hi}]")
    seeds = s.get(seeds_key) if seeds_key else None
    if seeds is not None and n is not None and "seed_set" in s:
        first, last = seeds
        try:
            seed_set = seed_set_of(first)
        except ValueError as e:
            fail(f"{seeds_key}: {e}")
        if seed_set != s["seed_set"] or last - first + 1 != n:
            fail(f"{seeds_key} {seeds} are not the {n} {s['seed_set']!r} seeds")


def check_results(path: str | os.PathLike) -> dict:
    """The parsed ``results.json`` at ``path`` if it passes :func:`results_schema`,
    :func:`check_counts` and its run's manifest; otherwise a one-line ``ValueError``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no results.json at {path} (is the run finished?)")
    if (path.parent / MANIFEST).is_file():
        verify_files(path.parent, [n for n in RUN_FILES if (path.parent / n).exists()],
                     read_manifest(path.parent))
    r = read_json(path)
    _validate(path, r, results_schema())
    check_counts(path, "final", r["final"])
    for i, c in enumerate(r["checkpoints"]):
        check_counts(path, f"checkpoints.{i}", c)
    if r.get("final_eval") is not None:
        check_counts(path, "final_eval", r["final_eval"], "seeds")
    else:   # a run from before the seeds protocol: its last checkpoint on the eval_seeds
        if not r["checkpoints"] or "eval_seeds" not in r:
            raise ValueError(f"{path}: no final_eval, and no checkpoints and eval_seeds to "
                             f"take the final evaluation from")
        try:
            seed_set_of(r["eval_seeds"][0])
        except ValueError as e:
            raise ValueError(f"{path}: eval_seeds: {e}") from None
    for i, e in enumerate(r.get("train_episodes") or []):
        if e.get("takeover_steps", 0) > e["steps"]:
            raise ValueError(f"{path}: train_episodes.{i}: takeover_steps "
                             f"{e['takeover_steps']} > steps {e['steps']}")
    return r


def check_evaluation(path: str | os.PathLike, env_id: str, method: str) -> dict:
    """The parsed ``bench eval`` summary at ``path`` if it is an evaluation of ``method`` on
    ``env_id`` that passes :func:`evaluation_schema` and :func:`check_counts`; otherwise a
    one-line ``ValueError``."""
    ev = read_json(path)
    _validate(path, ev, evaluation_schema())
    if ev["env_id"] != env_id:
        raise ValueError(f"{path}: env_id {ev['env_id']!r}, the file's directory is {env_id!r}")
    if ev.get("method", method) != method:
        raise ValueError(f"{path}: method {ev['method']!r}, its training cell's is {method!r}")
    if ev.get("env_kwargs"):
        raise ValueError(f"{path}: env_kwargs {ev['env_kwargs']}: an evaluation in a rebuilt "
                         f"scene (bench eval --clearance) is not a table entry")
    check_counts(path, "(top level)", ev, "eval_seeds")
    return ev
