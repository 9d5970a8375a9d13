"""The setting-B diagnostics (experiments/sanity/grasp_timing.py, student_gap.py): the gap they follow
is the env's engage quantity, and a policy that descends onto the panel with the vacuum on
is recorded as acquiring it within reach."""

import importlib.util
import json
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import window_bench  # noqa: F401
from window_bench.envs.env import SNAP_DISTANCE

SANITY = Path(__file__).parents[1] / "experiments" / "sanity"


def _script(name):
    sys.path.insert(0, str(SANITY))
    try:
        spec = importlib.util.spec_from_file_location(name, SANITY / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(SANITY))
    return module


def test_face_gap_is_the_tcp_height_above_the_suction_face_and_matches_the_engage_test():
    g = _script("grasp_timing")
    env = gym.make("WindowInstall-B-v0", obs_mode="flat")
    env.reset(seed=100000)
    u = env.unwrapped
    face_z = u.data.xpos[u.scene.panel_body][2] + u.cfg.panel_thickness / 2
    tcp_z = u.data.site_xpos[u.scene.tcp_site][2]
    assert g.face_gap(u) == pytest.approx(tcp_z - face_z, abs=1e-9)   # the panel lies flat
    assert g.face_gap(u) > SNAP_DISTANCE and not u.suction_valid()
    env.close()


class Descend:
    """Straight down (tool z points down at the start of B) with the vacuum on, creeping the
    last centimetres (the face is at 80 mm): a latch made while driving on breaks at once."""
    h = 1                                         # re-decide every step

    def act(self, obs):
        z = obs[16]                               # obs[14:17]: the TCP position
        down = 1.0 if z > 0.15 else 0.2 if z > 0.095 else 0.05
        return np.tile(np.array([0, 0, down, 0, 0, 0, 1.0], np.float32), (self.h, 1))


class Hover(Descend):
    def act(self, obs):
        return np.zeros((self.h, 7), np.float32)


def test_episode_records_acquisition_within_reach_and_a_miss_without_it():
    g = _script("grasp_timing")
    hit = g.episode(Descend(), "WindowInstall-B-v0", 100001)   # panel under the TCP
    assert hit["acquired"] and hit["vacuum_on_within_reach_steps"] >= 1
    assert hit["min_gap_mm"] <= 1000 * SNAP_DISTANCE and hit["steps"] < 100
    miss = g.episode(Hover(), "WindowInstall-B-v0", 100000)
    assert not miss["acquired"] and miss["vacuum_on_steps"] == 0 and miss["steps"] == 600
    s = g.summarize([hit, miss])
    assert (s["acquired"], s["missed"], s["missed_never_commanded_vacuum"]) == (1, 1, 1)


def test_student_gap_splits_by_latch_and_fresh_student_leaves_the_agent_alone():
    import torch

    from baselines.qcfql import QCFQLAgent, QCFQLConfig

    s = _script("student_gap")
    agent = QCFQLAgent(52, 7, QCFQLConfig(h=2, hidden=(16,)), seed=0)
    obs = np.zeros((6, 52), np.float32)
    obs[:2, s.VACUUM_INDEX] = 1.0                       # two latched states, four before
    gap = s.gap_by_stage(agent, obs)
    assert (gap["latched"]["states"], gap["before_latch"]["states"]) == (2, 4)
    o = agent.normalize(torch.as_tensor(obs))
    teacher = agent.teacher_actions(o, torch.zeros(6, 14))
    with torch.no_grad():
        d = (agent.ema_student(o, torch.zeros(6, 14)).clamp(-1, 1) - teacher).norm(dim=-1)
    assert gap["before_latch"]["student_teacher_l2_median"] == pytest.approx(
        float(d[2:].median()), rel=1e-6)
    before = [p.clone() for p in agent.student.parameters()]
    wide = s.fresh_student(agent, (32, 32), seed=1)
    widths = [m.out_features for m in wide.student.modules() if isinstance(m, torch.nn.Linear)]
    assert widths == [32, 32, 14] and wide.ema_student.net[0].out_features == 32
    assert all(torch.equal(p, q) for p, q in zip(agent.student.parameters(), before))
    assert torch.equal(wide.teacher_actions(agent.normalize(torch.as_tensor(obs)),
                                            torch.zeros(6, 14)), teacher)   # same teacher


def _touched(grasp, contact):
    return [{"grasp_mm": [gx, gy, 45.0], "first_contact": {"lateral_mm": [cx, 0.0, cz]}}
            for (gx, gy), (cx, cz) in zip(grasp, contact)]


def test_entry_contact_reads_a_carried_grip_offset_as_slope_minus_one_and_a_corrected_one_as_zero():
    ec = _script("entry_contact")
    grasp = [(-3.0, 1.0), (-1.0, -2.0), (0.5, 0.0), (2.0, 3.0), (4.0, -1.0)]
    carried = ec.follows_grasp(_touched(grasp, [(-gx, gy) for gx, gy in grasp]))
    assert carried["across"]["slope"] == pytest.approx(-1.0) and carried["across"]["r"] == -1.0
    assert carried["vertical"]["slope"] == pytest.approx(1.0) and carried["vertical"]["n"] == 5
    noise = [(0.3, -0.2), (-0.1, 0.4), (0.2, 0.1), (-0.4, -0.3), (0.1, 0.2)]
    corrected = ec.follows_grasp(_touched(grasp, noise))
    assert abs(corrected["across"]["slope"]) < 0.1
    # no grip recorded, or too few episodes: no number rather than a made-up one
    assert ec.follows_grasp(_touched(grasp[:2], noise[:2])) == {"across": None, "vertical": None}
    assert ec.follows_grasp([{"grasp_mm": None, "first_contact": {"lateral_mm": [1, 0, 1]}}]
                            * 4)["across"] is None


def test_budget_runs_splits_stage_iii_into_thirds_without_the_warm_start():
    br = _script("budget_runs")
    eps = ([{"steps": 100, "takeover_steps": 0}] * 2                 # warm start: 200 steps
           + [{"steps": 100, "takeover_steps": 50}] * 3              # first third
           + [{"steps": 100, "takeover_steps": 20}] * 3
           + [{"steps": 100, "takeover_steps": 0}] * 3)
    assert br.stage_iii_thirds(eps, warm_steps=200) == [0.5, 0.2, 0.0]
    assert br.stage_iii_thirds(eps, warm_steps=0)[0] == 0.25   # warm episodes dilute it


def test_budget_runs_counts_each_thirds_takeovers_by_cue():
    br = _script("budget_runs")
    eps = ([{"steps": 100, "takeover_steps": 9, "takeover_cues": ["wedging"]}]   # warm start
           + [{"steps": 100, "takeover_steps": 30, "takeover_cues": ["coverage", "stall"]},
              {"steps": 100, "takeover_steps": 0, "takeover_cues": []},
              {"steps": 100, "takeover_steps": 10, "takeover_cues": ["stall"]}])
    assert br.stage_iii_cues(eps, warm_steps=100) == [{"coverage": 1, "stall": 1}, {},
                                                      {"stall": 1}]
    # the episodes themselves, indexed among all training episodes (warm start included)
    assert br.takeover_episodes(eps, warm_steps=100) == [
        {"episode": 1, "third": 1, "takeover_steps": 30, "cues": ["coverage", "stall"]},
        {"episode": 3, "third": 3, "takeover_steps": 10, "cues": ["stall"]}]


def test_budget_runs_refuses_a_missing_run_in_one_line_before_writing(tmp_path, capsys):
    br = _script("budget_runs")
    out = tmp_path / "o.json"
    with pytest.raises(SystemExit) as e:
        br.main([str(tmp_path / "nope"), "--out", str(out)])
    assert e.value.code == 2 and not out.exists()
    assert len(capsys.readouterr().err.strip().splitlines()[-1]) > 0


def test_entry_contact_centre_grip_latches_the_cup_over_the_face_centre(monkeypatch):
    from window_bench.envs.env import WindowInstallEnv

    monkeypatch.setattr(WindowInstallEnv, "_set_latch", WindowInstallEnv._set_latch)  # restored
    ec = _script("entry_contact")
    ec._centre_grip_at_latch()
    env = gym.make("WindowInstall-B-v0", obs_mode="flat")
    env.reset(seed=100003)
    u = env.unwrapped
    before = u.tcp_on_face()
    assert np.hypot(before[0], before[1]) > 0.01          # the free panel lies elsewhere
    u._set_latch(True)
    after = u.tcp_on_face()
    assert abs(after[0]) < 1e-9 and abs(after[1]) < 1e-9   # over the centre of the face
    assert after[2] == pytest.approx(before[2], abs=1e-9)  # gap kept
    env.close()


def test_demo_label_noise_fits_slope_and_correlation_and_gives_none_without_spread():
    d = _script("demo_label_noise")
    x = np.linspace(-2, 2, 50)
    assert d.fit(x, 0.3 * x + 1.0) == {"slope": 0.3, "r": 1.0}
    assert d.fit(x, -0.5 * x)["r"] == -1.0
    assert d.fit(np.zeros(10), x[:10]) == {"slope": None, "r": None}
    assert d.fit(x[:2], x[:2]) == {"slope": None, "r": None}


def test_demo_label_noise_refuses_an_unknown_operator_before_writing(tmp_path, capsys):
    d = _script("demo_label_noise")
    out = tmp_path / "o.json"
    with pytest.raises(SystemExit) as e:
        d.main(["--operator", "nobody", "--episodes", "1", "--out", str(out)])
    assert e.value.code == 2 and not out.exists()
    assert "--operator 'nobody'" in capsys.readouterr().err


def test_demo_turnbacks_refuses_bad_arguments_before_writing(tmp_path, capsys):
    d = _script("demo_turnbacks")
    out = tmp_path / "o.json"
    for argv, msg in ((["--operators", "average", "nobody"], "--operators 'nobody'"),
                      (["--near-mm", "0"], "--near-mm 0.0; allowed: (0, 50]")):
        with pytest.raises(SystemExit) as e:
            d.main([*argv, "--episodes", "1", "--out", str(out)])
        assert e.value.code == 2 and not out.exists()
        assert msg in capsys.readouterr().err


def test_demo_turnbacks_records_each_recovery_of_a_demonstration(tmp_path):
    d = _script("demo_turnbacks")
    out = tmp_path / "o.json"
    assert d.main(["--operators", "average", "--episodes", "2", "--out", str(out)]) == 0
    row = json.loads(out.read_text())["operators"]["average"]
    assert row["seated"] == 2 and row["recoveries"] >= row["recoveries_within_8mm_of_stop"]
    assert row["of_which_turn_back_within_chunk"] <= row["near_steps_not_accepted_within_chunk"]


def test_offline_continuation_refuses_bad_arguments_before_any_work(tmp_path, capsys):
    d = _script("offline_continuation")
    out = tmp_path / "o.json"
    cases = ((["--operator", "nobody"], "--operator 'nobody'"),
             (["--extra", "0"], "--extra 0; allowed: 1..200000"),
             (["--extra", "100", "--every", "200"], "--every 200; allowed: 1..--extra (100)"),
             ([], f"{tmp_path / 'missing.safetensors'}:"))
    for argv, msg in cases:
        assert d.main([str(tmp_path / "missing.safetensors"), str(tmp_path), "--env",
                       "WindowInstall-A-v0", *argv, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1 and not out.exists()
