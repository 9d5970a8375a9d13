"""The files of a run directory, and how they are written and read back without trusting them.

* **A code-free state format** (:func:`save_state`, :func:`load_state`): nested dicts, lists
  and tuples of tensors, numpy arrays and JSON plain values go into ONE safetensors file; the
  arrays are its tensors, everything else is JSON in its header, with a sha256 over the whole
  content. Loading never unpickles, so a file cannot run code; a flipped byte or a cut file is
  a :class:`RunFileError`. ``state.safetensors`` (the training state) and the frozen policies
  ``policies/step_N.safetensors`` (acting weights only) use it.
* **The manifest** (``manifest.json``): the run's identity (method, env, profile, seed,
  operator, acceptance noise, agent config) and the sha256 and size of every file the run
  writes. A file is replaced in three steps (manifest lists old and new hash, rename, manifest
  lists the new hash), so a kill at any moment leaves a directory that verifies.
  ``tb/`` (TensorBoard's append-only log, never read back) and the lock are not listed.
* **One writer per run directory** (:class:`RunDir`): an ``fcntl`` lock on ``.lock``, released
  by the OS when the process dies; a second writer stops at once with the first one's pid and
  command. A directory that holds anything but this run is refused unless it is empty.

Every refusal is a :class:`RunFileError`: one line that names the file and what to do.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import sys
import time
from pathlib import Path

import numpy as np

from window_bench.harness.evaluation import atomic_write

STATE_FORMAT = "window-bench/state"
STATE_VERSION = 1
MANIFEST = "manifest.json"
STATE = "state.safetensors"
MANIFEST_FORMAT = "window-bench/run"
LOCK = ".lock"
UNLISTED = ("tb", LOCK, MANIFEST)      # top-level names the manifest does not cover
_PICKLE_MAGIC = (b"PK\x03\x04", b"\x80")   # torch.save zip archives, raw pickles


class RunFileError(ValueError):
    """A run file or directory that cannot be trusted or used; the message is one line."""


# ---------------------------------------------------------------------------- state format
def _encode(obj, tensors: dict, where: str):
    import torch

    if isinstance(obj, torch.Tensor):
        name = str(len(tensors))
        tensors[name] = obj.detach().cpu().contiguous().clone()   # clone: no shared storage
        return {"__tensor__": name}
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "US":
            return {"__strings__": obj.tolist(), "dtype": obj.dtype.str}
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"{where}: numpy dtype {obj.dtype} cannot be stored without pickle")
        name = str(len(tensors))
        native = np.ascontiguousarray(obj, dtype=obj.dtype.newbyteorder("="))
        tensors[name] = torch.from_numpy(native.copy())
        return {"__ndarray__": name}
    if isinstance(obj, np.generic):
        return {"__npscalar__": obj.dtype.str, "value": _encode(obj.item(), tensors, where)}
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else {"__float__": repr(obj)}
    if isinstance(obj, (list, tuple)):
        items = [_encode(v, tensors, f"{where}[{i}]") for i, v in enumerate(obj)]
        return items if isinstance(obj, list) else {"__tuple__": items}
    if isinstance(obj, dict):
        if all(isinstance(k, str) and not k.startswith("__") for k in obj):
            return {k: _encode(v, tensors, f"{where}.{k}") for k, v in obj.items()}
        return {"__items__": [[_encode(k, tensors, where), _encode(v, tensors, f"{where}.{k}")]
                              for k, v in obj.items()]}
    raise TypeError(f"{where}: a {type(obj).__name__} cannot be stored without pickle")


def _decode(obj, tensors: dict):
    if isinstance(obj, list):
        return [_decode(v, tensors) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if "__tensor__" in obj:
        return tensors[obj["__tensor__"]]
    if "__ndarray__" in obj:
        return tensors[obj["__ndarray__"]].numpy()
    if "__strings__" in obj:
        return np.array(obj["__strings__"], dtype=np.dtype(obj["dtype"]))
    if "__npscalar__" in obj:
        return np.dtype(obj["__npscalar__"]).type(_decode(obj["value"], tensors))
    if "__float__" in obj:
        return float(obj["__float__"])
    if "__tuple__" in obj:
        return tuple(_decode(v, tensors) for v in obj["__tuple__"])
    if "__items__" in obj:
        return {_decode(k, tensors): _decode(v, tensors) for k, v in obj["__items__"]}
    return {k: _decode(v, tensors) for k, v in obj.items()}


def _content_sha256(header: dict, tensors: dict) -> str:
    """sha256 over the JSON parts and every tensor's name, dtype, shape and bytes."""
    import torch

    h = hashlib.sha256()
    for key in ("format", "version", "kind", "meta", "tree"):
        h.update(header[key].encode())
        h.update(b"\0")
    for name in sorted(tensors, key=int):
        t = tensors[name]
        h.update(f"{name}:{t.dtype}:{list(t.shape)}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def dump_state(tree, kind: str, meta: dict | None = None) -> bytes:
    """The bytes of a state file of ``kind`` holding ``tree`` (``meta``: plain values)."""
    from safetensors.torch import save

    tensors: dict = {}
    header = {"format": STATE_FORMAT, "version": str(STATE_VERSION), "kind": kind,
              "meta": json.dumps(_encode(meta or {}, {}, "meta"), allow_nan=False),
              "tree": json.dumps(_encode(tree, tensors, kind), allow_nan=False)}
    header["sha256"] = _content_sha256(header, tensors)
    return _canonical(save(tensors, metadata=header))


def _canonical(data: bytes) -> bytes:
    """The same safetensors file with its JSON header in sorted key order: safetensors writes
    the header from a hash map, so without this equal states could get different file
    hashes (and ``final_eval.policy_sha256`` would not be reproducible)."""
    n = int.from_bytes(data[:8], "little")
    header = json.dumps(json.loads(data[8:8 + n]), sort_keys=True, separators=(",", ":"))
    raw = header.encode()
    raw += b" " * (-len(raw) % 8)     # the format pads the header to 8 bytes with spaces
    return len(raw).to_bytes(8, "little") + raw + data[8 + n:]


def parse_state(data: bytes, path, kind: str):
    """``(tree, meta)`` from the bytes of a state file of ``kind``; :class:`RunFileError`
    naming ``path`` for a pickle, a cut, corrupt or edited file, or another kind."""
    from safetensors import SafetensorError
    from safetensors.torch import load

    fix = "restore it from a copy or start a new run"
    try:
        (n,) = struct.unpack("<Q", data[:8])
        header = json.loads(data[8:8 + n])["__metadata__"]
        if header.get("format") != STATE_FORMAT:
            raise ValueError(f"format {header.get('format')!r}")
        tensors = load(data)
    except (SafetensorError, ValueError, KeyError, TypeError, AttributeError, RecursionError,
            struct.error) as e:
        # never unpickled: named, to say why; a safetensors file (its JSON header opens at
        # byte 8) whose header length happens to begin with 0x80 is a cut file, not a pickle
        if data.startswith(_PICKLE_MAGIC) and data[8:9] != b"{":
            raise RunFileError(f"{path}: a pickle file (torch.save), refused: loading pickle "
                               f"can run code; window-bench reads only the .safetensors files "
                               f"bench run writes") from None
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise RunFileError(f"{path}: not a window-bench {kind} file, or a truncated or corrupt "
                           f"one ({msg}); {fix}") from None
    if header.get("version") != str(STATE_VERSION):
        raise RunFileError(f"{path}: state format version {header.get('version')!r}, this "
                           f"window-bench reads {STATE_VERSION}")
    if header.get("kind") != kind:
        raise RunFileError(f"{path}: a window-bench {header.get('kind')!r} file, not a {kind} "
                           f"file")
    try:
        digest = _content_sha256(header, tensors)
    except (KeyError, AttributeError, TypeError, ValueError):
        digest = None   # a header without our fields: no digest can match
    if digest is None or digest != header.get("sha256"):
        raise RunFileError(f"{path}: content does not match its sha256 (corrupt or edited "
                           f"after bench wrote it); {fix}")
    try:
        return _decode(json.loads(header["tree"]), tensors), _decode(json.loads(header["meta"]), {})
    except (ValueError, KeyError, TypeError, IndexError, AttributeError, RecursionError) as e:
        raise RunFileError(f"{path}: not a window-bench {kind} file, or a corrupt one ({e}); "
                           f"{fix}") from None


def read_bytes(path) -> bytes:
    path = Path(path)
    try:
        if not path.is_file():
            why = "a directory, not a file" if path.is_dir() else "no such file"
            raise RunFileError(f"{path}: {why}")
        return path.read_bytes()
    except OSError as e:   # unreadable, or a name longer than the file system allows
        raise RunFileError(f"{path}: cannot be read ({e.strerror})") from None


def load_state(path, kind: str):
    """``(tree, meta)`` of a state file; see :func:`parse_state`."""
    return parse_state(read_bytes(path), path, kind)


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------- manifest
def read_manifest(run_dir) -> dict:
    path = Path(run_dir) / MANIFEST
    try:
        m = json.loads(read_bytes(path))
        if m.get("format") != MANIFEST_FORMAT or not isinstance(m.get("run"), dict) \
                or not isinstance(m.get("files"), dict):
            raise ValueError("not a window-bench manifest")
    except (ValueError, AttributeError) as e:
        if isinstance(e, RunFileError):
            raise
        raise RunFileError(f"{path}: unreadable ({str(e).splitlines()[0]}); the run's files "
                           f"cannot be checked: restore it from a copy or start a new run") from None
    return m


def verify_files(run_dir, names=None, manifest: dict | None = None) -> dict:
    """Check the files ``names`` (default: all listed) against ``manifest.json``; returns the
    manifest. A file matches its listed sha256, or the previous one while it is replaced."""
    run_dir = Path(run_dir)
    m = manifest or read_manifest(run_dir)
    for name in m["files"] if names is None else names:
        entry = m["files"].get(name)
        path = run_dir / name
        if entry is None:
            raise RunFileError(f"{path}: not listed in {run_dir / MANIFEST}, so it was not "
                               f"written by this run; remove it or restore the run")
        if not path.is_file():
            raise RunFileError(f"{path}: listed in {MANIFEST} but missing; restore it from a "
                               f"copy or start a new run")
        ok = {entry["sha256"], (entry.get("previous") or {}).get("sha256")}
        if sha256_file(path) not in ok:
            raise RunFileError(f"{path}: sha256 does not match {run_dir / MANIFEST} (changed "
                               f"after bench wrote it: truncated, corrupt or edited); restore "
                               f"it from a copy or start a new run")
    return m


def find_run_dir(path) -> Path | None:
    """The run directory whose manifest lists ``path`` (its parent or grandparent)."""
    path = Path(path).resolve()
    for d in (path.parent, path.parent.parent):
        if (d / MANIFEST).is_file():
            return d
    return None


# ---------------------------------------------------------------------------- the directory
def _holder(fd: int) -> str:
    text = os.pread(fd, 4096, 0).decode(errors="replace").strip()
    return text or "a process that has not written its pid yet"


def _in_use(out, holder: str) -> str:
    return (f"--out {out}: in use by another bench process ({holder}); wait for it to finish "
            f"or choose another --out")


def lock_holder(out) -> str | None:
    """Who holds ``out``'s lock (the holder's line: pid, command, since when), or None when
    no process does. A momentary shared lock, so it never blocks the holder;
    :meth:`RunDir._lock` retries briefly for this probe."""
    import fcntl

    path = Path(out) / LOCK
    if not path.is_file():
        return None
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _holder(fd)
    finally:
        os.close(fd)
    return None


def check_unlocked(out) -> None:
    """Stop at once, before any heavy import, when another process holds ``out``'s lock."""
    holder = lock_holder(out)
    if holder is not None:
        raise RunFileError(_in_use(out, holder))


def state_counters(path) -> dict | None:
    """The training counters a state file's header records (``stage``, ``offline_done``,
    ``env_steps``, ``episodes``...), read from its JSON header alone, without the tensors or
    the checksum; None for a file that is missing, cut or not a window-bench state. For a
    progress report only: a resume loads the file with :func:`load_state`."""
    try:
        with open(path, "rb") as f:
            (n,) = struct.unpack("<Q", f.read(8))
            if n > 64 << 20:
                return None
            header = json.loads(f.read(n))["__metadata__"]
        if header.get("format") != STATE_FORMAT:
            return None
        counters = json.loads(header["tree"]).get("counters")
    except (OSError, ValueError, KeyError, TypeError, AttributeError, struct.error):
        return None
    return counters if isinstance(counters, dict) else None


def check_out_dir(out, option: str = "--out") -> Path:
    """``out`` (the value of ``option``) must be a directory or creatable as one by this user;
    nothing is written."""
    out = Path(out)
    try:   # a name too long, a loop of links: refused here, not raised from a later mkdir
        if out.exists() and not out.is_dir():
            raise RunFileError(f"{option} {out}: a file, not a directory; choose a directory")
        probe = out
        while not probe.exists():
            probe = probe.parent
        if not probe.is_dir():
            raise RunFileError(f"{option} {out}: {probe} is a file, not a directory")
        writable = os.access(probe, os.W_OK | os.X_OK)
    except OSError as e:
        raise RunFileError(f"{option} {out}: cannot be used ({e.strerror}); choose another "
                           f"{option}") from None
    if not writable:
        raise RunFileError(f"{option} {out}: {probe} is not writable by this user; choose "
                           f"another {option}")
    return out


class RunDir:
    """A locked run directory and its manifest (see the module docstring).

    ``RunDir(out, identity, resume)`` checks the directory, takes the lock and, for a new run,
    writes the manifest; for ``resume`` it checks the identity and verifies every listed file.
    """

    def __init__(self, out, identity: dict, resume: bool):
        self.path = check_out_dir(out)
        self.identity = json.loads(json.dumps(identity))   # plain JSON, as stored
        has_manifest = (self.path / MANIFEST).is_file()
        others = ([p.name for p in self.path.iterdir() if p.name != LOCK]
                  if self.path.is_dir() else [])
        if others and not has_manifest:
            legacy = " (a run of an older window-bench, whose state.pt is a pickle file and " \
                     "cannot be resumed safely)" if (self.path / "state.pt").exists() else ""
            raise RunFileError(f"--out {self.path}: not empty and not a window-bench run"
                               f"{legacy}; choose a new or empty directory")
        self._fd = None
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            self._lock()
        except OSError as e:
            raise RunFileError(f"--out {self.path}: cannot be used ({e.strerror}); choose "
                               f"another --out") from None
        try:
            if (self.path / MANIFEST).is_file():
                self.manifest = read_manifest(self.path)
                self._check_identity(resume)
                verify_files(self.path, manifest=self.manifest)
            else:   # a new run; with --resume too, so that one command starts or continues
                self.manifest = {"format": MANIFEST_FORMAT, "run": self.identity, "files": {}}
                self._write_manifest()
        except BaseException:
            self.close()
            raise

    def _lock(self) -> None:
        import fcntl

        fd = os.open(self.path / LOCK, os.O_RDWR | os.O_CREAT, 0o666)
        for attempt in range(20):   # 1 s: outlasts another command's check_unlocked probe
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if attempt == 19:
                    holder = _holder(fd)
                    os.close(fd)
                    raise RunFileError(_in_use(self.path, holder)) from None
                time.sleep(0.05)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)} (since "
                      f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())})\n".encode(), 0)
        self._fd = fd

    def close(self) -> None:
        """Release the lock, emptying the holder's line (the OS releases the lock, not the
        line, when the process dies: the next holder overwrites it)."""
        if self._fd is not None:
            os.ftruncate(self._fd, 0)
            os.close(self._fd)
            self._fd = None

    def _check_identity(self, resume: bool) -> None:
        saved = self.manifest["run"]
        desc = ", ".join(f"{k} {saved.get(k)}" for k in ("method", "env_id", "profile", "seed"))
        if not resume and saved == self.identity and STATE not in self.manifest["files"]:
            return   # this run, stopped before its first state (e.g. in demo collection)
        if not resume:
            raise RunFileError(f"--out {self.path}: already holds a run ({desc}); pass --resume "
                               f"to continue it or choose another --out")
        for key in sorted(set(saved) | set(self.identity)):
            if saved.get(key) != self.identity.get(key):
                raise RunFileError(f"--resume: the run in {self.path} has {key} = "
                                   f"{saved.get(key)!r}, this command asks for "
                                   f"{self.identity.get(key)!r}")

    def _write_manifest(self) -> None:
        text = json.dumps(self.manifest, indent=1, sort_keys=True)
        atomic_write(self.path / MANIFEST, lambda f: f.write(text.encode()))

    # -------------------------------------------------------------- files
    def write(self, name: str, data: bytes) -> Path:
        """Atomically write ``data`` to ``name`` (relative), keeping the manifest true at
        every moment: it lists the old and the new hash while the file is renamed."""
        new = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
        old = self.manifest["files"].get(name)
        self.manifest["files"][name] = {**new, "previous": old and {"sha256": old["sha256"]}}
        self._write_manifest()
        atomic_write(self.path / name, lambda f: f.write(data))
        self.manifest["files"][name] = new
        self._write_manifest()
        return self.path / name

    def write_state(self, name: str, tree, kind: str, meta: dict | None = None) -> Path:
        return self.write(name, dump_state(tree, kind, meta))

    def record(self, folder: str) -> None:
        """List every file under ``folder`` (written by another library, e.g. Minari)."""
        for p in sorted((self.path / folder).rglob("*")):
            if p.is_file():
                self.manifest["files"][p.relative_to(self.path).as_posix()] = {
                    "sha256": sha256_file(p), "bytes": p.stat().st_size}
        self._write_manifest()

    def check_listed(self, folder) -> None:
        """Every file under ``folder`` (relative) is listed in the manifest, so that
        :func:`verify_files` checked it: a file added there after the run wrote it (a dataset
        whose metadata names code, say) is refused before anything reads it."""
        for p in sorted((self.path / folder).rglob("*")):
            name = p.relative_to(self.path).as_posix()
            if (p.is_file() or p.is_symlink()) and name not in self.manifest["files"]:
                raise RunFileError(f"{p}: not listed in {self.path / MANIFEST}, so it was not "
                                   f"written by this run; remove it or restore the run")

    def read_state(self, name: str, kind: str):
        """``(tree, meta)`` of a listed state file, after checking it against the manifest."""
        verify_files(self.path, [name], self.manifest)
        return load_state(self.path / name, kind)

    def write_run_state(self, name: str, tree, kind: str) -> Path:
        """A state file of this run, saved with the run's identity."""
        return self.write_state(name, tree, kind, self.identity)

    def read_run_state(self, name: str, kind: str):
        """The tree of a state file :meth:`write_run_state` wrote, once the manifest matched
        the command (``RunDir``) and the run that saved the state matches the manifest (a
        manifest edited to another seed would relabel the run)."""
        tree, saved = self.read_state(name, kind)
        run, saved = self.manifest["run"], saved if isinstance(saved, dict) else {}
        for key in sorted(set(saved) | set(run)):
            if saved.get(key) != run.get(key):
                raise RunFileError(f"{self.path / MANIFEST}: records {key} = {run.get(key)!r}, "
                                   f"the run's {name} was saved with {saved.get(key)!r} "
                                   f"(edited, or another run's manifest); restore it from a "
                                   f"copy or start a new run")
        return tree

    def has(self, name: str) -> bool:
        return name in self.manifest["files"]
