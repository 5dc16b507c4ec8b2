"""What a run is and how it goes, in one place: ``Run``, the skeleton every experiment's runner is
handed (the typed config, converted once at the runner boundary; the experiment's params, its
dataclass in sdexp.experiment_params; the run folder, where its tables and figures go), and the
bookkeeping every run shares: the preflight (validation, the simulator's checks, the params'
names), the one conversion of the config to dataclasses, the runner its ``experiment._target_``
names, seeding, the folder's lock, the saved resolved config, an atomic metrics.json, and resuming
(a job whose metrics.json exists skips).

A runner is ``run(run: Run) -> dict`` of metrics in ``sdexp/eval/<name>.py``, named by
``experiment._target_`` in its conf/experiment/<name>.yaml; optional beside it in its module:
``check(run)`` (its own input, before anything is written) and ``summary(params, metrics) -> str``
(what the run prints last).
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import logging
import os
import random
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf

from sdexp import conf
from sdexp.cache import atomic_write
from sdexp.config import Config, validate
from sdexp.errors import UserError, did_you_mean, disk_full, one_line

log = logging.getLogger(__name__)


@dataclass
class Run:
    cfg: Config       # the whole config, typed: cfg.drone, cfg.sim, ... are dataclasses
    out_dir: Path     # the run folder: tables, figures, metrics.json, config.yaml, cli.log

    @property
    def params(self) -> Any:
        """The experiment's params (its sdexp.experiment_params dataclass)."""
        return self.cfg.experiment.params

    def path(self, name: str) -> Path:
        """A file of the run folder."""
        return self.out_dir / name

    # written whole or not at all (a full disk mid-write leaves no short table, sdexp.cache.atomic_write)
    def table(self, frame, name: str, **to_csv) -> Path:
        """``<name>.csv`` in the run folder, without the frame's index."""
        path = self.path(f"{name}.csv")
        atomic_write(path, lambda tmp: frame.to_csv(tmp, index=False, **to_csv))
        return path

    def figure(self, fig, name: str, dpi: int = 120) -> Path:
        """``<name>.png`` in the run folder; the figure is closed."""
        from sdexp.figures import save_figure
        path = self.path(f"{name}.png")
        save_figure(fig, path, dpi)
        return path


def runner(cfg) -> Callable:
    """The experiment's runner: the function its ``experiment._target_`` names."""
    from hydra.utils import get_method
    try:
        return get_method(str(cfg.experiment._target_))
    except Exception as err:   # noqa: BLE001 - Hydra wraps whatever the import raised
        raise UserError(f"experiment._target_ = {cfg.experiment._target_!r} cannot be imported: {one_line(err)}") from None


def _hook(fn: Callable, name: str) -> Callable | None:
    """A function beside the runner in its module (check, summary), or None."""
    return getattr(importlib.import_module(fn.__module__), name, None)


def typed(cfg: DictConfig) -> Config:
    """The config as dataclasses, once, at the runner boundary: cfg.experiment.params becomes its
    experiment's params dataclass, whose construction checks its ranges (sdexp.experiment_params)."""
    return OmegaConf.to_object(cfg)


def known_names(kind: str) -> list[str]:
    """What a param's ``names`` metadata allows: the registered controllers, the effect library,
    or the options of that config group (a drone, an experiment)."""
    if kind == "controller":
        from sdexp.eval.controllers import CONTROLLERS   # the controllers' code: only for a run that names them
        return list(CONTROLLERS)
    if kind == "effect":
        from sdexp.sim.physics.effects import LIBRARY
        return list(LIBRARY)
    return conf.names(kind)


def compose_overrides(args: list[str], what: str) -> DictConfig:
    """The config composed from sdexp.conf with the Hydra overrides ``args`` (unchecked); one that
    does not compose is a UserError naming ``what`` with Hydra's own message on one line."""
    from hydra import compose, initialize_config_module
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException
    try:
        # initialize_config_module restores Hydra's global state on exit: safe inside a run too
        with initialize_config_module(config_module=conf.MODULE, version_base="1.3"):
            return compose(config_name="config", overrides=list(args))
    except (HydraException, OmegaConfBaseException) as err:
        raise UserError(f"{what}: {one_line(err)}") from None


def preflight(cfg: DictConfig) -> None:
    """Every check a composed config gets before anything is written: the schema and ranges
    (config.validate), what the simulator needs of it (sim.checks), the names its params give."""
    validate(cfg)
    simulator_checks(cfg)
    check_names(cfg)


def simulator_checks(cfg: DictConfig) -> None:
    """sim.checks on the composed config, its lists handed over plain."""
    from sdexp.sim.checks import check_config

    def plain(x):
        return OmegaConf.to_container(x, resolve=True) if isinstance(x, (DictConfig, ListConfig)) else x
    check_config(cfg.drone, plain(cfg.sim.effects), [plain(e) for e in cfg.discrepancy.candidates])


def check_names(cfg: DictConfig) -> None:
    """The params that name things (a drone, an experiment, a controller) name existing ones.
    Read from the composed config, before the conversion runs the params' rules between fields,
    so that a misspelled controller is reported as itself, not as a stray of sota's ``animate``."""
    params = cfg.experiment.params
    schema = OmegaConf.get_type(params)
    for f in dataclasses.fields(schema) if dataclasses.is_dataclass(schema) else ():
        kind, value = f.metadata.get("names"), params.get(f.name)
        if kind is None or value is None:
            continue
        known = known_names(kind)
        for v in (value if isinstance(value, ListConfig) else [value]):
            if v not in known:
                raise UserError(f"experiment.params.{f.name}: {kind} {v!r} is unknown{did_you_mean(v, known)}: "
                                f"choose from {', '.join(known)}")


# experiments that run a list of drones (experiment.params.drones): only the one named drone=<name>
# takes the drone.* overrides, the others are loaded from conf/drone/<name>.yaml
MULTI_DRONE = ("bench_sim", "fleet", "gallery")


def check_overrides_reach(cfg: Config, overrides: list[str] | None) -> None:
    """A drone.* override that no drone of the run would see is an error, not a silent no-op; so
    is a drone of one's own chosen by drone= alone, where the run draws the paper's twelve."""
    name = cfg.experiment.name
    if not overrides or name not in MULTI_DRONE:
        return
    touched = [o for o in overrides if o.lstrip("+~").startswith("drone.")]
    drones = getattr(cfg.experiment.params, "drones", None)
    if drones is None and cfg.drone.name not in conf.paper_drones():   # null: the twelve, never one's own
        raise UserError(f"drone={cfg.drone.name} is not among the drones {name} runs (experiment.params.drones = "
                        f"null: the paper's twelve): add experiment.params.drones=[{cfg.drone.name}] to run it")
    if touched and drones is not None and cfg.drone.name not in drones:
        raise UserError(f"{touched[0]} changes drone {cfg.drone.name}, which {name} does not run "
                        f"(experiment.params.drones = {list(drones)}; the others are loaded from "
                        f"conf/drone/): add drone={drones[0]} so that the override reaches it")


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    try:
        import torch
        torch.manual_seed(seed)
    except ImportError:  # torch is only needed by the learning side
        pass


def write_json(path: Path, data: Any) -> None:
    atomic_write(path, lambda tmp: tmp.write_text(json.dumps(data, indent=2, default=float)))


RUN_LOCK = ".sdexp-run.lock"


def _process_start(pid: int) -> str | None:
    """The kernel's start time of process ``pid`` (tells a live run from a reused pid), or None."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _alive(owner: dict) -> bool:
    if owner.get("host") != socket.gethostname():
        return True   # another machine's run: cannot tell, so it counts as live
    pid = int(owner.get("pid", -1))
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True
    start = _process_start(pid)
    return start is None or owner.get("start") in (None, start)


def claim(out_dir: Path) -> Path:
    """Take ``out_dir`` for this run: a lock file created exclusively, naming this process. A live
    run holding it is an error (two runs never write into one folder); a dead one's lock (a run
    killed mid-way) is taken over, so an interrupted run resumes."""
    lock = out_dir / RUN_LOCK
    me = {"pid": os.getpid(), "host": socket.gethostname(), "start": _process_start(os.getpid())}
    # written whole first and then hard-linked into place: a lock is never seen half-written (a
    # second run that read an empty lock took it for a dead one's and both went on)
    mine = out_dir / f".{RUN_LOCK}.{os.getpid()}.tmp"
    mine.write_text(json.dumps(me))
    try:
        for _ in range(3):
            try:
                os.link(mine, lock)
                return lock
            except FileExistsError:
                try:
                    owner = json.loads(lock.read_text() or "{}")
                except (OSError, ValueError):
                    owner = {}
                if owner and _alive(owner):
                    raise UserError(f"{out_dir} is in use by another run (pid {owner.get('pid')} on "
                                    f"{owner.get('host')}): wait for it, or choose another folder with "
                                    f"hydra.run.dir=<folder>; delete {lock} if no run is using it") from None
                lock.unlink(missing_ok=True)   # a killed run's lock (or a damaged one)
    finally:
        mine.unlink(missing_ok=True)
    raise UserError(f"{out_dir}: could not take the run lock {lock}: another run keeps taking it")


def _flat(node: Any, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: node}


# keys that say where a run looks things up or how many cores it may use, not what it computes
# (experiment._target_: where its code is)
# (sweep_dir: what a report reads is compared as experiment.params.sweep_dir; animate: whether
# a flight is also drawn, its numbers are the same bit for bit)
# how a result is computed or shown, not what it is: worker counts (data and fleet jobs are the
# same whichever process makes them), caches, the pictures
NOT_COMPARED = ("cache_dir", "cores", "sweep_dir", "experiment._target_", "experiment.params.animate",
                "experiment.params.paraview", "experiment.params.workers", "data.workers")


def config_differences(saved: dict, current: dict) -> list[str]:
    """Dotted keys whose values differ between two resolved configs, each as 'key: a -> b'."""
    a, b = _flat(saved), _flat(current)
    out = []
    for key in sorted(set(a) | set(b)):
        if key in NOT_COMPARED:
            continue
        if key not in a and b[key] is None:   # an option added since, at its off value
            continue
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            out.append(f"{key}: {a.get(key, '<absent>')!r} there, {b.get(key, '<absent>')!r} here")
    return out


def check_same_config(out_dir: Path, resolved: dict, finished: bool) -> None:
    """A folder that holds a run (finished or interrupted) is reused only by the same config."""
    saved_path = out_dir / "config.yaml"
    what = "a finished run" if finished else "an unfinished run"
    if not saved_path.exists():
        if finished:
            raise UserError(f"{out_dir} holds {what} without its config.yaml: cannot tell whether it "
                            f"ran this config; choose another folder with hydra.run.dir=<folder>, "
                            f"or delete {out_dir / 'metrics.json'} to run again here")
        return
    try:
        saved = OmegaConf.to_container(OmegaConf.load(saved_path))
    except Exception as err:   # noqa: BLE001 - a damaged file is the user's to sort out
        raise UserError(f"{saved_path} cannot be read ({err}): choose another folder with "
                        f"hydra.run.dir=<folder>, or delete it") from None
    diff = config_differences(saved, resolved)
    if diff:
        more = f" (and {len(diff) - 1} more)" if len(diff) > 1 else ""
        raise UserError(f"{out_dir} holds {what} with another config ({diff[0]}{more}): choose another "
                        f"folder with hydra.run.dir=<folder>, or delete "
                        f"{'its metrics.json and config.yaml' if finished else 'its config.yaml'} to "
                        f"run this config there")


def run_experiment(cfg: DictConfig, out_dir: Path, overrides: list[str] | None = None) -> dict:
    """Validate ``cfg``, take ``out_dir`` for this run, and run the experiment there; a folder
    whose run finished with the same resolved config returns that run's metrics."""
    name = cfg.experiment.name
    experiments = conf.names("experiment")
    if name not in experiments:
        raise UserError(f"experiment.name = {name!r} is unknown: choose one of {experiments}")
    preflight(cfg)
    config = typed(cfg)   # the one conversion: below here, dataclasses
    check_overrides_reach(config, overrides)
    from sdexp.sim.drone import make_shape
    make_shape(config.drone)   # the design's params (an unknown drone.params key) before anything is written
    fn = runner(cfg)
    out_dir = Path(out_dir)
    check = _hook(fn, "check")
    if check is not None:
        check(Run(config, out_dir))   # the experiment's own input (a report's sweep folder) before anything is written
    resolved = OmegaConf.to_container(cfg, resolve=True)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        lock = claim(out_dir)
    except OSError as err:
        raise UserError(f"cannot write the run's output folder {out_dir}: {err.strerror or err} "
                        f"(choose a writable one with hydra.run.dir=<folder>)") from None
    before = {p.name for p in out_dir.iterdir()}
    try:
        try:
            return _run_in(out_dir, config, fn, resolved, overrides)
        except OSError as err:
            cache = Path(str(config.cache_dir)).expanduser().resolve()
            in_cache = err.filename is not None and cache in Path(str(err.filename)).resolve().parents
            full = disk_full(err, out_dir, "or choose another cache with cache_dir=<folder> or SDEXP_CACHE"
                             if in_cache else "or choose another folder with hydra.run.dir=<folder>")
            if full is None:
                raise
            raise full from None
    except UserError:
        if "config.yaml" not in before:
            discard(out_dir, before)
        raise
    finally:
        lock.unlink(missing_ok=True)


def _run_in(out_dir: Path, config: Config, fn: Callable, resolved: dict, overrides: list[str] | None) -> dict:
    """The run proper, in the folder it holds the lock of: skip a finished run of the same config,
    save the config, run, write metrics.json."""
    name = config.experiment.name
    done = out_dir / "metrics.json"
    check_same_config(out_dir, resolved, done.exists())
    if done.exists():
        log.info(f"sdexp: {done} exists with the same config, skipping (delete it to rerun)")
        try:
            return json.loads(done.read_text())
        except (OSError, ValueError) as err:
            raise UserError(f"{done} cannot be read ({err}): delete it to rerun") from None
    try:
        atomic_write(out_dir / "config.yaml", lambda tmp: tmp.write_text(OmegaConf.to_yaml(resolved)))
        if overrides is not None:
            atomic_write(out_dir / "overrides.yaml",
                         lambda tmp: tmp.write_text(OmegaConf.to_yaml(list(overrides))))
    except OSError as err:
        if disk_full(err, out_dir, "") is not None:
            raise
        raise UserError(f"cannot write the run's output folder {out_dir}: {err.strerror or err} "
                        f"(choose a writable one with hydra.run.dir=<folder>)") from None
    seed_everything(int(config.seed))
    from sdexp.parallel import fit_to_cores, job_cores, limited_threads
    cores, jobs = job_cores(config.cores)
    config, changed = fit_to_cores(config, cores)
    log.info(f"sdexp: {name} (seed {config.seed}) on {cores} core{'s' if cores > 1 else ''}"
             + (f", {jobs} jobs side by side" if jobs > 1 else "")
             + (f" ({', '.join(changed)})" if changed else "") + f" -> {out_dir}")
    from sdexp.provenance import source
    log.info(f"sdexp: code: {source()}")
    compiling_said()
    with limited_threads(cores):
        metrics = fn(Run(config, out_dir))
    write_json(done, metrics)
    return metrics


def compiling_said() -> None:
    """What a cold machine spends a run's first minutes on, said in the log (sdexp.log's quiet
    phases: nothing when the caches have it): numba's compiling (sdexp.log.say_numba_compiles),
    and the FEM kernels' C build, once per machine and kernel source, done here ahead of the
    first simulator (sdexp.sim.physics.native.library, which loads it from then on)."""
    from sdexp.log import Phase, say_numba_compiles
    from sdexp.sim.physics.native import library
    say_numba_compiles()
    with Phase("compiling the FEM kernels (C, once per machine and kernel source)", quiet_for=2.0):
        library()


def discard(out_dir: Path, before: set[str]) -> None:
    """What a rejected run wrote into its folder (config.yaml, overrides.yaml, half its tables):
    gone, so that nothing blocks the corrected rerun into the same folder (its config.yaml would
    read as an unfinished run of another config). Only a run that started the folder afresh
    discards; one that resumed an earlier run keeps that run's files. The logs Hydra opened
    before the run are the cli's to remove (sdexp.cli)."""
    import shutil
    for p in out_dir.iterdir():
        if p.name in before or p.suffix == ".log":
            continue
        try:
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        except OSError:
            pass


def summary(cfg: DictConfig, metrics: dict, lines: int = 12) -> str:
    """What a run prints last: the runner's own table beside the paper's (its ``summary(params,
    metrics)``) where it has one, else the first scalar metrics rounded; all of them are in
    metrics.json."""
    own = _hook(runner(cfg), "summary")
    if own is not None:
        return own(OmegaConf.to_object(cfg.experiment.params), metrics)
    scalars = [(k, v) for k, v in metrics.items() if not isinstance(v, (dict, list))]
    text = [f"  {k}: {v:.4g}" if isinstance(v, float) else f"  {k}: {v}" for k, v in scalars[:lines]]
    if len(scalars) > lines:
        text.append(f"  ... {len(scalars) - lines} more in metrics.json")
    return "\n".join(text)
