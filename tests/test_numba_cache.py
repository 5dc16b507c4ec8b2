"""numba's disk cache as sdexp uses it (sdexp.numba_cache): a cached function that calls a
parallel one runs from the cache in a fresh process (numba 8578), concurrent saves keep every
entry, and an index that maps a signature to another signature's code is not trusted (4807)."""
import pickle
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from numba.core.caching import IndexDataCacheFile

from sdexp import numba_cache

ROOT = Path(__file__).resolve().parents[1]
TWICE = "import numba as nb\n\n@nb.njit(cache=True)\ndef twice(x):\n    return x * 2\n"
NESTED = """import numba as nb
import numpy as np

@nb.njit(parallel=True, cache=True)
def inner(n):
    out = np.zeros(n)
    for i in nb.prange(n):
        out[i] = i
    return out

@nb.njit(cache=True)
def outer(n):
    return inner(n).sum()
"""


def _run(folder: Path, call: str, install: bool) -> subprocess.CompletedProcess:
    """``call`` (a print of what the module in ``folder`` computes) in a fresh interpreter."""
    code = (f"import sys; sys.path[:0] = [{str(ROOT)!r}, {str(folder)!r}]\n"
            + ("from sdexp import numba_cache; numba_cache.install()\n" if install else "") + call)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={"PATH": "/usr/bin:/bin", "NUMBA_CACHE_DIR": str(folder / "nbcache")})


def _prints(result: subprocess.CompletedProcess, *words: str) -> bool:
    return result.returncode == 0 and result.stdout.split() == list(words)


@pytest.mark.parametrize("install", [False, True])
def test_a_cached_caller_of_a_parallel_function_runs_from_the_cache(tmp_path, install):
    # the order that drops numba's threading hook from the caller's entry: one process caches the
    # parallel callee, the next compiles the caller around the callee it loads, the third loads both
    (tmp_path / "nested.py").write_text(NESTED)
    assert _prints(_run(tmp_path, "import nested; print(nested.inner(4).sum())", install), "6.0")
    assert _prints(_run(tmp_path, "import nested; print(nested.outer(4))", install), "6.0")
    third = _run(tmp_path, "import nested; print(nested.outer(4))", install)
    if install:
        assert _prints(third, "6.0"), third.stderr
    else:   # the control: numba alone crashes; if this fails, numba fixed 8578 (its PR 9950)
        assert third.returncode != 0


def test_saves_from_many_writers_at_once_keep_every_entry(tmp_path, monkeypatch):
    # a slow index write opens numba's read-modify-write window wide: unpatched, the writers all
    # read the empty index and all name their data file 1, and one entry survives, pointing at
    # whichever data file landed last
    numba_cache.install()
    write_index = IndexDataCacheFile._save_index

    def slow_write(self, overloads):
        time.sleep(0.05)
        write_index(self, overloads)

    monkeypatch.setattr(IndexDataCacheFile, "_save_index", slow_write)
    caches = [IndexDataCacheFile(str(tmp_path), "f", source_stamp=1) for _ in range(6)]
    threads = [threading.Thread(target=c.save, args=((i,), f"code for {i}")) for i, c in enumerate(caches)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    reader = IndexDataCacheFile(str(tmp_path), "f", source_stamp=1)
    assert [reader.load((i,)) for i in range(6)] == [f"code for {i}" for i in range(6)]


def _swap_entries(folder: Path) -> None:
    """The damage the unlocked race leaves: each signature named the other's data file."""
    (index,) = (folder / "nbcache").rglob("*.nbi")
    with open(index, "rb") as fh:
        version = pickle.load(fh)
        stamp, overloads = pickle.loads(fh.read())
    keys = list(overloads)
    assert len(keys) == 2
    overloads = {keys[0]: overloads[keys[1]], keys[1]: overloads[keys[0]]}
    with open(index, "wb") as fh:
        pickle.dump(version, fh, protocol=-1)
        fh.write(pickle.dumps((stamp, overloads)))


@pytest.mark.parametrize("install", [False, True])
def test_an_entry_holding_another_signatures_code_is_compiled_afresh(tmp_path, install):
    (tmp_path / "cached_twice.py").write_text(TWICE)
    call = "import cached_twice; print(cached_twice.twice(3), cached_twice.twice(2.5))"
    assert _prints(_run(tmp_path, call, install), "6", "5.0")
    _swap_entries(tmp_path)
    damaged = _run(tmp_path, call, install)
    if install:   # the entry is refused, compiled again and saved over the damage
        assert _prints(damaged, "6", "5.0"), damaged.stderr
        assert _prints(_run(tmp_path, call, install=False), "6", "5.0")
    else:         # the control: numba alone runs the other signature's code
        assert not _prints(damaged, "6", "5.0")
