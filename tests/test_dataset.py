"""Minari storage of step logs: round trip, Minari compatibility, atomicity, corruption."""

from __future__ import annotations

import json
from pathlib import Path

import minari
import numpy as np
import pytest

from window_bench.data.dataset import SCHEMA_VERSION, load_episodes, save_episodes
from window_bench.data.steplog import EpisodeLog

OBS_DIM = 4
ENV_ID = "WindowBench-v0"


def _episode(T, *, episode_id, seed, end="terminated", takeover=None, rng=None, h=1):
    """A hand-built log: demo/policy steps, optionally a takeover block mid-episode."""
    rng = rng or np.random.default_rng(episode_id)
    prov = np.array(["policy"] * T, dtype=object)
    kind = np.array([""] * T, dtype=object)
    if episode_id % 2 == 0:
        prov[: T // 3] = "demo"
    if takeover is not None:
        start, stop, k = takeover
        prov[start:stop] = "takeover"
        kind[start:stop] = k
    term = np.zeros(T, bool)
    trunc = np.zeros(T, bool)
    (term if end == "terminated" else trunc)[-1] = True
    return EpisodeLog(
        observations=rng.normal(size=(T + 1, OBS_DIM)),
        actions=rng.uniform(-1, 1, size=(T, 7)),
        rewards=rng.normal(size=T),
        terminated=term, truncated=trunc,
        provenance=prov.astype(str), takeover_kind=kind.astype(str),
        episode_id=episode_id, env_id=ENV_ID, seed=seed,
        chunk_horizon=h, stage_flags=np.arange(T)[:, None] >= np.array([0, T // 2, T - 1]),
        randomization={"friction_buck": 0.5 + episode_id / 100, "solref_tc": 0.02},
        operator=("expert", "novice", "")[episode_id % 3],
    )


@pytest.fixture
def episodes():
    return [
        _episode(3, episode_id=0, seed=11, end="terminated"),
        _episode(8, episode_id=7, seed=-3, end="truncated", takeover=(2, 5, "safety")),
        _episode(12, episode_id=42, seed=2**40, end="terminated", takeover=(6, 9, "coverage"),
                 h=4),
        _episode(5, episode_id=3, seed=0, end="truncated", takeover=(1, 2, "safety")),
    ]


@pytest.fixture(autouse=True)
def _isolated_root(tmp_path, monkeypatch):
    # Nothing may land in ~/.minari even if a call forgets data_path.
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "default_root"))


def _assert_same(a: EpisodeLog, b: EpisodeLog):
    np.testing.assert_array_equal(a.observations, b.observations)
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.rewards, b.rewards)
    np.testing.assert_array_equal(a.terminated, b.terminated)
    np.testing.assert_array_equal(a.truncated, b.truncated)
    np.testing.assert_array_equal(a.provenance, b.provenance)
    np.testing.assert_array_equal(a.takeover_kind, b.takeover_kind)
    assert a.observations.dtype == b.observations.dtype == np.float32
    assert b.terminated.dtype == np.bool_ and b.truncated.dtype == np.bool_
    assert b.provenance.dtype.kind == "U" and b.takeover_kind.dtype.kind == "U"
    assert (a.episode_id, a.env_id, a.seed) == (b.episode_id, b.env_id, b.seed)
    assert (a.chunk_horizon, a.operator, a.randomization) == (
        b.chunk_horizon, b.operator, b.randomization)
    np.testing.assert_array_equal(a.chunk_index, b.chunk_index)
    np.testing.assert_array_equal(a.policy_chunk_start, b.policy_chunk_start)
    np.testing.assert_array_equal(a.stage_flags, b.stage_flags)
    assert b.stage_flags.dtype == np.bool_ and b.policy_chunk_start.dtype == np.bool_
    assert type(b.episode_id) is int and type(b.seed) is int


def test_round_trip_every_field(tmp_path, episodes):
    root = tmp_path / "ds"
    path = save_episodes(episodes, "wb/roundtrip-v0", env_id=ENV_ID, obs_dim=OBS_DIM,
                         data_path=str(root), metadata={"installer": "scripted", "n": 3})
    assert path == root / "wb" / "roundtrip-v0"
    assert (path / "data" / "main_data.hdf5").is_file()
    loaded = load_episodes("wb/roundtrip-v0", data_path=str(root))
    assert len(loaded) == len(episodes)
    for a, b in zip(episodes, loaded):
        _assert_same(a, b)
        b.validate()
    # takeovers really did survive (not all-"policy")
    assert list(loaded[2].provenance[6:9]) == ["takeover"] * 3
    assert list(loaded[2].takeover_kind[6:9]) == ["coverage"] * 3
    # no temporary directories left in the root
    assert sorted(p.name for p in root.iterdir()) == ["wb"]
    assert sorted(p.name for p in (root / "wb").iterdir() if p.is_dir()) == ["roundtrip-v0"]


def test_minari_itself_reads_it(tmp_path, monkeypatch, episodes):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    save_episodes(episodes, "plain-v1", env_id=ENV_ID, obs_dim=OBS_DIM,
                  metadata={"note": "hello"})
    ds = minari.load_dataset("plain-v1")
    assert ds.total_episodes == len(episodes)
    assert ds.total_steps == sum(e.T for e in episodes)
    assert ds.spec.dataset_id == "plain-v1"
    assert ds.observation_space.shape == (OBS_DIM,)
    assert ds.action_space.shape == (7,)
    assert np.all(ds.action_space.low == -1) and np.all(ds.action_space.high == 1)
    meta = ds.storage.metadata
    assert meta["schema_version"] == SCHEMA_VERSION
    assert meta["note"] == "hello"
    assert meta["window_bench_env_id"] == ENV_ID
    ep = ds[1]
    np.testing.assert_array_equal(ep.observations, episodes[1].observations)
    assert list(ep.infos["step_index"]) == [-1] + list(range(episodes[1].T))
    assert ep.infos["provenance"][3] == b"takeover"  # Minari hands strings back as bytes
    assert "plain-v1" in minari.list_local_datasets()


def test_overwrite_refused_then_allowed(tmp_path, episodes):
    root = tmp_path / "ds"
    save_episodes(episodes[:2], "ow-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    with pytest.raises(ValueError, match="already exists"):
        save_episodes(episodes[2:], "ow-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    # the refused write changed nothing
    assert [e.episode_id for e in load_episodes("ow-v0", root)] == [0, 7]
    save_episodes(episodes[2:], "ow-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root,
                  overwrite=True)
    loaded = load_episodes("ow-v0", root)
    assert [e.episode_id for e in loaded] == [42, 3]
    _assert_same(episodes[2], loaded[0])
    assert sorted(p.name for p in root.iterdir()) == ["ow-v0"]


def test_truncated_hdf5_is_unreadable(tmp_path, episodes):
    root = tmp_path / "ds"
    path = save_episodes(episodes, "cut-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    h5 = path / "data" / "main_data.hdf5"
    size = h5.stat().st_size
    with open(h5, "r+b") as f:
        f.truncate(size // 2)
    with pytest.raises(ValueError, match="unreadable") as exc:
        load_episodes("cut-v0", data_path=root)
    assert "cut-v0" in str(exc.value)


def test_missing_dataset_is_unreadable(tmp_path):
    with pytest.raises(ValueError, match="'nope-v0' at .* is unreadable"):
        load_episodes("nope-v0", data_path=tmp_path)


def test_garbage_hdf5_is_unreadable(tmp_path, episodes):
    root = tmp_path / "ds"
    path = save_episodes(episodes, "junk-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    (path / "data" / "main_data.hdf5").write_bytes(b"not an hdf5 file at all" * 10)
    with pytest.raises(ValueError, match="unreadable"):
        load_episodes("junk-v0", data_path=root)


def test_wrong_schema_version_names_both(tmp_path, episodes):
    root = tmp_path / "ds"
    path = save_episodes(episodes, "old-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    meta_file = path / "data" / "metadata.json"
    meta = json.loads(meta_file.read_text())
    assert meta["schema_version"] == SCHEMA_VERSION
    meta["schema_version"] = 99
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=rf"schema_version 99, expected {SCHEMA_VERSION}"):
        load_episodes("old-v0", data_path=root)
    del meta["schema_version"]
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=rf"schema_version None, expected {SCHEMA_VERSION}"):
        load_episodes("old-v0", data_path=root)


def test_bad_step_index_rejected(tmp_path, episodes):
    import h5py

    root = tmp_path / "ds"
    path = save_episodes(episodes, "idx-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    with h5py.File(path / "data" / "main_data.hdf5", "a") as f:
        d = f["episode_1/infos/step_index"]
        v = d[()]
        v[3], v[4] = v[4], v[3]
        d[...] = v
    with pytest.raises(ValueError, match="episode 1: step_index is not the monotone"):
        load_episodes("idx-v0", data_path=root)


def test_bad_provenance_rejected(tmp_path, episodes):
    import h5py

    root = tmp_path / "ds"
    path = save_episodes(episodes, "prov-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    with h5py.File(path / "data" / "main_data.hdf5", "a") as f:
        f["episode_2/infos/provenance"][4] = "alien"
    with pytest.raises(ValueError, match="unknown provenance 'alien' at step 3"):
        load_episodes("prov-v0", data_path=root)


@pytest.mark.parametrize("breakage", ["early_terminal", "obs_dim", "bad_kind", "action_range"])
def test_invalid_episode_refused_before_writing(tmp_path, episodes, breakage):
    root = tmp_path / "ds"
    bad = episodes[2]
    if breakage == "early_terminal":
        bad.terminated[4] = True
    elif breakage == "obs_dim":
        bad.observations = np.zeros((bad.T + 1, OBS_DIM + 1), np.float32)
    elif breakage == "bad_kind":
        bad.takeover_kind[0] = "safety"  # provenance there is not "takeover"
    else:
        bad.actions[0, 0] = 1.5
    with pytest.raises(ValueError, match="episode 2"):
        save_episodes(episodes, "bad-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    assert not (root / "bad-v0").exists()
    assert not root.exists() or list(root.iterdir()) == []


def test_failed_write_leaves_nothing(tmp_path, episodes, monkeypatch):
    import window_bench.data.dataset as wbd

    root = tmp_path / "ds"

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(wbd.os, "replace", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save_episodes(episodes, "crash-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path=root)
    assert list(root.iterdir()) == []


def test_bad_arguments(tmp_path, episodes):
    with pytest.raises(ValueError, match="invalid dataset id"):
        save_episodes(episodes, "no version", env_id=ENV_ID, obs_dim=OBS_DIM,
                      data_path=tmp_path)
    with pytest.raises(ValueError, match="JSON"):
        save_episodes(episodes, "meta-v0", env_id=ENV_ID, obs_dim=OBS_DIM,
                      data_path=tmp_path, metadata={"x": object()})
    with pytest.raises(ValueError, match="reserved"):
        save_episodes(episodes, "meta-v0", env_id=ENV_ID, obs_dim=OBS_DIM,
                      data_path=tmp_path, metadata={"schema_version": 2})
    assert not (tmp_path / "meta-v0").exists()


def test_relative_data_path(tmp_path, episodes, monkeypatch):
    # Minari joins a relative datasets root onto paths it already resolved; we pass it
    # an absolute one.
    monkeypatch.chdir(tmp_path)
    save_episodes(episodes, "wb/rel-v0", env_id=ENV_ID, obs_dim=OBS_DIM, data_path="rel/ds")
    assert (tmp_path / "rel" / "ds" / "wb" / "rel-v0" / "data" / "main_data.hdf5").is_file()
    assert len(load_episodes("wb/rel-v0", data_path="rel/ds")) == len(episodes)


def test_code_permalink_only_for_a_web_remote(monkeypatch):
    """A permalink is built only from an http(s) or ssh remote; a clone of a local folder
    (CI's case) or a dirty tree gets none, never a path that looks like a link."""
    from window_bench.data import dataset as D

    for remote, commit, want in (
            ("https://example.org/o/r.git", "abc", "https://example.org/o/r/tree/abc"),
            ("git@example.org:o/r.git", "abc", "https://example.org/o/r/tree/abc"),
            ("/work/main", "abc", None),
            ("https://example.org/o/r.git", "abc-dirty", None)):
        monkeypatch.setattr(D, "_git", lambda *a, r=remote: r)
        assert D._permalink(commit) == want


# ---------------------------------------------------------------- env specs that name code
def _window_dataset(root) -> Path:
    """A dataset of the registered WindowInstall-A-v0 (its 52-float observations)."""
    rng = np.random.default_rng(0)
    ep = _episode(3, episode_id=0, seed=1)
    ep.observations = rng.normal(size=(4, 52)).astype(np.float32)
    ep.env_id = "WindowInstall-A-v0"
    return save_episodes([ep], "wb/win-v0", env_id="WindowInstall-A-v0", obs_dim=52,
                         data_path=root)


def _edit_spec(path: Path, key: str = "env_spec", drop_spaces: bool = False, **changes) -> None:
    meta_file = path / "data" / "metadata.json"
    meta = json.loads(meta_file.read_text())
    meta[key] = json.dumps({**json.loads(meta["env_spec"]), **changes})
    if drop_spaces:
        del meta["observation_space"], meta["action_space"]
    meta_file.write_text(json.dumps(meta))


def test_our_env_is_recovered_with_our_registration(tmp_path):
    from window_bench.data.dataset import recover_env

    _window_dataset(tmp_path)
    env = recover_env("wb/win-v0", data_path=tmp_path)
    try:
        assert env.spec.id == "WindowInstall-A-v0" and env.spec.kwargs["obs_mode"] == "flat"
        assert env.observation_space.shape == (52,)
    finally:
        env.close()
    assert len(load_episodes("wb/win-v0", data_path=tmp_path)) == 1


@pytest.mark.parametrize("key,changes,drop_spaces,message", [
    ("env_spec", {"entry_point": "subprocess:run"}, False,
     "env spec names env 'WindowInstall-A-v0' with entry point 'subprocess:run'"),
    ("env_spec", {"entry_point": "subprocess:run"}, True, "records no observation_space"),
    ("env_spec", {"id": "CartPole-v1", "entry_point": "subprocess:run"}, False,
     "env spec names env 'CartPole-v1'"),
    ("env_spec", {"additional_wrappers": [{"name": "W", "entry_point": "subprocess:run",
                                           "kwargs": {}}]}, False, "with entry point"),
    ("eval_env_spec", {"entry_point": "subprocess:run"}, False, "eval_env_spec: its env spec"),
])
def test_a_spec_that_names_code_is_never_built(tmp_path, key, changes, drop_spaces, message):
    """Minari would import and call the entry point (here with kwargs that touch a marker)
    when a space is missing, and in recover_environment; window-bench refuses the file."""
    from window_bench.data.dataset import recover_env

    marker = tmp_path / "MARKER"
    path = _window_dataset(tmp_path / "ds")
    _edit_spec(path, key, drop_spaces, kwargs={"args": ["touch", str(marker)]}, **changes)
    with pytest.raises(ValueError, match=message) as exc:
        load_episodes("wb/win-v0", data_path=tmp_path / "ds")
    assert "\n" not in str(exc.value)
    with pytest.raises(ValueError, match=message):
        recover_env("wb/win-v0", data_path=tmp_path / "ds")
    assert not marker.exists()
