"""Step log validation and fixed-grid chunk transitions (paper Eq. 2-4).

Hand-built logs use obs_dim 3 with ``obs[t] = [t, t, t]`` so the picked state can be read
off directly, and ``actions[t, j] = 10 * t + j`` so every executed action is distinct.
"""

import numpy as np
import pytest

from window_bench.data.chunks import CHUNK_KEYS, chunk_transitions, concat_chunks
from window_bench.data.steplog import PROVENANCES, TAKEOVER_KINDS, EpisodeLog

OBS_DIM = 3


def make_log(T, end="terminated", rewards=None, provenance=None, takeover_kind=None,
             episode_id=0):
    """A valid log of T steps ending by ``end`` ("terminated" or "truncated")."""
    obs = np.repeat(np.arange(T + 1, dtype=np.float32)[:, None], OBS_DIM, axis=1)
    actions = 10.0 * np.arange(T, dtype=np.float32)[:, None] + np.arange(7, dtype=np.float32)
    if rewards is None:
        rewards = np.zeros(T, np.float32)
        if end == "terminated":
            rewards[-1] = 1.0
    term = np.zeros(T, bool)
    trunc = np.zeros(T, bool)
    (term if end == "terminated" else trunc)[-1] = True
    if provenance is None:
        provenance = ["policy"] * T
    if takeover_kind is None:
        takeover_kind = ["safety" if p == "takeover" else "" for p in provenance]
    return EpisodeLog(observations=obs, actions=actions, rewards=np.asarray(rewards, np.float32),
                      terminated=term, truncated=trunc, provenance=provenance,
                      takeover_kind=takeover_kind, episode_id=episode_id,
                      env_id="WindowInstall-A-v0", seed=7)


def reference_chunks(ep, h, gamma, stride=None):
    """Direct per-chunk loop over Eq. 4, written independently of the vectorized code
    (windows every ``stride`` steps, default ``h``)."""
    T = len(ep.rewards)
    stride = h if stride is None else stride
    rows = []
    k = 0
    while k * stride < T:
        t0 = k * stride
        real = [t for t in range(t0, t0 + h) if t < T]
        R = 0.0
        for i in range(h):
            if t0 + i < T:
                R += gamma ** i * float(ep.rewards[t0 + i])
        acts = np.zeros((h, 7), np.float32)
        for i, t in enumerate(real):
            acts[i] = ep.actions[t]
        ends_here = (T - 1) in real
        prov, kind = list(ep.provenance), list(ep.takeover_kind)
        onset = prov[t0] != "takeover" and any(
            prov[t] == "takeover" and kind[t] == "safety" and prov[t - 1] != "takeover"
            for t in range(t0 + 1, min(t0 + h + 1, T)))
        rows.append(dict(
            obs=ep.observations[t0], next_obs=ep.observations[min(t0 + h, T)], actions=acts,
            action_mask=np.array([i < len(real) for i in range(h)]), reward=R,
            n_steps=len(real), terminal=ends_here and bool(ep.terminated[-1]),
            valid=not (ends_here and bool(ep.truncated[-1]) and len(real) < h),
            chunk_start=t0,
            provenance_mix=[str(ep.provenance[t]) for t in real] + [""] * (h - len(real)),
            any_takeover=any(ep.provenance[t] == "takeover" for t in real),
            episode_accepted=bool(ep.terminated[-1]),
            episode_supervised=bool((np.asarray(ep.provenance) == "takeover").any()),
            takeover_onset=onset,
        ))
        k += 1
    return rows


def assert_matches_reference(out, ep, h, gamma, stride=None):
    ref = reference_chunks(ep, h, gamma, stride)
    K = len(ref)
    assert set(out) == set(CHUNK_KEYS)
    for key in CHUNK_KEYS:
        assert len(out[key]) == K, key
    for k, r in enumerate(ref):
        np.testing.assert_array_equal(out["obs"][k], r["obs"])
        np.testing.assert_array_equal(out["next_obs"][k], r["next_obs"])
        np.testing.assert_array_equal(out["actions"][k], r["actions"])
        np.testing.assert_array_equal(out["action_mask"][k], r["action_mask"])
        assert out["reward"][k] == pytest.approx(r["reward"], rel=1e-6, abs=1e-6)
        assert out["n_steps"][k] == r["n_steps"]
        assert bool(out["terminal"][k]) is r["terminal"]
        assert bool(out["valid"][k]) is r["valid"]
        assert out["chunk_start"][k] == r["chunk_start"]
        assert out["provenance_mix"][k].tolist() == r["provenance_mix"]
        assert bool(out["any_takeover"][k]) is r["any_takeover"]
        assert bool(out["episode_accepted"][k]) is r["episode_accepted"]
        assert bool(out["episode_supervised"][k]) is r["episode_supervised"]
        assert bool(out["takeover_onset"][k]) is r["takeover_onset"]
        assert out["discount"][k] == pytest.approx(gamma ** h, rel=1e-6)


# ----------------------------------------------------------------------------- step log
def test_valid_log_passes_and_time_axis():
    ep = make_log(5)
    ep.validate()
    np.testing.assert_array_equal(ep.step_index, np.arange(5))
    np.testing.assert_allclose(ep.time_s, [0.0, 0.1, 0.2, 0.3, 0.4])
    assert ep.T == 5
    assert PROVENANCES == ("demo", "policy", "takeover")
    assert TAKEOVER_KINDS == ("", "safety", "coverage")


def test_constructor_casts_float_fields_and_strings():
    ep = make_log(3)
    ep2 = EpisodeLog(observations=ep.observations.astype(np.float64).tolist(),
                     actions=ep.actions.astype(np.float64), rewards=[0, 0, 1],
                     terminated=ep.terminated, truncated=ep.truncated,
                     provenance=["demo", "demo", "demo"], takeover_kind=["", "", ""])
    assert ep2.observations.dtype == np.float32
    assert ep2.actions.dtype == np.float32
    assert ep2.rewards.dtype == np.float32
    assert ep2.provenance.dtype.kind == "U"
    ep2.validate()


def _set(field, value):
    def mutate(ep):
        setattr(ep, field, value(ep) if callable(value) else value)
    return mutate


def _edit(field, index, value):
    def mutate(ep):
        arr = getattr(ep, field).copy()
        if arr.dtype.kind == "U":
            arr = arr.astype(object)
        arr[index] = value
        setattr(ep, field, arr)
    return mutate


def _empty(ep):
    for field in ("actions", "rewards", "terminated", "truncated", "provenance",
                  "takeover_kind"):
        setattr(ep, field, getattr(ep, field)[:0])
    ep.observations = ep.observations[:1]


T_BAD = 6
INVALID_CASES = {
    "obs_not_T_plus_1": (_set("observations", lambda ep: ep.observations[:-1]),
                         r"observations.*T\+1 = 7 rows.*got 6"),
    "obs_1d": (_set("observations", lambda ep: ep.observations[:, 0]),
               r"observations.*expected shape \(T\+1, obs_dim\)"),
    "actions_wrong_width": (_set("actions", lambda ep: ep.actions[:, :6]),
                            r"actions.*expected shape \(T, 7\).*\(6, 6\)"),
    "actions_wrong_T": (_set("actions", lambda ep: ep.actions[:-1]),
                        r"actions.*expected 6 rows.*got 5"),
    "rewards_2d": (_set("rewards", lambda ep: ep.rewards[:, None]),
                   r"rewards.*expected shape \(T,\)"),
    "terminated_wrong_T": (_set("terminated", lambda ep: ep.terminated[1:]),
                           r"terminated.*expected shape \(6,\).*\(5,\)"),
    "truncated_wrong_T": (_set("truncated", lambda ep: np.zeros(7, bool)),
                          r"truncated.*expected shape \(6,\).*\(7,\)"),
    "provenance_wrong_T": (_set("provenance", lambda ep: ep.provenance[:-2]),
                           r"provenance.*expected shape \(6,\).*\(4,\)"),
    "kind_wrong_T": (_set("takeover_kind", lambda ep: ep.takeover_kind[:-1]),
                     r"takeover_kind.*expected shape \(6,\).*\(5,\)"),
    "empty": (_empty, r"rewards.*no steps"),
    "obs_nan": (_edit("observations", (2, 1), np.nan), r"observations.*non-finite.*\(2, 1\)"),
    "actions_inf": (_edit("actions", (4, 6), np.inf), r"actions.*non-finite.*\(4, 6\)"),
    "rewards_nan": (_edit("rewards", 3, np.nan), r"rewards.*non-finite.*\(3,\)"),
    "terminated_early": (_edit("terminated", 2, True), r"terminated.*step 2.*last step"),
    "truncated_early": (_edit("truncated", 0, True), r"truncated.*step 0.*last step"),
    "terminated_not_bool": (_set("terminated", lambda ep: ep.terminated.astype(np.int64)),
                            r"terminated.*bool"),
    "both_at_end": (_edit("truncated", -1, True), r"both set on the last step"),
    "neither_at_end": (_edit("terminated", -1, False), r"neither set on the last step"),
    "unknown_provenance": (_edit("provenance", 3, "installer"),
                           r"provenance.*unknown value 'installer' at step 3"),
    "unknown_kind": (_edit("takeover_kind", 1, "panic"),
                     r"takeover_kind.*unknown value 'panic' at step 1"),
    "kind_without_takeover": (_edit("takeover_kind", 4, "coverage"),
                              r"takeover_kind.*'coverage' at step 4.*provenance is 'policy'"),
}


@pytest.mark.parametrize("case", sorted(INVALID_CASES))
def test_validate_rejects(case):
    mutate, pattern = INVALID_CASES[case]
    ep = make_log(T_BAD)
    ep.validate()  # the unmutated log is fine, so the error below comes from the mutation
    mutate(ep)
    with pytest.raises(ValueError, match=pattern):
        ep.validate()
    # chunk_transitions validates its input too
    with pytest.raises(ValueError, match=pattern):
        chunk_transitions(ep, 3, 0.9)


def test_takeover_with_kind_is_valid():
    prov = ["policy", "takeover", "takeover", "policy"]
    ep = make_log(4, provenance=prov, takeover_kind=["", "safety", "coverage", ""])
    ep.validate()


# ----------------------------------------------------------------------------- argument checks
@pytest.mark.parametrize("h", [0, -1, 2.5, True, "3", None])
def test_bad_h(h):
    with pytest.raises(ValueError, match=r"h = .* integer >= 1"):
        chunk_transitions(make_log(5), h, 0.9)


@pytest.mark.parametrize("gamma", [-0.1, 1.01, float("nan"), float("inf"), "0.9", None])
def test_bad_gamma(gamma):
    with pytest.raises(ValueError, match=r"gamma = .* in \[0, 1\]"):
        chunk_transitions(make_log(5), 3, gamma)


def test_numpy_scalar_args_accepted():
    out = chunk_transitions(make_log(5), np.int64(2), np.float32(0.5))
    assert out["actions"].shape == (3, 2, 7)
    assert out["discount"][0] == pytest.approx(0.25)


def test_not_an_episode_log():
    with pytest.raises(TypeError, match="EpisodeLog"):
        chunk_transitions({"rewards": [1.0]}, 1, 0.9)


# ------------------------------------------------------------------ termination / truncation
H_T = [(h, T) for h in (1, 3, 10) for T in range(1, 3 * h + 2)]


@pytest.mark.parametrize("h,T", H_T)
def test_termination_at_every_offset(h, T):
    rng = np.random.default_rng(1000 * h + T)
    rewards = rng.uniform(-1, 1, T).astype(np.float32)
    ep = make_log(T, "terminated", rewards=rewards)
    gamma = 0.9
    out = chunk_transitions(ep, h, gamma)
    K = -(-T // h)
    off = (T - 1) % h  # offset of the terminal step inside the last chunk
    assert out["obs"].shape == (K, OBS_DIM)
    np.testing.assert_array_equal(out["chunk_start"], np.arange(K) * h)
    np.testing.assert_array_equal(out["obs"][:, 0], np.arange(K) * h)
    np.testing.assert_array_equal(out["next_obs"][:, 0], np.minimum(np.arange(K) * h + h, T))
    assert out["next_obs"][-1, 0] == T  # the last chunk always lands on s_T
    expected_terminal = np.zeros(K, bool)
    expected_terminal[-1] = True
    np.testing.assert_array_equal(out["terminal"], expected_terminal)
    assert out["valid"].all()  # a terminated chunk is valid
    expected_n = np.full(K, h)
    expected_n[-1] = off + 1
    np.testing.assert_array_equal(out["n_steps"], expected_n)
    np.testing.assert_array_equal(out["action_mask"][-1], np.arange(h) <= off)
    assert not out["actions"][-1, off + 1:].any()  # padding is zero
    # rewards after termination are zero: the last return sums only the real steps
    last_R = sum(gamma ** i * float(rewards[(K - 1) * h + i]) for i in range(off + 1))
    assert out["reward"][-1] == pytest.approx(last_R, rel=1e-6, abs=1e-6)
    assert_matches_reference(out, ep, h, gamma)


@pytest.mark.parametrize("h,T", H_T)
def test_truncation_at_every_offset(h, T):
    ep = make_log(T, "truncated", rewards=np.linspace(0.1, 1.0, T))
    gamma = 0.95
    out = chunk_transitions(ep, h, gamma)
    K = -(-T // h)
    assert not out["terminal"].any()  # truncation is never termination
    expected_valid = np.ones(K, bool)
    expected_valid[-1] = (T % h == 0)  # valid only if the truncation is on the boundary
    np.testing.assert_array_equal(out["valid"], expected_valid)
    assert out["next_obs"][-1, 0] == T
    assert out["n_steps"][-1] == (T - 1) % h + 1
    assert_matches_reference(out, ep, h, gamma)


def test_hand_checked_terminated_h3_T7():
    r = np.array([0, 0, 0, 0, 0, 0.5, 1.0], np.float32)
    out = chunk_transitions(make_log(7, "terminated", rewards=r), 3, 0.5)
    np.testing.assert_array_equal(out["chunk_start"], [0, 3, 6])
    np.testing.assert_array_equal(out["obs"][:, 0], [0, 3, 6])
    np.testing.assert_array_equal(out["next_obs"][:, 0], [3, 6, 7])
    np.testing.assert_array_equal(out["n_steps"], [3, 3, 1])
    np.testing.assert_array_equal(out["terminal"], [False, False, True])
    np.testing.assert_array_equal(out["valid"], [True, True, True])
    np.testing.assert_array_equal(out["action_mask"][2], [True, False, False])
    np.testing.assert_allclose(out["reward"], [0.0, 0.25 * 0.5, 1.0])
    np.testing.assert_allclose(out["discount"], [0.125] * 3)
    np.testing.assert_array_equal(out["actions"][1, :, 0], [30, 40, 50])
    np.testing.assert_array_equal(out["actions"][2, 0], np.arange(60, 67))
    np.testing.assert_array_equal(out["actions"][2, 1:], 0)


def test_hand_checked_truncated_boundary_vs_inside():
    on_boundary = chunk_transitions(make_log(6, "truncated"), 3, 0.9)
    np.testing.assert_array_equal(on_boundary["valid"], [True, True])
    np.testing.assert_array_equal(on_boundary["terminal"], [False, False])
    np.testing.assert_array_equal(on_boundary["next_obs"][:, 0], [3, 6])
    inside = chunk_transitions(make_log(5, "truncated"), 3, 0.9)
    np.testing.assert_array_equal(inside["valid"], [True, False])
    np.testing.assert_array_equal(inside["n_steps"], [3, 2])


def test_h_larger_than_episode():
    out = chunk_transitions(make_log(4, "terminated"), 10, 0.9)
    assert out["actions"].shape == (1, 10, 7)
    assert out["n_steps"][0] == 4 and out["terminal"][0] and out["valid"][0]
    assert out["next_obs"][0, 0] == 4
    out = chunk_transitions(make_log(4, "truncated"), 10, 0.9)
    assert not out["valid"][0] and not out["terminal"][0]


# ----------------------------------------------------------------------------- takeovers
def _prov(T, takeover_steps, base="policy"):
    return [("takeover" if t in takeover_steps else base) for t in range(T)]


@pytest.mark.parametrize("start,stop", [(4, 8), (4, 14), (7, 23), (10, 20), (0, 25), (19, 21)])
def test_takeovers_do_not_move_the_grid(start, stop):
    T, h = 25, 10
    rewards = np.random.default_rng(start * 100 + stop).uniform(0, 1, T)
    prov = _prov(T, range(start, stop))
    ep_to = make_log(T, "terminated", rewards=rewards, provenance=prov)
    ep_pol = make_log(T, "terminated", rewards=rewards)
    out_to = chunk_transitions(ep_to, h, 0.99)
    out_pol = chunk_transitions(ep_pol, h, 0.99)
    np.testing.assert_array_equal(out_to["chunk_start"], [0, 10, 20])
    for key in ("obs", "actions", "action_mask", "reward", "next_obs", "discount", "terminal",
                "valid", "n_steps", "chunk_start"):
        np.testing.assert_array_equal(out_to[key], out_pol[key], err_msg=key)
    # the executed actions (whoever issued them) are what is chunked
    np.testing.assert_array_equal(out_to["actions"][out_to["action_mask"]], ep_to.actions)
    expected_any = [any(start <= t < stop for t in range(k * h, min(k * h + h, T)))
                    for k in range(3)]
    np.testing.assert_array_equal(out_to["any_takeover"], expected_any)
    assert not out_pol["any_takeover"].any()
    for k in range(3):
        for i in range(h):
            t = k * h + i
            want = "" if t >= T else ("takeover" if start <= t < stop else "policy")
            assert out_to["provenance_mix"][k, i] == want
    assert_matches_reference(out_to, ep_to, h, 0.99)


def test_takeover_mid_chunk_executed_actions_chunked():
    T, h = 12, 4
    ep = make_log(T, "truncated", provenance=_prov(T, range(2, 7)))
    ep.actions[2:7] = -0.5  # installer's executed actions differ from what a policy would do
    out = chunk_transitions(ep, h, 0.9)
    np.testing.assert_array_equal(out["chunk_start"], [0, 4, 8])
    np.testing.assert_array_equal(out["actions"][0, 2:], -0.5)
    np.testing.assert_array_equal(out["actions"][1, :3], -0.5)
    np.testing.assert_array_equal(out["actions"][1, 3], np.arange(7) + 70)
    np.testing.assert_array_equal(out["obs"][:, 0], [0, 4, 8])
    np.testing.assert_array_equal(out["any_takeover"], [True, True, False])
    assert out["provenance_mix"][0].tolist() == ["policy", "policy", "takeover", "takeover"]


def test_demo_provenance_chunks_identically():
    ep_demo = make_log(9, "terminated", provenance=["demo"] * 9)
    ep_pol = make_log(9, "terminated")
    a, b = chunk_transitions(ep_demo, 3, 0.9), chunk_transitions(ep_pol, 3, 0.9)
    for key in ("obs", "actions", "reward", "next_obs", "terminal", "valid"):
        np.testing.assert_array_equal(a[key], b[key])
    assert (a["provenance_mix"] == "demo").all()
    assert not a["any_takeover"].any()


# ----------------------------------------------------------------------------- h = 1
@pytest.mark.parametrize("end", ["terminated", "truncated"])
def test_h1_is_one_step_transitions(end):
    T = 8
    rewards = np.arange(T, dtype=np.float32) * 0.1
    ep = make_log(T, end, rewards=rewards, provenance=_prov(T, {2, 3}))
    out = chunk_transitions(ep, 1, 0.97)
    np.testing.assert_array_equal(out["obs"], ep.observations[:-1])
    np.testing.assert_array_equal(out["next_obs"], ep.observations[1:])
    np.testing.assert_array_equal(out["actions"][:, 0], ep.actions)
    np.testing.assert_allclose(out["reward"], rewards)
    np.testing.assert_array_equal(out["terminal"], ep.terminated)
    assert out["valid"].all()
    np.testing.assert_allclose(out["discount"], 0.97)
    np.testing.assert_array_equal(out["n_steps"], 1)
    np.testing.assert_array_equal(out["any_takeover"], ep.provenance == "takeover")


# ----------------------------------------------------------------------------- reward / discount
@pytest.mark.parametrize("gamma", [0.0, 0.5, 0.9, 0.99, 1.0])
@pytest.mark.parametrize("h", [1, 2, 5, 10])
def test_reward_and_discount_against_loop(gamma, h):
    T = 23
    rewards = np.random.default_rng(h).normal(size=T).astype(np.float32)
    ep = make_log(T, "terminated", rewards=rewards)
    out = chunk_transitions(ep, h, gamma)
    for k in range(len(out["reward"])):
        R = 0.0
        for i in range(h):
            t = k * h + i
            if t < T:
                R += gamma ** i * float(rewards[t])
        assert out["reward"][k] == pytest.approx(R, rel=1e-5, abs=1e-6)
    np.testing.assert_allclose(out["discount"], gamma ** h, rtol=1e-6)


def test_gamma_zero_keeps_only_first_reward():
    rewards = np.arange(1, 8, dtype=np.float32)
    out = chunk_transitions(make_log(7, rewards=rewards), 3, 0.0)
    np.testing.assert_array_equal(out["reward"], [1.0, 4.0, 7.0])
    np.testing.assert_array_equal(out["discount"], 0.0)


def test_gamma_one_sums_rewards():
    rewards = np.arange(1, 8, dtype=np.float32)
    out = chunk_transitions(make_log(7, rewards=rewards), 3, 1.0)
    np.testing.assert_array_equal(out["reward"], [6.0, 15.0, 7.0])
    np.testing.assert_array_equal(out["discount"], 1.0)


# ------------------------------------------------------------------ dtypes, copies, concat
def test_output_dtypes_and_shapes():
    out = chunk_transitions(make_log(11, "truncated"), 4, 0.9)
    K, h = 3, 4
    expected = {"obs": ((K, OBS_DIM), np.float32), "actions": ((K, h, 7), np.float32),
                "action_mask": ((K, h), np.bool_), "reward": ((K,), np.float32),
                "next_obs": ((K, OBS_DIM), np.float32), "discount": ((K,), np.float32),
                "terminal": ((K,), np.bool_), "valid": ((K,), np.bool_),
                "n_steps": ((K,), np.int64), "chunk_start": ((K,), np.int64),
                "any_takeover": ((K,), np.bool_)}
    for key, (shape, dtype) in expected.items():
        assert out[key].shape == shape, key
        assert out[key].dtype == dtype, key
    assert out["provenance_mix"].shape == (K, h)
    assert out["provenance_mix"].dtype.kind == "U"


def test_outputs_do_not_alias_the_log():
    ep = make_log(6, "terminated", provenance=_prov(6, {1}))
    out = chunk_transitions(ep, 3, 0.9)
    out["obs"][:] = -1
    out["next_obs"][:] = -1
    out["actions"][:] = -1
    out["provenance_mix"][:] = "demo"
    assert ep.observations[0, 0] == 0 and ep.observations[3, 0] == 3
    assert ep.actions[0, 0] == 0
    assert ep.provenance[1] == "takeover"


def test_concat_chunks_shapes():
    a = chunk_transitions(make_log(7, "terminated"), 3, 0.9)  # K = 3
    b = chunk_transitions(make_log(10, "truncated", provenance=_prov(10, {4}), episode_id=5), 3, 0.9)  # K = 4
    out = concat_chunks([a, b])
    assert set(out) == set(CHUNK_KEYS)
    assert out["obs"].shape == (7, OBS_DIM)
    assert out["actions"].shape == (7, 3, 7)
    assert out["action_mask"].shape == (7, 3)
    assert out["provenance_mix"].shape == (7, 3)
    for key in ("reward", "discount", "terminal", "valid", "n_steps", "chunk_start",
                "any_takeover", "episode_id"):
        assert out[key].shape == (7,), key
    np.testing.assert_array_equal(out["chunk_start"], [0, 3, 6, 0, 3, 6, 9])
    np.testing.assert_array_equal(out["episode_id"], [0, 0, 0, 5, 5, 5, 5])
    np.testing.assert_array_equal(out["terminal"], [False, False, True, False, False, False,
                                                    False])
    np.testing.assert_array_equal(out["valid"], [True] * 6 + [False])
    np.testing.assert_array_equal(out["any_takeover"], [False] * 4 + [True] + [False] * 2)
    single = concat_chunks(iter([a]))
    for key in CHUNK_KEYS:
        np.testing.assert_array_equal(single[key], a[key])


def test_concat_chunks_errors():
    a = chunk_transitions(make_log(7), 3, 0.9)
    with pytest.raises(ValueError, match="empty"):
        concat_chunks([])
    with pytest.raises(ValueError, match=r"'actions'.*per-chunk shape"):
        concat_chunks([a, chunk_transitions(make_log(7), 2, 0.9)])
    partial = {k: v for k, v in a.items() if k != "valid"}
    with pytest.raises(ValueError, match="keys"):
        concat_chunks([a, partial])


def test_takeover_onset_marks_the_policy_chunk_a_safety_takeover_ends():
    P, T = "policy", "takeover"
    # h = 3: chunk 0 policy-only, the installer takes over on chunk 1's first step (the
    # boundary); chunk 2 starts with the installer; the policy resumes at 9 and is taken
    # over mid-chunk at 10; a coverage takeover at 13 is not the policy's failure.
    prov = [P, P, P, T, T, T, T, T, T, P, T, T, P, T, T]
    kind = ["safety" if p == T else "" for p in prov]
    kind[13] = kind[14] = "coverage"
    out = chunk_transitions(make_log(len(prov), provenance=prov, takeover_kind=kind), 3, 0.9)
    assert out["takeover_onset"].tolist() == [True, False, False, True, False]
    assert_matches_reference(out, make_log(len(prov), provenance=prov, takeover_kind=kind), 3,
                             0.9)


# ----------------------------------------------------------------------------- denser windows
@pytest.mark.parametrize("h,stride", [(1, 1), (3, 1), (3, 2), (10, 1), (10, 5), (10, 10)])
@pytest.mark.parametrize("T", [1, 4, 9, 10, 23])
@pytest.mark.parametrize("end", ["terminated", "truncated"])
def test_windows_every_stride_steps_against_loop(h, stride, T, end):
    """``stride < h``: a window at every ``stride``-th step, each Eq. 4 on its own start
    (every window holding the last step is the episode's end), takeover onsets included."""
    prov = ["policy"] * T
    for t in range(T // 3, min(T, T // 3 + 4)):
        prov[t] = "takeover"
    ep = make_log(T, end=end, provenance=prov)
    out = chunk_transitions(ep, h, 0.9, stride)
    assert len(out["obs"]) == -(-T // stride)
    assert_matches_reference(out, ep, h, 0.9, stride)


def test_stride_h_is_the_grid_and_bad_strides_are_refused():
    ep = make_log(17, provenance=_prov(17, range(4, 9)))
    grid, same = chunk_transitions(ep, 5, 0.99), chunk_transitions(ep, 5, 0.99, 5)
    assert all(np.array_equal(grid[k], same[k]) for k in CHUNK_KEYS)
    for bad in (0, 6, 2.0, True):
        with pytest.raises(ValueError, match=r"stride = .* windows start every 1\.\.h = 5"):
            chunk_transitions(ep, 5, 0.99, bad)
