"""Sweeps through Hydra's launcher plugins: jobs in parallel on this machine (joblib) or as
Slurm jobs (submitit; tested with its local executor), each job's threads fitted to its share
of the cores."""
import os
import re
import subprocess
import sys

import pytest
from hydra.core.hydra_config import HydraConfig
from omegaconf import OmegaConf

from sdexp.parallel import available_cores, concurrent_jobs, fit_to_cores, job_cores
from tests.conftest import make_cfg, make_config

TINY = ["experiment=gallery", "experiment.params.drones=[rod]"]   # a mesh and a plot: seconds


def test_fit_to_cores_caps_threads_and_workers_without_touching_the_config():
    cfg = make_config("experiment=discrepancy_bench", "sim.threads=0", "data.workers=2", "model.threads=2")
    one, changed = fit_to_cores(cfg, 1)
    assert (one.sim.threads, one.data.workers, one.model.threads, one.experiment.params.workers) == (1, 1, 1, 1)
    assert "data.workers 2 -> 1" in changed and "sim.threads 0 -> 1" in changed
    assert (cfg.sim.threads, cfg.data.workers, cfg.model.threads) == (0, 2, 2)   # a copy: the saved config stays
    two, changed = fit_to_cores(cfg, 2)
    assert (two.sim.threads, two.data.workers, two.model.threads) == (0, 2, 2) and changed == []
    big, _ = fit_to_cores(make_config("sim.threads=8"), 4)
    assert big.sim.threads == 4


@pytest.mark.parametrize("launcher, n_jobs, expected", [
    ("basic", None, 1),            # one job after another
    ("joblib", 2, 2),
    ("joblib", -1, 5),             # all 8 cores, but the sweep has 5 jobs
    ("joblib", -7, 2),             # all but 6 of 8
    ("submitit_local", None, 5),   # every job at once
    ("submitit_slurm", None, 1),   # each job on its own allocation
])
def test_concurrent_jobs_follow_the_launcher(tmp_path, launcher, n_jobs, expected):
    overrides = [f"hydra/launcher={launcher}", "hydra.mode=MULTIRUN", f"hydra.sweep.dir={tmp_path}"]
    if n_jobs is not None:
        overrides.append(f"hydra.launcher.n_jobs={n_jobs}")
    cfg = make_cfg(*overrides, "seed=0", hydra=True)
    (tmp_path / "multirun.yaml").write_text(OmegaConf.to_yaml(
        {"hydra": {"overrides": {"task": ["experiment=sota", "seed=0,1,2,3,4"]}}}))
    HydraConfig.instance().set_config(cfg)
    try:
        assert concurrent_jobs(cores=8) == expected
    finally:
        HydraConfig.instance().cfg = None
    assert concurrent_jobs(cores=8) == 1   # outside a sweep


def test_a_given_core_count_is_used_as_given():
    assert job_cores(3) == (3, 1) and job_cores(None) == (available_cores(), 1)


def _sweep(tmp_path, cache_dir, *launcher):
    env = {**os.environ, "HYDRA_FULL_ERROR": "", "SDEXP_CACHE": cache_dir}
    res = subprocess.run([sys.executable, "-m", "sdexp.cli", "-m", *TINY, "seed=0,1", *launcher,
                          f"hydra.sweep.dir={tmp_path / 'sweep'}"], capture_output=True, text=True,
                         cwd=tmp_path, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    jobs = sorted(p for p in (tmp_path / "sweep").iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name.rsplit("seed=", 1)[1] for p in jobs] == ["0", "1"]
    for job in jobs:
        assert (job / "metrics.json").exists() and (job / "config.yaml").exists()
    return jobs


def test_a_local_sweep_runs_its_jobs_in_parallel_with_a_share_of_the_cores_each(tmp_path, cache_dir):
    jobs = _sweep(tmp_path, cache_dir, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    share = max(1, available_cores() // 2)
    for job in jobs:
        log = (job / "cli.log").read_text()
        assert re.search(rf"on {share} cores?, 2 jobs side by side", log), log


def test_the_slurm_launcher_runs_the_sweep_through_submitit(tmp_path, cache_dir):
    """hydra/launcher=submitit_slurm with submitit's local executor (the same plugin, no Slurm):
    each job is pickled, run in its own process by submitit, and writes its folder."""
    jobs = _sweep(tmp_path, cache_dir, "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10")
    share = max(1, available_cores() // 2)
    for job in jobs:
        assert re.search(rf"on {share} cores?", (job / "cli.log").read_text())
    assert list((tmp_path / "sweep" / ".submitit").iterdir())   # submitit's own job folders
