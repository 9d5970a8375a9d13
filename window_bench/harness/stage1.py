"""The Stage I cache: one offline pretraining shared by every run that would compute it alike.

Five of Table 1's methods (complete pipeline, offline-only, offline + warm-start, w/o
warm-start, w/o intervention) pretrain the same QC-FQL agent on the same demonstrations with
the same seed: their Stage I is bit-identical. A grid computes it once per seed and the other
cells load it. What Stage I produces is fully determined by

* the agent kind and its complete config (``h`` and every ``--agent-config`` override included),
* the profile's Stage I budget (gradient steps, batch size),
* the demonstrations (a sha256 over their observations and actions, so hand-recorded demos
  count as different demos), and the run seed,
* the code that computes it (sha256 of the source files the agent's track names for its Stage I,
  and of the replay and its chunking) and the torch version,

and the cache key is the sha256 of exactly that (:func:`stage1_key`). An entry holds the
pretrained agent, the demo buffer's sampler state, torch's global RNG state, the Stage I
counters and, once the first run has measured it, checkpoint 0's evaluation rows (they depend
only on the pretrained policy, the env, the seeds and the episode cap, which the entry
records and a run checks before reusing them), in the code-free state format of
:mod:`window_bench.harness.files` (loading it can run no code), written atomically; ``<key>.json`` beside it records what the key hashes and how
long Stage I took. Two runs that need the same missing entry take an ``fcntl`` lock on
``<key>.lock``: the first computes, the second waits and then loads.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from window_bench.harness.evaluation import atomic_write, atomic_write_text
from window_bench.harness.tracks import get_track

KIND = "stage1"


def _source_sha256(*modules: str) -> str:
    import importlib.util

    h = hashlib.sha256()
    for name in modules:
        h.update(Path(importlib.util.find_spec(name).origin).read_bytes())
    return h.hexdigest()


def demos_sha256(demos) -> str:
    """sha256 over the demonstrations' observations and actions, in order."""
    h = hashlib.sha256()
    for ep in demos:
        for arr in (ep.observations, ep.actions):
            a = np.ascontiguousarray(arr, dtype=np.float32)
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()


def key_material(agent_kind: str, track: str, agent_config: dict, offline_steps: int,
                 batch_size: int, demos_digest: str, seed: int) -> dict:
    """Everything Stage I's result depends on (see the module docstring) for the agent kind
    ``agent_kind`` of ``track``; the code is what the track says that agent's Stage I
    depends on (:meth:`~window_bench.harness.tracks.Track.stage1_modules`)."""
    import torch

    modules = get_track(track).stage1_modules(agent_kind)
    if not modules:
        raise ValueError(f"agent kind {agent_kind!r} has no Stage I to cache")
    return {"agent": agent_kind, "agent_config": agent_config, "offline_steps": int(offline_steps),
            "batch_size": int(batch_size), "demos_sha256": demos_digest, "seed": int(seed),
            "code_sha256": _source_sha256(*modules, "window_bench.data.replay",
                                         "window_bench.data.chunks"),
            "torch": torch.__version__}


def stage1_key(material: dict) -> str:
    return hashlib.sha256(json.dumps(material, sort_keys=True).encode()).hexdigest()


class Stage1Cache:
    """A directory of Stage I results, ``<key>.safetensors`` + ``<key>.json``."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        return self.root / f"{key}.safetensors"

    @contextlib.contextmanager
    def lock(self, key: str):
        """Held while one run computes ``key``; the OS releases it if that run dies."""
        with open(self.root / f"{key}.lock", "a") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)

    def load(self, key: str):
        """``(tree, meta)`` of the entry, or ``None`` when there is none; an entry stored
        under another key (a file copied or renamed into place) is refused."""
        from window_bench.harness.files import RunFileError, load_state

        if not self.path(key).is_file():
            return None
        tree, meta = load_state(self.path(key), KIND)
        if not isinstance(meta, dict) or meta.get("key") != key:
            raise RunFileError(f"{self.path(key)}: the Stage I entry of another key; remove "
                               f"it to compute this one again")
        return tree, meta

    def store(self, key: str, tree: dict, material: dict | None, wall_clock_s: float) -> None:
        """Write (or rewrite, e.g. adding checkpoint 0's evaluation rows) an entry;
        ``material`` (what the key hashes) goes into ``<key>.json`` the first time."""
        from window_bench.harness.files import dump_state

        meta = {"key": key, "stage1_wall_clock_s": round(float(wall_clock_s), 2)}
        data = dump_state(tree, KIND, meta)
        atomic_write(self.path(key), lambda f: f.write(data))
        if material is not None:
            atomic_write_text(self.root / f"{key}.json",
                              json.dumps({**meta, "material": material}, indent=1, sort_keys=True))

    def compute_or_load(self, material: dict, compute: Callable[[], dict],
                        restore: Callable[[dict], None]) -> dict:
        """The entry of ``material``'s key: ``compute()`` makes it (stored) when the cache has
        none, else ``restore(tree)`` loads it, both under the key's lock. Returns the record a
        run keeps (``stage1`` in ``results.json``): the key, the demonstrations' and the
        code's digests it hashes (so a key can be traced to its demos), hit or miss, Stage I's
        wall clock, the lock wait and the load time."""
        key = stage1_key(material)
        t0 = time.perf_counter()
        with self.lock(key):
            waited = time.perf_counter() - t0
            entry = self.load(key)
            if entry is None:
                tree = compute()
                wall = time.perf_counter() - t0 - waited
                self.store(key, tree, material, wall)
            else:
                tree, meta = entry
                restore(tree)
                wall = meta["stage1_wall_clock_s"]
        return {"key": key, "demos_sha256": material["demos_sha256"],
                "code_sha256": material["code_sha256"], "cache_hit": entry is not None,
                "stage1_wall_clock_s": round(wall, 2), "lock_wait_s": round(waited, 2),
                "load_s": round(time.perf_counter() - t0 - waited, 2)
                if entry is not None else None}

    def checkpoint0_evaluator(self, key: str, evaluator, what: dict):
        """``(evaluator, hit)`` for checkpoint 0, which evaluates the Stage I result alone:
        the rows kept in the entry when they were made for ``what`` (env, seeds, episode
        cap; ``hit`` True), else ``evaluator`` keeping its rows there (``hit`` False);
        ``evaluator`` itself and None without an entry."""
        entry = self.load(key)
        if entry is None:
            return evaluator, None
        tree, meta = entry
        if tree.get("eval0", {}).get("what") == what:
            return (lambda agent_cls, state: tree["eval0"]["rows"]), True

        def evaluate_and_keep(agent_cls, state):
            rows = evaluator(agent_cls, state)
            self.store(key, {**tree, "eval0": {"what": what, "rows": rows}}, None,
                       meta["stage1_wall_clock_s"])
            return rows
        return evaluate_and_keep, False
