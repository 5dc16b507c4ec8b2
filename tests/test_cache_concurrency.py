"""The shared cache under concurrent jobs: two processes that need the same entry build it once,
and a builder killed mid-way leaves neither a half-written entry nor a lock that blocks."""
import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

import numpy as np

from sdexp.cache import cached_arrays

KEY = "mesh3d-concurrent"


def _make(counter: str, hold: float):
    def make():
        with open(counter, "a") as fh:   # one line per build
            fh.write(f"{os.getpid()}\n")
        time.sleep(hold)                 # a slow build: the other process asks meanwhile
        return {"points": np.arange(12.0).reshape(4, 3)}
    return make


def _build(cache: str, counter: str, barrier, out: str) -> None:
    barrier.wait()
    arrays = cached_arrays(cache, KEY, _make(counter, 1.0))
    np.save(out, arrays["points"])


def test_two_processes_build_the_same_entry_once(tmp_path):
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(2)
    counter = tmp_path / "builds.txt"
    procs = [ctx.Process(target=_build, args=(str(tmp_path / "cache"), str(counter), barrier,
                                               str(tmp_path / f"out{i}.npy"))) for i in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
        assert p.exitcode == 0
    assert len(counter.read_text().split()) == 1   # the builder ran once
    a, b = (np.load(tmp_path / f"out{i}.npy") for i in range(2))
    assert np.array_equal(a, b) and np.array_equal(a, np.arange(12.0).reshape(4, 3))
    assert not list((tmp_path / "cache").glob(".*.tmp"))


def _hold_forever(cache: str, started: str) -> None:
    def make():
        # a builder that dies mid-write: its temporary file exists, the entry does not
        Path(cache, f".{KEY}.npz.killed.tmp").write_bytes(b"half an npz")
        Path(started).write_text("building")
        time.sleep(600)
    cached_arrays(cache, KEY, make)


def _build_after(cache: str, counter: str) -> None:
    cached_arrays(cache, KEY, _make(counter, 0.0))


def test_a_killed_builder_leaves_no_half_written_entry_and_no_stale_lock(tmp_path):
    ctx = mp.get_context("spawn")
    cache, started, counter = tmp_path / "cache", tmp_path / "started", tmp_path / "builds.txt"
    holder = ctx.Process(target=_hold_forever, args=(str(cache), str(started)))
    holder.start()
    deadline = time.monotonic() + 120
    while not started.exists() and holder.is_alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert started.exists()
    os.kill(holder.pid, signal.SIGKILL)   # killed while it holds the lock
    holder.join()
    assert not (cache / f"{KEY}.npz").exists()
    later = ctx.Process(target=_build_after, args=(str(cache), str(counter)))
    later.start()
    later.join(120)                      # a stale lock would keep it waiting: it must end
    finished = later.exitcode
    if finished is None:
        later.kill()
    assert finished == 0
    assert len(counter.read_text().split()) == 1
    assert cached_arrays(cache, KEY, _make(str(counter), 0.0))["points"].shape == (4, 3)
    assert len(counter.read_text().split()) == 1   # read back, not built again
    assert not list(cache.glob(".*.tmp"))         # the killed builder's temporary file is gone
