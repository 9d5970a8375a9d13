"""Hostile files and malformed command lines.

* A Minari dataset whose ``metadata.json`` names code (``entry_point = "subprocess:run"``) is
  refused by every command that reads demonstrations, before Minari could build that env.
* ``--resume`` refuses a manifest edited to another run, and arguments the run did not record.
* A file a command writes is replaced only with ``--force``.
* More than a hundred malformed invocations, over every subcommand, each end in exit code 2
  with one line on stderr, no traceback and no file written.

One smoke run (``qcfql-offline``, its demos collected into its own ``demos/``) is shared by
the module; everything else fails at validation, before any work.
"""

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from window_bench.cli import main
from window_bench.installer.demos import demo_dataset_path
from window_bench.installer.operators import DEFAULT_OPERATOR

BENCH = [sys.executable, "-m", "window_bench.cli"]
RUN = ["run", "--method", "qcfql-offline", "--profile", "smoke", "--seed", "0",
       "--eval-workers", "1"]
POLICY = "policies/step_0000000.safetensors"
DATASET = demo_dataset_path("demos", "WindowInstall-A-v0", DEFAULT_OPERATOR)   # in a run dir
DATASET_ID = f"window-bench/demos-a-{DEFAULT_OPERATOR}-v0"


def snapshot(d: Path) -> dict:
    """Every file and directory under ``d`` (hidden ones too), files with their sha256."""
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
            if p.is_file() else "dir" for p in sorted(Path(d).rglob("*"))}


def one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def bench(argv, capsys) -> tuple[int, str]:
    """``bench ARGV`` in this process: its exit code (argparse's too) and its one stderr line."""
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    assert "Traceback" not in out
    return rc, one_line(err)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("smoke") / "run"
    assert main(RUN + ["--out", str(out)]) == 0
    assert (out / DATASET / "data" / "metadata.json").is_file()
    return out


def plant_code(dataset: Path, marker: Path) -> None:
    """Make ``dataset``'s metadata name ``subprocess:run`` as its env, with kwargs that touch
    ``marker``, and drop its spaces (so that opening it makes Minari build that env)."""
    path = dataset / "data" / "metadata.json"
    meta = json.loads(path.read_text())
    spec = json.loads(meta["env_spec"])
    spec.update(entry_point="subprocess:run", kwargs={"args": ["touch", str(marker)]})
    meta["env_spec"] = json.dumps(spec)
    del meta["observation_space"], meta["action_space"]
    path.write_text(json.dumps(meta))


@pytest.fixture
def evil_root(run_dir, tmp_path):
    """A datasets root holding the run's demos with code planted in their metadata."""
    root = tmp_path / "evil"
    shutil.copytree(run_dir / "demos", root)
    plant_code(root / DATASET.relative_to("demos"), tmp_path / "MARKER")
    return root


REFUSED = ("its env spec names env 'WindowInstall-A-v0' with entry point 'subprocess:run'; "
           "window-bench reads only datasets of its own envs")


# ---------------------------------------------------------------- code named by a dataset
def test_the_planted_payload_runs_under_minari_alone(evil_root, tmp_path, monkeypatch):
    """The crafted dataset is live: Minari's own loader runs the command it names."""
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(evil_root))
    with pytest.raises(Exception):   # subprocess.run returns no env: but it did run
        minari.load_dataset(DATASET_ID)
    assert (tmp_path / "MARKER").exists()


def test_bench_run_demos_refuses_a_dataset_that_names_code(evil_root, tmp_path, capsys,
                                                           monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    rc, line = bench(RUN + ["--out", "r", "--demos", str(evil_root)], capsys)
    assert rc == 2 and line.startswith(f"error: dataset '{DATASET_ID}' at "
                                       f"{evil_root / DATASET.relative_to('demos')}: ")
    assert "records no observation_space" in line and line.endswith("or pass another --demos")
    assert not (tmp_path / "MARKER").exists() and snapshot(tmp_path) == before
    # with its spaces left in place, the spec alone is refused all the same
    meta_file = evil_root / DATASET.relative_to("demos") / "data" / "metadata.json"
    meta = json.loads(meta_file.read_text())
    meta["observation_space"] = meta["action_space"] = '{"type": "Box"}'
    meta_file.write_text(json.dumps(meta))
    rc, line = bench(RUN + ["--out", "r", "--demos", str(evil_root)], capsys)
    assert rc == 2 and REFUSED in line and not (tmp_path / "MARKER").exists()


def test_bench_demos_refuses_an_out_holding_such_a_dataset(evil_root, tmp_path):
    """Through a real process: stderr is one line, exit code 2."""
    before = snapshot(tmp_path)
    r = subprocess.run(BENCH + ["demos", "--n", "2", "--out", str(evil_root)],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 2
    line = one_line(r.stderr)
    assert "records no observation_space" in line and line.endswith("collect into another --out")
    assert not (tmp_path / "MARKER").exists() and snapshot(tmp_path) == before


def test_resume_refuses_code_planted_in_the_runs_own_demos(run_dir, tmp_path, capsys):
    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    plant_code(d / DATASET, tmp_path / "MARKER")
    meta = d / DATASET / "data" / "metadata.json"
    before = snapshot(tmp_path)
    rc, line = bench(RUN + ["--out", str(d), "--resume"], capsys)
    assert rc == 2 and line == (f"error: {meta}: sha256 does not match {d / 'manifest.json'} "
                                f"(changed after bench wrote it: truncated, corrupt or edited); "
                                f"restore it from a copy or start a new run")
    assert snapshot(tmp_path) == before
    # the manifest forged to match: the run's own files verify, the dataset is still refused
    m = json.loads((d / "manifest.json").read_text())
    m["files"][f"{DATASET}/data/metadata.json"] = {
        "sha256": hashlib.sha256(meta.read_bytes()).hexdigest(), "bytes": meta.stat().st_size}
    (d / "manifest.json").write_text(json.dumps(m))
    before = snapshot(tmp_path)
    rc, line = bench(RUN + ["--out", str(d), "--resume"], capsys)
    assert rc == 2 and "records no observation_space" in line
    # a file added beside the listed ones is refused before the dataset is opened
    (d / DATASET / "data" / "extra.json").write_text("{}")
    rc, line = bench(RUN + ["--out", str(d), "--resume"], capsys)
    assert rc == 2 and line == (f"error: {d / DATASET / 'data' / 'extra.json'}: not listed in "
                                f"{d / 'manifest.json'}, so it was not written by this run; "
                                f"remove it or restore the run")
    (d / DATASET / "data" / "extra.json").unlink()
    assert not (tmp_path / "MARKER").exists() and snapshot(tmp_path) == before


# ---------------------------------------------------------------- inconsistent resumes
def test_resume_refuses_a_manifest_edited_to_another_seed(run_dir, tmp_path, capsys):
    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    m = json.loads((d / "manifest.json").read_text())
    m["run"]["seed"] = 1
    (d / "manifest.json").write_text(json.dumps(m))
    before = snapshot(tmp_path)
    rc, line = bench(RUN[:-3] + ["1", "--eval-workers", "1", "--out", str(d), "--resume"],
                     capsys)
    assert rc == 2 and line == (f"error: {d / 'manifest.json'}: records seed = 1, the run's "
                                f"state.safetensors was saved with 0 (edited, or another run's "
                                f"manifest); restore it from a copy or start a new run")
    assert snapshot(tmp_path) == before
    assert json.loads((d / "results.json").read_text())["seed"] == 0


@pytest.mark.parametrize("change,key,saved,asked", [
    (["--method", "qcfql"], "method", "'qcfql-offline'", "'qcfql'"),
    (["--seed", "3"], "seed", "0", "3"),
    (["--profile", "cpu"], "profile", "'smoke'", "'cpu'"),
    (["--agent-config", "alpha=3"], "agent_config", "{}", "{'alpha': 3}"),
    (["--operator", "expert"], "operator", f"'{DEFAULT_OPERATOR}'", "'expert'"),
])
def test_resume_refuses_arguments_the_run_did_not_record(run_dir, tmp_path, capsys, change,
                                                         key, saved, asked):
    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    argv = RUN + ["--out", str(d), "--resume"]
    i = argv.index(change[0]) if change[0] in argv else len(argv)
    argv[i:i + 2] = change
    before = snapshot(tmp_path)
    rc, line = bench(argv, capsys)
    assert rc == 2 and line == (f"error: --resume: the run in {d} has {key} = {saved}, this "
                                f"command asks for {asked}")
    assert snapshot(tmp_path) == before


def test_resume_refuses_other_demonstrations(run_dir, tmp_path, capsys):
    from window_bench.installer.demos import collect_demos

    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    collect_demos("WindowInstall-A-v0", 2, tmp_path / "other", seed=5, progress=False)
    before = snapshot(tmp_path)
    rc, line = bench(RUN + ["--out", str(d), "--resume", "--demos", str(tmp_path / "other")],
                     capsys)
    assert rc == 2 and line.startswith(f"error: --resume: the run in {d} began on other "
                                       f"demonstrations than those in {tmp_path / 'other'} ")
    assert snapshot(tmp_path) == before


# ---------------------------------------------------------------- nothing overwritten unasked
def test_eval_out_replaces_a_file_only_with_force(run_dir, tmp_path, capsys):
    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    argv = ["eval", str(d / POLICY), "--episodes", "1", "--eval-workers", "1",
            "--out", str(d / "results.json")]
    before = snapshot(tmp_path)
    rc, line = bench(argv, capsys)
    assert rc == 2 and line == f"error: {d / 'results.json'} exists; pass --force to overwrite it"
    assert snapshot(tmp_path) == before
    assert main(argv + ["--force"]) == 0
    r = json.loads((d / "results.json").read_text())
    assert r["policy"] == str(d / POLICY) and r["episodes"] == 1 and "final" not in r


def test_encoder_train_without_opengl_is_one_line(tmp_path, capsys, monkeypatch):
    """A machine that cannot render stops the command before any episode, in one line."""
    import mujoco

    import window_bench.gl

    def no_gl(*args):
        raise mujoco.FatalError("an OpenGL platform library has not been loaded into this "
                                "process, this most likely means ...")
    monkeypatch.setattr(window_bench.gl, "renderer", no_gl)
    monkeypatch.chdir(tmp_path)
    rc, line = bench(["encoder", "train", "--out", "enc.safetensors"], capsys)
    assert rc == 2 and line == (f"error: cannot render with MUJOCO_GL="
                                f"{os.environ.get('MUJOCO_GL')}: an OpenGL platform library has "
                                f"not been loaded into this process, this most likely means ...")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- malformed invocations
LONG = "x" * 300    # longer than a file name may be
MALFORMED = [
    # bench itself
    [], ["nope"], ["--bogus"], ["methods", "extra"], ["methods", "--json"], ["encoder"],
    ["encoder", "fit"],
    # install
    ["install", "--env", "WindowInstall-C-v0"], ["install", "--env", ""],
    ["install", "--episodes", "0"], ["install", "--episodes", "-1"],
    ["install", "--episodes", "x"], ["install", "--episodes", "1.5"], ["install", "--episodes"],
    ["install", "--seed", "-1"], ["install", "--seed", "2147483648"],
    ["install", "--seed", "1e3"], ["install", "--controller", "magic"],
    ["install", "--out", "adir"], ["install", "--out", "afile/x.json"],
    ["install", "--out", "existing.json"], ["install", "--out", f"{LONG}/x.json"],
    ["install", "--frobnicate"],
    # calibrate
    ["calibrate", "--env", "X-v0"], ["calibrate", "--env"], ["calibrate", "--controllers", "magic"],
    ["calibrate", "--episodes", "0"], ["calibrate", "--seed", "-5"], ["calibrate", "--out", "afile"],
    ["calibrate", "--out", "afile/sub"], ["calibrate", "--episodes", "abc"],
    ["calibrate", "--out", LONG],
    ["calibrate", "--env", "WindowInstall-B-v0", "--controllers", "installer", "--out", "cal"],
    # demos
    ["demos", "--n", "0"], ["demos", "--n", "x"], ["demos", "--max-attempts", "0"],
    ["demos", "--operator", "nobody"], ["demos", "--env", "X"], ["demos", "--out", "afile"],
    ["demos", "--seed", "99999999999999"], ["demos", "--n", "3", "--max-attempts", "2",
                                             "--out", "d"],
    # supervise
    ["supervise", "--controller", "x"], ["supervise", "--operator", "x"],
    ["supervise", "--episodes", "0"], ["supervise", "--h", "0"], ["supervise", "--seed", "-1"],
    ["supervise", "--out", "existing.json"], ["supervise", "--out", "adir"],
    # teleop
    ["teleop", "--episodes", "0"], ["teleop", "--device", "joystick"],
    ["teleop", "--max-steps", "0"], ["teleop", "--env", "X"], ["teleop", "--seed", "-1"],
    # encoder
    ["encoder", "train"], ["encoder", "train", "--out", "existing.json"],
    ["encoder", "train", "--out", "adir"], ["encoder", "train", "--out", "e", "--env", "X"],
    ["encoder", "train", "--out", "e", "--episodes", "0"],
    ["encoder", "train", "--out", "e", "--lr", "0"], ["encoder", "train", "--out", "e", "--lr", "2"],
    ["encoder", "train", "--out", "e", "--lr", "nan"],
    ["encoder", "train", "--out", "e", "--max-minutes", "0"],
    ["encoder", "train", "--out", "e", "--batch", "0"],
    ["encoder", "train", "--out", "e", "--seed", "-1"],
    ["encoder", "info"], ["encoder", "info", "none.safetensors"], ["encoder", "info", "adir"],
    ["encoder", "info", "garbage.bin"], ["encoder", "info", "existing.json"],
    # run: arguments
    ["run"], ["run", "--method", "x", "--out", "r"], ["run", "--method", "qcfql"],
    ["run", "--method", "qcfql", "--out", "afile"],
    ["run", "--method", "qcfql", "--out", "afile/r"],
    ["run", "--method", "qcfql", "--out", "r", "--profile", "x"],
    ["run", "--method", "qcfql", "--out", "r", "--seed", "-1"],
    ["run", "--method", "qcfql", "--out", "r", "--seed", "99999999999999999999999"],
    ["run", "--method", "qcfql", "--out", "r", "--track", "x"],
    ["run", "--method", "qcfql", "--out", "r", "--operator", "x"],
    ["run", "--method", "qcfql", "--out", "r", "--h", "0"],
    ["run", "--method", "sac", "--out", "r", "--h", "5"],
    ["run", "--method", "qcfql", "--out", "r", "--final-episodes", "0"],
    ["run", "--method", "qcfql", "--out", "r", "--final-episodes", "400001"],
    ["run", "--method", "qcfql", "--out", "r", "--final-seed-set", "x"],
    ["run", "--method", "qcfql", "--out", "r", "--eval-workers", "0"],
    ["run", "--method", "qcfql", "--out", "r", "--eval-workers", "65"],
    ["run", "--method", "qcfql", "--out", "r", "--demos", "afile"],
    ["run", "--method", "qcfql", "--out", "r", "--demos", "afile/x"],
    ["run", "--method", "qcfql", "--out", "r", "--demos", "r/elsewhere"],
    ["run", "--method", "qcfql", "--out", "r", "--stage1-cache", "afile"],
    ["run", "--method", "qcfql", "--out", "r", "--track", "pixels",
     "--pixel-demos-cache", "afile"],
    ["run", "--method", "qcfql", "--out", "r", "--track", "pixels",
     "--encoder-weights", "none.safetensors"],
    ["run", "--method", "qcfql", "--out", "r", "--track", "pixels",
     "--encoder-weights", "garbage.bin"],
    ["run", "--method", "qcfql", "--out", "adir"],   # not empty and not a run
    ["run", "--method", "qcfql", "--out", "r", "--acceptance-noise", "a", "b", "c"],
    ["run", "--method", "qcfql", "--out", "r", "--acceptance-noise", "0.1", "0.1"],
    ["run", "--method", "qcfql", "--out", "r", "--acceptance-noise", "2", "0", "0"],
    ["run", "--method", "qcfql", "--out", "r", "--acceptance-noise", "nan", "0", "0"],
    ["run", "--method", "qcfql", "--out", "r", "--acceptance-noise", "0.1", "0.1", "-1"],
    ["run", "--method", "qcfql", "--out", "r", "--acceptance-noise", "0.1", "0.1", "1.5"],
    # run: agent configs
    *[["run", "--method", m, "--out", "r", "--agent-config", *items] for m, items in [
        ("qcfql", ["foo"]), ("qcfql", ["nope=1"]), ("qcfql", ["hidden=-5"]),
        ("qcfql", ["hidden=[]"]), ("qcfql", ["hidden=[0]"]), ("qcfql", ["hidden=[[1]]"]),
        ("qcfql", ["hidden=[99999999]"]), ("qcfql", ["alpha=Infinity"]), ("qcfql", ["alpha=NaN"]),
        ("qcfql", ["lr=1e30"]), ("qcfql", ["gamma=1.5"]), ("qcfql", ["batch_size=0"]),
        ("qcfql", ["batch_size=true"]), ("qcfql", ["batch_size=99999999999"]),
        ("qcfql", ["q_agg=x"]), ("qcfql", ["q_agg=1"]), ("qcfql", ["h=3"]),
        ("qcfql", ["student_hidden={}"]), ("qcfql", ["policy_ema=-0.1"]),
        ("hil-serl", ["hidden=-5"]), ("hil-serl", ["vacuum_epsilon=2"]),
        ("hil-serl", ["target_range=[1]"]), ("hil-serl", ["target_range=[1, NaN]"]),
        ("hil-serl", ["log_std_min=Infinity"]), ("hil-serl", ["num_min=3"]),
        ("act", ["dropout=1"]), ("act", ["n_heads=3"]), ("act", ["chunk=0"]),
        ("act", ["loss=l3"]), ("act", ["lr=-1"]), ("sac", ["x=1"]),
    ]],
    # eval
    ["eval"], ["eval", "none.safetensors"], ["eval", "adir"], ["eval", "garbage.bin"],
    ["eval", "existing.json"], ["eval", "p.safetensors", "--episodes", "0"],
    ["eval", "p.safetensors", "--episodes", "400001"], ["eval", "p.safetensors", "--env", "X"],
    ["eval", "p.safetensors", "--seed-set", "x"], ["eval", "p.safetensors", "--eval-workers", "0"],
    ["eval", "p.safetensors", "--eval-workers", "65"], ["eval", "p.safetensors", "--clearance", "30"],
    ["eval", "p.safetensors", "--clearance", "x"], ["eval", "p.safetensors", "--clearance", "nan"],
    ["eval", "p.safetensors", "--out", "existing.json"], ["eval", "p.safetensors", "--out", "adir"],
    # leaderboard, sweep, tables
    ["leaderboard", "--root", "afile"], ["leaderboard", "--root", "nowhere"],
    ["leaderboard", "--add", "nowhere", "--root", "lb"], ["leaderboard", "--add", "adir",
                                                          "--root", "lb"],
    ["sweep"], ["sweep", "none.toml"], ["sweep", "garbage.bin"], ["sweep", "g.toml", "--workers", "0"],
    ["sweep", "g.toml", "--out", "afile"],
    ["tables"], ["tables", "--out", "t", "--runs", "nowhere"], ["tables", "--out", "afile"],
    ["tables", "--out", "t", "--runs", "afile"],
    # video
    ["video", "--policy", "none.safetensors"], ["video", "--policy", "garbage.bin"],
    ["video", "--cameras", "x"], ["video", "--size", "0"], ["video", "--size", "100000"],
    ["video", "--fps", "0"], ["video", "--fps", "1000"], ["video", "--episodes", "0"],
    ["video", "--env", "X"], ["video", "--out", "afile"], ["video", "--out", "recording"],
    ["video", "--seed", "-1"],
    # names longer than the file system allows
    ["run", "--method", "qcfql", "--out", LONG], ["run", "--method", "qcfql", "--out", "r",
                                                  "--demos", LONG],
    ["eval", LONG], ["encoder", "info", LONG], ["video", "--policy", LONG],
    ["video", "--out", LONG], ["tables", "--out", "t", "--runs", LONG],
    ["sweep", "g.toml", "--out", LONG], ["leaderboard", "--root", LONG],
]


@pytest.fixture
def hostile_cwd(tmp_path, monkeypatch):
    """A working directory with a file, a directory that is not a run, an output that exists,
    a garbage file, a recording and a calibration row that is not one."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir" / "notes.txt").write_text("mine")
    (tmp_path / "existing.json").write_text('{"mine": true}')
    (tmp_path / "garbage.bin").write_bytes(b"\x80\x04garbage" * 10)
    (tmp_path / "recording").mkdir()
    (tmp_path / "recording" / "videos.json").write_text("{}")
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "WindowInstall-B-v0__installer.jsonl").write_text('[1, 2]\n')
    return tmp_path


def test_malformed_invocations_are_one_line_exit_2_and_write_nothing(hostile_cwd, capsys):
    assert len(MALFORMED) >= 100
    before = snapshot(hostile_cwd)
    failures = []
    for argv in MALFORMED:
        try:
            rc, line = bench(argv, capsys)
        except Exception as e:   # noqa: BLE001 - a traceback, or more than one line
            failures.append(f"{argv}: {type(e).__name__}: {str(e).splitlines()[:3]}")
            capsys.readouterr()
            continue
        if rc != 2 or not line.startswith(("error: ", "bench")):
            failures.append(f"{argv}: exit {rc}: {line}")
        if snapshot(hostile_cwd) != before:
            failures.append(f"{argv}: wrote {set(snapshot(hostile_cwd)) - set(before)}")
            before = snapshot(hostile_cwd)
    assert not failures, "\n".join(failures)
