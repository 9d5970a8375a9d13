"""Installer-in-the-loop: the rollout's chunk grid under takeovers, takeover triggering on
constructed situations, operator profiles, human-like demonstrations and their collection."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

import window_bench  # noqa: F401  (registers the envs)
from window_bench.envs import scene as S
from window_bench.data.chunks import chunk_transitions
from window_bench.data.dataset import load_episodes
from window_bench.installer.demos import collect_demos, demo_dataset_id, measure_supervision
from window_bench.data.effort import takeover_count
from window_bench.installer.scripted import ScriptedInstaller
from window_bench.installer.operators import OPERATORS, HumanlikeInstaller, OperatorProfile, get_operator
from window_bench.installer.rollout import Rollout
from window_bench.installer.supervisor import (ENTRY_DEPTH, FLAT_DIM, FLAT_SLICES, InstallerSupervisor,
                                     observation_fields)


@pytest.fixture(scope="module")
def env():
    e = gym.make("WindowInstall-A-v0", obs_mode="flat")
    yield e
    e.close()


class ChunkCounter:
    """Proposes chunks whose actions encode (proposal number, position) for bookkeeping."""

    def __init__(self, h):
        self.h, self.proposals = h, []

    def reset(self, seed=None):
        self.proposals = []

    def act(self, obs):
        k = len(self.proposals)
        self.proposals.append(obs.copy())
        chunk = np.zeros((self.h, 7), np.float32)
        chunk[:, 0] = 0.01 * k            # tiny motions: the panel stays put
        chunk[:, 1] = 0.001 * np.arange(self.h)
        chunk[:, 6] = 1.0                 # keep the vacuum on
        return chunk


class Scripted:
    """A takeover source that overrides exactly the given steps."""

    def __init__(self, steps, kind="safety"):
        self.steps, self.kind = set(steps), kind

    def reset(self, env, seed=None):
        self.t = -1

    def intervene(self, obs, info):
        self.t += 1
        if self.t in self.steps:
            return np.array([0, 0, 0, 0, 0, 0, 1.0], np.float32) + 0.5 * np.eye(7, dtype=np.float32)[3], self.kind
        return None


def _run(env, h, takeover_steps, T=14):
    policy = ChunkCounter(h)
    ro = Rollout(env, policy, supervisor=Scripted(takeover_steps), h=h)
    ro.reset(seed=0)
    for _ in range(T):
        ro.step()
    ro.done, ro.truncated = True, True      # cut the episode by hand for the log
    return ro.episode_log(), policy


def test_chunks_proposed_only_on_the_grid(env):
    log, policy = _run(env, 4, [])
    assert np.flatnonzero(log.policy_chunk_start).tolist() == [0, 4, 8, 12]
    assert len(policy.proposals) == 4
    # Executed actions are the chunk entries, in order.
    np.testing.assert_allclose(log.actions[:, 0], 0.01 * (np.arange(14) // 4), atol=1e-7)
    np.testing.assert_allclose(log.actions[:, 1], 0.001 * (np.arange(14) % 4), atol=1e-7)
    assert log.chunk_index.tolist() == (np.arange(14) // 4).tolist()


def test_mid_chunk_takeover_resumes_at_next_boundary(env):
    # h = 4; takeover at steps 5, 6 (inside chunk 1); hand back at 7 -> hold at 7,
    # the policy proposes again at 8 from the observation at 8.
    log, policy = _run(env, 4, [5, 6])
    prov = log.provenance.tolist()
    assert prov[:5] == ["policy"] * 5
    assert prov[5:8] == ["takeover"] * 3
    assert prov[8:] == ["policy"] * 6
    assert log.takeover_kind[5:8].tolist() == ["safety"] * 3
    np.testing.assert_array_equal(log.actions[7], [0, 0, 0, 0, 0, 0, 1.0])   # the hold
    assert np.flatnonzero(log.policy_chunk_start).tolist() == [0, 4, 8, 12]
    np.testing.assert_array_equal(policy.proposals[2], log.observations[8])
    assert takeover_count(log) == 1


def test_takeover_across_boundaries_and_ending_on_one(env):
    # Takeover 3..8 spans the boundaries 4 and 8; it ends (None) at 9 -> hold 9..11, policy at 12.
    log, _ = _run(env, 4, range(3, 9))
    assert np.flatnonzero(log.provenance == "takeover").tolist() == list(range(3, 12))
    assert np.flatnonzero(log.policy_chunk_start).tolist() == [0, 12]
    # Ending exactly on a boundary: takeover 4..7, the policy proposes at 8 with no hold.
    log, _ = _run(env, 4, range(4, 8))
    assert np.flatnonzero(log.provenance == "takeover").tolist() == [4, 5, 6, 7]
    assert np.flatnonzero(log.policy_chunk_start).tolist() == [0, 8, 12]


def test_rollout_log_feeds_chunk_transitions(env):
    log, _ = _run(env, 4, [5, 6])
    ch = chunk_transitions(log, 4, 0.99)
    assert ch["any_takeover"].tolist() == [False, True, False, False]
    np.testing.assert_array_equal(ch["actions"][1], log.actions[4:8])


def test_rollout_rejects_bad_input(env):
    with pytest.raises(ValueError, match="chunk horizon"):
        Rollout(env, ChunkCounter(2), h=0)
    with pytest.raises(ValueError, match="provenance"):
        Rollout(env, ChunkCounter(2), provenance="takeover")
    ro = Rollout(env, ChunkCounter(5), h=2)      # chunk longer than the grid
    ro.reset(seed=0)
    with pytest.raises(ValueError, match=r"policy.act returned shape \(5, 7\)"):
        ro.step()
    with pytest.raises(ValueError, match="obs_mode='flat'"):
        Rollout(gym.make("WindowInstall-A-v0"), ChunkCounter(1)).reset(seed=0)


# ---------------------------------------------------------------- supervisor cues
def _obs(depth=-0.3, lateral=0.0, tilt=0.0, vacuum=1.0, blocked=0.0, eef=(0.5, 0.0, 0.5)):
    o = np.zeros(FLAT_DIM, np.float32)
    o[FLAT_SLICES["window_pos_rel"]] = depth * S.INSERTION_AXIS + np.array([lateral, 0, 0])
    o[FLAT_SLICES["window_rot_rel"]] = [tilt, 0, 0]
    o[FLAT_SLICES["robot0_vacuum"]] = vacuum
    o[FLAT_SLICES["contact_proxy"]] = [blocked, 0, 0, 0, 0, 0]
    o[FLAT_SLICES["robot0_eef_pos"]] = eef
    return o


def _feed(env, sup, observations, seed=0, infos=None):
    env.reset(seed=seed)
    sup.reset(env, seed=seed)
    out = []
    for i, o in enumerate(observations):
        d = sup.intervene(o, {} if infos is None else infos[i])
        out.append(None if d is None else d[1])
    return out


def _profile(**kw):
    base = dict(reaction_latency_steps=0, coverage_rate=0.0)
    base.update(kw)
    return OperatorProfile("test", **base)


def test_flat_layout_matches_the_env(env):
    obs, _ = env.reset(seed=3)
    d = gym.make("WindowInstall-A-v0").reset(seed=3)[0]
    f = observation_fields(obs)
    for k in d:
        np.testing.assert_allclose(f[k], d[k], rtol=1e-6, atol=1e-7)


def test_wedging_cue_fires_after_latency(env):
    inside = ENTRY_DEPTH + 0.02
    sup = InstallerSupervisor(_profile(reaction_latency_steps=3, tilt_threshold_deg=1.5))
    calm = [_obs(depth=inside, tilt=np.deg2rad(0.5))] * 5
    tilted = [_obs(depth=inside, tilt=np.deg2rad(2.0), blocked=0.004)] * 8
    kinds = _feed(env, sup, calm + tilted)
    assert kinds[:5] == [None] * 5
    # Cue on the 2nd tilted step (index 6), takeover 3 steps later (index 9).
    assert kinds[6:9] == [None] * 3 and kinds[9] == "safety"
    assert sup.events[0] == (9, "wedging", "safety")
    # The same tilt outside the opening is not a cue.
    sup2 = InstallerSupervisor(_profile(tilt_threshold_deg=1.5))
    assert _feed(env, sup2, [_obs(depth=-0.3, tilt=np.deg2rad(5.0), blocked=0.004)] * 10) \
        == [None] * 10
    # Nor is a misaligned panel at the entry that still moves freely (no contact): the
    # policy may yet correct it; wedging is misalignment under blocked motion.
    sup3 = InstallerSupervisor(_profile(tilt_threshold_deg=1.5, lateral_threshold_mm=2.0))
    free = [_obs(depth=inside, tilt=np.deg2rad(2.0), lateral=0.004, blocked=0.0)] * 10
    assert _feed(env, sup3, free) == [None] * 10
    sup4 = InstallerSupervisor(_profile(lateral_threshold_mm=2.0))
    kinds = _feed(env, sup4, [_obs(depth=inside, lateral=0.003, blocked=0.002)] * 4)
    assert kinds == [None, "safety", "safety", "safety"] and sup4.events[0][1] == "wedging"
    # A patient operator lets the policy work at the blocked entry for wedge_steps steps.
    sup5 = InstallerSupervisor(_profile(lateral_threshold_mm=2.0, wedge_steps=6))
    kinds = _feed(env, sup5, [_obs(depth=inside, lateral=0.003, blocked=0.002)] * 7)
    assert kinds == [None] * 5 + ["safety"] * 2 and sup5.events[0] == (5, "wedging", "safety")


def test_hover_cue_counts_steps_in_front_of_the_opening_since_the_last_entry(env):
    front, inside = ENTRY_DEPTH - 0.02, ENTRY_DEPTH + 0.01
    sup = InstallerSupervisor(_profile(hover_steps=4, patience_steps=600))
    kinds = _feed(env, sup, [_obs(depth=front)] * 3 + [_obs(depth=inside)]
                  + [_obs(depth=front)] * 4)
    assert kinds == [None] * 7 + ["safety"] and sup.events[0] == (7, "hover", "safety")
    # Off in the shipped profiles but `attentive`, and far from the wall it never counts.
    assert get_operator("average").hover_steps == 0 < get_operator("attentive").hover_steps
    sup = InstallerSupervisor(_profile(hover_steps=4, patience_steps=600))
    assert _feed(env, sup, [_obs(depth=ENTRY_DEPTH - 0.2)] * 8) == [None] * 8


def test_suction_lost_cue(env):
    sup = InstallerSupervisor(_profile())
    kinds = _feed(env, sup, [_obs(vacuum=1.0)] * 3 + [_obs(vacuum=0.0)] * 2)
    assert kinds == [None, None, None, "safety", "safety"]
    assert sup.events[0][1] == "suction_lost"
    # Letting go of a panel already in the opening is the policy's call, and so is a grip
    # that breaks more than half-way in; a grip that breaks at the entry, or letting go in
    # front of the wall, is a cue.
    entry, deep, outside = ENTRY_DEPTH + 0.01, ENTRY_DEPTH + 0.06, ENTRY_DEPTH - 0.05
    for depth, broke, expected in ((entry, False, None), (entry, True, "safety"),
                                   (deep, True, None), (outside, False, "safety")):
        sup = InstallerSupervisor(_profile(suction_cue_in_opening=False))
        kinds = _feed(env, sup, [_obs(depth=depth, vacuum=1.0), _obs(depth=depth, vacuum=0.0)],
                      infos=[{}, {"suction_failed": broke}])
        assert kinds == [None, expected], (depth, broke)
        # The shipped profiles but `attentive` keep the cue wherever the panel is.
        sup = InstallerSupervisor(_profile())
        kinds = _feed(env, sup, [_obs(depth=depth, vacuum=1.0), _obs(depth=depth, vacuum=0.0)],
                      infos=[{}, {"suction_failed": broke}])
        assert kinds == [None, "safety"], (depth, broke)
    assert get_operator("average").suction_cue_in_opening
    assert not get_operator("attentive").suction_cue_in_opening
    # Vacuum that was never on (B before acquisition) is not a loss.
    sup = InstallerSupervisor(_profile())
    assert _feed(env, sup, [_obs(vacuum=0.0)] * 5) == [None] * 5


def test_suction_load_is_the_nearest_holding_limit(env):
    from window_bench.envs.env import VACUUM_HOLD_FORCE, VACUUM_HOLD_MOMENT

    u = env.unwrapped
    env.reset(seed=5)
    for a in ([0, 0.4, 0, 0, 0, 0, 1], [0, 0.4, 0, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0, 0]):
        env.step(np.array(a, np.float32))
        pull, shear, moment = u.suction_wrench()
        mu = u._randomization["friction_cup"]
        expected = max(pull / VACUUM_HOLD_FORCE, shear / (mu * VACUUM_HOLD_FORCE),
                       moment / VACUUM_HOLD_MOMENT, 0.0) if u.suction_engaged else 0.0
        assert u.suction_load() == pytest.approx(expected, abs=1e-12)
    assert not u.suction_engaged and u.suction_load() == 0.0      # released: nothing held


def _push_into_rack(env, profile, steps=40):
    """A's panel, held on the rack, pushed along the tool's y (into the rack) every step the
    supervisor leaves to the policy; (takeover kind per step, step of the first grip break)."""
    push = np.array([0, 0.4, 0, 0, 0, 0, 1.0], np.float32)
    sup = InstallerSupervisor(profile, coverage=False)
    obs, info = env.reset(seed=100001)
    sup.reset(env, seed=100001)
    kinds, broke = [], None
    for t in range(steps):
        out = sup.intervene(obs, info)
        a, kind = (push, None) if out is None else out
        kinds.append(kind)
        obs, _, _, _, info = env.step(a)
        if info["suction_failed"] and broke is None:
            broke = t
    return sup, kinds, broke


def test_unstable_suction_cue_lifts_a_strained_panel_clear_before_the_grip_breaks(env):
    # Without the cue (every shipped profile) the grip breaks on the rack.
    assert all(p.strain_threshold == 0.0 for p in OPERATORS.values())
    sup, kinds, broke = _push_into_rack(env, get_operator("attentive"))
    assert broke is not None and broke < 10 and sup.events[0][1] == "suction_lost"
    # With it, the installer takes over while the seal strains, lifts the panel, hands back.
    sup, kinds, broke = _push_into_rack(env, dataclasses.replace(OPERATORS["attentive"],
                                                                 strain_threshold=0.5), steps=16)
    start = sup.events[0][0]
    assert sup.events[0][1] == "unstable_suction" and broke is None
    assert kinds[start] == "safety" and None in kinds[start:]            # handed back
    assert sup.installer.phase == "transport"                             # lifted clear
    assert env.unwrapped.panel_pose()[0][2] > 0.392                      # above the rack pose


def test_unstable_suction_cue_waits_for_a_fresh_seal(env, monkeypatch):
    # The load of a cup sealing onto a panel (B's pick) is not a cue for LATCH_GRACE_STEPS.
    from window_bench.installer.supervisor import LATCH_GRACE_STEPS

    monkeypatch.setattr(type(env.unwrapped), "suction_load", lambda self: 0.9)
    far = ENTRY_DEPTH - 0.3
    seq = [_obs(depth=far, vacuum=0.0)] * 2 + [_obs(depth=far, vacuum=1.0)] * 20
    kinds = _feed(env, InstallerSupervisor(_profile(strain_threshold=0.5)), seq)
    assert kinds.index("safety") == 2 + LATCH_GRACE_STEPS
    # Held from the start (A): at once; near the opening the insertion cues judge it.
    assert _feed(env, InstallerSupervisor(_profile(strain_threshold=0.5)),
                 [_obs(depth=far)] * 2)[0] == "safety"
    assert _feed(env, InstallerSupervisor(_profile(strain_threshold=0.5, patience_steps=600)),
                 [_obs(depth=ENTRY_DEPTH - 0.02)] * 20) == [None] * 20
    with pytest.raises(ValueError, match=r"strain_threshold = 1.5 is outside \[0.0, 1.0\]"):
        _profile(strain_threshold=1.5)


def test_stall_cue_needs_blocked_motion(env):
    inside = ENTRY_DEPTH + 0.03
    prof = _profile(stall_steps=4)
    sup = InstallerSupervisor(prof)
    kinds = _feed(env, sup, [_obs(depth=inside, blocked=0.004)] * 8)
    assert kinds.index("safety") == 4 and sup.events[0][1] == "stall"
    # Not moving but not commanded either (blocked ~ 0): no stall.
    sup = InstallerSupervisor(prof)
    assert _feed(env, sup, [_obs(depth=inside, blocked=0.0)] * 8) == [None] * 8
    # Progressing 1 mm per step against contact: no stall.
    sup = InstallerSupervisor(prof)
    moving = [_obs(depth=inside + 0.001 * i, blocked=0.004) for i in range(8)]
    assert _feed(env, sup, moving) == [None] * 8


def test_reinsertion_and_no_progress_cues(env):
    inside, outside = ENTRY_DEPTH + 0.01, ENTRY_DEPTH - 0.05
    sup = InstallerSupervisor(_profile(max_reinsertions=2))
    seq = [_obs(depth=outside), _obs(depth=inside)] * 3
    kinds = _feed(env, sup, seq)
    assert kinds.index("safety") == 5 and sup.events[0][1] == "reinsertion"
    sup = InstallerSupervisor(_profile(patience_steps=20))
    kinds = _feed(env, sup, [_obs(depth=-0.3)] * 25)
    assert kinds.index("safety") == 20 and sup.events[0][1] == "no_progress"


def test_acquisition_cue_and_hand_back(env):
    """B habit: the tool at the free panel for ``acquire_patience_steps`` without a latch is
    a failed pick; that takeover hands back once the installer has lifted the panel."""
    env.reset(seed=0)
    at_panel = tuple(env.unwrapped.seated_pose[0] + (-0.3) * S.INSERTION_AXIS + [0, 0, 0.05])
    far = tuple(np.asarray(at_panel) + [0, 0, 0.2])
    sup = InstallerSupervisor(_profile(acquire_patience_steps=10))
    kinds = _feed(env, sup, [_obs(vacuum=0.0, eef=at_panel)] * 15)
    assert kinds.index("safety") == 9 and sup.events[0][1] == "acquisition"
    sup.installer._set("transport")          # the installer has picked and lifted the panel
    assert sup.intervene(_obs(vacuum=1.0, eef=at_panel), {}) is None and sup.active is None
    # Off by default, and not while the tool is away from the panel.
    assert _feed(env, InstallerSupervisor(_profile()), [_obs(vacuum=0.0, eef=at_panel)] * 15) \
        == [None] * 15
    sup = InstallerSupervisor(_profile(acquire_patience_steps=10))
    assert _feed(env, sup, [_obs(vacuum=0.0, eef=far)] * 15) == [None] * 15


def test_insertion_takeover_runs_on_to_the_seat(env):
    inside = ENTRY_DEPTH + 0.02
    wedged = [_obs(depth=inside, lateral=0.003, blocked=0.002)] * 4
    for through, expect_active in ((False, None), (True, "safety")):
        sup = InstallerSupervisor(_profile(lateral_threshold_mm=2.0,
                                           seat_after_insertion_takeover=through))
        _feed(env, sup, wedged)
        sup.installer._set("insert")         # re-squared in front of the opening
        sup.steps_in = 5
        sup.intervene(wedged[0], {})
        assert sup.active == expect_active


def test_grasp_settle_holds_still_before_the_lift():
    e = gym.make("WindowInstall-B-v0")
    e.reset(seed=1)
    inst = ScriptedInstaller(e, 0.0, 0.0, seed=1, grasp_settle_steps=10)
    actions = []
    while inst.phase != "lift" and len(actions) < 400:
        actions.append(inst.act())
        e.step(actions[-1])
    phases = [p for _, p in inst.events]
    assert phases[-3:] == ["descend", "settle_grasp", "lift"], phases
    t_settle = dict((p, t) for t, p in inst.events)["settle_grasp"]
    held = np.array(actions[t_settle + 1:])   # from the step after the latch was seen
    assert len(held) == 10 and np.all(held[:, :6] == 0) and np.all(held[:, 6] == 1.0)
    assert e.unwrapped.suction_engaged
    with pytest.raises(ValueError, match=r"grasp_settle_steps = 51 is outside \[0, 50\]"):
        ScriptedInstaller(e, grasp_settle_steps=51)
    e.close()


def test_by_eye_placement_is_corrected_before_the_insertion(env):
    """With a by-eye placement the installer first stops in front of the opening off by the
    coarse error, looks, corrects to within its close-look error, and seats; without one the
    demonstration is the same as before (the coarse draw comes after the close look's)."""
    e = env.unwrapped
    plain = ScriptedInstaller(env, 1.0, 0.5, seed=2)
    coarse = ScriptedInstaller(env, 1.0, 0.5, seed=2, coarse_align_error_mm=6.0,
                               coarse_align_error_deg=1.5)
    assert np.array_equal(plain.err_pos, coarse.err_pos)
    assert np.array_equal(plain.err_rot, coarse.err_rot)
    lateral = np.abs(coarse.coarse_pos[[0, 2]]).max()
    assert 0.003 < lateral <= 0.006
    env.reset(seed=2)
    at_look, term = None, False
    for _ in range(600):
        _, _, term, trunc, _ = env.step(coarse.act())
        if coarse.phase == "look" and at_look is None:
            p, _ = e.panel_pose()
            at_look = p - e.seated_pose[0]
        if term or trunc:
            break
    phases = [p for _, p in coarse.events]
    assert phases.index("align") < phases.index("look") < phases.index("insert"), phases
    # placed by eye: off by about the coarse error, then corrected
    assert np.abs(at_look[[0, 2]] - coarse.coarse_pos[[0, 2]]).max() < 0.0015
    assert term   # accepted: the env terminates on acceptance
    with pytest.raises(ValueError, match="alignment errors must be >= 0"):
        ScriptedInstaller(env, coarse_align_error_mm=-1.0)
    with pytest.raises(ValueError, match=r"coarse_align_error_mm = 21.0 is outside \[0.0, 20.0\]"):
        OperatorProfile("x", coarse_align_error_mm=21.0)


def test_safety_off_and_coverage(env):
    sup = InstallerSupervisor(_profile(), safety=False)
    assert _feed(env, sup, [_obs(vacuum=1.0)] * 2 + [_obs(vacuum=0.0)] * 3) == [None] * 5
    # Coverage rate 1: one coverage intervention when the panel is held near the opening.
    sup = InstallerSupervisor(_profile(coverage_rate=1.0), safety=False)
    near = _obs(depth=ENTRY_DEPTH - 0.05, lateral=0.005)
    kinds = _feed(env, sup, [_obs(depth=-0.6)] * 3 + [near] * 3)
    assert kinds[:3] == [None] * 3 and kinds[3] == "coverage"
    assert [e[2] for e in sup.events] == ["coverage"]


def test_coverage_pauses_while_no_episode_needs_a_rescue(env):
    # coverage_stop_after = 2: after two episodes in a row without a safety takeover the
    # installer stops planning coverage interventions; a rescue starts the count again.
    sup = InstallerSupervisor(_profile(coverage_rate=1.0, coverage_stop_after=2))
    planned = []
    for events in ([], [], [], [(5, "wedging", "safety")], [(3, "coverage", "coverage")], []):
        sup.reset(env, seed=0)
        planned.append(sup.coverage_planned)
        sup.events = list(events)        # what the episode that follows would record
    assert planned == [True, True, False, False, True, True]
    assert sup.state_dict() == {"calm_episodes": 2}      # a coverage takeover is no rescue
    # A resumed run restores the count; pausing draws the same random numbers.
    paused, fresh = (InstallerSupervisor(_profile(coverage_rate=1.0, coverage_stop_after=2))
                     for _ in range(2))
    paused.load_state_dict({"calm_episodes": 2})
    for sup in (paused, fresh):
        sup.reset(env, seed=4)
    assert (paused.coverage_planned, fresh.coverage_planned) == (False, True)
    assert paused.rng.random() == fresh.rng.random()
    with pytest.raises(ValueError, match=r"calm_episodes = -1: must be an integer >= 0"):
        paused.load_state_dict({"calm_episodes": -1})
    with pytest.raises(ValueError, match=r"coverage_stop_after = 1001 is outside \[0, 1000\]"):
        OperatorProfile("x", coverage_stop_after=1001)


def test_supervisor_rejects_other_observations(env):
    sup = InstallerSupervisor("average")
    sup.reset(env, seed=0)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        sup.intervene(np.zeros(3), {})


def test_takeover_recovers_a_wedged_straight_push():
    """End to end on real physics: supervising the straight push, safety takeovers happen,
    are logged with cues, and the run ends with more successes than the push alone (seeded)."""
    r = measure_supervision("WindowInstall-A-v0", "straight_push", "expert", 3, seed=0,
                            progress=False)
    assert r["takeovers"] >= 1 and r["takeover_minutes"] > 0
    assert set(r["safety_cues"]) <= {"suction_lost", "wedging", "stall", "reinsertion",
                                     "acquisition", "no_progress"}
    assert 0 < r["takeover_fraction"] < 1


@pytest.mark.parametrize("steady", [True, False])
def test_steady_hands_near_contact_let_a_takeover_seat(steady):
    """On the insertion alone (compliant arm), the straight push wedges and the attentive
    installer takes over through to the seat. With its hands steady near contact (the
    takeover noise at a fifth while it aligns, inserts, recovers or seats) the takeover
    seats the panel; with full noise throughout (the same seed) it does not."""
    import dataclasses

    from window_bench.installer.scripted import CONTROLLERS

    env_id = "WindowInstall-Insert-Compliant-v0"
    env = gym.make(env_id, obs_mode="flat")
    push = CONTROLLERS["straight_push"](env)

    class Push:
        h = 10

        def reset(self, seed=None):
            push.reset(seed)

        def act(self, obs):
            return np.asarray(push.act(obs), np.float32)[None]

    profile = dataclasses.replace(get_operator("attentive"), steady_near_contact=steady)
    sup = InstallerSupervisor(profile)
    log = Rollout(env, Push(), supervisor=sup, env_id=env_id, operator="attentive").run(
        seed=1, episode_id=1)
    env.close()
    assert [cue for _, cue, kind in sup.events] == ["wedging"]
    assert bool(log.terminated[-1]) is steady


# ---------------------------------------------------------------- profiles, demos
def test_operator_profiles():
    assert set(OPERATORS) == {"expert", "average", "novice", "attentive", "by-eye", "flush",
                              "attentive-flush"}
    by_eye = OPERATORS["by-eye"]
    assert (by_eye.coarse_align_error_mm, by_eye.coarse_align_error_deg) == (5.0, 2.0)
    assert dataclasses.replace(by_eye, name="average", coarse_align_error_mm=0.0,
                               coarse_align_error_deg=0.0) == OPERATORS["average"]
    att = OPERATORS["attentive"]
    assert att.grasp_settle_steps > 0 and att.acquire_patience_steps > 0
    assert att.seat_after_insertion_takeover and not OPERATORS["average"].grasp_settle_steps
    e, a, n = (OPERATORS[k] for k in ("expert", "average", "novice"))
    assert e.reaction_latency_steps < a.reaction_latency_steps < n.reaction_latency_steps
    assert e.stall_steps < a.stall_steps < n.stall_steps
    assert e.recovery_noise < a.recovery_noise < n.recovery_noise
    assert e.demo_speed > a.demo_speed > n.demo_speed
    with pytest.raises(ValueError, match=r"unknown operator profile 'pro'.*average"):
        get_operator("pro")
    with pytest.raises(ValueError, match=r"coverage_rate = 1.5 is outside \[0.0, 1.0\]"):
        OperatorProfile("x", coverage_rate=1.5)
    with pytest.raises(ValueError, match=r"press_at_stop = 1 must be true or false"):
        OperatorProfile("x", press_at_stop=1)
    # flush is the average installer that presses a panel flat at the stop, nothing else
    flush, average = OPERATORS["flush"].as_dict(), OPERATORS["average"].as_dict()
    assert {k for k in flush if flush[k] != average[k]} == {"name", "press_at_stop"}
    # attentive-flush: the attentive installer that presses at the stop, pauses its coverage
    # and waits longer at the pick and the opening, nothing else
    af, att = OPERATORS["attentive-flush"].as_dict(), OPERATORS["attentive"].as_dict()
    assert {k for k in af if af[k] != att[k]} == {"name", "press_at_stop", "coverage_stop_after",
                                                  "acquire_patience_steps", "hover_steps"}
    assert {p.name for p in OPERATORS.values() if p.coverage_stop_after} == {"attentive-flush"}


def test_humanlike_demonstrator_is_seeded_and_not_the_script(env):
    def actions(ctl, seed, T=60):
        obs, _ = env.reset(seed=seed)
        ctl.reset(seed=seed)
        out = []
        for _ in range(T):
            a = ctl.act(obs)
            out.append(a)
            obs, *_ = env.step(a)
        return np.stack(out)

    h = HumanlikeInstaller(env, "novice")
    a1, a2 = actions(h, 5), actions(h, 5)
    np.testing.assert_array_equal(a1, a2)
    assert not np.array_equal(a1, actions(h, 6))
    scripted = actions(ScriptedInstaller(env, seed=5), 5)
    assert np.abs(a1[:, :6] - scripted[:, :6]).mean() > 0.01
    # Hesitations are zero-motion steps with the vacuum held.
    still = np.all(a1[:, :6] == 0, axis=1)
    assert still.any() and np.all(a1[still, 6] == a1[np.flatnonzero(still) - 1, 6])


def test_collect_demos_keeps_successes_and_resumes(tmp_path, monkeypatch):
    import window_bench.installer.demos as demos

    # A collection killed after its episodes, before the dataset is written.
    def killed(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(demos, "save_episodes", killed)
    with pytest.raises(KeyboardInterrupt):
        collect_demos("WindowInstall-A-v0", 2, tmp_path, operator="expert", seed=0,
                      progress=False)
    partial = sorted((tmp_path / ".partial").rglob("*.npz"))
    assert len(partial) >= 2
    mtimes = [p.stat().st_mtime_ns for p in partial]
    monkeypatch.undo()
    # Resume: the per-episode checkpoints are reused (not rewritten), then removed.
    reads, load = [], demos._load_partial
    monkeypatch.setattr(demos, "_load_partial",
                        lambda path, *a: reads.append(path.stat().st_mtime_ns) or load(path, *a))
    s = collect_demos("WindowInstall-A-v0", 2, tmp_path, operator="expert", seed=0,
                      progress=False)
    assert reads == mtimes and s["attempts"] == len(partial)
    assert not (tmp_path / ".partial").exists()
    assert s["kept"] == 2 and s["attempts"] >= 2
    eps = load_episodes(demo_dataset_id("WindowInstall-A-v0", "expert"), data_path=tmp_path)
    assert len(eps) == 2
    for ep in eps:
        assert ep.terminated[-1] and set(ep.provenance.tolist()) == {"demo"}
        assert ep.operator == "expert" and ep.randomization and ep.stage_flags[-1].all()
    # Collected again from scratch: the same dataset (seeded).
    s2 = collect_demos("WindowInstall-A-v0", 2, tmp_path, operator="expert", seed=0,
                       progress=False)
    assert s2["episodes"] == s["episodes"]
    eps2 = load_episodes(demo_dataset_id("WindowInstall-A-v0", "expert"), data_path=tmp_path)
    for a, b in zip(eps, eps2):
        np.testing.assert_array_equal(a.actions, b.actions)
    with pytest.raises(ValueError, match="n = 0"):
        collect_demos("WindowInstall-A-v0", 0, tmp_path)
