"""Content-addressed cache for expensive artefacts (meshes, datasets, trained networks).

An entry's key is a hash of everything that produced it plus a format version, so a change
of config or of the code's format reads as a miss, never as a stale hit. Entries are written
to a temporary name in the same folder and renamed, so a killed run never leaves a
half-written entry behind.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np


def key_of(kind: str, version: int, payload: Any) -> str:
    text = json.dumps({"kind": kind, "version": version, "payload": payload}, sort_keys=True, default=str)
    return f"{kind}-{hashlib.sha256(text.encode()).hexdigest()[:16]}"


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp_path)`` then rename tmp_path to ``path`` (atomic on one filesystem)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def cached_arrays(cache_dir: str | Path, key: str, make: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Load the arrays stored under ``key``, or make, store and return them. An entry that cannot
    be read back whole is made again."""
    path = Path(cache_dir).expanduser() / f"{key}.npz"
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            if arrays:
                return arrays
            reason = "it holds no arrays"
        except Exception as err:   # noqa: BLE001 - truncated, overwritten, not a zip: any damage
            reason = f"{type(err).__name__}: {err}"
        # a damaged entry (a disk filled mid-copy, a file edited by hand): made again, not a traceback
        print(f"sdexp: cache entry {path} is damaged ({reason}); rebuilding it", file=sys.stderr)
        path.unlink(missing_ok=True)
    arrays = make()

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    try:
        atomic_write(path, write)
    except OSError as err:
        from sdexp.errors import UserError
        raise UserError(f"cache_dir {Path(cache_dir).expanduser()} cannot be written ({err.strerror or err}): "
                        f"choose a writable one with cache_dir=<folder> or SDEXP_CACHE") from None
    return arrays
