"""Chunked transitions (paper Eq. 2-4) built from a 10 Hz step log.

For chunk horizon ``h`` the chunk grid is FIXED at ``t = k*h`` (``k = 0, 1, ...`` while
``k*h < T``), whoever issued the actions: a takeover that starts mid-chunk or spans chunk
boundaries does not shift it (Section 3.2, "Logging and chunk-transition construction under
takeovers"). Chunk ``k`` is the transition

    (s_kh, u_k = (a_kh, ..., a_kh+h-1), R_k = sum_{i<h} gamma^i r_kh+i, s_min(kh+h, T))

with the executed actions and the rewards actually received. Steps past the episode end are
padded: zero actions, zero rewards, ``action_mask`` False, provenance ``""``. With
``stride < h`` (an agent's ``demo_chunk_stride``, for D_demo) windows start every ``stride``
steps instead and overlap, as the reference implementation samples windows at any step.

Episode-end semantics for the TD target ``y = R_k + Gamma * (1 - terminal) * Q(next_obs, .)``:

* ``terminal``: the episode TERMINATED inside this chunk (including on its last step);
  the bootstrap is masked. Such a chunk is ``valid``.
* ``valid``: usable in the TD loss. False only for a chunk cut short by TRUNCATION (time
  limit) with fewer than ``h`` real steps: its ``h``-step target would need states past the
  log. A chunk ending exactly at the truncation (``kh + h == T``) is valid and bootstraps
  from ``s_T``.
* ``discount`` is ``Gamma = gamma ** h`` for every chunk (Eq. 3).
"""

from __future__ import annotations

import numbers

import numpy as np

from window_bench.data.steplog import EpisodeLog

#: Keys of the dict returned by :func:`chunk_transitions`, in order.
CHUNK_KEYS = ("obs", "actions", "action_mask", "reward", "next_obs", "discount", "terminal",
              "valid", "n_steps", "provenance_mix", "chunk_start", "any_takeover", "episode_id",
              "episode_accepted", "episode_supervised", "takeover_onset")


def _check_args(h, gamma) -> tuple[int, float]:
    if isinstance(h, bool) or not isinstance(h, numbers.Integral) or h < 1:
        raise ValueError(f"h = {h!r} is not allowed: the chunk horizon must be an integer >= 1")
    if (isinstance(gamma, bool) or not isinstance(gamma, numbers.Real)
            or not (0.0 <= float(gamma) <= 1.0)):
        raise ValueError(f"gamma = {gamma!r} is not allowed: the discount must be a real "
                         f"number in [0, 1]")
    return int(h), float(gamma)


def check_stride(stride, h: int) -> int:
    """Where windows start, as an int: every ``stride`` steps (``None``: ``h``, the grid);
    ``ValueError`` outside ``1..h``."""
    stride = h if stride is None else stride
    if isinstance(stride, bool) or not isinstance(stride, numbers.Integral) \
            or not 1 <= stride <= h:
        raise ValueError(f"stride = {stride!r} is not allowed: windows start every 1..h = "
                         f"{h} steps")
    return int(stride)


def chunk_transitions(episode: EpisodeLog, h: int, gamma: float,
                      stride: int | None = None) -> dict[str, np.ndarray]:
    """Chunked transitions of one episode on the fixed grid ``t = k*h`` (Eq. 4).

    ``stride`` (default ``h``, the paper's grid): windows start at ``t = k*stride``; 1 starts
    one at every step, as the reference implementation samples its windows. Windows then
    overlap; each is still ``(s_t, a_t..a_t+h-1, R, s_min(t+h, T))`` with the executed
    actions, and every window that holds the episode's last step is its end (``terminal`` /
    ``valid`` as below).

    Returns a dict of arrays with leading dimension ``K = ceil(T / stride)``:

    ``obs`` (K, obs_dim) float32 ``s_kh``; ``actions`` (K, h, 7) float32 executed actions,
    zero-padded; ``action_mask`` (K, h) bool, True on real steps; ``reward`` (K,) float32
    ``R_k``; ``next_obs`` (K, obs_dim) float32 ``s_min(kh+h, T)``; ``discount`` (K,) float32
    ``gamma ** h``; ``terminal`` (K,) bool; ``valid`` (K,) bool; ``n_steps`` (K,) int64 real
    steps; ``provenance_mix`` (K, h) str, padded with ``""``; ``chunk_start`` (K,) int64
    ``k*h``; ``any_takeover`` (K,) bool; ``episode_id`` (K,) int64; ``episode_accepted`` (K,)
    bool, the same for every chunk: the episode ended in acceptance (it terminated), so a
    learner can tell chunks of accepted episodes from the rest (``QCFQLConfig.prior_data``);
    ``episode_supervised`` (K,) bool, the same for every chunk: a takeover happened somewhere
    in the episode (an accepted one may owe its acceptance to the installer);
    ``takeover_onset`` (K,) bool: the chunk began with the policy's own steps and a *safety*
    takeover started inside it or on the first step after it (the policy's segment ends
    here: ``QCFQLConfig.takeover_value``). Coverage takeovers are not the policy's failures
    and do not count.

    Raises ``ValueError`` for ``h`` not an integer >= 1, ``gamma`` outside [0, 1], or an
    invalid episode (:meth:`EpisodeLog.validate`).
    """
    h, gamma = _check_args(h, gamma)
    stride = check_stride(stride, h)
    if not isinstance(episode, EpisodeLog):
        raise TypeError(f"episode must be an EpisodeLog, got {type(episode).__name__}")
    episode.validate()

    T = episode.T
    obs = np.asarray(episode.observations, dtype=np.float32)
    K = -(-T // stride)  # ceil(T / stride) >= 1 since T >= 1
    starts = np.arange(K, dtype=np.int64) * stride
    needed = np.concatenate([starts, np.minimum(starts + h, T)])
    observed = episode.observed
    if not observed[needed].all():
        t = int(needed[~observed[needed]][0])
        raise ValueError(f"chunk_transitions(h={h}): s_{t} was not observed (an all-NaN row); "
                         f"the chunk grid needs every s_kh and s_T. Observe on this grid "
                         f"(PixelFeatures(observe_every=h) with the same h) or every step")
    steps = starts[:, None] + np.arange(h, dtype=np.int64)[None, :]  # (K, h)
    mask = steps < T
    idx = np.minimum(steps, T - 1)  # safe gather index; padded entries are overwritten

    actions = np.where(mask[..., None], episode.actions[idx], np.float32(0)).astype(np.float32)
    rewards = np.where(mask, episode.rewards[idx].astype(np.float64), 0.0)
    weights = gamma ** np.arange(h, dtype=np.float64)  # 0.0 ** 0 == 1.0
    reward = (rewards * weights).sum(axis=1).astype(np.float32)

    n_steps = mask.sum(axis=1).astype(np.int64)
    last = starts + h >= T  # the windows that hold the episode's last step (on the grid: one)
    terminal = last & bool(episode.terminated[-1])
    valid = ~(last & bool(episode.truncated[-1]) & (n_steps < h))

    prov = np.asarray(episode.provenance).astype(str)
    provenance_mix = np.where(mask, prov[idx], "")
    # A safety takeover starts at step t when step t is the installer's and step t-1 was not;
    # it ends the segment of the policy's chunk holding step t-1 (t may be the next chunk's
    # first step: the installer took over right at the boundary).
    safety = (prov == "takeover") & (np.asarray(episode.takeover_kind).astype(str) == "safety")
    onset_steps = np.flatnonzero(safety[1:] & (prov[:-1] != "takeover")) + 1
    held = (onset_steps[None, :] - 1 >= starts[:, None]) \
        & (onset_steps[None, :] - 1 < starts[:, None] + h)
    takeover_onset = held.any(axis=1) & (prov[starts] != "takeover")

    return {
        "obs": obs[starts],  # fancy indexing: a copy
        "actions": actions,
        "action_mask": mask,
        "reward": reward,
        "next_obs": obs[np.minimum(starts + h, T)],
        "discount": np.full(K, gamma ** h, dtype=np.float32),
        "terminal": terminal,
        "valid": valid,
        "n_steps": n_steps,
        "provenance_mix": provenance_mix,
        "chunk_start": starts,
        "any_takeover": (provenance_mix == "takeover").any(axis=1),
        # After concat_chunks, (episode_id, chunk_start) still names the step-log window.
        "episode_id": np.full(K, episode.episode_id, dtype=np.int64),
        "episode_accepted": np.full(K, bool(episode.terminated[-1])),
        "episode_supervised": np.full(K, bool((prov == "takeover").any())),
        "takeover_onset": takeover_onset,
    }


def concat_chunks(chunk_dicts) -> dict[str, np.ndarray]:
    """Stack the outputs of several :func:`chunk_transitions` calls along the chunk axis.

    All dicts must have the same keys, the same ``h`` and the same observation size.
    """
    chunk_dicts = list(chunk_dicts)
    if not chunk_dicts:
        raise ValueError("concat_chunks: got an empty list; need at least one chunk dict")
    keys = set(chunk_dicts[0])
    for i, d in enumerate(chunk_dicts[1:], start=1):
        if set(d) != keys:
            raise ValueError(f"concat_chunks: dict {i} has keys {sorted(d)}, "
                             f"dict 0 has {sorted(keys)}")
    out = {}
    for key in chunk_dicts[0]:
        arrays = [np.asarray(d[key]) for d in chunk_dicts]
        tail = arrays[0].shape[1:]
        for i, a in enumerate(arrays[1:], start=1):
            if a.shape[1:] != tail:
                raise ValueError(f"concat_chunks: {key!r} of dict {i} has per-chunk shape "
                                 f"{a.shape[1:]}, dict 0 has {tail} (different h or obs_dim?)")
        out[key] = np.concatenate(arrays, axis=0)
    return out
