"""numba's on-disk cache (``cache=True``) made safe for sdexp's use: several processes, and
cached functions that call parallel ones. Two numba bugs, both open upstream, are worked around:

- numba issue 8578 (PR 9950): a cached function compiled in a process that *loaded* its
  ``parallel=True`` callee from the cache is saved without the hook that starts numba's threading
  layer; loaded in a fresh process it calls a null pointer. sdexp's reference.element_forces calls the
  parallel forces_2d, and whether its entry lacks the hook depends on which process
  compiled what first: CI on a fresh checkout crashed with a SIGSEGV this way (2026-11-26).
  Any entry loaded here starts the threading layer first, as numba's own hook would.
- numba issue 4807: the index (signature -> data file) is rewritten by read, modify, write with
  no lock (numba.core.caching.IndexDataCacheFile.save); two processes saving different
  signatures of one function at once, as sdexp's data workers, a parallel sweep or
  ``pytest -n 2`` on a fresh install do, can both pick data file 1, and the index then maps one
  signature to the other's machine code. A save here takes an exclusive ``flock`` on
  ``<index>.lock`` and writes the data file before the index that names it, and a load checks
  that the entry holds code for the signature asked for (else: not cached, so numba compiles
  and the save repairs the entry; a cache damaged before this existed heals itself).

``install()`` patches numba's cache file class in this process; sdexp.sensing and sdexp.sim,
the packages whose modules cache, call it on import.
"""
from __future__ import annotations

import contextlib
import itertools

_INSTALLED = False


@contextlib.contextmanager
def _locked(path: str):
    """An exclusive lock on ``path`` across processes (none where fcntl is missing: Windows)."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    with open(path, "a+b") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _save(self, key, data):
    """IndexDataCacheFile.save, under the lock and data first."""
    with _locked(self._index_path + ".lock"):
        overloads = self._load_index()
        name = overloads.get(key)
        if name is None:
            taken = set(overloads.values())
            name = next(n for n in map(self._data_name, itertools.count(1)) if n not in taken)
        self._save_data(name, data)
        if overloads.get(key) != name:
            overloads[key] = name
            self._save_index(overloads)


def _compiled_for(data, key) -> bool:
    """The loaded entry ``data`` holds code for the signature in ``key``, as far as it says: a
    CompileResult's reduction carries its signature fourth (numba.core.compiler.CompileResult
    ._reduce); other payloads (cfuncs' code libraries) carry none and are taken as they are."""
    try:
        signature = data[3]
        args = signature.args
    except (TypeError, IndexError, AttributeError):
        return True
    asked = key[0]
    asked = getattr(asked, "args", asked)
    return tuple(args) == tuple(asked)


def _launch_threads() -> None:
    """Start numba's threading layer (once per process; later calls return at once)."""
    from numba.np.ufunc.parallel import _launch_threads as launch
    launch()


def install() -> None:
    """Patch numba's cache file class in this process (idempotent; a no-op without numba)."""
    global _INSTALLED
    if _INSTALLED:
        return
    try:
        from numba.core.caching import IndexDataCacheFile
    except ImportError:
        return
    load = IndexDataCacheFile.load

    def checked_load(self, key):
        data = load(self, key)
        if data is None or not _compiled_for(data, key):
            return None
        _launch_threads()   # numba 8578: the entry may call parallel code without saying so
        return data

    IndexDataCacheFile.save = _save
    IndexDataCacheFile.load = checked_load
    _INSTALLED = True


