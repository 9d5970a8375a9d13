"""``bench``: the command line of window-bench.

    bench install   --env WindowInstall-A-v0 --episodes 3      # scripted installer, verbose
    bench calibrate --env WindowInstall-A-v0 --episodes 100    # difficulty calibration
    bench demos     --env WindowInstall-A-v0 --n 50 --out data # human-like demonstrations
    bench supervise --env WindowInstall-A-v0 --controller random --operator novice
    bench teleop    --env WindowInstall-A-v0 --record demos    # a person at the keyboard
    bench methods                                              # Table 1 from the registry
    bench run --method qcfql --env WindowInstall-A-v0 --profile smoke --seed 0 --out runs/x
    bench eval runs/x/policies/step_0000400.safetensors --episodes 20
    bench leaderboard --add runs/x                             # tables from raw run files
    bench sweep experiments/table2.toml --out leaderboard/runs # a grid of runs on Ray
    bench tables --runs leaderboard/runs --out results         # Tables 2-7, Figs. 10/11
    bench encoder train --out enc.safetensors                  # pixel track: in-domain backbone
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import textwrap
from pathlib import Path

from window_bench import cli_args as arg
from window_bench.harness.evaluation import atomic_write_text, evaluate, provenance, summarize
from window_bench.installer.scripted import CONTROLLERS



def _agent_config(preset: str | None, items: list[str] | None) -> dict:
    """The run's agent-config overrides: the preset's, then ``--agent-config`` on top."""
    from window_bench.harness.agent import parse_overrides
    from window_bench.harness.methods import get_preset

    return {**(dict(get_preset(preset)) if preset else {}), **parse_overrides(items)}

def _fmt_rate(s: dict) -> str:
    lo, hi = s["wilson95"]
    return f"{100 * s['success_rate']:.1f} % [{100 * lo:.1f}, {100 * hi:.1f}]"


def cmd_install(args) -> int:
    rows = evaluate(args.env, args.controller, args.episodes, seed=args.seed, progress=False)
    print(f"{args.controller} on {args.env}, seeds {args.seed}..{args.seed + args.episodes - 1}")
    print(f"{'seed':>5} {'success':>8} {'cycle s':>8} {'suction':>8} {'entered':>8} {'seated':>7}  failure")
    fmt = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    for r in rows:
        print(f"{r['seed']:>5} {str(r['success']):>8} {r['cycle_time_s']:>8.1f} "
              f"{fmt(r['t_suction_acquired']):>8} {fmt(r['t_insertion_entered']):>8} "
              f"{fmt(r['t_seated']):>7}  {r['failure_mode'] or ''}")
    s = summarize(rows)
    cyc = s["cycle_time_s_mean"]
    print(f"success {s['successes']}/{s['episodes']} = {_fmt_rate(s)} (95 % Wilson); "
          f"mean cycle time {'-' if cyc is None else f'{cyc:.1f} s'}")
    if args.out:
        atomic_write_text(args.out, json.dumps({"env_id": args.env, "controller": args.controller,
                                                "summary": s, "episodes": rows,
                                                "provenance": provenance()}, indent=1))
    return 0


def _plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from window_bench.envs.task import FAILURE_MODES
    envs = list(results)
    ctrls = sorted({c for e in envs for c in results[e]}, key=list(CONTROLLERS).index)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / len(ctrls)
    for i, c in enumerate(ctrls):
        xs, ys, err = [], [], [[], []]
        for j, e in enumerate(envs):
            if c not in results[e]:
                continue
            s = results[e][c]
            xs.append(j + i * width)
            ys.append(100 * s["success_rate"])
            err[0].append(max(0.0, 100 * (s["success_rate"] - s["wilson95"][0])))
            err[1].append(max(0.0, 100 * (s["wilson95"][1] - s["success_rate"])))
        axes[0].bar(xs, ys, width, yerr=err, capsize=3, label=c)
    axes[0].set_xticks([j + width * (len(ctrls) - 1) / 2 for j in range(len(envs))], envs, fontsize=8)
    axes[0].set_ylabel("success rate, % (95 % Wilson)")
    axes[0].set_ylim(0, 105)
    axes[0].legend(fontsize=8)
    labels, bottoms = [], None
    cols = [f"{e.replace('WindowInstall-', '').replace('-v0', '')}\n{c}" for e in envs for c in ctrls if c in results[e]]
    import numpy as np
    bottoms = np.zeros(len(cols))
    for mode in FAILURE_MODES:
        vals = np.array([results[e][c]["failure_modes"].get(mode, 0) / results[e][c]["episodes"] * 100
                         for e in envs for c in ctrls if c in results[e]])
        if vals.sum() == 0:
            continue
        axes[1].bar(range(len(cols)), vals, bottom=bottoms, label=mode)
        bottoms += vals
        labels.append(mode)
    axes[1].set_xticks(range(len(cols)), cols, fontsize=7)
    axes[1].set_ylabel("episodes, %")
    axes[1].set_title("failure modes", fontsize=9)
    if labels:
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def calibration_table(results: dict) -> str:
    lines = ["| env | controller | episodes | success (95 % Wilson) | mean cycle time | failure modes |",
             "|---|---|---|---|---|---|"]
    for e, per in results.items():
        for c, s in per.items():
            modes = ", ".join(f"{m} {k}" for m, k in s["failure_modes"].items()) or "-"
            cyc = "-" if s["cycle_time_s_mean"] is None else f"{s['cycle_time_s_mean']:.1f} s"
            lines.append(f"| {e} | {c} | {s['episodes']} | {_fmt_rate(s)} | {cyc} | {modes} |")
    return "\n".join(lines) + "\n"


def cmd_calibrate(args) -> int:
    from window_bench.harness.evaluation import read_rows

    out = Path(args.out)
    try:   # the rows a killed calibration left, all checked before any episode runs
        for env_id in args.env:
            for c in args.controllers:
                read_rows(out / f"{env_id}__{c}.jsonl")
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    results: dict = {}
    for env_id in args.env:
        results[env_id] = {}
        for c in args.controllers:
            rows = evaluate(env_id, c, args.episodes, seed=args.seed,
                            rows_path=out / f"{env_id}__{c}.jsonl")
            results[env_id][c] = summarize(rows)
    meta = {"episodes": args.episodes, "seed": args.seed, "provenance": provenance()}
    atomic_write_text(out / "calibration.json", json.dumps({"results": results, **meta}, indent=1))
    table = calibration_table(results)
    atomic_write_text(out / "calibration.md", table)
    _plot(results, out / "calibration.png")
    print(table)
    print(f"wrote {out / 'calibration.json'}, {out / 'calibration.md'}, {out / 'calibration.png'}")
    return 0


def cmd_demos(args) -> int:
    from window_bench.installer.demos import collect_demos

    try:
        s = collect_demos(args.env, args.n, args.out, operator=args.operator, seed=args.seed,
                          max_attempts=args.max_attempts, progress=True)
    except ValueError as e:   # bad sizes, or an existing dataset that cannot be read
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{s['kept']}/{s['attempts']} demonstrations succeeded "
          f"({100 * s['success_rate']:.0f} %) on {args.env}, operator {args.operator}, "
          f"seeds {args.seed}..{args.seed + s['attempts'] - 1}")
    print(f"episode length {s['episode_seconds_mean']:.1f} s mean "
          f"[{s['episode_seconds_min']:.1f}, {s['episode_seconds_max']:.1f}], "
          f"{s['recoveries_mean']:.1f} recoveries per demo; "
          f"{s['simulated_minutes_all_attempts']:.1f} simulated minutes, "
          f"{s['wall_clock_s']:.0f} s wall clock, {s['cpu_time_s']:.0f} s CPU")
    if s["failure_modes"]:
        print(f"discarded: {s['failure_modes']}")
    print(f"wrote Minari dataset {s['dataset_id']!r} under {args.out}")
    return 0 if s["kept"] == args.n else 1


def cmd_supervise(args) -> int:
    from window_bench.installer.demos import measure_supervision

    rows = []
    for op in args.operator:
        r = measure_supervision(args.env, args.controller, op, args.episodes, seed=args.seed,
                                h=args.h)
        rows.append(r)
    print("| operator | controller | episodes | successes | takeovers / ep | takeover min "
          "| takeover share | safety cues | coverage |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['operator']} | {r['controller']} | {r['episodes']} | {r['successes']} | "
              f"{r['takeovers_per_episode']:.1f} | {r['takeover_minutes']:.2f} | "
              f"{100 * r['takeover_fraction']:.0f} % | {r['safety_cues']} | "
              f"{r['coverage_interventions']} |")
    if args.out:
        atomic_write_text(args.out, json.dumps(rows, indent=1))
    return 0


def cmd_methods(args) -> int:
    from window_bench.harness.methods import PROFILES, methods_table

    print(methods_table())
    print()
    for p in PROFILES.values():
        print(f"profile {p.name}: budget {p.budget_steps} env steps, warm start {p.warm_steps}, "
              f"offline {p.offline_steps} updates, UTD {p.utd}, M = {p.eval_episodes} every "
              f"{p.checkpoint_every} steps, MLPs {'x'.join(map(str, p.hidden))}")
    return 0


def _chosen(final_eval: dict) -> str:
    if final_eval.get("checkpoint", "last") == "last":
        return ""
    return f" of the {final_eval['checkpoint']} checkpoint (env step {final_eval['env_steps']})"


def cmd_run(args) -> int:
    from window_bench.harness.files import RunFileError, check_unlocked

    try:   # before importing torch: a second writer stops at once
        check_unlocked(args.out)
    except RunFileError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from window_bench.harness.run import Run

    try:
        noise = None
        if args.acceptance_noise is not None:
            fp, fn, delay = args.acceptance_noise
            try:
                noise = {"false_positive_rate": float(fp), "false_negative_rate": float(fn),
                         "delay_steps": int(delay), "seed": args.seed}
            except ValueError:
                raise ValueError(f"--acceptance-noise {fp} {fn} {delay}: expected two rates "
                                 f"in [0, 1] and a delay in steps (an integer >= 0)") from None
        run = Run(args.method, args.env, args.profile, args.seed, args.out, resume=args.resume,
                  operator=args.operator, demos=args.demos, acceptance_noise=noise,
                  track=args.track, encoder_weights=args.encoder_weights,
                  agent_config=_agent_config(args.preset, args.agent_config), h=args.h,
                  final_episodes=args.final_episodes, final_seed_set=args.final_seed_set,
                  final_checkpoint=args.final_checkpoint,
                  stage1_cache=args.stage1_cache, eval_workers=args.eval_workers,
                  pixel_demos_cache=args.pixel_demos_cache, demo_actions=args.demo_actions)
    except (ValueError, FileExistsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        r = run.train()
    except RunFileError as e:   # a run file that fails its check when it is read
        print(f"error: {e}", file=sys.stderr)
        return 2
    f = {**r["final"], **{k: r["final_eval"][k] for k in ("success_rate", "wilson95", "episodes")}}
    lo, hi = f["wilson95"]
    t95 = f["time_to_95_sim_hours"]
    print(f"{args.method} on {args.env} ({args.profile}, seed {args.seed}): final success "
          f"{100 * f['success_rate']:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}] over "
          f"{f['episodes']} rollouts{_chosen(r['final_eval'])}; "
          f"time-to-95 {'-' if t95 is None else f'{t95:.2f} h'}; "
          f"takeover {f['takeover_minutes']:.1f} min; {f['sim_hours']:.2f} simulated h, "
          f"{f['wall_clock_s'] / 60:.1f} min wall clock")
    print(f"wrote {Path(args.out) / 'results.json'}, checkpoints.csv, learning_curve.png")
    return 0


def cmd_eval(args) -> int:
    from window_bench.harness.evaluation import evaluate_policy_file

    try:
        r = evaluate_policy_file(args.checkpoint, args.episodes, args.eval_workers,
                                 env_id=args.env, seed_set=args.seed_set, progress=True,
                                 clearance=None if args.clearance is None
                                 else args.clearance / 1000.0)
    except (FileNotFoundError, ValueError) as e:   # a missing, foreign or corrupt file
        print(f"error: {e}", file=sys.stderr)
        return 2
    lo, hi = r["wilson95"]
    at = f" at {1000 * r['env_kwargs']['clearance']:g} mm clearance" if r["env_kwargs"] else ""
    print(f"{r['method']} ({r['trained_env_steps']} env steps) on {r['env_id']}{at}: "
          f"{r['successes']}/{r['episodes']} = {100 * r['success_rate']:.0f} % "
          f"[{100 * lo:.0f}, {100 * hi:.0f}]; Pr(S) {r['pr_S']}, Pr(I|S) {r['pr_I_given_S']}, "
          f"Pr(T|I) {r['pr_T_given_I']}; failures {r['failure_modes']}")
    if args.out:
        atomic_write_text(args.out, json.dumps(r, indent=1))
    return 0


def _refuse_overwrite(paths, force: bool) -> None:
    """Outputs are never overwritten unless the user asks (``--force``)."""
    hit = None if force else next((p for p in paths if Path(p).exists()), None)
    if hit is not None:
        raise ValueError(f"{hit} exists; pass --force to overwrite it")


def _refuse_other_revision(dest, results: dict) -> None:
    """A run of one revision of the defaults never replaces a run of another under the same
    name (names depart from each run's own revision's defaults), not even with ``--force``."""
    from window_bench.harness.results import revision_of

    try:
        old = json.loads(Path(dest).read_text())
    except (OSError, ValueError):
        return   # nothing there, or not a results file: --force decides
    if isinstance(old, dict) and revision_of(old) != revision_of(results):
        raise ValueError(f"{dest} holds a run made under revision {revision_of(old)} of the "
                         f"defaults, the new run revision {revision_of(results)}; move it "
                         f"away first (e.g. to a defaults-{revision_of(old)}/ folder)")


def cmd_leaderboard(args) -> int:
    from window_bench.harness.files import check_out_dir
    from window_bench.harness.leaderboard import add_run, build, check_results, run_dest

    try:   # every run and every output is checked before anything is written
        if args.add:
            try:
                check_out_dir(args.root)
            except ValueError as e:
                raise ValueError(str(e).replace("--out ", "--root ", 1)) from None
        elif not Path(args.root).is_dir():
            raise ValueError(f"--root {args.root}: no such directory")
        adds = [check_results(Path(run_dir) / "results.json") for run_dir in args.add or []]
        dests = [run_dest(r, args.root) for r in adds]
        for results, dest in zip(adds, dests):   # --force replaces a run, never a revision's
            _refuse_other_revision(dest / "results.json", results)
        _refuse_overwrite([d / "results.json" for d in dests]
                          + [p for p in (args.readme, args.snippet) if p], args.force)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for run_dir in args.add or []:
        print(f"added {add_run(run_dir, args.root)}")
    print(build(args.root, readme=args.readme, snippet=args.snippet))
    return 0


def cmd_sweep(args) -> int:
    from window_bench.harness.sweep import GridError, Sweep, grid_report, load_grid, select

    if args.status:
        try:
            grid = select(load_grid(args.grid), args.only)
        except GridError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        rows = grid_report(grid, args.out)
        width = max(len(r["cell"]) for r in rows)
        for r in rows:
            print(f"{r['status']:<9} {r['cell']:<{width}}  {r['detail']}".rstrip())
        counts = collections.Counter(r["status"] for r in rows)
        print(f"grid {grid.name} under {args.out}: {len(rows)} cells; "
              + ", ".join(f"{k} {counts[k]}" for k in
                          ("done", "running", "partial", "new", "failed", "conflict")
                          if counts[k]))
        return 0
    from window_bench.harness.files import check_out_dir

    try:
        check_out_dir(args.out)
        sweep = Sweep(load_grid(args.grid), args.out, workers=args.workers,
                      address=args.address, progress=not args.no_progress,
                      stage1_cache=not args.no_stage1_cache, only=args.only)
    except (GridError, ValueError) as e:      # RunFileError (check_out_dir) is a ValueError
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        summary = sweep.run()
    except KeyboardInterrupt:
        print("interrupted: every cell is resumable; rerun the same command", file=sys.stderr)
        return 130
    cells = summary["cells"].values()
    failed = [name for name, c in summary["cells"].items() if c["status"] != "done"]
    print(f"grid {summary['grid']}: {len(cells) - len(failed)}/{len(cells)} cells done in "
          f"{summary['wall_clock_s'] / 60:.1f} min on {summary['workers']} worker(s)"
          + (f"; not done: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


def cmd_tables(args) -> int:
    from window_bench.harness.tables import HEADLINE_END, HEADLINE_START, build, outputs

    try:   # every output is checked before anything is read or written
        if not Path(args.runs).is_dir():
            raise ValueError(f"--runs {args.runs}: no such directory")
        if args.readme is not None:
            text = Path(args.readme).read_text() if Path(args.readme).is_file() else ""
            if HEADLINE_START not in text or HEADLINE_END not in text:
                raise ValueError(f"--readme {args.readme}: not a file with the headline "
                                 f"markers {HEADLINE_START} ... {HEADLINE_END}")
        _refuse_overwrite(outputs(args.out, not args.no_figures, args.readme), args.force)
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    pages = build(args.runs, args.out, figures=not args.no_figures, readme=args.readme)
    figures = "" if args.no_figures else ", fig10/fig11/budget .png/.svg"
    print(f"wrote {', '.join(sorted(pages))}{figures} under {args.out}")
    return 0


def cmd_video(args) -> int:
    from window_bench.gl import NoOpenGLError
    from window_bench.video import check_args, record

    try:
        check_args(args.cameras, args.size, args.fps, args.policy)
        if args.policy not in CONTROLLERS:   # a foreign or damaged file: before --out is made
            from window_bench.harness.evaluation import load_policy_file

            load_policy_file(args.policy)
        rows = record(args.env, args.policy, list(range(args.seed, args.seed + args.episodes)),
                      args.out, cameras=args.cameras, size=args.size, fps=args.fps)
    except (ValueError, OSError, NoOpenGLError) as e:   # OSError: e.g. a --policy name too long
        print(f"error: {e}", file=sys.stderr)              # to look up; as encoder train, teleop: 2
        return 2
    for r in rows:
        outcome = "seated" if r["success"] else r["failure_mode"]
        print(f"seed {r['seed']}: {outcome} after {r['steps']} steps -> "
              f"{Path(args.out) / r['file']} ({r['bytes'] / 1e6:.2f} MB)")
    return 0


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Every option's default in its help line (not for a required option, nor a default of
    None: the help says what happens then); descriptions kept as written."""

    def _get_help_string(self, action):
        if action.required or action.default is None:
            return action.help
        return super()._get_help_string(action)


class _Subcommands(argparse._SubParsersAction):
    """Subcommands whose ``--help`` opens with the line ``bench --help`` shows for them."""

    def add_parser(self, name, **kwargs):
        if kwargs.get("help") and "description" not in kwargs:
            text = kwargs["help"][0].upper() + kwargs["help"][1:]
            kwargs["description"] = textwrap.fill(text + ("" if text.endswith(".") else "."), 79)
        return super().add_parser(name, **kwargs)


class _Parser(argparse.ArgumentParser):
    """Bad input is one line on stderr and exit code 2 (argparse adds the whole usage)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register("action", "parsers", _Subcommands)

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _SubParser(_Parser):
    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)


ENV_HELP = "registered env id: WindowInstall-{A,B}[-Panel40x40|-Panel60x60|-Panel60x40]-v0"


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="bench", description=__doc__,
                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, parser_class=_SubParser)
    i = sub.add_parser("install", help="run a reference controller and print per-episode stages")
    i.add_argument("--env", type=arg.env_id, default="WindowInstall-A-v0", help=ENV_HELP)
    i.add_argument("--episodes", type=arg.positive, default=3, help="episodes (>= 1)")
    i.add_argument("--seed", type=arg.seed, default=0, help="first episode seed")
    i.add_argument("--controller", choices=sorted(CONTROLLERS), default="installer",
                   help="reference controller")
    arg.add_out_file(i, "also write the episodes and summary to this JSON file")
    i.set_defaults(func=cmd_install)
    c = sub.add_parser("calibrate", help="difficulty calibration: success and failure modes per controller")
    c.add_argument("--env", type=arg.env_id, nargs="+", default=["WindowInstall-A-v0", "WindowInstall-B-v0"],
                   help=ENV_HELP + "; one or more")
    c.add_argument("--controllers", nargs="+", choices=sorted(CONTROLLERS),
                   default=["installer", "straight_push", "random"], help="reference controllers")
    c.add_argument("--episodes", type=arg.positive, default=100, help="episodes per env and controller")
    c.add_argument("--seed", type=arg.seed, default=0, help="first episode seed")
    c.add_argument("--out", type=arg.out_dir, default="runs/calibration", help="results directory (resumes if present)")
    c.set_defaults(func=cmd_calibrate)
    from window_bench.data.steplog import DEFAULT_DEMO_ACTIONS, DEMO_ACTIONS
    from window_bench.installer.operators import DEFAULT_OPERATOR, OPERATORS

    d = sub.add_parser("demos", help="collect successful human-like demonstrations (Minari)")
    d.add_argument("--env", type=arg.env_id, default="WindowInstall-A-v0", help=ENV_HELP)
    d.add_argument("--n", type=arg.positive, default=50, help="successful demonstrations to keep")
    d.add_argument("--out", type=arg.out_dir, default="data", help="Minari datasets root (resumes if present)")
    d.add_argument("--operator", choices=sorted(OPERATORS), default=DEFAULT_OPERATOR,
                   help="operator profile of the demonstrator")
    d.add_argument("--seed", type=arg.seed, default=0, help="seed of the first attempt")
    d.add_argument("--max-attempts", type=arg.positive, default=None,
                   help="give up after this many episodes (None: 2 n)")
    d.set_defaults(func=cmd_demos)
    v = sub.add_parser("supervise", help="takeover counts and minutes of operator profiles "
                                         "supervising a reference controller")
    v.add_argument("--env", type=arg.env_id, default="WindowInstall-A-v0", help=ENV_HELP)
    v.add_argument("--controller", choices=sorted(CONTROLLERS), default="random",
                   help="the supervised reference controller")
    v.add_argument("--operator", choices=sorted(OPERATORS), nargs="+",
                   default=["expert", "average", "novice"], help="operator profiles, one after another")
    v.add_argument("--episodes", type=arg.positive, default=20, help="episodes per operator")
    v.add_argument("--seed", type=arg.seed, default=0, help="first episode seed")
    v.add_argument("--h", type=arg.positive, default=10, help="chunk grid of the supervised policy")
    arg.add_out_file(v, "write the rows to this JSON file")
    v.set_defaults(func=cmd_supervise)
    from window_bench.installer.teleop import add_teleop_parser

    add_teleop_parser(sub)
    from window_bench.pixels.cli import add_encoder_parser

    add_encoder_parser(sub)
    from window_bench.harness.methods import METHODS, PROFILES

    m = sub.add_parser("methods", help="print Table 1 (the methods and their components) and "
                                       "the budget profiles")
    m.set_defaults(func=cmd_methods)
    r = sub.add_parser("run", help="train one method through the matched-budget harness")
    r.add_argument("--method", required=True, type=arg.choice(METHODS, "method"),
                   help="Table 1 method: " + ", ".join(METHODS))
    r.add_argument("--env", type=arg.env_id, default="WindowInstall-A-v0", help=ENV_HELP)
    r.add_argument("--profile", type=arg.choice(PROFILES, "profile"), choices=list(PROFILES),
                   default="smoke",
                   help="budget profile (bench methods lists what each one sets)")
    r.add_argument("--seed", type=arg.seed, default=0, help="run seed (agent, envs, evaluation order)")
    r.add_argument("--out", type=arg.out_dir, required=True, help="run directory")
    r.add_argument("--resume", action="store_true", help="continue the run saved in --out")
    r.add_argument("--operator", choices=sorted(OPERATORS), default=DEFAULT_OPERATOR,
                   help="operator profile for demonstrations and takeovers")
    r.add_argument("--demos", type=arg.dir_path, help="Minari datasets root holding the "
                   "demonstrations (None: collect them into OUT/demos)")
    r.add_argument("--demo-actions", choices=list(DEMO_ACTIONS), default=DEFAULT_DEMO_ACTIONS,
                   help="the actions learners train on from D_demo: as the demonstrator meant "
                        "them, before its hand's noise (DART-style labels; "
                        "docs/results/diagnoses/b-demos.md), or as executed (the paper's record)")
    r.add_argument("--acceptance-noise", nargs=3, metavar=("FP", "FN", "DELAY"), default=None,
                   help="train on a noisy acceptance sensor: false-positive rate per step, "
                        "false-negative rate, delay in steps (evaluation keeps true acceptance)")
    from window_bench.harness.tracks import DEFAULT_TRACK, TRACKS

    r.add_argument("--track", choices=list(TRACKS), default=DEFAULT_TRACK,
                   help="observation track: the privileged state; the paper's two RGB views "
                        "+ proprioception through the frozen ResNet-10 (pixels); the same with "
                        "two cameras on the opening's corners (pixels-seat) (docs/pixels.md)")
    r.add_argument("--encoder-weights", metavar="PATH",
                   help="pixel track: backbone weights (safetensors, timm resnet10t names); "
                        "default: the shipped in-domain encoder")
    r.add_argument("--agent-config", nargs="+", metavar="KEY=VALUE",
                   help="override fields of the agent's config (recorded in the results), "
                        "e.g. act_noise_scale=0.0 alpha=100")
    from window_bench.harness.methods import PRESETS

    r.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help="start from a published agent config (its overrides; --agent-config "
                        "entries win), e.g. hilserl-own: HIL-SERL as its authors run it")
    from window_bench.harness.results import FINAL_CHECKPOINTS
    from window_bench.harness.seeds import MAX_EPISODES, SEED_SETS

    r.add_argument("--h", type=arg.positive, default=None,
                   help="chunk horizon of a QC-FQL method (Tables 5/6; default: the method's)")
    r.add_argument("--final-episodes", type=arg.int_in(1, MAX_EPISODES), default=None, metavar="M",
                   help="evaluate the final checkpoint with M fresh rollouts (reported runs: "
                        "100 on the test seeds); default: the last checkpoint's evaluation")
    r.add_argument("--final-seed-set", choices=sorted(SEED_SETS), default="dev",
                   help="seeds of the final evaluation: dev (tuning) or test (reported)")
    r.add_argument("--final-checkpoint", choices=FINAL_CHECKPOINTS, default="last",
                   help="the policy the final evaluation runs: the last checkpoint's, or the "
                        "one with the best development-seed success (ties: the later), as a "
                        "HIL-SERL operator picks one to evaluate")
    r.add_argument("--stage1-cache", type=arg.writable_dir("--stage1-cache"), default=None,
                   metavar="DIR",
                   help="share Stage I with runs of the same agent config, h, demos and seed "
                        "through this cache directory (bench sweep sets it)")
    r.add_argument("--pixel-demos-cache", type=arg.writable_dir("--pixel-demos-cache"),
                   default=None, metavar="DIR",
                   help="--track pixels: keep the demos re-observed under the encoder in this "
                        "cache directory (default: pixel_cache/ in the demos directory)")
    r.add_argument("--eval-workers", type=arg.workers, default=None, metavar="N",
                   help="evaluation processes per checkpoint, 1-64 (default: the profile's; 1 "
                        "evaluates in the training process, so a run uses one core)")
    r.set_defaults(func=cmd_run)
    e = sub.add_parser("eval", help="evaluate a saved policy (interventions off)")
    e.add_argument("checkpoint", help="a policies/step_*.safetensors file of a run")
    e.add_argument("--episodes", type=arg.int_in(1, MAX_EPISODES), default=100,
                   help="evaluation episodes")
    e.add_argument("--env", type=arg.env_id, default=None,
                   help=ENV_HELP + " (None: the env the policy was trained on)")
    arg.add_out_file(e, "write the summary to this JSON file")
    e.add_argument("--seed-set", choices=sorted(SEED_SETS), default="dev",
                   help="evaluation seeds: dev (tuning, default) or test (reported numbers)")
    e.add_argument("--eval-workers", type=arg.workers, default=2, metavar="N",
                   help="evaluation processes, 1-64 (1: in this process)")
    e.add_argument("--clearance", type=arg.clearance_mm, default=None, metavar="MM",
                   help="rebuild the opening with this clearance per side, 0.5-20 mm (None: "
                        "the env's 2 mm); a tolerance-sensitivity check, not a table entry")
    e.set_defaults(func=cmd_eval)
    lb = sub.add_parser("leaderboard", help="regenerate the leaderboard from raw run files")
    lb.add_argument("--add", nargs="+", metavar="RUN_DIR", help="first copy these finished "
                                                                "runs' raw files in")
    lb.add_argument("--root", type=arg.dir_path, default="leaderboard/runs",
                    help="leaderboard runs root")
    lb.add_argument("--readme", type=arg.out_file, default=None,
                    help="also write the leaderboard page to this file (the table is always "
                         "printed)")
    lb.add_argument("--snippet", type=arg.out_file, default=None,
                    help="also write the table alone to this file, for the docs")
    lb.add_argument("--force", action="store_true",
                    help="overwrite --readme and --snippet, and runs already in --root; "
                         "the committed pages: --readme leaderboard/README.md --snippet "
                         "docs/snippets/leaderboard.md --force")
    lb.set_defaults(func=cmd_leaderboard)
    sw = sub.add_parser("sweep", help="run a grid of cells (experiments/*.toml) on Ray; "
                                      "finished cells are skipped, partial ones resumed")
    sw.add_argument("grid", help="a grid file, e.g. experiments/table2.toml")
    sw.add_argument("--out", type=arg.dir_path, default="runs/grid",
                    help="runs root: one directory per cell; nothing is written outside it")
    sw.add_argument("--workers", type=arg.positive, default=None,
                    help="cells at a time (None: one per CPU of the Ray cluster)")
    sw.add_argument("--address", default=None,
                    help="join an existing Ray cluster (e.g. 127.0.0.1:6379 after "
                         "`ray start --head`); None: start one on this machine")
    sw.add_argument("--only", nargs="+", metavar="GLOB", default=None,
                    help="run only the cells whose name (<env>/<run>, as in the progress "
                         "view) matches one of these shell patterns, e.g. '*/qcfql-cpu-s*'")
    sw.add_argument("--no-progress", action="store_true", help="one line per finished cell only")
    sw.add_argument("--status", action="store_true",
                    help="start nothing: print each cell's state (done with its result, "
                         "running, partial with its stage and counters, new, failed) from "
                         "the files under --out, and the counts")
    sw.add_argument("--no-stage1-cache", action="store_true",
                    help="every cell computes its own Stage I (to measure what the cache saves)")
    sw.set_defaults(func=cmd_sweep)
    tb = sub.add_parser("tables", help="regenerate the paper's Tables 2-7 and Figs. 10/11 "
                                       "from raw run files")
    tb.add_argument("--runs", type=arg.dir_path, default="leaderboard/runs",
                    help="runs root to read")
    tb.add_argument("--out", type=arg.out_dir, required=True,
                    help="directory for the pages and figures (the committed ones: "
                         "docs/results)")
    tb.add_argument("--no-figures", action="store_true", help="tables only")
    tb.add_argument("--readme", default=None,
                    help="also rewrite this file's headline block, between its "
                         "'<!-- bench tables: headline -->' markers")
    tb.add_argument("--force", action="store_true",
                    help="overwrite existing pages, figures and the --readme block; the "
                         "committed ones: --runs leaderboard/runs --out docs/results "
                         "--readme README.md --force")
    tb.set_defaults(func=cmd_tables)
    from window_bench.video import CAMERAS, FPS_RANGE, SIZE_RANGE

    vd = sub.add_parser("video", help="record episodes of a policy file or reference controller "
                                      "as MP4 (wrist, side and overview cameras)")
    vd.add_argument("--policy", default="installer",
                    help="a reference controller (" + ", ".join(sorted(CONTROLLERS)) + ") or a "
                         "policies/step_*.safetensors file of a run")
    vd.add_argument("--env", type=arg.env_id, default="WindowInstall-A-v0", help=ENV_HELP)
    vd.add_argument("--seed", type=arg.seed, default=0, help="first episode seed")
    vd.add_argument("--episodes", type=arg.positive, default=1, help="episodes, one file each")
    vd.add_argument("--out", type=arg.out_dir, default="runs/videos", help="directory for the MP4s "
                    "and videos.json")
    vd.add_argument("--cameras", nargs="+", choices=list(CAMERAS), default=list(CAMERAS),
                    help="views, tiled left to right")
    vd.add_argument("--size", type=arg.positive, default=240,
                    help=f"view height in px, {SIZE_RANGE[0]}-{SIZE_RANGE[1]}")
    vd.add_argument("--fps", type=arg.positive, default=10,
                    help=f"frames per second, {FPS_RANGE[0]}-{FPS_RANGE[1]} (10 = real time)")
    vd.add_argument("--force", action="store_true",
                    help="record into an --out that already holds videos.json or MP4s, "
                         "replacing them")
    # a recording rewrites videos.json and names its MP4s by env, policy and seed
    vd.set_defaults(func=cmd_video, outputs=lambda args: [Path(args.out) / "videos.json",
                                                          *sorted(Path(args.out).glob("*.mp4"))])
    return p


def main(argv: list[str] | None = None) -> int:
    # Logs go to stderr, results to stdout: torchrl's console logger writes to stdout unless
    # told otherwise when it is first imported (spawned workers inherit the setting).
    import os

    os.environ.setdefault("TORCHRL_CONSOLE_STREAM", "stderr")
    args = build_parser().parse_args(argv)
    try:   # before any work: a file the command would write is replaced only with --force
        if "outputs" in args:
            _refuse_overwrite(args.outputs(args), args.force)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
