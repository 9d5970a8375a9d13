"""Storage of step logs as Minari datasets (HDF5), and a validating loader back into numpy.

:func:`save_episodes` writes a list of :class:`~window_bench.data.steplog.EpisodeLog` with
``minari.create_dataset_from_buffers``, so ``minari.load_dataset(dataset_id)`` reads what we
write; :func:`load_episodes` reads it back into ``EpisodeLog`` objects and validates it, so a
corrupt or truncated file gives a clear ``ValueError`` instead of a crash deep inside an agent.

Layout of one episode in the Minari dataset (``T`` steps):

* ``observations`` (T+1, obs_dim) float32, ``actions`` (T, 7) float32 in [-1, 1],
  ``rewards`` / ``terminations`` / ``truncations`` (T,).
* ``infos`` follow Minari's convention of one row per observation (T+1 rows): row 0 is the
  reset info and row ``t + 1`` the info returned by step ``t``. Keys: ``step_index`` (int64;
  ``-1`` at reset, then ``0 .. T-1``), ``provenance`` and ``takeover_kind`` (strings, ``""`` at
  reset; Minari stores them as UTF-8 and hands them back as ``bytes``), ``time_s`` (float,
  start time of the step, ``-0.1`` at reset), ``chunk_index`` (int64, ``-1`` at reset),
  ``policy_chunk_start`` and the stage flags ``suction_acquired`` / ``insertion_entered`` /
  ``seated`` (bool, False at reset); where the log records them, ``meant_action`` ((T+1, 7)
  float32, zeros at reset: the command meant before the hand's noise).
* Episode-level attributes: ``seed`` (Minari's own) and ``options/episode_id``,
  ``options/env_id``, ``options/chunk_horizon``, ``options/operator`` and
  ``options/randomization`` (a JSON string of the Table 9 draws).

Dataset metadata (``metadata.json``) carries ``schema_version`` (:data:`SCHEMA_VERSION`),
``window_bench_env_id``, ``obs_dim``, ``window_bench_git_commit`` and every key of the
caller's ``metadata``. For a registered env id Minari's ``env_spec`` is that id's spec with
the constructor arguments the episodes were logged with (``obs_mode="flat"`` unless told
otherwise), so ``minari.load_dataset(id).recover_environment()`` builds an env whose
spaces are the dataset's, and ``requirements`` names this window-bench version. Author and
e-mail default to the git identity of the checkout (``git config user.name`` /
``user.email``), the code permalink to ``<origin URL>/tree/<commit>``; what git does not
know is left empty rather than invented.

Writes are atomic: the dataset is built under a temporary dataset id in the same datasets
directory and then renamed into place with ``os.replace``.

Reads trust no file to name code: Minari builds the env a ``metadata.json`` names (any
``entry_point``, with the file's ``kwargs``) when a space is missing there, and in
``recover_environment``. :func:`load_episodes` opens a dataset only when it records both
spaces and every env spec in it is one of window-bench's registered ids with window-bench's
entry point; :func:`recover_env` builds that env with window-bench's own registration.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import uuid
import warnings
from pathlib import Path

import numpy as np

from window_bench.data.steplog import (ACTION_DIM, PROVENANCES, STAGE_FLAGS, STEP_DT, TAKEOVER_KINDS,
                                  EpisodeLog)

#: Version of the on-disk layout described in the module docstring (2: chunk grid, stage
#: flags, time, operator and randomization added).
SCHEMA_VERSION = 2

_TMP_PREFIX = "_window_bench_tmp_"
_METADATA_FILE = "metadata.json"
# Keys Minari itself writes into metadata.json; user metadata may not shadow them.
_RESERVED_KEYS = frozenset({
    "dataset_id", "total_episodes", "total_steps", "data_format", "jpeg_encoding",
    "observation_space", "action_space", "env_spec", "eval_env_spec", "minari_version",
    "author", "author_email", "algorithm_name", "code_permalink", "description",
    "requirements", "dataset_size", "combined_datasets", "ref_min_score", "ref_max_score",
    "num_episodes_average_score", "schema_version", "window_bench_env_id", "obs_dim",
    "window_bench_git_commit",
})


def _git(*args: str) -> str | None:
    import subprocess

    try:
        out = subprocess.run(["git", *args], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def _permalink(commit: str) -> str | None:
    """``<origin>/tree/<commit>`` for a clean, pushed-style checkout; None without a remote
    or for uncommitted code (no link can point at it), and for a remote that is a local
    path (a clone of a folder on this machine has nothing to link to)."""
    url = _git("remote", "get-url", "origin")
    if not url or commit.endswith("-dirty") or commit == "unknown":
        return None
    if url.startswith("git@"):   # git@host:owner/repo.git -> https://host/owner/repo
        url = "https://" + url[4:].replace(":", "/", 1)
    if not url.startswith(("https://", "http://")):
        return None
    return f"{url.removesuffix('.git')}/tree/{commit}"


def _env_for(env_id: str, env_kwargs: dict, obs_dim: int):
    """The registered env the episodes were logged in, made with ``env_kwargs``; None for
    an id that is not registered. Its observation space must be the dataset's."""
    import gymnasium as gym

    try:
        gym.spec(env_id)
    except gym.error.Error:
        return None
    env = gym.make(env_id, **env_kwargs)
    shape = getattr(env.observation_space, "shape", None)
    if shape != (obs_dim,):
        env.close()
        raise ValueError(f"env {env_id!r} with {env_kwargs} observes {env.observation_space}, "
                         f"the episodes have obs_dim {obs_dim}")
    return env


@contextlib.contextmanager
def _datasets_root(data_path):
    """Point ``MINARI_DATASETS_PATH`` at ``data_path`` (if given) for the duration."""
    if data_path is None:
        yield
        return
    old = os.environ.get("MINARI_DATASETS_PATH")
    # Absolute: Minari joins a relative root onto paths it already resolved.
    os.environ["MINARI_DATASETS_PATH"] = os.path.abspath(os.fspath(data_path))
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def _check_dataset_id(dataset_id: str) -> None:
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        parse_dataset_id(dataset_id)
    except (ValueError, TypeError) as e:
        raise ValueError(f"invalid dataset id {dataset_id!r}: {e}") from None


def _env_spec(text, where: str) -> dict:
    """A dataset's recorded env spec (JSON), if it names one of window-bench's own envs with
    window-bench's own entry point and no extra wrappers; else a one-line ``ValueError``. Such
    a spec only ever names code that is already ours: an env is never built from a file."""
    import window_bench
    from gymnasium.envs.registration import registry

    try:
        spec = json.loads(text) if isinstance(text, str) else None
    except ValueError:
        spec = None
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: its env spec is not a JSON object")
    env_id = spec.get("id")
    ours = registry.get(env_id) if env_id in window_bench.ENV_IDS else None
    if (ours is None or spec.get("entry_point") != ours.entry_point
            or spec.get("vector_entry_point") != ours.vector_entry_point
            or spec.get("additional_wrappers") or not isinstance(spec.get("kwargs"), dict)):
        raise ValueError(f"{where}: its env spec names env {env_id!r} with entry point "
                         f"{spec.get('entry_point')!r}; window-bench reads only datasets of its "
                         f"own envs ({', '.join(window_bench.ENV_IDS)}) with their own entry "
                         f"point, and never builds an env a file names")
    return spec


def _checked_metadata(path: Path, dataset_id: str) -> dict:
    """``metadata.json`` of the dataset at ``path``, checked before Minari opens it: Minari
    builds the env of ``env_spec`` with ``gym.make`` (importing and calling any entry point,
    with the file's kwargs) when a space is missing, and ``recover_environment`` always
    does. So both spaces must be recorded, and every env spec must be one of ours."""
    where = f"dataset {dataset_id!r} at {path}"
    try:
        meta = json.loads((path / "data" / _METADATA_FILE).read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{where} is unreadable: {_METADATA_FILE}: "
                         f"{e.strerror if isinstance(e, OSError) else e}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{where} is unreadable: {_METADATA_FILE} is not a JSON object")
    for key in ("observation_space", "action_space"):
        if not isinstance(meta.get(key), str):
            raise ValueError(f"{where}: {_METADATA_FILE} records no {key}; window-bench reads "
                             f"only datasets that record their spaces")
    for key in ("env_spec", "eval_env_spec"):
        if meta.get(key) is not None:
            _env_spec(meta[key], f"{where}, {_METADATA_FILE} {key}")
    return meta


def recover_env(dataset_id: str, data_path: str | os.PathLike | None = None, **kwargs):
    """The env a dataset was logged in, built by window-bench: its registered id made with
    the constructor arguments the dataset records (and ``kwargs``), after :func:`_env_spec`
    checked them. Use it instead of Minari's ``recover_environment``, which imports and calls
    whatever entry point the file names."""
    import gymnasium as gym

    with _datasets_root(data_path):
        from minari.storage.datasets_root_dir import get_dataset_path

        path = Path(get_dataset_path(dataset_id))
    where = f"dataset {dataset_id!r} at {path}"
    meta = _checked_metadata(path, dataset_id)
    if meta.get("env_spec") is None:
        raise ValueError(f"{where} records no env (it was saved for an unregistered env id)")
    spec = _env_spec(meta["env_spec"], where)
    try:
        return gym.make(spec["id"], **{**spec["kwargs"], **kwargs})
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: its env arguments {spec['kwargs']} are not "
                         f"{spec['id']}'s ({str(e).splitlines()[0]})") from None


def _spaces(obs_dim: int):
    from gymnasium import spaces

    obs_space = spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32)
    act_space = spaces.Box(-1.0, 1.0, shape=(ACTION_DIM,), dtype=np.float32)
    return obs_space, act_space


def _check_episode(i: int, ep: EpisodeLog, obs_dim: int) -> None:
    if not isinstance(ep, EpisodeLog):
        raise ValueError(f"episode {i}: expected an EpisodeLog, got {type(ep).__name__}")
    try:
        ep.validate()
    except ValueError as e:
        raise ValueError(f"episode {i} (episode_id={ep.episode_id}): {e}") from None
    if ep.observations.shape[1] != obs_dim:
        raise ValueError(f"episode {i} (episode_id={ep.episode_id}): observations have "
                         f"obs_dim {ep.observations.shape[1]}, dataset obs_dim is {obs_dim}")
    if np.abs(ep.actions).max() > 1.0:
        raise ValueError(f"episode {i} (episode_id={ep.episode_id}): actions outside the "
                         f"action space [-1, 1]^{ACTION_DIM}")
    for name in ("episode_id", "seed"):
        v = getattr(ep, name)
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
            raise ValueError(f"episode {i}: {name} must be an int, got {v!r}")
    if not isinstance(ep.env_id, str):
        raise ValueError(f"episode {i}: env_id must be a str, got {ep.env_id!r}")


def _to_buffer(ep: EpisodeLog, meant: bool):
    from minari.data_collector import EpisodeBuffer

    T = ep.T
    infos = {
        "step_index": np.concatenate([[-1], np.arange(T)]).astype(np.int64),
        "provenance": [""] + [str(p) for p in ep.provenance],
        "takeover_kind": [""] + [str(k) for k in ep.takeover_kind],
        "time_s": (np.arange(-1, T) * STEP_DT).astype(np.float64),
        "chunk_index": np.concatenate([[-1], ep.chunk_index]).astype(np.int64),
        "policy_chunk_start": np.concatenate([[False], ep.policy_chunk_start]).astype(bool),
    }
    for j, name in enumerate(STAGE_FLAGS):
        infos[name] = np.concatenate([[False], ep.stage_flags[:, j]]).astype(bool)
    if meant:
        infos["meant_action"] = np.concatenate([np.zeros((1, ACTION_DIM), np.float32),
                                                ep.meant_actions]).astype(np.float32)
    return EpisodeBuffer(
        seed=int(ep.seed),
        options={"episode_id": int(ep.episode_id), "env_id": str(ep.env_id),
                 "chunk_horizon": int(ep.chunk_horizon), "operator": str(ep.operator),
                 "randomization": json.dumps(ep.randomization, sort_keys=True)},
        observations=np.ascontiguousarray(ep.observations, dtype=np.float32),
        actions=np.ascontiguousarray(ep.actions, dtype=np.float32),
        rewards=np.asarray(ep.rewards, dtype=np.float32),
        terminations=np.asarray(ep.terminated, dtype=bool),
        truncations=np.asarray(ep.truncated, dtype=bool),
        infos=infos,
    )


def save_episodes(episodes: list[EpisodeLog], dataset_id: str, *, env_id: str, obs_dim: int,
                  data_path: str | os.PathLike | None = None, metadata: dict | None = None,
                  overwrite: bool = False, env_kwargs: dict | None = None,
                  author: str | None = None, author_email: str | None = None) -> Path:
    """Write ``episodes`` as the Minari dataset ``dataset_id``; return its directory.

    ``env_kwargs`` (default ``{"obs_mode": "flat"}``, what :class:`Rollout` logs) are the
    constructor arguments recorded in the env spec; ``author`` / ``author_email`` default
    to the checkout's git identity.

    ``dataset_id`` follows Minari's syntax ``(namespace/)name-vN``. ``data_path`` is the
    datasets root (default: ``$MINARI_DATASETS_PATH`` or ``~/.minari/datasets``). Every
    episode is validated before anything is written; ``metadata`` (JSON-serialisable, keys not
    clashing with Minari's own) is recorded in the dataset metadata. An existing dataset raises
    ``ValueError`` unless ``overwrite=True``. The write is atomic (temporary id + rename).
    """
    import minari

    # ------------------------------------------------------------ checks (nothing written)
    _check_dataset_id(dataset_id)
    if not isinstance(obs_dim, (int, np.integer)) or obs_dim < 1:
        raise ValueError(f"obs_dim must be a positive int, got {obs_dim!r}")
    obs_dim = int(obs_dim)
    episodes = list(episodes)
    if not episodes:
        raise ValueError("no episodes to save")
    for i, ep in enumerate(episodes):
        _check_episode(i, ep, obs_dim)
    metadata = dict(metadata or {})
    clash = sorted(_RESERVED_KEYS.intersection(metadata))
    if clash:
        raise ValueError(f"metadata keys {clash} are reserved")
    try:
        json.dumps(metadata)
    except (TypeError, ValueError) as e:
        raise ValueError(f"metadata is not JSON-serialisable: {e}") from None

    from window_bench import __version__
    from window_bench.harness.evaluation import git_commit

    env_kwargs = {"obs_mode": "flat"} if env_kwargs is None else dict(env_kwargs)
    commit = git_commit()
    # Minari keeps one set of info keys: meant actions only where every episode has them.
    meant = all(ep.meant_actions is not None for ep in episodes)
    with _datasets_root(data_path):
        from minari.storage.datasets_root_dir import get_dataset_path

        final_dir = Path(get_dataset_path(dataset_id))
        if final_dir.exists() and not overwrite:
            raise ValueError(f"dataset {dataset_id!r} already exists at {final_dir}; "
                             "pass overwrite=True to replace it")
        root = Path(get_dataset_path())
        tmp_id = f"{_TMP_PREFIX}{uuid.uuid4().hex}-v0"
        tmp_dir = Path(get_dataset_path(tmp_id))
        obs_space, act_space = _spaces(obs_dim)
        env = _env_for(env_id, env_kwargs, obs_dim)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Minari nags about unset optional fields
                minari.create_dataset_from_buffers(
                    dataset_id=tmp_id,
                    buffer=[_to_buffer(ep, meant) for ep in episodes],
                    env=env,
                    observation_space=obs_space,
                    action_space=act_space,
                    algorithm_name="window-bench step log",
                    author=author or _git("config", "user.name"),
                    author_email=author_email or _git("config", "user.email"),
                    code_permalink=_permalink(commit),
                    description=f"window-bench step logs of {env_id} ({env_kwargs})",
                    requirements=[f"window-bench=={__version__}"],
                    data_format="hdf5",
                )
            # The final id is written by hand: Minari refuses to update `dataset_id`.
            meta_file = tmp_dir / "data" / _METADATA_FILE
            meta = json.loads(meta_file.read_text())
            meta.update(metadata)
            meta.update({"dataset_id": dataset_id, "schema_version": SCHEMA_VERSION,
                         "window_bench_env_id": str(env_id), "obs_dim": obs_dim,
                         "window_bench_git_commit": commit})
            meta_file.write_text(json.dumps(meta))

            # Namespaced ids need their namespace directory (and Minari's namespace file).
            namespace = dataset_id.rsplit("/", 1)[0] if "/" in dataset_id else None
            if namespace is not None:
                from minari.namespace import create_namespace, list_local_namespaces

                if namespace not in list_local_namespaces():
                    create_namespace(namespace)
            final_dir.parent.mkdir(parents=True, exist_ok=True)

            if final_dir.exists():  # overwrite: move the old one aside, then swap
                trash = root / f"{_TMP_PREFIX}old_{uuid.uuid4().hex}"
                os.replace(final_dir, trash)
                try:
                    os.replace(tmp_dir, final_dir)
                except BaseException:
                    os.replace(trash, final_dir)
                    raise
                shutil.rmtree(trash, ignore_errors=True)
            else:
                os.replace(tmp_dir, final_dir)
        finally:
            if env is not None:
                env.close()
            if tmp_dir.exists():
                shutil.rmtree(tmp_dir, ignore_errors=True)
    return final_dir


def _decode_strings(arr, what: str) -> np.ndarray:
    out = []
    for v in np.asarray(arr).reshape(-1):
        if isinstance(v, (bytes, np.bytes_)):
            v = v.decode("utf-8")
        if not isinstance(v, str):
            raise ValueError(f"{what}: expected strings, got {type(v).__name__}")
        out.append(v)
    return np.asarray(out, dtype=str)


def load_episodes(dataset_id: str, data_path: str | os.PathLike | None = None
                  ) -> list[EpisodeLog]:
    """Read the Minari dataset ``dataset_id`` written by :func:`save_episodes`.

    Raises ``ValueError`` if the dataset is missing or unreadable (corrupt/truncated HDF5),
    has another schema version, or fails any shape / step-index / provenance / EpisodeLog check.
    """
    import minari

    with _datasets_root(data_path):
        from minari.storage.datasets_root_dir import get_dataset_path

        path = Path(get_dataset_path(dataset_id))

        def unreadable(cause):
            return ValueError(f"dataset {dataset_id!r} at {path} is unreadable: {cause}")

        if not path.is_dir():
            raise unreadable("no such dataset")
        _checked_metadata(path, dataset_id)   # before Minari: it may build the env it names
        try:
            ds = minari.load_dataset(dataset_id)
            meta = ds.storage.metadata
        except Exception as e:  # noqa: BLE001 - any failure to open is "unreadable"
            raise unreadable(f"{type(e).__name__}: {e}") from e

        found = meta.get("schema_version")
        if found != SCHEMA_VERSION:
            raise ValueError(f"dataset {dataset_id!r} at {path} has schema_version {found!r}, "
                             f"expected {SCHEMA_VERSION}")
        obs_dim = meta.get("obs_dim")
        if not isinstance(obs_dim, int) or obs_dim < 1:
            raise ValueError(f"dataset {dataset_id!r} at {path}: bad obs_dim {obs_dim!r} "
                             "in metadata")

        try:
            n = ds.total_episodes
            raw = list(ds.iterate_episodes())
            ep_meta = list(ds.storage.get_episode_metadata(range(n)))
        except Exception as e:  # noqa: BLE001 - h5py/KeyError/OSError deep in Minari
            raise unreadable(f"{type(e).__name__}: {e}") from e
        if len(raw) != n or len(ep_meta) != n:
            raise unreadable(f"metadata says {n} episodes, read {len(raw)}")

    episodes = []
    for i, (data, em) in enumerate(zip(raw, ep_meta)):
        where = f"dataset {dataset_id!r} at {path}, episode {i}"
        obs = np.asarray(data.observations)
        act = np.asarray(data.actions)
        rew = np.asarray(data.rewards)
        T = rew.shape[0] if rew.ndim == 1 else -1
        if T < 1:
            raise ValueError(f"{where}: rewards have shape {rew.shape}, expected (T,) with T >= 1")
        if obs.shape != (T + 1, obs_dim):
            raise ValueError(f"{where}: observations have shape {obs.shape}, "
                             f"expected {(T + 1, obs_dim)}")
        if act.shape != (T, ACTION_DIM):
            raise ValueError(f"{where}: actions have shape {act.shape}, "
                             f"expected {(T, ACTION_DIM)}")
        if int(em.get("total_steps", T)) != T:
            raise ValueError(f"{where}: total_steps attribute {em.get('total_steps')} != {T}")
        infos = data.infos or {}
        keys = ("step_index", "provenance", "takeover_kind", "chunk_index",
                "policy_chunk_start", *STAGE_FLAGS)
        missing = set(keys) - set(infos)
        if missing:
            raise ValueError(f"{where}: infos lack {sorted(missing)}")
        for key in keys:
            if np.shape(infos[key]) != (T + 1,):
                raise ValueError(f"{where}: infos[{key!r}] has shape {np.shape(infos[key])}, "
                                 f"expected {(T + 1,)}")
        step = np.asarray(infos["step_index"])
        if not np.issubdtype(step.dtype, np.integer) or not np.array_equal(
                step, np.arange(-1, T)):
            raise ValueError(f"{where}: step_index is not the monotone sequence "
                             f"-1 (reset), 0..{T - 1}")
        prov = _decode_strings(infos["provenance"], f"{where}: provenance")
        kind = _decode_strings(infos["takeover_kind"], f"{where}: takeover_kind")
        if prov[0] != "" or kind[0] != "":
            raise ValueError(f"{where}: reset info must have empty provenance/takeover_kind")
        bad = ~np.isin(prov[1:], PROVENANCES)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{where}: unknown provenance {str(prov[1 + j])!r} at step {j}")
        bad = ~np.isin(kind[1:], TAKEOVER_KINDS)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{where}: unknown takeover_kind {str(kind[1 + j])!r} at step {j}")
        options = em.get("options") or {}
        if "episode_id" not in options or em.get("seed") is None:
            raise ValueError(f"{where}: episode_id / seed attributes missing")
        def text(key):
            v = options.get(key, "")
            return v.decode("utf-8") if isinstance(v, (bytes, np.bytes_)) else str(v)

        meant = infos.get("meant_action")
        if meant is not None:
            meant = np.asarray(meant)
            if meant.shape != (T + 1, ACTION_DIM) or meant.dtype != np.float32:
                raise ValueError(f"{where}: infos['meant_action'] is {meant.dtype} "
                                 f"{meant.shape}, expected float32 {(T + 1, ACTION_DIM)}")
            meant = meant[1:]
        env_id = text("env_id")
        try:
            randomization = json.loads(text("randomization") or "{}")
            chunk_horizon = int(options.get("chunk_horizon", 1))
        except (ValueError, TypeError) as e:
            raise ValueError(f"{where}: bad episode attributes: {e}") from None
        ep = EpisodeLog(
            observations=obs.astype(np.float32, copy=False),
            actions=act.astype(np.float32, copy=False),
            rewards=rew.astype(np.float32, copy=False),
            terminated=np.asarray(data.terminations),
            truncated=np.asarray(data.truncations),
            provenance=prov[1:],
            takeover_kind=kind[1:],
            episode_id=int(options["episode_id"]),
            env_id=str(env_id),
            seed=int(em["seed"]),
            chunk_horizon=chunk_horizon,
            chunk_index=np.asarray(infos["chunk_index"])[1:].astype(np.int64),
            policy_chunk_start=np.asarray(infos["policy_chunk_start"])[1:].astype(bool),
            stage_flags=np.stack([np.asarray(infos[k])[1:].astype(bool) for k in STAGE_FLAGS],
                                 axis=1),
            randomization=randomization,
            operator=text("operator"),
            meant_actions=meant,
        )
        try:
            ep.validate()
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        episodes.append(ep)
    return episodes
