"""Work on spawned processes, one thread each, with progress reported back through a queue.

Why processes of one thread: on 2 cores, two one-thread processes degrade gracefully when the
machine is busy, while OpenMP barriers of a two-thread process collapse (measured 10-30x). The
children read their thread counts from the environment they start with, set here for the
duration of the start. 'spawn' keeps numba, torch and OpenMP state out of the children; a
calling script must guard its top level with ``if __name__ == "__main__":``.
"""
from __future__ import annotations

import contextlib
import logging
import os
import time
from typing import Callable, Sequence

ONE_THREAD_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                  "MKL_NUM_THREADS": "1"}

_REPORT = None
log = logging.getLogger(__name__)


def _init(q, parent: int) -> None:
    global _REPORT
    _REPORT = q.put
    import faulthandler
    import threading
    faulthandler.enable()   # a crash in compiled code prints where it happened, not only "terminated abruptly"
    threading.Thread(target=exit_with_parent, args=(parent,), daemon=True).start()


def exit_with_parent(parent: int, every: float = 1.0) -> None:
    """End this worker when the process that started it is gone (killed runs otherwise leave
    their workers simulating to the end of their task); its outputs are written atomically, so
    nothing half-written stays behind."""
    while os.getppid() == parent:
        time.sleep(every)
    os._exit(1)


def _call(fn, args):
    return fn(*args, report=_REPORT)


def run_spawned(fn: Callable, tasks: Sequence[tuple], workers: int, progress: Callable | None = None,
                retries: int = 1) -> list:
    """[fn(*task, report=...) for task in tasks] on ``workers`` spawned processes; ``report(n)``
    in a child calls ``progress(n)`` here. A child's error is raised here; the tasks not yet
    started are cancelled (a task that already wrote its own output keeps it). Interrupted
    (Ctrl-C, KeyboardInterrupt here), the workers are ended at once, their tasks unfinished (a
    pool would otherwise run the tasks it had queued to the end first).

    A worker that dies without an error of its own (killed by a signal: the kernel's OOM killer,
    an operator, a crash) breaks the whole pool: the tasks it left unfinished run again on a fresh
    pool, ``retries`` times, with a warning that names how the worker ended (the tasks are
    deterministic and write their outputs atomically, so a rerun changes nothing)."""
    from concurrent.futures.process import BrokenProcessPool

    results: dict[int, object] = {}
    todo = list(range(len(tasks)))
    for attempt in range(retries + 1):
        try:
            _run_pool(fn, tasks, todo, workers, progress, results)
            break
        except _Broken as broken:
            todo = [i for i in todo if i not in results]
            if attempt == retries:
                raise BrokenProcessPool(f"{broken}; {len(todo)} of {len(tasks)} tasks unfinished") from None
            log.warning(f"sdexp: {broken}; running its {len(todo)} unfinished tasks again")
    return [results[i] for i in range(len(tasks))]


class _Broken(Exception):
    """A worker of the pool ended abruptly; the message says how."""


def _run_pool(fn, tasks, todo, workers, progress, results: dict) -> None:
    import multiprocessing as mp
    import signal
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("spawn")
    # a SimpleQueue writes each report in the worker's own call, not from a feeder thread: a
    # worker the pool ends with SIGTERM once another died (its finished tasks kept) could take
    # its last reports down with it (CI counted 3 of 4 tasks, twice, on a loaded machine)
    q = ctx.SimpleQueue()
    drain = progress or (lambda n: None)
    try:
        with ProcessPoolExecutor(min(workers, len(todo)) or 1, mp_context=ctx, initializer=_init,
                                 initargs=(q, os.getpid())) as pool:
            with one_thread_children(), _deaf_to_ctrl_c():
                futures = {i: pool.submit(_call, fn, tasks[i]) for i in todo}  # children start here
            processes = list(getattr(pool, "_processes", {}).values())   # for their exit codes
            try:
                while not all(f.done() for f in futures.values()):
                    _drain(q, drain, wait=0.2)
                for i, f in futures.items():
                    if not f.cancelled() and f.exception() is None:
                        results[i] = f.result()
                for f in futures.values():
                    f.result()   # re-raises a child's error
            except BrokenProcessPool:
                for p in processes:
                    p.join(timeout=5)
                codes = [p.exitcode for p in processes if p.exitcode not in (None, 0)]
                # the pool ends the other workers with SIGTERM once one has died: name the first
                codes = [c for c in codes if c != -signal.SIGTERM] or codes
                how = ", ".join(f"signal {signal.Signals(-c).name}" if c < 0 else f"exit code {c}" for c in codes)
                raise _Broken(f"a worker process ended abruptly ({how or 'cause unknown'})") from None
            except BaseException as err:
                if isinstance(err, Exception):
                    for f in futures.values():
                        f.cancel()
                else:   # interrupted: the workers end now, not after the tasks they hold; the pool
                    # fails the futures (cancelled ones would make Python 3.11's pool thread raise)
                    end_processes(processes)
                raise
    finally:
        # what the workers reported before the pool ended, broken or not
        _drain(q, drain)


@contextlib.contextmanager
def one_thread_children():
    """Processes started within start with one thread each: they read their thread counts
    (ONE_THREAD_ENV) from the environment they start with, set here for the duration."""
    saved = {k: os.environ.get(k) for k in ONE_THREAD_ENV}
    os.environ.update(ONE_THREAD_ENV)
    try:
        yield
    finally:
        _restore(saved)


@contextlib.contextmanager
def _deaf_to_ctrl_c():
    """Processes started within never see SIGINT: they start with it blocked (a blocked signal
    stays blocked across fork and exec, and stays pending there, never delivered). Ctrl-C reaches
    a terminal's whole process group, and the parent ends its workers (run_spawned); a worker's
    own interrupt would print a traceback, or fail only its task and take the next. A Ctrl-C in
    that moment is kept and raised when the children have started: ignoring it instead (as
    before) lost it, and under load, where starting two workers takes seconds, the run went on
    (the Ctrl-C test timed out at 30 s)."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():   # the main thread's mask is what children inherit
        yield
        return
    # the mask is per thread: another thread of this process may still take the signal, so for
    # the moment it is only noted (the disposition is the process's), and raised after
    noted = []
    handler = signal.signal(signal.SIGINT, lambda *_: noted.append(True))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)   # one pending here is delivered now: noted
        signal.signal(signal.SIGINT, handler)
    if noted:
        raise KeyboardInterrupt


def end_processes(processes, wait: float = 2.0) -> None:
    """SIGTERM to each process still running, SIGKILL to any still there ``wait`` s later."""
    for p in processes:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + wait
    for p in processes:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(1.0)


def _drain(q, drain: Callable, wait: float = 0.0) -> None:
    """Pass every report waiting in q on; with ``wait``, sleep that long when there is none."""
    if q.empty():
        if wait:
            time.sleep(wait)
        return
    while not q.empty():
        drain(q.get())


def _restore(saved: dict) -> None:
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


# ------------------------------------------------------------------ cores per job (sweeps)

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


def available_cores() -> int:
    """The cores this process may run on: a Slurm job's allocation (SLURM_CPUS_PER_TASK, else
    its CPU affinity), a taskset's, or the machine's."""
    slurm = os.environ.get("SLURM_CPUS_PER_TASK")
    if slurm and slurm.isdigit() and int(slurm) > 0:
        return int(slurm)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _sweep_size(hc) -> int | None:
    """How many jobs the running sweep launches (from its multirun.yaml), or None if unknown."""
    try:
        from pathlib import Path

        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.override_parser.overrides_parser import OverridesParser
        from omegaconf import OmegaConf

        saved = OmegaConf.load(Path(str(hc.sweep.dir)) / "multirun.yaml")
        if OmegaConf.select(saved, "hydra.sweeper.params"):
            return None   # sweeps declared in the config: not counted here
        overrides = list(OmegaConf.select(saved, "hydra.overrides.task") or [])
        parsed = OverridesParser.create().parse_overrides(overrides)
        return sum(len(batch) for batch in BasicSweeper.split_arguments(parsed, None))
    except Exception:   # noqa: BLE001 - any unreadable sweep: unknown
        return None


def concurrent_jobs(cores: int | None = None) -> int:
    """How many of this sweep's jobs run at the same time on this machine: 1 for a single run,
    Hydra's basic launcher (one job after another) and Slurm (each job has its own allocation);
    hydra/launcher=joblib: its n_jobs (-1: all cores, -2: all but one, ...), at most the sweep's
    jobs; submitit_local: all of the sweep's jobs at once."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode
    except ImportError:
        return 1
    if not HydraConfig.initialized():
        return 1
    hc = HydraConfig.get()
    if hc.mode != RunMode.MULTIRUN:
        return 1
    target = str(hc.launcher.get("_target_", ""))
    cores = cores or available_cores()
    total = _sweep_size(hc)
    if "joblib" in target:
        n = int(hc.launcher.get("n_jobs") or -1)
        n = n if n > 0 else max(1, cores + 1 + n)
    elif target.endswith("submitit_launcher.LocalLauncher"):
        n = total or cores
    else:
        return 1
    return max(1, min(n, total) if total else n)


def job_cores(requested: int | None = None) -> tuple[int, int]:
    """(cores this job may use, jobs running beside it, itself included): ``requested`` (the
    config's ``cores``) when given, else the available cores shared evenly by the jobs."""
    jobs = concurrent_jobs()
    if requested:
        return int(requested), jobs
    return max(1, available_cores() // jobs), jobs


def fit_to_cores(cfg, cores: int):
    """A copy of ``cfg`` (the typed config, sdexp.config.Config) whose thread and worker counts
    fit in ``cores``: sim.threads (0 = auto, which may take 2), data.workers, model.threads and
    an experiment's ``workers``. The data, the nets and the caches' keys do not depend on these
    counts (sdexp.config.NOT_KEY)."""
    from dataclasses import replace

    changed = []

    def cap(node, key, value, label):
        old = getattr(node, key)
        if old == value:
            return node
        changed.append(f"{label} {old} -> {value}")
        return replace(node, **{key: value})

    sim, data, model, params = cfg.sim, cfg.data, cfg.model, cfg.experiment.params
    if int(sim.threads) == 0:
        if cores < 2:
            sim = cap(sim, "threads", 1, "sim.threads")
    elif int(sim.threads) > cores:
        sim = cap(sim, "threads", cores, "sim.threads")
    if int(data.workers) > cores:
        data = cap(data, "workers", cores, "data.workers")
    if int(model.threads) > cores:
        model = cap(model, "threads", cores, "model.threads")
    if isinstance(getattr(params, "workers", None), int) and params.workers > cores:
        params = cap(params, "workers", cores, "experiment.params.workers")
    experiment = replace(cfg.experiment, params=params)
    return replace(cfg, sim=sim, data=data, model=model, experiment=experiment), changed


@contextlib.contextmanager
def limited_threads(cores: int):
    """For the duration: this process's thread pools (torch, numba, BLAS/OpenMP through
    threadpoolctl) and its children's (the environment they start with) at most ``cores``."""
    import sys

    from threadpoolctl import threadpool_limits

    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    for var in THREAD_ENV:
        current = saved[var]
        if current is None or not current.isdigit() or int(current) > cores:
            os.environ[var] = str(cores)
    torch = sys.modules.get("torch")
    torch_threads = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(cores)
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.set_num_threads(min(cores, numba.config.NUMBA_NUM_THREADS))
    try:
        with threadpool_limits(limits=cores):
            yield
    finally:
        _restore(saved)
        if torch is not None:
            torch.set_num_threads(torch_threads)
