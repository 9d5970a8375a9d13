"""Environment speed: env steps/s against raw MuJoCo physics of the same scene.

Measures, in one run and side by side; every block below runs in every repeat, so slow
phases of a shared machine hit all rows, and MEDIANS over repeats are reported.

(a) state-mode env steps/s through ``gym.make`` (all default wrappers), with a "hold"
    policy (zero motion, ``a[6] = 1`` keeps the panel on the cup) and a uniformly random
    policy. Only ``env.step`` calls are timed; resets are excluded. Each policy runs twice
    per repeat: a plain loop of env steps followed by plain loops of the replays (b) and
    (c) of the same steps (the headline numbers), and an interleaved loop in which each
    env step is immediately followed by its replays (same machine load for env and raw
    physics, but the replays evict the env's data from the CPU caches, which makes the
    env step slower than in a plain loop).
(b) raw physics: ``mujoco.mj_step(model, data, 100)`` on a copy of the model, started from
    the exact state (qpos, qvel, ctrl, warm start, suction weld and cup-contact switch) that
    the env was in at the beginning of each timed env step, with that step's initial
    ``ctrl`` held.
    100 = ``CONTROL_SUBSTEPS * PHYSICS_PER_CONTROL`` physics steps per env step.
    The ratio env-step time / raw-physics time is taken per repeat (median, min, max).
(c) the controller alone: the 50 OSC updates of one env step (``mj_jacSite``,
    ``mj_fullM``, the payload ``mj_jac`` while latched, the numba ``osc_torque`` and the
    ``ctrl`` write) at each step's initial state, without stepping the physics. The time
    the env spends inside its own ``OSC.run`` (physics + controller + the Python substep
    loop) is timed too, which splits an env step into physics, controller, substep-loop
    overhead and the 10 Hz env logic (action, suction checks, observation, wrappers).
(d) pixel mode (``obs_mode="pixels"``, wrist + side cameras at ``--image-size``) steps/s.

Usage::

    MUJOCO_GL=egl python benchmarks/env_speed.py [--env WindowInstall-A-v0] [--steps 2000]
        [--repeats 5] [--pixel-steps 100]

Results go to ``--out`` (default ``runs/benchmarks/env_speed.json``, untracked; written
atomically); ``benchmarks/results/env_speed.json`` is the tracked run that ``docs/speed.md``
quotes.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # must precede the first mujoco import

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

import window_bench  # noqa: E402,F401  (registers the ids)
from window_bench.envs import scene as S  # noqa: E402
from window_bench.envs.controller import OSC, OSCGains, osc_torque  # noqa: E402
from window_bench.harness.evaluation import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PHYS_PER_ENV_STEP = S.CONTROL_SUBSTEPS * S.PHYSICS_PER_CONTROL  # 100

TARGET_STEPS_PER_S = 500.0
TARGET_RATIO = 2.5


# ---------------------------------------------------------------------------- metadata
def hardware() -> dict:
    model = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"cpu_model": model, "cpu_count": os.cpu_count(), "cpus_usable": usable,
            "machine": platform.machine(), "os": platform.platform()}


def versions() -> dict:
    def pkg(name):
        try:
            from importlib.metadata import version
            return version(name)
        except Exception:
            return None
    return {"python": platform.python_version(), "mujoco": mujoco.__version__,
            "mujoco_core": pkg("mujoco-core"), "mujoco_lib": mujoco.mj_versionString(),
            "numpy": np.__version__, "numba": numba.__version__,
            "gymnasium": gym.__version__, "window_bench": window_bench.__version__}


def git_commit() -> dict:
    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except Exception:
            return ""
    return {"commit": git("rev-parse", "HEAD") or None,
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}


# ---------------------------------------------------------------------------- recording
class Snapshot:
    """The integration state at the start of one env step, plus what ``env.step`` set up
    for its substep loop (OSC target, suction latch), read back after the step."""

    __slots__ = ("qpos", "qvel", "act", "ctrl", "warm", "latched", "eq_data",
                 "target_pos", "target_mat")

    def __init__(self, d):
        self.qpos = d.qpos.copy()
        self.qvel = d.qvel.copy()
        self.act = d.act.copy()
        self.ctrl = d.ctrl.copy()
        self.warm = d.qacc_warmstart.copy()

    def complete(self, base, info):
        # The latch is decided at the start of env.step; a holding-limit release happens
        # after the substep loop (info["suction_failed"]), so the weld was on during it.
        self.latched = bool(base.suction_engaged or info.get("suction_failed", False))
        self.eq_data = base.model.eq_data[base.scene.suction_eq].copy()
        self.target_pos = base.osc.target_pos.copy()
        self.target_mat = base.osc.target_mat.copy()

    def apply(self, m, d, sc):
        d.qpos[:] = self.qpos
        d.qvel[:] = self.qvel
        d.act[:] = self.act
        d.ctrl[:] = self.ctrl
        d.qacc_warmstart[:] = self.warm
        d.eq_active[sc.suction_eq] = self.latched
        m.eq_data[sc.suction_eq] = self.eq_data
        m.geom_contype[sc.cup_geom] = 0 if self.latched else S.CUP_PANEL_BIT


def hold_action() -> np.ndarray:
    a = np.zeros(7, np.float32)
    a[6] = 1.0
    return a


class Replayer:
    """Re-runs one env step's work on a private copy of the model and data.

    ``raw``: ``mj_step(m, d, 100)`` with the step's initial ctrl held (pure physics).
    ``controller``: the 50 OSC updates of ``OSC.run`` (``mj_jacSite``, ``mj_fullM``, the
    payload ``mj_jac`` while latched, the numba ``osc_torque``, the ``ctrl`` write) at the
    step's initial state, without stepping the physics.
    """

    def __init__(self, base):
        self.base = base
        self.m = copy.copy(base.model)
        self.d = mujoco.MjData(self.m)
        sc = base.scene
        self.sc = sc
        self.mass = base.cfg.mass
        self.osc = OSC(self.m, sc.tcp_site, sc.tool_body, OSCGains(), q_null=base.osc.q_null)
        o = self.osc
        self.jacp, self.jacr = np.zeros_like(o.jacp), np.zeros_like(o.jacr)
        self.M, self.tau = np.zeros_like(o.M), np.zeros(7)
        self.pj, self.pf = np.zeros_like(o.payload_jacp), np.zeros(3)

    def sync_model(self):
        """Per-episode randomized contact parameters (friction, solref) of the env's model."""
        src, dst = self.base.model, self.m
        dst.pair_friction[:] = src.pair_friction
        dst.pair_solref[:] = src.pair_solref
        dst.geom_friction[:] = src.geom_friction
        dst.geom_solref[:] = src.geom_solref

    def raw(self, s: Snapshot) -> float:
        m, d = self.m, self.d
        s.apply(m, d, self.sc)
        t0 = time.perf_counter()
        mujoco.mj_step(m, d, PHYS_PER_ENV_STEP)
        return time.perf_counter() - t0

    def controller(self, s: Snapshot) -> float:
        m, d, sc, o = self.m, self.d, self.sc, self.osc
        s.apply(m, d, self.sc)
        mujoco.mj_step1(m, d)
        site, tool, panel = sc.tcp_site, sc.tool_body, sc.panel_body
        jacp, jacr, M, pj, pf = self.jacp, self.jacr, self.M, self.pj, self.pf
        latched = s.latched
        if latched:
            pf[:] = self.mass * -m.opt.gravity
        else:
            pj[:] = 0.0
            pf[:] = 0.0
        tp, tm = s.target_pos, s.target_mat
        gains, tlim, q_null = o.gains, o.torque_limit, o.q_null
        xpos, xmat = d.site_xpos, d.site_xmat
        t0 = time.perf_counter()
        for _ in range(S.CONTROL_SUBSTEPS):
            mujoco.mj_jacSite(m, d, jacp, jacr, site)
            mujoco.mj_fullM(m, d, M)
            if latched:
                mujoco.mj_jac(m, d, pj, None, d.xipos[panel], tool)
            osc_torque(jacp, jacr, M, d.qfrc_bias, d.qpos, d.qvel, xpos[site],
                       xmat[site].reshape(3, 3), tp, tm, q_null, pj, pf, gains, tlim, d.ctrl,
                       o.max_abs_tau)
        return time.perf_counter() - t0


def run_env(env, n_steps: int, policy: str, rng: np.random.Generator, seed: int,
            replay: Replayer | None = None, interleave: bool = False) -> dict:
    """Time ``n_steps`` env.step calls (resets excluded) and the time spent inside the env's
    own ``OSC.run``. With ``replay``, the raw-physics and controller replays of the same
    steps are timed too: right after each env step (``interleave=True``, same machine
    load, but the replays evict the env's data from the caches) or as separate plain loops
    after all env steps (``interleave=False``)."""
    base = env.unwrapped
    hold = hold_action()
    t = {"env": 0.0, "osc_run": 0.0, "raw": 0.0, "ctrl": 0.0}
    perf = time.perf_counter
    osc = base.osc
    inner = osc.run

    def timed_run(*a, **k):  # shadows the bound method on this instance only
        t0 = perf()
        inner(*a, **k)
        t["osc_run"] += perf() - t0

    osc.run = timed_run
    if replay is not None:
        replay.sync_model()
    snaps = []
    resets = unstable = 0
    try:
        for _ in range(n_steps):
            a = hold if policy == "hold" else rng.uniform(-1.0, 1.0, 7).astype(np.float32)
            snap = Snapshot(base.data) if replay is not None else None
            t0 = perf()
            _, _, term, trunc, info = env.step(a)
            t["env"] += perf() - t0
            if replay is not None:
                snap.complete(base, info)
                if interleave:
                    t["raw"] += replay.raw(snap)
                    t["ctrl"] += replay.controller(snap)
                else:
                    snaps.append(snap)
            if term or trunc:
                unstable += bool(info.get("sim_unstable", False))
                resets += 1
                env.reset(seed=seed + resets)
                if replay is not None and interleave:
                    replay.sync_model()
    finally:
        del osc.run
    if snaps:
        # Contact parameters of the last episode for all replays: they change the contact
        # forces, not the cost of a step.
        t["raw"] = sum(replay.raw(s) for s in snaps)
        t["ctrl"] = sum(replay.controller(s) for s in snaps)
    return {"times": t, "resets": resets, "unstable": unstable, "n": n_steps}


def run_pixels(env, n_steps: int, seed: int) -> float:
    hold = hold_action()
    total = 0.0
    resets = 0
    perf = time.perf_counter
    for _ in range(n_steps):
        t0 = perf()
        _, _, term, trunc, _ = env.step(hold)
        total += perf() - t0
        if term or trunc:
            resets += 1
            env.reset(seed=seed + resets)
    return total


# ---------------------------------------------------------------------------- stats
def summary(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values),
            "values": values}


def write_json_atomic(path: Path, payload: dict) -> None:
    atomic_write_text(path, json.dumps(payload, indent=2) + "\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--env", default="WindowInstall-A-v0", choices=window_bench.ENV_IDS,
                   help="registered env id")
    p.add_argument("--steps", type=int, default=2000, help="timed env steps per repeat (state mode)")
    p.add_argument("--repeats", type=int, default=5, help="repeats; medians over them are reported")
    p.add_argument("--warmup", type=int, default=100, help="untimed env steps before timing")
    p.add_argument("--pixel-steps", type=int, default=100,
                   help="timed env steps per repeat in pixel mode (0 skips it)")
    p.add_argument("--image-size", type=int, default=128, help="camera image side in pixel mode")
    p.add_argument("--seed", type=int, default=0, help="reset seed")
    # The tracked results file changes only when asked for by name.
    p.add_argument("--out", type=Path, default=ROOT / "runs" / "benchmarks" / "env_speed.json",
                   help="JSON file to write; benchmarks/results/env_speed.json is the "
                        "tracked one quoted in docs/speed.md")
    args = p.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        p.error("--steps and --repeats must be >= 1")

    hw, ver, git = hardware(), versions(), git_commit()
    print(f"CPU: {hw['cpu_model']}  ({hw['cpus_usable']} usable of {hw['cpu_count']} cores, {hw['machine']})")
    print("versions: " + ", ".join(f"{k} {v}" for k, v in ver.items()))
    print(f"git: {git['commit']}{' (dirty)' if git['dirty'] else ''}")
    print(f"env {args.env}: {args.steps} steps x {args.repeats} repeats; 1 env step = "
          f"{S.CONTROL_SUBSTEPS} OSC updates x {S.PHYSICS_PER_CONTROL} physics steps of "
          f"{S.TIMESTEP * 1e3:g} ms = {PHYS_PER_ENV_STEP} mj_step")

    # -- set-up and warm-up (numba compilation / cache load happens in the first step)
    envs = {}
    rngs = {}
    for k, policy in enumerate(("hold", "random")):
        env = gym.make(args.env)
        env.reset(seed=args.seed)
        rngs[policy] = np.random.default_rng(args.seed + 1000 * k)
        t0 = time.perf_counter()
        env.step(hold_action())
        first = time.perf_counter() - t0
        run_env(env, args.warmup, policy, rngs[policy], args.seed)
        envs[policy] = env
        if policy == "hold":
            print(f"first env.step (numba compile or cache load): {first * 1e3:.0f} ms")
    replayers = {k: Replayer(e.unwrapped) for k, e in envs.items()}
    penv = None
    if args.pixel_steps > 0:
        penv = gym.make(args.env, obs_mode="pixels", image_size=args.image_size)
        penv.reset(seed=args.seed)
        run_pixels(penv, 5, args.seed)  # creates the GL context and renderer

    keys = ("env", "osc_run", "raw", "ctrl")
    rows = {f"{mode}_{k}_{policy}": [] for mode in ("plain", "inter") for k in keys
            for policy in ("hold", "random")}
    rows["pixels"] = []
    meta = {"resets": {"hold": 0, "random": 0}, "sim_unstable_episodes": {"hold": 0, "random": 0}}
    for rep in range(args.repeats):
        for policy in ("hold", "random"):
            for mode in ("plain", "inter"):
                r = run_env(envs[policy], args.steps, policy, rngs[policy], args.seed,
                            replay=replayers[policy], interleave=(mode == "inter"))
                meta["resets"][policy] += r["resets"]
                meta["sim_unstable_episodes"][policy] += r["unstable"]
                for k in keys:
                    rows[f"{mode}_{k}_{policy}"].append(r["times"][k] / r["n"])
        if penv is not None:
            rows["pixels"].append(run_pixels(penv, args.pixel_steps, args.seed) / args.pixel_steps)
        ratio = rows["plain_env_hold"][-1] / rows["plain_raw_hold"][-1]
        print(f"  repeat {rep + 1}/{args.repeats}: hold {1 / rows['plain_env_hold'][-1]:.0f} steps/s, "
              f"ratio {ratio:.2f}x raw"
              + (f", pixels {1 / rows['pixels'][-1]:.1f} steps/s" if penv is not None else ""),
              flush=True)
    for e in envs.values():
        e.close()
    if penv is not None:
        penv.close()

    # -- table
    def per_s(xs):
        return summary([1.0 / x for x in xs])

    def ms(xs):
        return summary([x * 1e3 for x in xs])

    def ratio(a, b):
        return summary([x / y for x, y in zip(rows[a], rows[b])])

    R = rows
    table = [
        ("state env steps/s, hold (a[6]=1)", per_s(R["plain_env_hold"]), "steps/s"),
        ("state env steps/s, random actions", per_s(R["plain_env_random"]), "steps/s"),
    ]
    for policy in ("hold", "random"):
        for mode, label in (("plain", "plain loops"), ("inter", "interleaved")):
            p = f"_{policy}"
            table += [
                (f"[{policy}, {label}] env step", ms(R[f"{mode}_env{p}"]), "ms"),
                (f"[{policy}, {label}] raw physics, 100 mj_step", ms(R[f"{mode}_raw{p}"]), "ms"),
                (f"[{policy}, {label}] ratio env / raw physics", ratio(f"{mode}_env{p}", f"{mode}_raw{p}"), "x"),
                (f"[{policy}, {label}] controller alone, 50 updates", ms(R[f"{mode}_ctrl{p}"]), "ms"),
                (f"[{policy}, {label}] OSC.run inside env.step", ms(R[f"{mode}_osc_run{p}"]), "ms"),
                (f"[{policy}, {label}] substep-loop overhead",
                 ms([o - r - c for o, r, c in zip(R[f"{mode}_osc_run{p}"], R[f"{mode}_raw{p}"], R[f"{mode}_ctrl{p}"])]), "ms"),
                (f"[{policy}, {label}] env logic outside OSC.run",
                 ms([e - o for e, o in zip(R[f"{mode}_env{p}"], R[f"{mode}_osc_run{p}"])]), "ms"),
            ]
    table += [
        ("controller / raw physics (hold, plain)", ratio("plain_ctrl_hold", "plain_raw_hold"), "x"),
        ("controller per OSC update (hold, plain)",
         summary([x * 1e6 / S.CONTROL_SUBSTEPS for x in R["plain_ctrl_hold"]]), "us"),
        ("raw physics per mj_step (hold, plain)",
         summary([x * 1e6 / PHYS_PER_ENV_STEP for x in R["plain_raw_hold"]]), "us"),
    ]
    if rows["pixels"]:
        table.append((f"pixel env steps/s ({args.image_size}px wrist+side)", per_s(rows["pixels"]), "steps/s"))
        table.append(("pixel env step time", ms(rows["pixels"]), "ms"))

    w = max(len(r[0]) for r in table)
    print()
    print(f"{'measurement':<{w}}  {'median':>10}  {'min':>10}  {'max':>10}  unit")
    print("-" * (w + 45))
    for name, s, unit in table:
        print(f"{name:<{w}}  {s['median']:>10.3f}  {s['min']:>10.3f}  {s['max']:>10.3f}  {unit}")

    sps = statistics.median(1.0 / x for x in rows["plain_env_hold"])
    ratio = statistics.median(x / y for x, y in zip(rows["plain_env_hold"], rows["plain_raw_hold"]))
    checks = {
        f"state steps/s (hold) >= {TARGET_STEPS_PER_S:g}": sps >= TARGET_STEPS_PER_S,
        f"env/raw ratio (hold) <= {TARGET_RATIO:g}": ratio <= TARGET_RATIO,
    }
    print()
    for k, v in checks.items():
        print(f"target {k}: {'PASS' if v else 'FAIL'}")
    print(f"resets during timing: {meta['resets']}; sim_unstable episodes: {meta['sim_unstable_episodes']}")

    payload = {
        "benchmark": "env_speed",
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "hardware": hw, "versions": ver, "git": git,
        "physics_steps_per_env_step": PHYS_PER_ENV_STEP,
        "timestep_s": S.TIMESTEP,
        "results": {name: {**s, "unit": unit} for name, s, unit in table},
        "raw_seconds_per_step": rows,
        "targets": {"steps_per_s_min": TARGET_STEPS_PER_S, "ratio_max": TARGET_RATIO,
                    "checks": checks},
        **meta,
        "command": " ".join([sys.executable, *sys.argv]),
    }
    write_json_atomic(args.out, payload)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
