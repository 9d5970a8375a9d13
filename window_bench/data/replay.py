"""Replay of chunk transitions on TorchRL components, and the 1:1 demo/online batch.

A :class:`ChunkReplay` holds the chunk transitions (paper Eq. 4) of whole episodes, built by
:func:`window_bench.data.chunks.chunk_transitions` on the paper's FIXED grid ``t = k*h``. The
reference implementation (``qc``) instead samples a window start uniformly at any step and
masks windows that cross an episode end; we follow the paper: every stored window starts on
the grid, so a takeover never shifts it (Section 3.2). ``stride < h`` (for D_demo, an
agent's ``demo_chunk_stride``) stores a window at every ``stride``-th step instead. Windows
cut short by the time limit are stored with ``valid = False`` and stay in the buffer; the
agent's TD loss masks them (``baselines.qcfql``), and its flow loss masks padded steps with
``action_mask``.

Storage is a :class:`torchrl.data.ReplayBuffer` over a fixed-capacity
:class:`torchrl.data.LazyTensorStorage` with a round-robin writer (FIFO: when full, the
oldest chunks are overwritten first; nothing is dropped while the capacity suffices) and a
uniform :class:`torchrl.data.RandomSampler` drawing from the buffer's own seeded
``torch.Generator``, so a run's batches are reproducible and a resumed run continues the
same sequence (:meth:`ChunkReplay.state_dict`).

Stored keys, per chunk (``K`` chunks of one episode, see :func:`chunk_transitions`): ``obs``,
``next_obs`` (float32, obs_dim), ``actions`` (float32, h x 7), ``action_mask`` (bool, h),
``reward``, ``discount`` (float32), ``terminal``, ``valid``, ``any_takeover`` (bool),
``n_steps``, ``chunk_start``, ``episode_id`` (int64), ``episode_accepted`` (bool: the chunk's
episode ended in acceptance), ``episode_supervised`` and ``takeover_onset`` (bool, see
:func:`chunk_transitions`) and ``provenance_code`` (uint8, h): the
per-step ``provenance_mix`` strings as codes :data:`PROVENANCE_CODES` (TensorDicts hold no
strings). With ``half_obs = n > 0`` the first ``n`` values of ``obs`` / ``next_obs`` are
stored as float16 under ``obs_half`` / ``next_obs_half`` (the pixel track's cached feature
maps, which :class:`window_bench.pixels.features.PixelFeatures` rounds to float16, so nothing
is lost: a value float16 cannot hold exactly is refused) and the rest as float32;
:meth:`ChunkReplay.sample` returns them joined, float32, as without it.

:func:`mixed_batch` draws the paper's fixed 1:1 demo:online batch (Stage III, after RLPD's
symmetric sampling): exactly ``round(n * demo_fraction)`` from the demo buffer and the rest
from the online buffer, every batch, not merely in expectation.
"""

from __future__ import annotations

import numbers

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, RandomSampler, ReplayBuffer, RoundRobinWriter

from window_bench.data.chunks import _check_args, check_stride, chunk_transitions
from window_bench.data.steplog import EpisodeLog

#: ``provenance_mix`` string -> stored ``provenance_code`` (0 marks a padded step).
PROVENANCE_CODES = {"": 0, "demo": 1, "policy": 2, "takeover": 3}

#: Keys of a sampled batch, in order (the numeric keys of :func:`chunk_transitions` plus
#: ``provenance_code`` in place of the ``provenance_mix`` strings).
REPLAY_KEYS = ("obs", "actions", "action_mask", "reward", "next_obs", "discount", "terminal",
               "valid", "n_steps", "chunk_start", "any_takeover", "episode_id",
               "episode_accepted", "episode_supervised", "takeover_onset", "provenance_code")


def _check_count(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{name} = {value!r} is not allowed: it must be an integer "
                         f">= {minimum}")
    return int(value)


def chunks_to_tensordict(chunks: dict[str, np.ndarray]) -> TensorDict:
    """The output of :func:`chunk_transitions` as a TensorDict with batch size ``(K,)``.

    String keys are not storable; ``provenance_mix`` becomes ``provenance_code`` (uint8,
    :data:`PROVENANCE_CODES`). Keys a newer :func:`chunk_transitions` adds are kept if
    numeric or boolean and ignored otherwise.
    """
    K = len(chunks["obs"])
    data = {}
    for key, value in chunks.items():
        arr = np.asarray(value)
        if key == "provenance_mix":
            codes = np.zeros(arr.shape, dtype=np.uint8)
            for name, code in PROVENANCE_CODES.items():
                codes[arr == name] = code
            data["provenance_code"] = torch.from_numpy(codes)
        elif arr.dtype == np.bool_ or np.issubdtype(arr.dtype, np.number):
            data[key] = torch.from_numpy(np.ascontiguousarray(arr))
    return TensorDict(data, batch_size=[K])


class _RowGatherStorage(LazyTensorStorage):
    """:class:`torchrl.data.LazyTensorStorage` whose batch reads gather rows with
    ``index_select``: the same rows as its advanced indexing, 1.5-6x faster on the pixel
    track's 32 KiB float16 feature-map rows, the bulk of a pixel update's sampling cost."""

    def get(self, index):
        if isinstance(index, torch.Tensor) and index.ndim == 1 and self.initialized:
            return self._storage.apply(lambda x: x.index_select(0, index),
                                       batch_size=[len(index)])
        return super().get(index)


class ChunkReplay:
    """FIFO replay of fixed-grid chunk transitions with seeded uniform sampling.

    Parameters
    ----------
    capacity : int
        Maximum number of chunks held (>= 1). When full, the oldest chunks are overwritten.
    h : int
        Chunk horizon used to cut every added episode (>= 1).
    gamma : float
        Per-step discount in [0, 1] for the chunk return ``R_k`` and ``discount = gamma**h``.
    seed : int
        Seed of the buffer's own ``torch.Generator`` used by :meth:`sample`.
    half_obs : int
        Leading observation values stored as float16 (see the module docstring); 0: none.
    """

    def __init__(self, capacity: int, h: int, gamma: float, seed: int = 0, half_obs: int = 0,
                 stride: int | None = None):
        self.capacity = _check_count("capacity", capacity, 1)
        self.h, self.gamma = _check_args(h, gamma)
        #: Windows start every ``stride`` steps of an episode (``h``: the paper's grid).
        self.stride = check_stride(stride, self.h)
        self.seed = _check_count("seed", seed, 0)
        self.half_obs = _check_count("half_obs", half_obs, 0)
        self._generator = torch.Generator().manual_seed(self.seed)
        self._buffer = self._make_buffer()
        self.chunks_added = 0  # total ever added, overwritten ones included
        self.episodes_added = 0

    def __len__(self) -> int:
        return len(self._buffer)

    def _make_buffer(self) -> ReplayBuffer:
        return ReplayBuffer(storage=_RowGatherStorage(self.capacity), sampler=RandomSampler(),
                            writer=RoundRobinWriter(), generator=self._generator)

    def _pack(self, td: TensorDict) -> TensorDict:
        """``obs``/``next_obs`` -> their float16 head (``*_half``) and float32 tail."""
        for key in ("obs", "next_obs") if self.half_obs else ():
            x = td[key]
            if x.shape[1] < self.half_obs:
                raise ValueError(f"ChunkReplay: {key!r} has {x.shape[1]} values, fewer than "
                                 f"half_obs = {self.half_obs}")
            head = x[:, :self.half_obs].to(torch.float16)
            if not torch.equal(head.float(), x[:, :self.half_obs]):
                raise ValueError(f"ChunkReplay: {key!r} values 0..{self.half_obs - 1} are not "
                                 f"float16-exact; storing them as float16 would change them")
            td[f"{key}_half"], td[key] = head, x[:, self.half_obs:].contiguous()
        return td

    def _unpack(self, parts: list[TensorDict]) -> TensorDict:
        """Stored rows (one or more draws) -> one batch with float32 ``obs``/``next_obs``.
        Several draws are joined before the float16 maps are widened, each straight into
        its rows of the batch: no float32 copy is concatenated (64 KiB per row and key)."""
        heads = {key: [p.pop(f"{key}_half") for p in parts]
                 for key in (("obs", "next_obs") if self.half_obs else ())}
        td = parts[0] if len(parts) == 1 else torch.cat(parts, dim=0)
        for key, halves in heads.items():
            tail = td[key]
            out = torch.empty(len(tail), self.half_obs + tail.shape[1])
            row = 0
            for head in halves:             # widened in the copy: one pass
                out[row:row + len(head), :self.half_obs].copy_(head)
                row += len(head)
            out[:, self.half_obs:].copy_(tail)
            td[key] = out
        return td

    def _draw(self, n: int) -> TensorDict:
        """``n`` stored rows drawn uniformly with replacement, as stored (see :meth:`sample`)."""
        n = _check_count("n", n, 1)
        if len(self) == 0:
            raise ValueError(f"ChunkReplay.sample({n}): the buffer is empty; add episodes "
                             f"with add_episode() before sampling")
        return self._buffer.sample(n)

    def add_episode(self, episode: EpisodeLog) -> int:
        """Cut ``episode`` into chunk transitions on the fixed grid (every ``stride`` steps)
        and append them.

        Returns the number of chunks added (``ceil(T / stride)``). Raises ``ValueError`` for an
        invalid episode (see :meth:`EpisodeLog.validate`) or one whose observation size
        differs from the chunks already stored.
        """
        td = self._pack(chunks_to_tensordict(chunk_transitions(episode, self.h, self.gamma,
                                                               self.stride)))
        if len(self) > 0:
            stored = self._buffer.storage._storage
            for key in ("obs", "actions") + (("obs_half",) if self.half_obs else ()):
                if td[key].shape[1:] != stored[key].shape[1:]:
                    raise ValueError(f"ChunkReplay.add_episode: {key!r} has per-chunk shape "
                                     f"{tuple(td[key].shape[1:])}, the buffer holds "
                                     f"{tuple(stored[key].shape[1:])}")
        self._buffer.extend(td)
        self.chunks_added += td.batch_size[0]
        self.episodes_added += 1
        return int(td.batch_size[0])

    def sample(self, n: int) -> TensorDict:
        """``n`` chunks drawn uniformly with replacement, as a TensorDict of batch size (n,).

        Raises ``ValueError`` if the buffer is empty or ``n`` is not an integer >= 1.
        """
        return self._unpack([self._draw(n)])

    def state_dict(self) -> dict:
        """Everything for an exact resume: settings, the stored chunks in storage order, the
        write cursor and the sampler's RNG state.

        Only the filled rows are saved (not the whole preallocated capacity), as a dict of
        tensor copies: later writes to the buffer do not change a saved state dict.
        """
        n = len(self)
        data = ({key: value.clone() for key, value in self._buffer.storage[:n].items()}
                if n else {})
        return {"capacity": self.capacity, "h": self.h, "gamma": self.gamma,
                "seed": self.seed, "half_obs": self.half_obs, "stride": self.stride,
                "chunks_added": self.chunks_added,
                "episodes_added": self.episodes_added, "data": data,
                "writer": dict(self._buffer.writer.state_dict()),
                "rng_state": self._generator.get_state()}

    def load_state_dict(self, sd: dict) -> None:
        """Restore a :meth:`state_dict` into this buffer, replacing its contents.

        ``capacity``, ``h``, ``gamma`` and ``half_obs`` must match this buffer's
        (``ValueError`` otherwise).
        """
        # Saved before the settings existed: float32 throughout, windows on the grid.
        sd = {"half_obs": 0, "stride": sd["h"], **sd}
        for key in ("capacity", "h", "gamma", "half_obs", "stride"):
            if sd[key] != getattr(self, key):
                raise ValueError(f"ChunkReplay.load_state_dict: {key} = {sd[key]!r} in the "
                                 f"state dict, {getattr(self, key)!r} in this buffer")
        self.seed = sd["seed"]
        self._generator = torch.Generator()
        self._generator.set_state(sd["rng_state"].clone())
        self._buffer = self._make_buffer()
        if sd["data"]:
            # rows were saved in storage order: writing them from slot 0 puts every chunk
            # back in its slot; the saved cursor then restores the FIFO overwrite order
            data = {key: value.clone() for key, value in sd["data"].items()}
            n = len(next(iter(data.values())))
            if "episode_accepted" not in data:   # saved before the key existed: an
                # episode was accepted iff one of its chunks terminated
                accepted = data["episode_id"][data["terminal"]]
                data["episode_accepted"] = torch.isin(data["episode_id"], accepted)
            if "episode_supervised" not in data:   # saved before the key existed
                supervised = data["episode_id"][data["any_takeover"]]
                data["episode_supervised"] = torch.isin(data["episode_id"], supervised)
            if "takeover_onset" not in data:   # saved before the key existed, by a run whose
                # agent could not read it; the takeover kinds it needs were not stored
                data["takeover_onset"] = torch.zeros(n, dtype=torch.bool)
            self._buffer.extend(TensorDict(data, batch_size=[n]))
        self._buffer.writer.load_state_dict(dict(sd["writer"]))
        self.chunks_added = sd["chunks_added"]
        self.episodes_added = sd["episodes_added"]


def mixed_batch(demo: ChunkReplay, online: ChunkReplay, n: int,
                demo_fraction: float = 0.5) -> TensorDict:
    """A batch of ``n`` chunks: exactly ``round(n * demo_fraction)`` from ``demo``, the rest
    from ``online`` (the paper's fixed 1:1 ratio at the default; demo rows come first).

    If ``online`` is empty (before any online episode), all ``n`` come from ``demo``.
    ``round`` is Python's (halves to even). Raises ``ValueError`` for ``demo_fraction``
    outside [0, 1], ``n`` < 1, buffers with different ``h``, or an empty buffer that must
    supply rows.
    """
    n = _check_count("n", n, 1)
    if (isinstance(demo_fraction, bool) or not isinstance(demo_fraction, numbers.Real)
            or not 0.0 <= float(demo_fraction) <= 1.0):
        raise ValueError(f"demo_fraction = {demo_fraction!r} is not allowed: it must be a "
                         f"real number in [0, 1]")
    if demo.h != online.h:
        raise ValueError(f"mixed_batch: demo buffer has h = {demo.h}, online buffer has "
                         f"h = {online.h}; both must use the same chunk horizon")
    n_demo = n if len(online) == 0 else int(round(n * float(demo_fraction)))
    draws = [(rb, k) for rb, k in ((demo, n_demo), (online, n - n_demo)) if k > 0]
    if demo.half_obs == online.half_obs:    # joined as stored, widened once (_unpack)
        return demo._unpack([rb._draw(k) for rb, k in draws])
    return torch.cat([rb.sample(k) for rb, k in draws], dim=0)
