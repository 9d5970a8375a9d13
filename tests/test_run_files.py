"""Run files you can trust (issue 14): no file we load runs code, every file a run writes is
checked against its sha256, one writer per run directory, user data is never replaced, and
every bad input is one line with exit code 2 before any work. Each refusal is asserted
exactly, and so is that nothing changed on disk.

One smoke run (``qcfql-offline``) is shared by the module; a second ``bench run`` into the
same ``--out`` is started while it runs."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from window_bench.cli import main
from window_bench.harness.evaluation import atomic_write_text
from window_bench.harness.files import (RunFileError, dump_state, load_state, parse_state,
                                        verify_files)
from window_bench.installer.demos import collect_demos
from window_bench.installer.operators import DEFAULT_OPERATOR

BENCH = [sys.executable, "-m", "window_bench.cli"]
RUN = ["run", "--method", "qcfql-offline", "--profile", "smoke", "--seed", "0"]
POLICY = "policies/step_0000000.safetensors"


def snapshot(d: Path) -> dict:
    """Every file under ``d`` (hidden ones too) with its sha256."""
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(d).rglob("*")) if p.is_file()}


def one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@pytest.fixture(scope="module")
def demos_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("demos")
    collect_demos("WindowInstall-A-v0", 2, root, operator=DEFAULT_OPERATOR, seed=0,
                  progress=False)
    return root


@pytest.fixture(scope="module")
def runs(tmp_path_factory, demos_root):
    """One smoke run, and a second ``bench run`` (seed 1) into the same --out meanwhile."""
    out = tmp_path_factory.mktemp("runs") / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.Popen(BENCH + RUN + ["--out", str(out), "--demos", str(demos_root)],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not ((out / ".lock").exists() and (out / ".lock").read_text().startswith("pid")):
        assert first.poll() is None and time.monotonic() < deadline, first.stderr.read()
        time.sleep(0.05)
    t = time.monotonic()
    second = subprocess.run(BENCH + ["run", "--method", "qcfql-offline", "--profile", "smoke",
                                     "--seed", "1", "--out", str(out), "--demos", str(demos_root)],
                            env=env, capture_output=True, text=True, timeout=300)
    second_s = time.monotonic() - t
    first_running = first.poll() is None
    _, first_err = first.communicate(timeout=900)
    assert first.returncode == 0, first_err
    return SimpleNamespace(out=out, demos=demos_root, first_pid=first.pid, second=second,
                           second_s=second_s, first_running=first_running)


def copy_run(runs, tmp_path) -> Path:
    d = tmp_path / "copy"
    shutil.copytree(runs.out, d)
    return d


# ---------------------------------------------------------------- one writer
def test_second_writer_stops_at_once_naming_the_first(runs):
    assert runs.second.returncode == 2 and runs.first_running
    line = one_line(runs.second.stderr)
    assert line.startswith(f"error: --out {runs.out}: in use by another bench process "
                           f"(pid {runs.first_pid}: ")
    assert "wait for it to finish or choose another --out" in line
    assert runs.second_s < 60          # python and torch imports; no work was started
    assert json.loads((runs.out / "results.json").read_text())["seed"] == 0


def test_run_files_are_listed_verified_and_follow_the_umask(runs):
    m = verify_files(runs.out)
    assert {"results.json", "checkpoints.csv", "learning_curve.png", "state.safetensors",
            POLICY} <= set(m["files"])
    assert m["run"]["method"] == "qcfql-offline" and m["run"]["seed"] == 0
    for name in ("results.json", "state.safetensors", POLICY, "manifest.json"):
        assert (runs.out / name).stat().st_mode & 0o777 == 0o666 & ~umask(), name
    assert not list(runs.out.glob("*.pt"))
    policy, meta = load_state(runs.out / POLICY, "policy")
    assert meta == {"agent_kind": "qcfql", "method": "qcfql-offline", "env_id": "WindowInstall-A-v0",
                    "profile": "smoke", "seed": 0, "track": "state", "env_steps": 0}
    assert (runs.out / POLICY).stat().st_size < 1_000_000
    assert "critic" not in policy and "optimizer" not in json.dumps(list(policy))


def test_a_sigkill_at_a_random_moment_resumes_to_the_same_run(runs, tmp_path):
    """The same run as the module's, SIGKILLed at a random moment after it took its directory,
    then resumed: every file still verifies, and the result is bit-identical."""
    import random
    import signal

    out = tmp_path / "killed"
    cmd = BENCH + RUN + ["--out", str(out), "--demos", str(runs.demos)]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not (out / ".lock").exists() or not (out / ".lock").read_text():
        assert p.poll() is None
        time.sleep(0.02)
    time.sleep(random.Random().uniform(0.0, 20.0))
    p.send_signal(signal.SIGKILL)
    p.wait()
    verify_files(out)
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    strip = lambda cps: [{k: v for k, v in c.items() if k != "wall_clock_s"} for c in cps]  # noqa: E731
    a, b = (json.loads((d / "results.json").read_text()) for d in (runs.out, out))
    assert strip(a["checkpoints"]) == strip(b["checkpoints"])
    pa, pb = (load_state(d / POLICY, "policy")[0] for d in (runs.out, out))
    assert json.dumps(pa, default=lambda t: t.tolist()) == json.dumps(pb, default=lambda t: t.tolist())


def test_atomic_write_respects_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o640


# ---------------------------------------------------------------- code-carrying files
class _Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def test_a_pickle_payload_is_refused_by_eval_and_resume(runs, tmp_path, capsys):
    marker = tmp_path / "PAYLOAD_RAN"
    torch.save({"agent_kind": "qcfql", "agent": _Payload(marker)}, tmp_path / "evil.pt")
    assert main(["eval", str(tmp_path / "evil.pt"), "--episodes", "1"]) == 2
    assert one_line(capsys.readouterr().err) == (
        f"error: {tmp_path / 'evil.pt'}: a pickle file (torch.save), refused: loading pickle "
        f"can run code; window-bench reads only the .safetensors files bench run writes")
    d = copy_run(runs, tmp_path)
    shutil.copyfile(tmp_path / "evil.pt", d / "state.safetensors")
    before = snapshot(d)
    assert main(RUN + ["--out", str(d), "--resume", "--demos", str(runs.demos)]) == 2
    assert one_line(capsys.readouterr().err).startswith(
        f"error: {d / 'state.safetensors'}: sha256 does not match {d / 'manifest.json'}")
    # the same payload with a manifest forged to match still never reaches an unpickler
    m = json.loads((d / "manifest.json").read_text())
    m["files"]["state.safetensors"] = {"sha256": before["state.safetensors"],
                                       "bytes": (d / "state.safetensors").stat().st_size}
    (d / "manifest.json").write_text(json.dumps(m))
    before = snapshot(d)
    assert main(RUN + ["--out", str(d), "--resume", "--demos", str(runs.demos)]) == 2
    assert "a pickle file (torch.save), refused" in one_line(capsys.readouterr().err)
    assert not marker.exists() and snapshot(d) == before


def test_a_cut_state_file_is_not_named_a_pickle(tmp_path):
    """A safetensors header length whose low byte is 0x80 (as a raw pickle's first byte) in a
    cut file is reported as cut or corrupt; a real pickle is still named as one."""
    import pickle

    cut = (0x80).to_bytes(8, "little") + b'{"__metadata__": {"format": '
    with pytest.raises(RunFileError, match=r"x.safetensors: not a window-bench state file, or a "
                                           r"truncated or corrupt one"):
        parse_state(cut, tmp_path / "x.safetensors", "state")
    with pytest.raises(RunFileError, match=r"a pickle file \(torch.save\), refused"):
        parse_state(pickle.dumps({"a": 1}), tmp_path / "y.pt", "state")


# ---------------------------------------------------------------- flipped bytes, truncation
@pytest.mark.parametrize("fault", ["flip", "truncate"])
@pytest.mark.parametrize("target", ["state", "policy", "policy outside its run"])
def test_a_damaged_file_is_refused_naming_it(runs, tmp_path, capsys, fault, target):
    d = copy_run(runs, tmp_path)
    path = d / ("state.safetensors" if target == "state" else POLICY)
    if target == "policy outside its run":
        path = Path(shutil.copyfile(path, tmp_path / "policy.safetensors"))
    data = bytearray(path.read_bytes())
    if fault == "flip":
        data[-100] ^= 0x01       # one bit of a weight
    else:
        del data[len(data) // 2:]
    path.write_bytes(bytes(data))
    before = snapshot(tmp_path)
    if target == "state":
        rc = main(RUN + ["--out", str(d), "--resume", "--demos", str(runs.demos)])
    else:
        rc = main(["eval", str(path), "--episodes", "1"])
    line = one_line(capsys.readouterr().err)
    assert rc == 2 and line.startswith(f"error: {path}: ")
    if target == "policy outside its run":   # no manifest: the file's own sha256 catches it
        assert ("content does not match its sha256" if fault == "flip"
                else "not a window-bench policy file, or a truncated or corrupt one (") in line
    else:
        assert f"sha256 does not match {d / 'manifest.json'}" in line
    assert line.endswith("restore it from a copy or start a new run")
    assert snapshot(tmp_path) == before


def test_the_state_format_round_trips_exactly_and_refuses_objects():
    g = torch.Generator().manual_seed(3)
    tree = {"w": torch.randn(3, 4), "rng": g.get_state(), "ids": np.arange(4, dtype=np.int64),
            "prov": np.array(["demo", "takeover"]), "opt": {"state": {0: {"step": torch.tensor(2.)}}},
            "betas": (0.9, 0.999), "np_rng": np.random.default_rng(5).bit_generator.state,
            "inf": float("inf"), "f32": np.float32(1.5), "__odd": None, "flags": np.array([True])}
    out, meta = parse_state(dump_state(tree, "state", {"seed": 0}), "x", "state")
    assert meta == {"seed": 0} and out["opt"]["state"][0]["step"].item() == 2.0
    assert out["betas"] == (0.9, 0.999) and out["np_rng"] == tree["np_rng"]
    assert out["inf"] == float("inf") and type(out["f32"]) is np.float32 and out["__odd"] is None
    assert torch.equal(out["w"], tree["w"]) and torch.equal(out["rng"], tree["rng"])
    assert out["prov"].tolist() == ["demo", "takeover"] and out["ids"].dtype == np.int64
    with pytest.raises(TypeError, match=r"state.bad: a object cannot be stored without pickle"):
        dump_state({"bad": object()}, "state")
    with pytest.raises(RunFileError, match="a window-bench 'state' file, not a policy file"):
        parse_state(dump_state(tree, "state"), "x", "policy")


# ---------------------------------------------------------------- directories
def test_a_directory_that_is_not_this_run_is_refused(runs, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my thesis")
    before = snapshot(tmp_path)
    assert main(RUN + ["--out", str(mine), "--demos", str(runs.demos)]) == 2
    assert one_line(capsys.readouterr().err) == (
        f"error: --out {mine}: not empty and not a window-bench run; choose a new or empty "
        f"directory")
    (mine / "notes.txt").unlink()    # a finished run of an older window-bench: results, no state
    shutil.copyfile(runs.out / "results.json", mine / "results.json")
    before = snapshot(tmp_path)
    assert main(RUN + ["--out", str(mine), "--demos", str(runs.demos)]) == 2
    assert "not empty and not a window-bench run" in one_line(capsys.readouterr().err)
    d = copy_run(runs, tmp_path)
    before = snapshot(tmp_path)
    assert main(RUN[:-1] + ["1", "--out", str(d), "--demos", str(runs.demos)]) == 2
    assert one_line(capsys.readouterr().err) == (
        f"error: --out {d}: already holds a run (method qcfql-offline, env_id WindowInstall-A-v0, "
        f"profile smoke, seed 0); pass --resume to continue it or choose another --out")
    assert main(["run", "--method", "qcfql", "--profile", "smoke", "--out", str(d), "--resume",
                 "--demos", str(runs.demos)]) == 2
    assert one_line(capsys.readouterr().err) == (
        f"error: --resume: the run in {d} has method = 'qcfql-offline', this command asks for "
        f"'qcfql'")
    assert snapshot(tmp_path) == before


def test_an_unreadable_demo_dataset_is_an_error_not_recollected(runs, tmp_path, capsys):
    demos = tmp_path / "demos"
    shutil.copytree(runs.demos, demos)
    h5 = next(demos.rglob("main_data.hdf5"))
    h5.write_bytes(h5.read_bytes()[: h5.stat().st_size // 2])
    before = snapshot(tmp_path)
    assert main(RUN + ["--out", str(tmp_path / "run"), "--demos", str(demos)]) == 2
    line = one_line(capsys.readouterr().err)
    name = f"demos-a-{DEFAULT_OPERATOR}-v0"
    assert line.startswith(f"error: dataset 'window-bench/{name}' at "
                           f"{demos / 'window-bench' / name} is unreadable: ")
    assert line.endswith("it was not replaced: repair or remove it, or pass another --demos")
    assert snapshot(tmp_path) == before and not (tmp_path / "run").exists()


# ---------------------------------------------------------------- validation before work
@pytest.mark.parametrize("item,message", [
    ("alpha=Infinity", "QCFQLConfig.alpha = inf is not allowed: it must be a real number in "
                       "[0.0, 1000000.0]"),
    ("lr=1e30", "QCFQLConfig.lr = 1e+30 is not allowed: it must be a real number in (0.0, 1.0]"),
    ("gamma=1.5", "QCFQLConfig.gamma = 1.5 is not allowed: it must be a real number in [0.0, 1.0]"),
    ("alpha=abc", "QCFQLConfig.alpha = 'abc' is not allowed: it must be a real number in "
                  "[0.0, 1000000.0]"),
    ("h=3", "--agent-config h = 3: the method qcfql has h = 10 (Table 1); choose the method "
            "with the chunk horizon you want"),
    ("nope=1", "unknown agent config field 'nope'; fields of QCFQLConfig: h, hidden, "),
    ("hidden=-5", "QCFQLConfig.hidden = -5 is not allowed: it must be a list of integers"),
    ("hidden=[100000]", "QCFQLConfig.hidden = (100000,) is not allowed: each entry must be at "
                        "most 8192"),
    ("student_hidden=5", "QCFQLConfig.student_hidden = 5 is not allowed: it must be a list "
                         "of integers or null"),
])
def test_a_bad_agent_config_stops_before_demos_or_files(tmp_path, capsys, item, message):
    out, demos = tmp_path / "run", tmp_path / "demos"
    assert main(["run", "--method", "qcfql", "--profile", "smoke", "--out", str(out), "--demos",
                 str(demos), "--agent-config", item]) == 2
    assert one_line(capsys.readouterr().err).startswith(f"error: {message}")
    assert not out.exists() and not demos.exists()


@pytest.mark.parametrize("argv,message", [
    (RUN[:-1] + ["-1", "--out", "x"],
     "bench run: error: argument --seed: must be in 0..2147483647, got -1"),
    (["install", "--seed", "-1"],
     "bench install: error: argument --seed: must be in 0..2147483647, got -1"),
    (["demos", "--seed", "-2"],
     "bench demos: error: argument --seed: must be in 0..2147483647, got -2"),
    (["supervise", "--seed", "-1"], "bench supervise: error: argument --seed: must be in 0.."),
    (RUN[:-1] + ["99999999999999999999999", "--out", "x"],   # torch cannot seed with it
     "bench run: error: argument --seed: must be in 0..2147483647, got 99999999999999999999999"),
])
def test_a_seed_out_of_range_is_one_line_and_exit_2(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert one_line(capsys.readouterr().err).startswith(message)


def test_bad_paths_are_one_line_errors(runs, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(SystemExit) as exc:
        main(RUN + ["--out", str(tmp_path / "afile" / "run")])
    assert exc.value.code == 2
    assert one_line(capsys.readouterr().err).startswith(
        f"bench run: error: argument --out: {tmp_path / 'afile' / 'run'}: {tmp_path / 'afile'} "
        f"is a file, not a directory")
    assert main(["eval", str(runs.out / "results.json"), "--episodes", "1"]) == 2
    assert one_line(capsys.readouterr().err).startswith(
        f"error: {runs.out / 'results.json'}: not a window-bench policy file, or a truncated or "
        f"corrupt one (")
    assert main(["eval", str(tmp_path / "none.safetensors")]) == 2
    assert one_line(capsys.readouterr().err) == f"error: {tmp_path / 'none.safetensors'}: no such file"
    assert snapshot(tmp_path) == {"afile": hashlib.sha256(b"x").hexdigest()}


# ---------------------------------------------------------------- leaderboard
@pytest.mark.parametrize("edit,message", [
    (lambda r: r["final"].update(success_rate=7.5),
     "final.success_rate: 7.5 is greater than the maximum of 1"),
    (lambda r: r.update(env_id="../../x"), "env_id: '../../x' is not one of ['WindowInstall-A-v0'"),
    (lambda r: r.update(agent_config_overrides={"alpha": "../../x"}),
     "agent_config_overrides.alpha: '../../x' does not match"),
])
def test_the_leaderboard_checks_results_before_copying(runs, tmp_path, capsys, monkeypatch,
                                                       edit, message):
    monkeypatch.chdir(tmp_path)
    d = copy_run(runs, tmp_path)
    res = json.loads((d / "results.json").read_text())
    edit(res)
    (d / "results.json").write_text(json.dumps(res))
    m = json.loads((d / "manifest.json").read_text())   # a forged run forges its manifest too
    m["files"]["results.json"] = {"sha256": snapshot(d)["results.json"],
                                  "bytes": (d / "results.json").stat().st_size}
    (d / "manifest.json").write_text(json.dumps(m))
    before = snapshot(tmp_path)
    assert main(["leaderboard", "--add", str(d), "--root", "lb/runs"]) == 2
    assert one_line(capsys.readouterr().err).startswith(f"error: {d / 'results.json'}: {message}")
    assert snapshot(tmp_path) == before


def test_one_bad_file_in_the_root_does_not_break_the_build(runs, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["leaderboard", "--add", str(runs.out), "--root", "lb"]) == 0
    dest = tmp_path / "lb" / "WindowInstall-A-v0" / "qcfql-offline-smoke-s0"
    assert sorted(p.name for p in dest.iterdir()) == ["checkpoints.csv", "learning_curve.png",
                                                       "manifest.json", "policies", "results.json"]
    (tmp_path / "lb" / "x").mkdir()
    (tmp_path / "lb" / "x" / "results.json").write_text('{"schema_version": 1, "final": NaN}')
    capsys.readouterr()
    assert main(["leaderboard", "--root", "lb"]) == 0
    out, err = capsys.readouterr()
    assert "| WindowInstall-A-v0 | Ours (offline-only) (`qcfql-offline`) | smoke | 0 |" in out
    assert one_line(err).startswith(f"skipped lb/x/results.json: not readable JSON (NaN is not")


def test_equal_states_give_byte_identical_files():
    """safetensors writes its header from a hash map; dump_state sorts it, so the same state
    always hashes the same (final_eval.policy_sha256 is reproducible)."""
    import torch

    from window_bench.harness import files as F

    tree = {"w": torch.arange(12.0).reshape(3, 4), "b": torch.zeros(2),
            "config": {"hidden": [256, 256], "lr": 3e-4, "name": "x"}}
    meta = {"method": "qcfql", "env_id": "WindowInstall-A-v0", "seed": 0, "env_steps": 3000}
    blobs = {F.dump_state(tree, "policy", meta) for _ in range(16)}
    assert len(blobs) == 1
    back, got = F.parse_state(blobs.pop(), "p.safetensors", "policy")
    assert got == meta and torch.equal(back["w"], tree["w"])


def test_resume_on_a_new_directory_starts_the_run(tmp_path):
    """README's main command passes --resume on a fresh machine: one command starts or
    continues a run, so --resume into a new (or empty) directory starts it."""
    from window_bench.harness.files import MANIFEST, RunDir

    for out in (tmp_path / "new", tmp_path / "empty"):
        if out.name == "empty":
            out.mkdir()
        rd = RunDir(out, {"method": "qcfql", "seed": 0}, resume=True)
        try:
            assert (out / MANIFEST).is_file()
        finally:
            rd.close()
