"""The pixel-demo cache (window_bench.pixels.demo_cache): a miss re-observes and writes, a hit
returns the re-observation bit for bit without replaying, the key follows the encoder and the
demonstrations, a bad entry is never used, one computation per key under concurrency, and a
run records the key and whether it hit."""

from __future__ import annotations

import dataclasses
import json
import threading
import time

import numpy as np
import pytest
import torch

from window_bench.pixels import track
from window_bench.pixels.demo_cache import (PixelDemoCache, cache_key, cached_pixel_demos,
                                            key_material)
from window_bench.pixels.encoder import ResNet10, frozen

ENV = "WindowInstall-A-v0"


def _backbone(seed: int):
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return frozen(ResNet10())


@pytest.fixture(scope="module")
def backbone():
    """A seeded random backbone: the cache's plumbing, not what features mean."""
    return _backbone(0)


@pytest.fixture(scope="module")
def demos():
    """Two 4-step state-track episodes (random actions) to re-observe."""
    from window_bench.installer.rollout import Rollout
    from window_bench.installer.scripted import RandomPolicy

    env = track.make_track_env(ENV, "state", max_episode_steps=4)
    logs = [Rollout(env, RandomPolicy(env, seed=s), provenance="demo").run(seed=21 + s,
                                                                            episode_id=s)
            for s in range(2)]
    env.close()
    return logs


@pytest.fixture(scope="module")
def reference(demos, backbone):
    """What ``pixel_demos`` computes today, without any cache."""
    return track.pixel_demos(demos, ENV, backbone)


@pytest.fixture
def counted(monkeypatch):
    """``track.pixel_demos`` counting its calls (the real one underneath)."""
    calls, real = [], track.pixel_demos

    def pixel_demos(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(track, "pixel_demos", pixel_demos)
    return calls


@pytest.fixture
def recorded(monkeypatch, reference):
    """``track.pixel_demos`` answering from ``reference`` (what it computed once), counting
    its calls: the tests of bad entries then need no rendering."""
    calls = []

    def pixel_demos(eps, *args, **kwargs):
        calls.append(1)
        return reference[: len(eps)]

    monkeypatch.setattr(track, "pixel_demos", pixel_demos)
    return calls


def _assert_bit_identical(got: list, want: list) -> None:
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert a.observations.dtype == b.observations.dtype == np.float32
        assert a.observations.shape == b.observations.shape
        assert a.observations.tobytes() == b.observations.tobytes()
        for f in dataclasses.fields(a):   # everything else is the demonstration's own
            if f.name != "observations":
                x, y = getattr(a, f.name), getattr(b, f.name)
                assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, f.name


def test_a_miss_computes_and_writes_a_hit_returns_it_bit_for_bit(tmp_path, demos, backbone,
                                                                  reference, counted):
    out, rec = cached_pixel_demos(demos, ENV, backbone, tmp_path)
    assert counted == [1] and rec["cache_hit"] is False
    _assert_bit_identical(out, reference)
    key = rec["key"]
    entry = json.loads((tmp_path / f"{key}.json").read_text())
    assert entry["key"] == key
    assert entry["bytes"] == (tmp_path / f"{key}.safetensors").stat().st_size
    assert entry["material"] == key_material(demos, ENV, backbone)
    assert cache_key(entry["material"]) == key
    # float16 feature maps + float32 proprioception: about half of the float32 observations
    n = sum(ep.T + 1 for ep in demos)
    assert entry["bytes"] < 0.6 * n * reference[0].observations.shape[1] * 4

    again, rec2 = cached_pixel_demos(demos, ENV, backbone, tmp_path)
    assert counted == [1], "a hit must not re-observe"
    assert rec2["cache_hit"] is True and rec2["key"] == key
    _assert_bit_identical(again, reference)


def test_the_key_follows_the_encoder_the_demos_and_the_env(demos, backbone):
    key = cache_key(key_material(demos, ENV, backbone))
    assert key == cache_key(key_material(demos, ENV, _backbone(0)))      # deterministic
    assert key != cache_key(key_material(demos, ENV, _backbone(1)))      # other weights
    bn = _backbone(0)
    bn.bn1.running_mean += 1e-3                                          # buffers count
    assert key != cache_key(key_material(demos, ENV, bn))
    acted = [dataclasses.replace(demos[0], actions=demos[0].actions + 1e-6), demos[1]]
    assert key != cache_key(key_material(acted, ENV, backbone))
    assert key != cache_key(key_material(demos[:1], ENV, backbone))      # fewer demos
    reseeded = [dataclasses.replace(demos[0], seed=demos[0].seed + 1), demos[1]]
    assert key != cache_key(key_material(reseeded, ENV, backbone))
    assert key != cache_key(key_material(demos, "WindowInstall-B-v0", backbone))
    assert key == cache_key(key_material(demos, ENV, backbone, "paper"))
    assert key != cache_key(key_material(demos, ENV, backbone, "seat"))  # other cameras
    assert set(key_material(demos, ENV, backbone)) >= {
        "demos_sha256", "encoder_sha256", "layout", "code_sha256", "mujoco", "torch"}


@pytest.mark.parametrize("damage", ["truncated", "flipped byte", "other entry"])
def test_a_bad_entry_is_reported_and_recomputed_never_used(tmp_path, demos, backbone,
                                                           reference, recorded, capsys,
                                                           damage):
    _, rec = cached_pixel_demos(demos, ENV, backbone, tmp_path)
    path = tmp_path / f"{rec['key']}.safetensors"
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
        said = "cannot be used"
    elif damage == "flipped byte":
        path.write_bytes(data[:-100] + bytes([data[-100] ^ 1]) + data[-99:])
        said = "does not match its sha256"
    else:   # a valid entry of other demonstrations under this key
        _, other = cached_pixel_demos(demos[:1], ENV, backbone, tmp_path)
        path.write_bytes((tmp_path / f"{other['key']}.safetensors").read_bytes())
        said = "it is the entry of key"
    calls = len(recorded)
    capsys.readouterr()
    out, rec2 = cached_pixel_demos(demos, ENV, backbone, tmp_path)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and said in err[0] and "recomputing" in err[0] and str(path) in err[0]
    assert len(recorded) == calls + 1 and rec2["cache_hit"] is False
    _assert_bit_identical(out, reference)
    _, rec3 = cached_pixel_demos(demos, ENV, backbone, tmp_path)   # repaired
    assert rec3["cache_hit"] is True and len(recorded) == calls + 1


def test_an_entry_of_other_episode_lengths_is_refused(tmp_path, demos, backbone, reference):
    cache = PixelDemoCache(tmp_path)
    material = key_material(demos, ENV, backbone)
    key = cache_key(material)
    cache.store(key, [reference[0], reference[0]], material, 0.0)   # other seeds
    assert cache.load(key, demos) is None
    short = [dataclasses.replace(ep, observations=ep.observations[:-1]) for ep in reference]
    cache.store(key, short, material, 0.0)
    assert cache.load(key, demos) is None
    cache.store(key, reference, material, 0.0)
    _assert_bit_identical(cache.load(key, demos), reference)


def test_two_runs_missing_the_same_entry_compute_it_once(tmp_path, monkeypatch, demos,
                                                         backbone, reference):
    """Two concurrent misses of one key (threads: ``flock`` locks conflict between separate
    opens of the lock file, as between processes): one re-observes, the other waits and
    loads the entry it wrote."""
    calls = []

    def slow_pixel_demos(*args, **kwargs):
        calls.append(1)
        time.sleep(1.0)               # long enough for the other thread to reach the lock
        return reference

    monkeypatch.setattr(track, "pixel_demos", slow_pixel_demos)
    results = [None, None]

    def run(i):
        results[i] = cached_pixel_demos(demos, ENV, backbone, tmp_path)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert calls == [1]
    recs = [r for _, r in results]
    assert sorted(r["cache_hit"] for r in recs) == [False, True]
    assert max(r["lock_wait_s"] for r in recs) > 0.5
    assert len(list(tmp_path.glob("*.safetensors"))) == 1
    for out, _ in results:
        _assert_bit_identical(out, reference)


def test_an_unwritable_cache_directory_re_observes_without_it(tmp_path, demos, backbone,
                                                              reference, recorded, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    out, rec = cached_pixel_demos(demos, ENV, backbone, blocker / "cache")
    assert "cannot be written" in capsys.readouterr().err
    assert recorded == [1] and rec["cache_hit"] is False and rec["cache_dir"] is None
    _assert_bit_identical(out, reference)


def test_a_pixel_run_records_the_cache_key_and_hit(tmp_path, monkeypatch, demos_root):
    """``Run(track="pixels")``: the first run misses and re-observes, a second run on the same
    demonstrations hits without re-observing and ends with the same checkpoint; both
    results.json record the key and the hit. Offline-only at the smoke profile, one
    10-step evaluation episode; ``pixel_demos`` is replaced by a deterministic stand-in
    (float16-exact feature maps), so the run tests the plumbing, not the features."""
    from window_bench.harness import methods
    from window_bench.harness.run import Run
    from window_bench.pixels.encoder import FEATURE_VALUES, OBS_DIM

    monkeypatch.setitem(methods.PROFILES, "smoke", dataclasses.replace(
        methods.PROFILES["smoke"], eval_episodes=1, max_episode_steps=10))
    calls = []

    def stand_in(eps, env_id, backbone, progress=False):
        calls.append(1)
        out = []
        for ep in eps:
            rng = np.random.default_rng(int(ep.seed))
            obs = rng.standard_normal((ep.T + 1, OBS_DIM)).astype(np.float32)
            obs[:, :FEATURE_VALUES] = obs[:, :FEATURE_VALUES].astype(np.float16)
            out.append(dataclasses.replace(ep, observations=obs))
        return out

    monkeypatch.setattr(track, "pixel_demos", stand_in)
    cache = tmp_path / "cache"
    saved = []
    for name in ("a", "b"):
        Run("qcfql-offline", ENV, "smoke", 0, tmp_path / name, track="pixels", demos=demos_root,
            progress=False, eval_workers=1, pixel_demos_cache=cache).train()
        saved.append(json.loads((tmp_path / name / "results.json").read_text()))
    assert calls == [1]
    (a,), (b,) = (s["pixel_demos"] for s in saved)
    assert a["key"] == b["key"] and (a["cache_hit"], b["cache_hit"]) == (False, True)
    assert (cache / f"{a['key']}.safetensors").is_file()
    drop = lambda cps: [{k: v for k, v in c.items() if k != "wall_clock_s"} for c in cps]  # noqa: E731
    assert drop(saved[0]["checkpoints"]) == drop(saved[1]["checkpoints"])
