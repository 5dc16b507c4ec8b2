"""Work on spawned processes, one thread each, with progress reported back through a queue.

Why processes of one thread: on 2 cores, two one-thread processes degrade gracefully when the
machine is busy, while OpenMP barriers of a two-thread process collapse (measured 10-30x). The
children read their thread counts from the environment they start with, set here for the
duration of the start. 'spawn' keeps numba, torch and OpenMP state out of the children; a
calling script must guard its top level with ``if __name__ == "__main__":``.
"""
from __future__ import annotations

import os
import queue
from typing import Callable, Sequence

ONE_THREAD_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                  "MKL_NUM_THREADS": "1"}

_REPORT = None


def _init(q, parent: int) -> None:
    global _REPORT
    _REPORT = q.put
    import threading
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()


def _exit_with(parent: int, every: float = 1.0) -> None:
    """End this worker when the process that started it is gone (killed runs otherwise leave
    their workers simulating to the end of their task); its outputs are written atomically, so
    nothing half-written stays behind."""
    import time
    while os.getppid() == parent:
        time.sleep(every)
    os._exit(1)


def _call(fn, args):
    return fn(*args, report=_REPORT)


def run_spawned(fn: Callable, tasks: Sequence[tuple], workers: int, progress: Callable | None = None) -> list:
    """[fn(*task, report=...) for task in tasks] on ``workers`` spawned processes; ``report(n)``
    in a child calls ``progress(n)`` here. A child's error is raised here; the tasks not yet
    started are cancelled (a task that already wrote its own output keeps it)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    drain = progress or (lambda n: None)
    saved = {k: os.environ.get(k) for k in ONE_THREAD_ENV}
    os.environ.update(ONE_THREAD_ENV)
    try:
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init, initargs=(q, os.getpid())) as pool:
            futures = [pool.submit(_call, fn, task) for task in tasks]  # children start here
            _restore(saved)
            try:
                while not all(f.done() for f in futures):
                    try:
                        drain(q.get(timeout=0.2))
                    except queue.Empty:
                        pass
                results = [f.result() for f in futures]  # re-raises a child's error
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    finally:
        _restore(saved)
    while True:
        try:
            drain(q.get_nowait())
        except queue.Empty:
            return results


def _restore(saved: dict) -> None:
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
