"""Issue 14: the faults of its "Why" section, each run against one code tree with ``bench``.

    python benchmarks/run_files_faults.py CODE_TREE WORKDIR [CASE ...]

CODE_TREE is a checkout to test (e.g. `git worktree add /tmp/before 114b308` for the code
before issue 14, or this repository); WORKDIR is created afresh. Cases: eval-pickle,
resume-pickle, concurrent, results-no-state, truncated-demos, flip-state, flip-policy,
lb-rate, lb-path, lb-root, config, seed, eval-nonpolicy, resume-other, out, umask.

Each case prints: name | exit code | seconds | traceback? | last stderr line | observation.
"""

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

TREE, WORK = Path(sys.argv[1]).resolve(), Path(sys.argv[2]).resolve()
ONLY = set(sys.argv[3:])
ENV = {**os.environ, "PYTHONPATH": str(TREE), "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
BASE = ["--method", "qcfql-offline", "--profile", "smoke", "--seed", "0"]


def bench(*args, timeout=400, cwd=None):
    t = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "window_bench.cli", *map(str, args)],
                           capture_output=True, text=True, env=ENV, timeout=timeout,
                           cwd=cwd or WORK)
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired as e:
        rc, err = "timeout", (e.stderr or b"").decode() if isinstance(e.stderr, bytes) else (e.stderr or "")
    lines = [ln for ln in err.splitlines() if ln.strip() and "%|" not in ln and "it/s]" not in ln]
    return {"rc": rc, "s": round(time.perf_counter() - t, 1), "tb": "Traceback" in err,
            "last": (lines[-1][:150] if lines else ""), "nlines": len(lines)}


def sha(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12] if Path(path).exists() else None


def tree_sha(d):
    d = Path(d)
    return {str(p.relative_to(d)): sha(p) for p in sorted(d.rglob("*")) if p.is_file()} if d.exists() else None


def row(name, r, obs=""):
    print(f"| {name} | {r['rc']} | {r['s']} | {'yes' if r['tb'] else 'no'} | "
          f"{r['last'].replace('|', '/')} | {obs} |", flush=True)


def want(name):
    return not ONLY or name in ONLY


def state_file(d):
    for n in ("state.safetensors", "state.pt"):
        if (d / n).exists():
            return d / n


def last_policy(d):
    return sorted((d / "policies").iterdir())[-1]


def evil(path, marker):
    code = ("import os, torch\n"
            "class Evil:\n"
            f"    def __reduce__(self): return (os.mkdir, ({str(marker)!r},))\n"
            f"torch.save({{'agent': Evil()}}, {str(path)!r})\n")
    subprocess.run([sys.executable, "-c", code], check=True, env=ENV)


if WORK.exists():   # only a directory this script made is replaced
    if not (WORK / ".run_files_faults").exists():
        sys.exit(f"{WORK} exists and was not made by this script; choose a new WORKDIR")
    shutil.rmtree(WORK)
WORK.mkdir(parents=True)
(WORK / ".run_files_faults").touch()
demos = WORK / "demos"
r = bench("demos", "--n", "2", "--out", demos)
assert r["rc"] == 0, r
base = WORK / "base"
r = bench("run", *BASE, "--out", base, "--demos", demos)
assert r["rc"] == 0, r
print("| case | exit | s | traceback | last stderr line | observed |\n|---|---|---|---|---|---|")

if want("eval-pickle"):
    marker = WORK / "PWNED-eval"
    evil(WORK / "evil.pt", marker)
    row("bench eval evil.pt (__reduce__ payload)", bench("eval", WORK / "evil.pt", "--episodes", "1"),
        f"payload ran: {marker.exists()}")

if want("resume-pickle"):
    marker = WORK / "PWNED-resume"
    d = WORK / "crafted"
    shutil.copytree(base, d)
    evil(d / "state.pt", marker)
    if (d / "state.safetensors").exists():
        shutil.copyfile(d / "state.pt", d / "state.safetensors")
    row("bench run --resume, crafted state", bench("run", *BASE, "--out", d, "--resume", "--demos", demos),
        f"payload ran: {marker.exists()}")

if want("concurrent"):
    d = WORK / "shared"
    args = lambda s: [sys.executable, "-m", "window_bench.cli", "run", "--method", "qcfql-offline",  # noqa: E731
                      "--profile", "smoke", "--seed", s, "--out", str(d), "--demos", str(demos)]
    t = time.perf_counter()
    a = subprocess.Popen(args("0"), env=ENV, cwd=WORK, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(4)
    b = subprocess.Popen(args("1"), env=ENV, cwd=WORK, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    eb = b.communicate()[1]
    tb_ = round(time.perf_counter() - t - 4, 1)
    ea = a.communicate()[1]
    seed = json.loads((d / "results.json").read_text())["seed"] if (d / "results.json").exists() else None
    lines = [ln for ln in eb.splitlines() if ln.strip() and "%|" not in ln]
    row("two bench run, same --out, seeds 0 and 1", {"rc": f"{a.returncode} / {b.returncode}", "s": tb_,
        "tb": "Traceback" in eb, "last": lines[-1][:150] if lines else ""},
        f"results.json seed: {seed}")

if want("results-no-state"):
    d = WORK / "finished"
    shutil.copytree(base, d)
    state_file(d).unlink()
    before = sha(d / "results.json")
    r = bench("run", *BASE, "--out", d, "--demos", demos)
    row("bench run into a dir with results.json, no state", r,
        f"results.json replaced: {sha(d / 'results.json') != before}")

if want("truncated-demos"):
    d = WORK / "demos-cut"
    shutil.copytree(demos, d)
    h5 = next(d.rglob("main_data.hdf5"))
    h5.write_bytes(h5.read_bytes()[: h5.stat().st_size // 2])
    before = tree_sha(d / "window-bench")
    r = bench("run", *BASE, "--out", WORK / "cut-run", "--demos", d)
    row("--demos dataset truncated", r, f"dataset replaced: {tree_sha(d / 'window-bench') != before}")

if want("flip-state"):
    d = WORK / "flip-state"
    shutil.copytree(base, d)
    f = state_file(d)
    b = bytearray(f.read_bytes())
    b[len(b) - 100] ^= 0x01
    f.write_bytes(bytes(b))
    r = bench("run", *BASE, "--out", d, "--resume", "--demos", demos)
    row("one flipped byte in the state, --resume", r, "")

if want("flip-policy"):
    d = WORK / "flip-pol"
    shutil.copytree(base, d)
    f = last_policy(d)
    b = bytearray(f.read_bytes())
    b[len(b) - 100] ^= 0x01
    f.write_bytes(bytes(b))
    row("one flipped byte in a policy, bench eval", bench("eval", f, "--episodes", "1"), "")

if want("lb-rate") or want("lb-path") or want("lb-root"):
    for case, edit in (("lb-rate", lambda r: r["final"].update(success_rate=7.5)),
                       ("lb-path", lambda r: r.update(env_id="../../../x"))):
        if not want(case):
            continue
        d = WORK / case
        shutil.copytree(base, d)
        res = json.loads((d / "results.json").read_text())
        edit(res)
        (d / "results.json").write_text(json.dumps(res))
        if (d / "manifest.json").exists():   # a forged run also forges its manifest
            m = json.loads((d / "manifest.json").read_text())
            m["files"]["results.json"] = {"sha256": hashlib.sha256((d / "results.json").read_bytes()).hexdigest(),
                                          "bytes": (d / "results.json").stat().st_size}
            (d / "manifest.json").write_text(json.dumps(m))
        root = WORK / "lbroot" / case / "a" / "b" / "runs"
        root.mkdir(parents=True)
        lb_readme = WORK / "lbroot" / case / "a" / "b" / "leaderboard" / "README.md"
        lb_readme.parent.mkdir(parents=True)
        r = bench("leaderboard", "--add", d, "--root", root, "--readme", lb_readme,
                  cwd=WORK / "lbroot" / case / "a" / "b")
        outside = sorted(str(p.relative_to(WORK / "lbroot" / case)) for p in (WORK / "lbroot" / case).rglob("*")
                         if p.is_file() and not str(p).startswith(str(root))
                         and p.name not in ("README.md", "leaderboard.md"))   # the tables it regenerates
        table = (WORK / "lbroot" / case / "a" / "b" / "leaderboard" / "README.md")
        shown = "750" in table.read_text() if table.exists() else False
        row(f"leaderboard --add, {'success 7.5' if case == 'lb-rate' else 'env_id ../../../x'}", r,
            f"files in root: {len(list(root.rglob('*.json')))}; written outside root: {outside or 'none'}"
            + ("; '750' in table: %s" % shown if case == "lb-rate" else ""))
    if want("lb-root"):
        cwd = WORK / "lbroot" / "bad"
        root = cwd / "runs"
        shutil.copytree(base, root / "WindowInstall-A-v0" / "good")
        (root / "WindowInstall-A-v0" / "bad").mkdir(parents=True)
        (root / "WindowInstall-A-v0" / "bad" / "results.json").write_text('{"schema_version": 1}')
        table = cwd / "leaderboard" / "README.md"
        table.parent.mkdir(parents=True)
        r = bench("leaderboard", "--root", root, "--readme", table, cwd=cwd)
        row("one bad results.json in the root, bench leaderboard", r,
            f"table written: {table.exists() and 'qcfql-offline' in table.read_text()}")

for key, value in (("nope", "1"), ("alpha", "abc"), ("h", "3"), ("gamma", "1.5"), ("alpha", "Infinity"),
                   ("lr", "1e30")):
    if not want("config"):
        break
    out, droot = WORK / f"cfg-{key}-{value}", WORK / f"cfg-demos-{key}-{value}"
    r = bench("run", "--method", "qcfql", "--profile", "smoke", "--out", out, "--demos", droot,
              "--agent-config", f"{key}={value}")
    row(f"--agent-config {key}={value}", r,
        f"demos collected: {droot.exists()}; state written: {bool(out.exists() and state_file(out))}; "
        f"stderr lines: {r['nlines']}")

if want("seed"):
    for cmd in (["run", "--method", "qcfql-offline", "--profile", "smoke", "--out", WORK / "neg",
                 "--demos", WORK / "neg-demos"], ["install", "--episodes", "1"], ["demos", "--n", "1", "--out", WORK / "negd"],
                ["supervise", "--episodes", "1", "--operator", "expert"]):
        row(f"{cmd[0]} --seed -1", bench(*cmd, "--seed", "-1", timeout=300), "")

if want("eval-nonpolicy"):
    row("bench eval results.json (not a policy)", bench("eval", base / "results.json", "--episodes", "1"), "")

if want("resume-other"):
    d = WORK / "other"
    shutil.copytree(base, d)
    before = tree_sha(d)
    r = bench("run", "--method", "qcfql", "--profile", "smoke", "--out", d, "--resume", "--demos", demos)
    row("--resume with another method", r, f"files changed: {tree_sha(d) != before}")

if want("out"):
    (WORK / "afile").write_text("x")
    row("--out under a file (afile/run)", bench("run", *BASE, "--out", WORK / "afile" / "run", "--demos", demos), "")
    row("--out under an unwritable path (/sys/wb14)", bench("run", *BASE, "--out", "/sys/wb14/run", "--demos", demos), "")

if want("umask"):
    files = [base / "results.json", last_policy(base), state_file(base)]
    print(f"| file modes, umask {oct(os.umask(0o022))} | - | - | - | - | "
          + ", ".join(f"{p.name} {oct(p.stat().st_mode & 0o777)}" for p in files) + " |")
