"""The only @hydra.main: resolve the output directory and hand over to a runner.

Every user error, whichever layer finds it (Hydra composing the config, sdexp's checks, an
output folder that cannot be written), prints one line ``sdexp: error: ...`` and exits with
:data:`sdexp.errors.EXIT_USER_ERROR`; only a bug prints a traceback (exit 1). Ctrl-C or SIGTERM
stops a run where it is (its worker processes ended, its lock released, what it finished kept:
the same command resumes it) with one line, exit 130.
"""
from __future__ import annotations

import logging
import os
import re
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException, MissingConfigException, OverrideParseException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from sdexp import conf
from sdexp.config import unknown_key_error
from sdexp.errors import EXIT_USER_ERROR, UserError, did_you_mean, one_line


_started = False   # the task function was entered: errors after this are the run's, not Hydra's
_interrupted: Path | None = None   # the run folder of a run Ctrl-C or SIGTERM stopped
EXIT_INTERRUPTED = 130   # 128 + SIGINT, as a shell reports a command Ctrl-C stopped
log = logging.getLogger("sdexp.cli")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the run is, so that it stops as Ctrl-C stops it (its cleanup runs:
    workers ended, lock released) instead of dying on the spot."""


def _terminate(signum, frame) -> None:
    raise Terminated()


@hydra.main(version_base="1.3", config_path=conf.SEARCH_PATH, config_name="config")
def _main(cfg: DictConfig) -> None:
    global _started
    from sdexp.eval.run import run_experiment

    _started = True
    _end_with_the_sweep()
    logging.captureWarnings(True)   # the library's warnings in the run's log file too
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        metrics = run_experiment(cfg, out_dir, overrides=OmegaConf.to_container(HydraConfig.get().overrides.task))
    except UserError as err:
        _discard_if_empty(out_dir)
        if out_dir.exists():   # a run that had started: its log says why it stopped
            from sdexp.log import to_log_files
            to_log_files(f"sdexp: error: {err}")
        fail(str(err))
    except KeyboardInterrupt as err:
        global _interrupted
        _interrupted = out_dir
        from sdexp.log import to_log_files
        to_log_files(f"sdexp: {_interruption(err)}", logging.WARNING)
        raise
    from sdexp.eval.run import summary
    log.info(f"sdexp: {cfg.experiment.name} done -> {out_dir}\n{summary(cfg, metrics)}")


# the sdexp process a command started: a sweep's launcher (joblib's loky workers, submitit's local
# jobs) runs the jobs in its child processes, which inherit this
PARENT_ENV = "SDEXP_PARENT_PID"
_watching = False


def _end_with_the_sweep() -> None:
    """In a sweep's worker process: end it when the sdexp process that launched it is gone. A
    killed sweep otherwise leaves its workers running their jobs to the end, holding the jobs'
    folders (the rerun is refused: "in use by another run"); its run lock is then a dead process's,
    which the rerun takes over, and its outputs are written atomically."""
    global _watching
    parent = os.environ.get(PARENT_ENV, "")
    if _watching or not parent.isdigit() or int(parent) == os.getpid() or os.getppid() != int(parent):
        return
    import threading

    from sdexp.parallel import exit_with_parent
    threading.Thread(target=exit_with_parent, args=(int(parent), 0.5), daemon=True).start()
    _watching = True


def _discard_if_empty(out_dir: Path) -> None:
    """Hydra creates the run folder (and the job log) before the run: a run that stopped on bad
    input leaves nothing behind. A folder left with logs only held no run before this one (a
    rejected run discards what it wrote, sdexp.eval.run.discard; one that resumed keeps its
    config.yaml): the logs are this run's, and go with it."""
    try:
        if out_dir.is_dir() and all(p.suffix == ".log" and p.is_file() for p in out_dir.iterdir()):
            for log in out_dir.glob("*.log"):
                log.unlink()
        cwd = Path.cwd().resolve()
        sweep = Path(HydraConfig.get().sweep.dir).resolve() if HydraConfig.initialized() else None
        for folder in [out_dir.resolve(), *out_dir.resolve().parents]:
            if folder == cwd or cwd not in folder.parents:
                break
            if folder == sweep and [p.name for p in folder.iterdir()] == ["multirun.yaml"]:
                (folder / "multirun.yaml").unlink()   # a sweep whose first job was rejected
            folder.rmdir()   # only succeeds on an empty folder: outputs/<experiment>/<drone>/
    except OSError:
        pass


def _interruption(err: KeyboardInterrupt) -> str:
    how = "SIGTERM" if isinstance(err, Terminated) else "Ctrl-C"
    where = "" if _interrupted is None else \
        f": {_interrupted} keeps what the run finished, and the same command resumes it"
    return f"interrupted ({how}){where}"


def fail(message: str) -> None:
    print(f"sdexp: error: {message}", file=sys.stderr)
    sys.exit(EXIT_USER_ERROR)


def _failing_override(args: list[str]) -> str | None:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for arg in args:
        if arg.startswith("-"):
            continue
        try:
            parser.parse_override(arg)
        except Exception:   # noqa: BLE001 - whichever the grammar raises
            return arg
    return None


def describe(err: BaseException, args: list[str]) -> str:
    """Hydra's and OmegaConf's composition errors as one line naming the key and what is allowed."""
    if isinstance(err, MissingConfigException) and err.missing_cfg_file and err.options:
        group, _, name = err.missing_cfg_file.rpartition("/")
        hint = did_you_mean(name, err.options, f"{group}=")
        return f"{group}={name} is unknown{hint}: choose one of {', '.join(err.options)}"
    if isinstance(err, OverrideParseException):
        bad = _failing_override(args)
        return f"cannot parse the override {bad!r}: {one_line(err)}" if bad else one_line(err)
    match = re.match(r"Could not override '([^']+)'", str(err))
    if match:
        key = match.group(1)
        if key.startswith("hydra."):
            return _unknown_hydra_key(key, args)
        schema = unknown_key_error(key)
        if schema is not None:
            return str(schema)
        if key.startswith("experiment.params."):
            return _unknown_param(key, args)
        return f"{key} is not a config key"
    match = re.match(r"Error merging override (\S+)", str(err))
    if match and err.__cause__ is not None:
        return f"{match.group(1)}: {one_line(err.__cause__)}"
    return one_line(err)


def _unknown_param(key: str, args: list[str]) -> str:
    from sdexp.config import unknown_param_error
    from sdexp.experiment_params import PARAMS
    name = next((a.split("=", 1)[1] for a in args if a.startswith("experiment=")), None)
    if name is None:
        defaults = OmegaConf.to_container(conf.read("config").defaults)
        name = next((d["experiment"] for d in defaults if isinstance(d, dict) and "experiment" in d), "?")
    return str(unknown_param_error(key[len("experiment.params."):], PARAMS.get(name), name))


def _unknown_hydra_key(key: str, args: list[str]) -> str:
    """A misspelled hydra.* key (hydra.launcher.njobs): the keys of its parent as composed with the
    command's own hydra/... choices (the launcher picked), not sdexp's schema, which has no hydra."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    parent, _, name = key.rpartition(".")
    choices = [a for a in args if a.startswith("hydra/")]
    try:
        GlobalHydra.instance().clear()
        with initialize_config_module(config_module="sdexp.conf", version_base="1.3"):
            node = OmegaConf.select(compose("config", overrides=choices, return_hydra_config=True), parent)
    except Exception:   # noqa: BLE001 - whatever composing raises: the plain message then
        node = None
    if not isinstance(node, DictConfig):
        return f"{key} is not a config key"
    names = sorted(str(k) for k in node.keys())
    hint = did_you_mean(name, names, f"{parent}.")
    what = f" ({', '.join(choices)})" if choices else ""
    if parent == "hydra.launcher" and not any(c.startswith("hydra/launcher=") for c in choices):
        what = " (the basic launcher, which has no settings: choose hydra/launcher=joblib, submitit_local or submitit_slurm)"
    return f"{key} is not a key of {parent}{what}{hint}: allowed {', '.join(names)}"


def _list_index(err: ValueError, args: list[str]) -> str:
    """OmegaConf raises a bare ValueError for ``refine.x=2`` on a list (the items are indexed by
    number): the override, and how a list is set."""
    match = re.search(r"invalid literal for int\(\) with base 10: '([^']*)'", str(err))
    bad = next((a for a in args if match and a.split("=", 1)[0].lstrip("+~").rsplit(".", 1)[-1] == match.group(1)), None)
    if bad is None:
        return f"cannot apply the overrides: {one_line(err)}"
    key = bad.split("=", 1)[0].lstrip("+~")
    return (f"{bad}: {key.rsplit('.', 1)[0]} is a list: allowed an item by its index "
            f"({key.rsplit('.', 1)[0]}.0=...) or the whole list ({key.rsplit('.', 1)[0]}=[...])")


def main() -> None:
    """The ``sdexp`` command."""
    global _started, _interrupted
    import signal
    import threading
    args = sys.argv[1:]
    previous = {k: os.environ.get(k) for k in ("HYDRA_FULL_ERROR", PARENT_ENV)}
    os.environ["HYDRA_FULL_ERROR"] = "1"   # Hydra raises instead of printing and exiting 1
    os.environ[PARENT_ENV] = str(os.getpid())
    _started, _interrupted = False, None
    in_main = threading.current_thread() is threading.main_thread()   # where signal handlers can be set
    on_term = signal.signal(signal.SIGTERM, _terminate) if in_main else None
    try:
        _main()
    except KeyboardInterrupt as err:
        print(f"sdexp: {_interruption(err)}", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    except UserError as err:
        fail(str(err))
    except (HydraException, OmegaConfBaseException) as err:
        if _started and not isinstance(err, HydraException):
            raise   # an OmegaConf error inside a run is a bug, not a config mistake
        fail(describe(err, args))
    except ValueError as err:
        if _started:
            raise
        fail(_list_index(err, args))
    except BrokenPipeError:   # the output piped into a reader that stopped (sdexp --help | head)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(0)
    except OSError as err:
        if _started:
            raise
        fail(f"cannot create the run's output folder: {err} (choose a writable one with "
             f"hydra.run.dir=<folder>, or hydra.sweep.dir=<folder> with -m)")
    finally:   # main() called in-process (tests, notebooks) leaves the environment as it was
        if in_main:
            signal.signal(signal.SIGTERM, on_term)
        for key, value in previous.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


if __name__ == "__main__":
    main()
