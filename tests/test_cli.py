"""The ``bench`` command line: the README's main job and its error messages."""

import json
import subprocess
import sys

import pytest

from window_bench.cli import main


def test_bench_install_prints_stages_and_summary(capsys, tmp_path):
    out = tmp_path / "install.json"
    assert main(["install", "--env", "WindowInstall-A-v0", "--episodes", "2", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "success 2/2" in text and "Wilson" in text and "mean cycle time" in text
    assert "suction" in text and "entered" in text and "seated" in text
    data = json.loads(out.read_text())
    assert data["summary"]["episodes"] == 2
    prov = data["provenance"]
    assert {"window_bench", "mujoco", "numpy", "gymnasium", "git_commit"} <= set(prov)
    assert [e["seed"] for e in data["episodes"]] == [0, 1]


@pytest.mark.parametrize("argv,needle", [
    (["install", "--env", "WindowInstall-C-v0"], "unknown env 'WindowInstall-C-v0'"),
    (["install", "--episodes", "0"], "must be >= 1, got 0"),
    (["install", "--episodes", "three"], "expected an integer, got 'three'"),
    (["install", "--controller", "magic"], "invalid choice: 'magic'"),
    (["eval", "p.safetensors", "--clearance", "30"],
     "30 mm is outside the supported range [0.5, 20] mm per side"),
    (["eval", "p.safetensors", "--clearance", "0.2"], "0.2 mm is outside the supported range"),
    (["eval", "p.safetensors", "--clearance", "wide"], "'wide' is not a number of millimetres"),
])
def test_bench_rejects_bad_input_with_a_clear_message(argv, needle, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert needle in capsys.readouterr().err


def test_run_preset_gives_its_overrides_and_agent_config_wins(tmp_path, capsys):
    """``--preset hilserl-own`` runs HIL-SERL with its authors' settings (recorded in the
    manifest); ``--agent-config`` entries override the preset's; a preset for another agent
    is one line naming the field, exit 2, nothing written."""
    from baselines.hilserl import HILSERL_OWN
    from window_bench.cli import _agent_config

    assert _agent_config("hilserl-own", None) == dict(HILSERL_OWN)
    assert _agent_config("hilserl-own", ["gamma=0.97"])["gamma"] == 0.97
    assert _agent_config(None, ["alpha=100"]) == {"alpha": 100}
    out = tmp_path / "run"
    assert main(["run", "--method", "qcfql", "--profile", "smoke", "--preset", "hilserl-own",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown agent config field 'log_std_min'" in err[0]
    assert not out.exists()
    with pytest.raises(SystemExit):
        main(["run", "--preset", "nobody"])
    assert "invalid choice: 'nobody'" in capsys.readouterr().err


def test_bench_calibrate_writes_table_json_and_plot(tmp_path):
    out = tmp_path / "cal"
    assert main(["calibrate", "--env", "WindowInstall-B-v0", "--controllers", "installer",
                 "--episodes", "2", "--out", str(out)]) == 0
    data = json.loads((out / "calibration.json").read_text())
    s = data["results"]["WindowInstall-B-v0"]["installer"]
    assert s["episodes"] == 2 and 0.0 <= s["wilson95"][0] <= s["success_rate"] <= s["wilson95"][1]
    assert data["seed"] == 0 and "git_commit" in data["provenance"]
    assert "| WindowInstall-B-v0 | installer | 2 |" in (out / "calibration.md").read_text()
    assert (out / "calibration.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len((out / "WindowInstall-B-v0__installer.jsonl").read_text().splitlines()) == 2


def test_console_script_is_installed():
    r = subprocess.run([sys.executable, "-m", "window_bench.cli", "--help"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "calibrate" in r.stdout and "install" in r.stdout


def test_every_option_has_help_and_shows_its_default():
    import argparse

    from window_bench.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name, parser in sub.choices.items():
        for action in parser._actions:
            if action.option_strings and not isinstance(action, argparse._HelpAction):
                assert action.help, f"bench {name} {action.option_strings[0]} has no help"
        text = parser.format_help()
        if any(a.default not in (None, False, argparse.SUPPRESS) for a in parser._actions
               if a.option_strings and a.help):
            assert "(default:" in text, f"bench {name} --help shows no defaults"
