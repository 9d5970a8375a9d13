"""Chunk replay on TorchRL storage and the 1:1 demo/online batch.

Hand-built logs use obs_dim 2 with ``obs[t] = [episode_id, t]`` so every sampled chunk names
its episode and start step; ``(episode_id, chunk_start)`` identifies a stored chunk.
"""

import numpy as np
import pytest
import torch

from window_bench.data.replay import PROVENANCE_CODES, REPLAY_KEYS, ChunkReplay, mixed_batch
from window_bench.data.steplog import EpisodeLog


def make_log(T, episode_id, end="terminated", provenance="policy"):
    obs = np.stack([np.full(T + 1, episode_id), np.arange(T + 1)], axis=1).astype(np.float32)
    rewards = np.zeros(T, np.float32)
    term, trunc = np.zeros(T, bool), np.zeros(T, bool)
    if end == "terminated":
        term[-1], rewards[-1] = True, 1.0
    else:
        trunc[-1] = True
    prov = [provenance] * T if isinstance(provenance, str) else list(provenance)
    return EpisodeLog(observations=obs, actions=np.full((T, 7), 0.5, np.float32),
                      rewards=rewards, terminated=term, truncated=trunc, provenance=prov,
                      takeover_kind=["safety" if p == "takeover" else "" for p in prov],
                      episode_id=episode_id)


def ids(batch):
    """Set of (episode_id, chunk_start) pairs in a batch."""
    return set(zip(batch["episode_id"].tolist(), batch["chunk_start"].tolist()))


def test_add_episode_counts_and_sample_layout():
    rb = ChunkReplay(capacity=100, h=3, gamma=0.9, seed=0)
    assert len(rb) == 0
    assert rb.add_episode(make_log(7, 1)) == 3  # ceil(7 / 3)
    assert rb.add_episode(make_log(6, 2, end="truncated")) == 2
    assert len(rb) == 5
    batch = rb.sample(11)
    assert batch.batch_size == torch.Size([11])
    assert set(batch.keys()) == set(REPLAY_KEYS)
    assert batch["obs"].shape == (11, 2) and batch["obs"].dtype == torch.float32
    assert batch["actions"].shape == (11, 3, 7)
    assert batch["action_mask"].dtype == torch.bool and batch["valid"].dtype == torch.bool
    # the observation names the chunk: obs = [episode_id, chunk_start]
    assert torch.equal(batch["obs"][:, 0].long(), batch["episode_id"])
    assert torch.equal(batch["obs"][:, 1].long(), batch["chunk_start"])
    assert torch.allclose(batch["discount"], torch.full((11,), 0.9 ** 3))


def test_truncated_short_window_is_stored_invalid_and_padded():
    rb = ChunkReplay(capacity=10, h=3, gamma=0.9)
    rb.add_episode(make_log(5, 4, end="truncated"))  # chunks start at 0 and 3 (2 real steps)
    batch = rb.sample(200)
    last = batch["chunk_start"] == 3
    assert last.any() and (~last).any()
    assert not batch["valid"][last].any() and batch["valid"][~last].all()
    assert torch.equal(batch["action_mask"][last][0], torch.tensor([True, True, False]))
    assert torch.equal(batch["provenance_code"][last][0],
                       torch.tensor([PROVENANCE_CODES["policy"]] * 2 + [0], dtype=torch.uint8))
    assert not batch["terminal"].any()


def test_provenance_codes():
    rb = ChunkReplay(capacity=10, h=3, gamma=0.9)
    rb.add_episode(make_log(3, 0, provenance=["demo", "takeover", "policy"]))
    batch = rb.sample(1)
    assert batch["provenance_code"][0].tolist() == [1, 3, 2]
    assert bool(batch["any_takeover"][0])


def test_fifo_keeps_newest_chunks_when_full():
    rb = ChunkReplay(capacity=5, h=2, gamma=0.99, seed=3)
    rb.add_episode(make_log(6, 0))  # 3 chunks: (0,0) (0,2) (0,4)
    rb.add_episode(make_log(6, 1))  # 3 more: the oldest, (0,0), is overwritten
    assert len(rb) == 5 and rb.chunks_added == 6
    seen = ids(rb.sample(500))
    assert seen == {(0, 2), (0, 4), (1, 0), (1, 2), (1, 4)}
    rb.add_episode(make_log(4, 2))  # 2 more: (0,2) and (0,4) go next
    assert ids(rb.sample(500)) == {(1, 0), (1, 2), (1, 4), (2, 0), (2, 2)}


def test_never_drops_while_capacity_suffices():
    rb = ChunkReplay(capacity=12, h=2, gamma=0.99, seed=1)
    for e in range(3):
        rb.add_episode(make_log(8, e))  # 4 chunks each: exactly the capacity
    assert len(rb) == 12
    assert ids(rb.sample(2000)) == {(e, s) for e in range(3) for s in (0, 2, 4, 6)}


def test_sampling_is_seeded():
    def filled(seed):
        rb = ChunkReplay(capacity=50, h=2, gamma=0.99, seed=seed)
        for e in range(4):
            rb.add_episode(make_log(9, e))
        return rb

    a, b, c = filled(7), filled(7), filled(8)
    sa, sb, sc = a.sample(64), b.sample(64), c.sample(64)
    assert torch.equal(sa["episode_id"], sb["episode_id"])
    assert torch.equal(sa["chunk_start"], sb["chunk_start"])
    assert not (torch.equal(sa["episode_id"], sc["episode_id"])
                and torch.equal(sa["chunk_start"], sc["chunk_start"]))
    # sampling does not touch the global torch RNG
    torch.manual_seed(0)
    before = torch.rand(1)
    torch.manual_seed(0)
    a.sample(10)
    assert torch.equal(torch.rand(1), before)


def test_empty_buffer_error_and_argument_errors():
    rb = ChunkReplay(capacity=4, h=2, gamma=0.9)
    with pytest.raises(ValueError, match="buffer is empty"):
        rb.sample(3)
    rb.add_episode(make_log(2, 0))
    with pytest.raises(ValueError, match="n = 0"):
        rb.sample(0)
    with pytest.raises(ValueError, match="capacity = 0"):
        ChunkReplay(capacity=0, h=2, gamma=0.9)
    with pytest.raises(ValueError, match="h = 0"):
        ChunkReplay(capacity=4, h=0, gamma=0.9)
    with pytest.raises(ValueError, match="gamma = 1.5"):
        ChunkReplay(capacity=4, h=2, gamma=1.5)
    wide = make_log(2, 1)
    wide.observations = np.zeros((3, 5), np.float32)
    with pytest.raises(ValueError, match="per-chunk shape"):
        rb.add_episode(wide)


def test_state_dict_round_trip_is_exact():
    rb = ChunkReplay(capacity=7, h=2, gamma=0.9, seed=11)
    for e in range(3):
        rb.add_episode(make_log(5, e))  # 9 chunks into 7 slots: wrapped cursor
    rb.sample(5)  # advance the sampler RNG
    sd = rb.state_dict()
    rb.add_episode(make_log(3, 99))  # writes after the snapshot must not leak into it
    restored = ChunkReplay(capacity=7, h=2, gamma=0.9, seed=0)
    restored.load_state_dict(sd)
    rb_again = ChunkReplay(capacity=7, h=2, gamma=0.9, seed=0)
    rb_again.load_state_dict(sd)
    assert len(restored) == 7 and restored.chunks_added == 9
    assert 99 not in rb_again.sample(300)["episode_id"].tolist()
    # continued sampling and FIFO overwrite order match the original from the snapshot on
    original = ChunkReplay(capacity=7, h=2, gamma=0.9, seed=11)
    for e in range(3):
        original.add_episode(make_log(5, e))
    original.sample(5)
    for buf in (original, restored):
        buf.add_episode(make_log(4, 50))
    x, y = original.sample(40), restored.sample(40)
    for key in REPLAY_KEYS:
        assert torch.equal(x[key], y[key]), key
    assert ids(original.sample(500)) == ids(restored.sample(500))
    with pytest.raises(ValueError, match="capacity = 7"):
        ChunkReplay(capacity=8, h=2, gamma=0.9).load_state_dict(sd)


def test_state_dict_of_empty_buffer():
    rb = ChunkReplay(capacity=3, h=2, gamma=0.9, seed=2)
    other = ChunkReplay(capacity=3, h=2, gamma=0.9, seed=5)
    other.add_episode(make_log(4, 0))
    other.load_state_dict(rb.state_dict())
    assert len(other) == 0
    with pytest.raises(ValueError, match="buffer is empty"):
        other.sample(1)


def test_mixed_batch_exact_split():
    demo = ChunkReplay(capacity=100, h=2, gamma=0.9, seed=0)
    online = ChunkReplay(capacity=100, h=2, gamma=0.9, seed=1)
    for e in range(3):
        demo.add_episode(make_log(6, e, provenance="demo"))
    # before any online data: everything from demo
    only_demo = mixed_batch(demo, online, 10)
    assert len(only_demo) == 10 and set(only_demo["episode_id"].tolist()) <= {0, 1, 2}
    for e in (100, 101):
        online.add_episode(make_log(6, e))
    for n, frac, n_demo in ((256, 0.5, 128), (10, 0.5, 5), (7, 0.5, 4), (5, 0.5, 2),
                            (10, 0.25, 2), (10, 1.0, 10), (10, 0.0, 0)):
        batch = mixed_batch(demo, online, n, demo_fraction=frac)
        from_demo = batch["episode_id"] < 100
        assert len(batch) == n
        assert int(from_demo.sum()) == n_demo == round(n * frac), (n, frac)
        assert from_demo[:n_demo].all()  # demo rows first
    with pytest.raises(ValueError, match="demo_fraction = 1.5"):
        mixed_batch(demo, online, 8, demo_fraction=1.5)
    with pytest.raises(ValueError, match="chunk horizon"):
        mixed_batch(demo, ChunkReplay(capacity=5, h=3, gamma=0.9), 8)
    with pytest.raises(ValueError, match="buffer is empty"):
        mixed_batch(ChunkReplay(capacity=5, h=2, gamma=0.9), online, 8)


def saved_without(rb: ChunkReplay, key: str) -> ChunkReplay:
    """``rb`` saved as a buffer from before ``key`` existed, and loaded again."""
    sd = rb.state_dict()
    del sd["data"][key]
    old = ChunkReplay(capacity=rb.capacity, h=rb.h, gamma=rb.gamma)
    old.load_state_dict(sd)
    return old


def test_episode_accepted_is_stored_and_derived_for_states_saved_without_it():
    rb = ChunkReplay(capacity=20, h=2, gamma=0.9, seed=0)
    rb.add_episode(make_log(5, 1))                     # accepted: 3 chunks
    rb.add_episode(make_log(4, 2, end="truncated"))    # not accepted: 2 chunks
    batch = rb.sample(200)
    expected = batch["episode_id"] == 1
    assert torch.equal(batch["episode_accepted"], expected)
    batch = saved_without(rb, "episode_accepted").sample(200)
    assert torch.equal(batch["episode_accepted"], batch["episode_id"] == 1)


def test_episode_supervised_marks_every_chunk_of_an_episode_with_a_takeover():
    rb = ChunkReplay(capacity=20, h=2, gamma=0.9, seed=0)
    rb.add_episode(make_log(6, 1, provenance=["policy"] * 4 + ["takeover"] * 2))  # last chunk
    rb.add_episode(make_log(4, 2))
    batch = rb.sample(200)
    assert torch.equal(batch["episode_supervised"], batch["episode_id"] == 1)
    assert not batch["any_takeover"][batch["chunk_start"] == 0].any()
    batch = saved_without(rb, "episode_supervised").sample(200)
    assert torch.equal(batch["episode_supervised"], batch["episode_id"] == 1)
