"""Experiment registry and the bookkeeping every run shares: validation, seeding, the saved
resolved config, an atomic metrics.json, and resuming (a job whose metrics.json exists skips)."""
from __future__ import annotations

import difflib
import importlib
import json
import logging
import os
import random
import socket
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from sdexp import conf
from sdexp.cache import atomic_write
from sdexp.config import ELEMENTS, validate
from sdexp.errors import UserError

log = logging.getLogger(__name__)

# name -> "module:function"; each function is run(cfg, out_dir) -> dict of metrics
RUNNERS = {
    "ablation_decomposition": "sdexp.eval.ablation_decomposition:run",
    "ablation_fixed_point": "sdexp.eval.ablation_fixed_point:run",
    "bench_control": "sdexp.eval.bench_control:run",
    "bench_sim": "sdexp.eval.bench_sim:run",
    "bench_sweep": "sdexp.eval.bench_sweep:run",
    "discrepancy": "sdexp.discrepancy.workflow:run",
    "discrepancy_bench": "sdexp.discrepancy.bench:run",
    "gallery": "sdexp.eval.gallery:run",
    "hover_deform": "sdexp.eval.hover_deform:run",
    "model_test": "sdexp.eval.model_test:run",
    "record": "sdexp.discrepancy.record:run",
    "report": "sdexp.eval.report:run",
    "nsweep": "sdexp.eval.nsweep:run",
    "obstacle": "sdexp.eval.obstacle:run",
    "sota": "sdexp.eval.sota:run",
    "validate_fem": "sdexp.eval.validate_fem:run",
}


# experiment.params entries that are themselves structured: (experiment, key) -> "module:dataclass"
NESTED_PARAMS = {("validate_fem", "beam"): "sdexp.eval.validate_fem:Beam"}

# ranges of the params that several experiments share (by name); the rest need only their type
_POSITIVE = (lambda v: v > 0, "> 0")
_NONNEGATIVE = (lambda v: v >= 0, ">= 0")
PARAM_RANGES = {
    "seconds": _POSITIVE, "scaling_seconds": _POSITIVE, "rollout_seconds": _POSITIVE,
    "horizon_seconds": _POSITIVE, "plot_seconds": _POSITIVE, "settle_seconds": _NONNEGATIVE,
    "ramp_seconds": _POSITIVE, "hold_seconds": _NONNEGATIVE, "fold_start": _NONNEGATIVE,
    "fold_seconds": _POSITIVE, "distance": _POSITIVE, "bend_load": _NONNEGATIVE,
    "samples": _POSITIVE, "trials": _POSITIVE, "descent_steps": _POSITIVE, "relinearize_every": _POSITIVE,
    "flight_attempts": _POSITIVE, "workers": _POSITIVE, "seeds": _NONNEGATIVE, "nulls": _NONNEGATIVE,
    "unmodelled": _NONNEGATIVE, "variants": _NONNEGATIVE, "raw_hidden": _POSITIVE, "drone_edge_length": _POSITIVE,
    "test_seed_offset": _NONNEGATIVE, "scaling_edges": _POSITIVE, "n_values": _POSITIVE,
    "layers": _POSITIVE, "jobs": _POSITIVE, "refine": _POSITIVE, "noise_levels": _NONNEGATIVE,
}


def param_defaults(name: str) -> dict:
    """The experiment's params as its conf/experiment/<name>.yaml declares them: the keys a run
    may set (every one, with its default), nothing else."""
    declared = conf.read("experiment", name)
    if declared is None:
        return {}
    params = OmegaConf.select(declared, "experiment.params")
    return dict(OmegaConf.to_container(params)) if params is not None else {}


def _kind(value: Any) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, (list, tuple)):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__


def _same_kind(default: Any, value: Any) -> bool:
    if default is None or value is None:
        return True
    if isinstance(default, float) and not isinstance(value, bool):
        return isinstance(value, (int, float))
    return _kind(default) == _kind(value)


def _check_nested(full: str, default: dict, value: dict) -> None:
    """A mapping param with declared entries (e.g. layers: {linear: {...}}): no entry it lacks."""
    for sub, v in value.items():
        if sub not in default:
            raise UserError(f"{full}.{sub} is not a parameter: allowed {', '.join(map(str, default))}")
        if isinstance(default[sub], dict) and default[sub] and isinstance(v, dict):
            _check_nested(f"{full}.{sub}", default[sub], v)


def _leaves(value) -> list:
    """The numbers of a param: itself, a list's items, or (a dict of lists, per element type
    or dimension) all of theirs."""
    if isinstance(value, dict):
        return [v for sub in value.values() for v in _leaves(sub)]
    return list(value) if isinstance(value, list) else [value]


def check_params(cfg: DictConfig) -> None:
    """experiment.params against the experiment's declared params: a misspelled or foreign key,
    a missing one, a value of the wrong type or range, an unknown drone: a UserError naming
    experiment.params.<key> and what is allowed."""
    name = cfg.experiment.name
    defaults = param_defaults(name)
    given = OmegaConf.to_container(cfg.experiment.params, resolve=True) or {}
    allowed = ", ".join(sorted(defaults)) or "none"
    for key in given:
        if key not in defaults:
            close = difflib.get_close_matches(key, list(defaults), n=1)
            hint = f" (did you mean experiment.params.{close[0]}?)" if close else ""
            raise UserError(f"experiment.params.{key} is not a parameter of {name}{hint}: "
                            f"allowed {allowed}")
    for key, default in defaults.items():
        full = f"experiment.params.{key}"
        if key not in given:
            raise UserError(f"{full} is missing: {name} needs it (its default is {default!r} "
                            f"in conf/experiment/{name}.yaml)")
        value = given[key]
        if not _same_kind(default, value):
            raise UserError(f"{full} = {value!r} is {_kind(value)}: allowed {_kind(default)} "
                            f"like the default {default!r}")
        if isinstance(default, int) and not isinstance(default, bool) and isinstance(value, float):
            raise UserError(f"{full} = {value!r}: allowed a whole number")
        if key in PARAM_RANGES and value is not None:
            ok, text = PARAM_RANGES[key]
            items = _leaves(value)
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and ok(v) for v in items):
                raise UserError(f"{full} = {value!r} is out of range: allowed {text}"
                                + (" each" if isinstance(value, list) else ""))
        if isinstance(default, dict) and default and isinstance(value, dict):
            _check_nested(full, default, value)
        if (name, key) in NESTED_PARAMS and isinstance(value, dict):
            module, attr = NESTED_PARAMS[(name, key)].split(":")
            import dataclasses
            fields = [f.name for f in dataclasses.fields(getattr(importlib.import_module(module), attr))]
            for sub in value:
                if sub not in fields:
                    raise UserError(f"{full}.{sub} is not a parameter of {name}'s {key}: allowed "
                                    f"{', '.join(fields)}")
        if key == "animate" and isinstance(value, list):   # sota: which of its flights are drawn
            flown = list(given.get("controllers") or [])
            stray = [c for c in value if c not in flown]
            if stray:
                raise UserError(f"{full} = {value!r}: {stray[0]!r} is not flown: allowed a list of the "
                                f"controllers in experiment.params.controllers ({', '.join(map(str, flown)) or 'none'})")
        if key == "elements" and not set(value) <= set(ELEMENTS):
            raise UserError(f"{full} = {value!r}: allowed a list of {', '.join(ELEMENTS)}")
        if key in ("drones", "scaling_drone") and value is not None:
            names = conf.names("drone")
            for d in (value if isinstance(value, list) else [value]):
                if d not in names:
                    raise UserError(f"{full}: drone {d!r} is unknown: choose from {', '.join(names)}")


# experiments that run a list of drones (experiment.params.drones): only the one named drone=<name>
# takes the drone.* overrides, the others are loaded from conf/drone/<name>.yaml
MULTI_DRONE = ("bench_sim", "gallery")


def check_overrides_reach(cfg: DictConfig, overrides: list[str] | None) -> None:
    """A drone.* override that no drone of the run would see is an error, not a silent no-op."""
    name = cfg.experiment.name
    if not overrides or name not in MULTI_DRONE:
        return
    touched = [o for o in overrides if o.lstrip("+~").startswith("drone.")]
    drones = cfg.experiment.params.get("drones")
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
# (sweep_dir: what a report reads is compared as experiment.params.sweep_dir; animate: whether
# a flight is also drawn, its numbers are the same bit for bit)
NOT_COMPARED = ("cache_dir", "cores", "sweep_dir", "experiment.params.animate", "experiment.params.paraview")


def config_differences(saved: dict, current: dict) -> list[str]:
    """Dotted keys whose values differ between two resolved configs, each as 'key: a -> b'."""
    a, b = _flat(saved), _flat(current)
    out = []
    for key in sorted(set(a) | set(b)):
        if key in NOT_COMPARED:
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
    if name not in RUNNERS:
        raise UserError(f"experiment.name = {name!r} is unknown: choose one of {sorted(RUNNERS)}")
    validate(cfg)
    check_params(cfg)
    check_overrides_reach(cfg, overrides)
    from sdexp.sim.drone import make_shape
    make_shape(cfg.drone)   # the design's params (an unknown drone.params key) before anything is written
    module, func = RUNNERS[name].split(":")
    runner = importlib.import_module(module)
    if hasattr(runner, "check"):
        runner.check(cfg)   # the experiment's own input (a report's sweep folder) before anything is written
    out_dir = Path(out_dir)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        lock = claim(out_dir)
    except OSError as err:
        raise UserError(f"cannot write the run's output folder {out_dir}: {err.strerror or err} "
                        f"(choose a writable one with hydra.run.dir=<folder>)") from None
    try:
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
            raise UserError(f"cannot write the run's output folder {out_dir}: {err.strerror or err} "
                            f"(choose a writable one with hydra.run.dir=<folder>)") from None
        seed_everything(int(cfg.seed))
        from sdexp.parallel import fit_to_cores, job_cores, limited_threads
        cores, jobs = job_cores(cfg.get("cores"))
        run_cfg, changed = fit_to_cores(cfg, cores)
        log.info(f"sdexp: {name} (seed {cfg.seed}) on {cores} core{'s' if cores > 1 else ''}"
                 + (f", {jobs} jobs side by side" if jobs > 1 else "")
                 + (f" ({', '.join(changed)})" if changed else "") + f" -> {out_dir}")
        with limited_threads(cores):
            metrics = getattr(runner, func)(run_cfg, out_dir)
        write_json(done, metrics)
        return metrics
    finally:
        lock.unlink(missing_ok=True)


def summary(cfg, metrics: dict, lines: int = 12) -> str:
    """What a run prints last: the runner's own table beside the paper's (its ``summary(cfg,
    metrics)``) where it has one, else the first scalar metrics rounded; all of them are in
    metrics.json."""
    runner = importlib.import_module(RUNNERS[cfg.experiment.name].split(":")[0])
    if hasattr(runner, "summary"):
        return runner.summary(cfg, metrics)
    scalars = [(k, v) for k, v in metrics.items() if not isinstance(v, (dict, list))]
    text = [f"  {k}: {v:.4g}" if isinstance(v, float) else f"  {k}: {v}" for k, v in scalars[:lines]]
    if len(scalars) > lines:
        text.append(f"  ... {len(scalars) - lines} more in metrics.json")
    return "\n".join(text)
