"""The Stage I cache: one offline pretraining shared by every run that would compute it alike.

Five of Table 1's methods (complete pipeline, offline-only, offline + warm-start, w/o
warm-start, w/o intervention) pretrain the same QC-FQL agent on the same demonstrations with
the same seed: their Stage I is bit-identical. A grid computes it once per seed and the other
cells load it. What Stage I produces is fully determined by

* the agent kind and its complete config (``h`` and every ``--agent-config`` override included),
* the profile's Stage I budget (gradient steps, batch size),
* the demonstrations (a sha256 over their observations and actions, so hand-recorded demos
  count as different demos), and the run seed,
* the code that computes it (sha256 of the agent's and the replay's source files) and the torch
  version,

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
from pathlib import Path

import numpy as np

from window_bench.harness.evaluation import atomic_write, atomic_write_text

KIND = "stage1"


def _source_sha256(*modules: str) -> str:
    import importlib.util

    h = hashlib.sha256()
    for name in modules:
        h.update(Path(importlib.util.find_spec(name).origin).read_bytes())
    return h.hexdigest()


_AGENT_MODULES = {"qcfql": "baselines.qcfql", "hilserl": "baselines.hilserl", "act": "baselines.act"}
#: What a pixel-track agent adds to its state-track agent's code (window_bench/pixels/track.py
#: PIXEL_KINDS): the front end (aggregation, fusion) and the encoder it trains through.
_PIXEL_MODULES = ("window_bench.pixels.agent", "window_bench.pixels.encoder")


def agent_modules(agent_kind: str) -> tuple[str, ...]:
    """The modules whose source a Stage I result of ``agent_kind`` depends on (beside the
    replay); a state kind hashes exactly its own module, so its keys are as they always were."""
    from window_bench.pixels.track import PIXEL_KINDS

    if agent_kind in _AGENT_MODULES:
        return (_AGENT_MODULES[agent_kind],)
    state_kind = {v: k for k, v in PIXEL_KINDS.items()}.get(agent_kind)
    if state_kind in _AGENT_MODULES:
        return (_AGENT_MODULES[state_kind], *_PIXEL_MODULES)
    raise ValueError(f"agent kind {agent_kind!r} has no Stage I to cache; kinds with one: "
                     f"{', '.join([*_AGENT_MODULES, *(PIXEL_KINDS[k] for k in _AGENT_MODULES)])}")


def demos_sha256(demos) -> str:
    """sha256 over the demonstrations' observations and actions, in order."""
    h = hashlib.sha256()
    for ep in demos:
        for arr in (ep.observations, ep.actions):
            a = np.ascontiguousarray(arr, dtype=np.float32)
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()


def key_material(agent_kind: str, agent_config: dict, offline_steps: int, batch_size: int,
                 demos_digest: str, seed: int) -> dict:
    """Everything Stage I's result depends on (see the module docstring)."""
    import torch

    return {"agent": agent_kind, "agent_config": agent_config, "offline_steps": int(offline_steps),
            "batch_size": int(batch_size), "demos_sha256": demos_digest, "seed": int(seed),
            "code_sha256": _source_sha256(*agent_modules(agent_kind), "window_bench.data.replay"),
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
