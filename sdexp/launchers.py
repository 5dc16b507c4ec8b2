"""The sweep launcher's settings, checked before a sweep starts (a Hydra callback, registered in
conf/config.yaml as ``hydra.callbacks.check_launcher``).

The launcher plugins take their settings as given and fail deep inside the sweep: joblib's
``n_jobs=0`` is a ValueError after the sweep folder exists, ``n_jobs=-5`` on 2 cores quietly runs
one job at a time, submitit's ``tasks_per_node=0`` an IndexError, ``timeout_min=-1`` kills every
job and leaves job folders with empty logs, and the Slurm launcher off a cluster a RuntimeError.
Each is a UserError here, before any job folder is made, naming the key and what is allowed.
"""
from __future__ import annotations

import shutil
from typing import Any

from hydra.experimental.callback import Callback

from sdexp.errors import UserError


def _int(key: str, value: Any, allowed: str, ok) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not ok(value):
        raise UserError(f"hydra.launcher.{key} = {value!r} is not allowed: {allowed}")


def _number(key: str, value: Any, allowed: str, ok) -> None:
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not ok(value):
        raise UserError(f"hydra.launcher.{key} = {value!r} is not allowed: {allowed}")


def check_joblib(launcher, cores: int) -> None:
    # joblib reads a negative n_jobs as "all cores but |n_jobs| - 1" and clamps what is left to 1
    _int("n_jobs", launcher.n_jobs, f"a number of jobs >= 1, or -1 to -{cores} (-1: all {cores} cores of this "
         f"machine, -2: all but one, ...)", lambda n: n >= 1 or -cores <= n <= -1)
    _number("timeout", launcher.get("timeout"), "null (none) or > 0 seconds per job", lambda t: t > 0)
    batch = launcher.get("batch_size", "auto")
    if batch != "auto" and not (str(batch).isdigit() and int(batch) >= 1):
        raise UserError(f"hydra.launcher.batch_size = {batch!r} is not allowed: 'auto' or a whole number >= 1")


def check_submitit(launcher, slurm: bool) -> None:
    _int("timeout_min", launcher.timeout_min, "> 0 minutes per job", lambda t: t > 0)
    _int("tasks_per_node", launcher.tasks_per_node, ">= 1", lambda n: n >= 1)
    _int("nodes", launcher.nodes, ">= 1", lambda n: n >= 1)
    for key, floor in (("cpus_per_task", 1), ("gpus_per_node", 0), ("mem_gb", 1)):
        if launcher.get(key) is not None:
            _int(key, launcher.get(key), f"null (the cluster's default) or >= {floor}", lambda n, f=floor: n >= f)
    if slurm:
        missing = [tool for tool in ("sbatch", "srun") if shutil.which(tool) is None]
        if missing:
            raise UserError(f"hydra/launcher=submitit_slurm needs Slurm ({' and '.join(missing)} not found on PATH): "
                            f"launch the sweep on the cluster's login node, or choose hydra/launcher=joblib "
                            f"(jobs side by side on this machine) or submitit_local")


def check_launcher(launcher) -> None:
    """The settings of the sweep's launcher (``hydra.launcher``), before the sweep starts."""
    from sdexp.parallel import available_cores
    target = str(launcher.get("_target_", ""))
    if "joblib" in target:
        check_joblib(launcher, available_cores())
    elif "submitit_launcher" in target:
        check_submitit(launcher, slurm=target.endswith("SlurmLauncher"))


class CheckLauncher(Callback):
    def on_multirun_start(self, config, **kwargs) -> None:
        try:
            check_launcher(config.hydra.launcher)
        except UserError as err:
            # Hydra turns a callback's exception into a warning and starts the sweep anyway:
            # stop here, in the cli's one-line form
            from sdexp.cli import fail
            fail(str(err))
