"""Content-addressed cache for expensive artefacts (meshes, datasets, trained networks).

An entry's key is a hash of everything that produced it plus a format version, so a change
of config or of the code's format reads as a miss, never as a stale hit. Entries are written
to a temporary name in the same folder and renamed, so a killed run never leaves a
half-written entry behind.

Concurrent jobs (a sweep's parallel jobs, several Slurm jobs on one shared cache) that need the
same entry build it once: the builder holds an exclusive lock (:func:`build_lock`, ``flock`` on
``<cache>/.locks/<entry>.lock``) while it checks, builds and writes; the others wait, then read
what it wrote. The kernel releases the lock when its holder ends, however it ends, so a killed
builder blocks nobody: the next process takes the lock, removes the killed one's temporary
files and builds the entry itself.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sdexp.files import atomic_write  # noqa: F401 - also this module's: callers import it from here

try:
    import fcntl
except ImportError:   # not a POSIX system: no locking (one job at a time)
    fcntl = None

log = logging.getLogger(__name__)

LOCK_DIR = ".locks"


# A field added after caches were built, marked metadata={"key": KEY_UNLESS_DEFAULT}: it enters
# the key only when set away from its default, so the artefacts of every earlier config (which
# ran at that default) keep their keys and need no rebuilding (sim.precision, sim.mass_scaling).
KEY_UNLESS_DEFAULT = "unless_default"


def config_key(node: Any) -> Any:
    """A config dataclass as a cache key's payload: its fields, nested dataclasses alike, less
    those marked ``metadata={"key": False}`` (how a result is computed, not what: threads,
    worker processes) and those marked KEY_UNLESS_DEFAULT while at their default. Which artefact a field determines is the caller's to say (it passes the
    parts of the config that make the artefact); a change to what the fields mean or to the
    artefact is a bump of the caller's format version, never a special case here."""
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        return {f.name: config_key(getattr(node, f.name)) for f in dataclasses.fields(node)
                if f.metadata.get("key", True) is True
                or (f.metadata.get("key") == KEY_UNLESS_DEFAULT and getattr(node, f.name) != _default(f))}
    if isinstance(node, (list, tuple)):
        return [config_key(v) for v in node]
    if isinstance(node, dict):
        return {k: config_key(v) for k, v in node.items()}
    return node


def _default(f: dataclasses.Field) -> Any:
    return f.default_factory() if f.default is dataclasses.MISSING and f.default_factory is not dataclasses.MISSING else f.default


def content_digest(*objs: Any) -> str:
    """A hash of the values in ``objs``, for artefacts made from built objects rather than from a
    config (a drone as meshed, a FEM model): arrays by dtype, shape and bytes, dataclasses field by
    field (every field: a config's threads too, which change a simulation's last bits), lists and
    dicts item by item, anything else by its repr."""
    h = hashlib.sha256()

    def feed(o: Any) -> None:
        if isinstance(o, np.ndarray):
            a = np.ascontiguousarray(o)
            h.update(f"<{a.dtype}{a.shape}>".encode())
            h.update(a.tobytes())
        elif dataclasses.is_dataclass(o) and not isinstance(o, type):
            h.update(f"{type(o).__name__}(".encode())
            for f in dataclasses.fields(o):
                h.update(f"{f.name}=".encode())
                feed(getattr(o, f.name))
            h.update(b")")
        elif isinstance(o, (list, tuple)):
            h.update(b"[")
            for v in o:
                feed(v)
            h.update(b"]")
        elif isinstance(o, dict):
            h.update(b"{")
            for k in sorted(o, key=str):
                h.update(f"{k!r}:".encode())
                feed(o[k])
            h.update(b"}")
        else:
            h.update(f"{type(o).__name__}:{o!r};".encode())

    for o in objs:
        feed(o)
    return h.hexdigest()[:24]


def key_of(kind: str, version: int, payload: Any) -> str:
    text = json.dumps({"kind": kind, "version": version, "payload": payload}, sort_keys=True, default=str)
    return f"{kind}-{hashlib.sha256(text.encode()).hexdigest()[:16]}"


def _unwritable(folder: Path, err: OSError):
    from sdexp.errors import UserError, disk_full
    full = disk_full(err, folder, "or choose another cache with cache_dir=<folder> or SDEXP_CACHE")
    if full is not None:
        return full
    return UserError(f"cache_dir {folder} cannot be written ({err.strerror or err}): "
                     f"choose a writable one with cache_dir=<folder> or SDEXP_CACHE")


@contextlib.contextmanager
def build_lock(path: str | Path):
    """Hold the exclusive right to build the cache entry ``path`` (or folder) for the duration:
    other processes asking for the same entry wait here. On entry, the temporary files a killed
    builder of this entry left behind are removed (only their owner, now gone, wrote them)."""
    path = Path(path).expanduser()
    if fcntl is None:
        yield
        return
    folder = path.parent / LOCK_DIR
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f"{path.name}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise _unwritable(path.parent, err) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info(f"sdexp: waiting for another process that builds {path.name}")
            fcntl.flock(fd, fcntl.LOCK_EX)
        for stale in path.parent.glob(f".{path.name}.*.tmp"):
            stale.unlink(missing_ok=True)
        yield
    finally:
        os.close(fd)   # releases the lock


def _read_arrays(path: Path) -> tuple[dict[str, np.ndarray] | None, str | None]:
    """(arrays, None), (None, None) for a missing entry, or (None, why it is damaged)."""
    if not path.exists():
        return None, None
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
        if arrays:
            return arrays, None
        return None, "it holds no arrays"
    except Exception as err:   # noqa: BLE001 - truncated, overwritten, not a zip: any damage
        return None, f"{type(err).__name__}: {err}"


def cached_arrays(cache_dir: str | Path, key: str, make: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Load the arrays stored under ``key``, or make, store and return them (once, whichever
    processes ask at the same time). An entry that cannot be read back whole is made again."""
    path = Path(cache_dir).expanduser() / f"{key}.npz"
    arrays, _ = _read_arrays(path)
    if arrays is not None:
        return arrays
    with build_lock(path):
        arrays, damage = _read_arrays(path)   # another process may have built it meanwhile
        if arrays is not None:
            return arrays
        if damage is not None:
            # a damaged entry (a disk filled mid-copy, a file edited by hand): made again, not a traceback
            log.warning(f"sdexp: cache entry {path} is damaged ({damage}); rebuilding it")
        arrays = make()

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)

        try:
            atomic_write(path, write)
        except OSError as err:
            raise _unwritable(Path(cache_dir).expanduser(), err) from None
    return arrays
