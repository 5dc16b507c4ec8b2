"""``sdexp experiment=bench_sweep``: the wall time of a multi-seed sweep run one job at a time and
k jobs side by side (Hydra's joblib launcher, each job given its share of the cores by
sdexp.parallel), every sweep from an empty cache, so each includes building its meshes, data and
nets, as a user's first sweep does.

Writes ``bench_sweep.csv`` (jobs side by side, wall seconds, speed-up over one at a time, jobs
finished) and the sweeps' folders under ``sweeps/``. A figure, not a test: run it on an idle
machine.
"""
from __future__ import annotations

import logging
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from sdexp.eval.run import Run

log = logging.getLogger(__name__)


def sweep_command(experiment: str, seeds: int, jobs: int, cache_dir: str, sweep_dir: Path,
                  overrides: list[str]) -> list[str]:
    return [sys.executable, "-m", "sdexp.cli", "-m", f"experiment={experiment}",
            f"seed={','.join(str(s) for s in range(seeds))}", "hydra/launcher=joblib",
            f"hydra.launcher.n_jobs={jobs}", f"cache_dir={cache_dir}", f"hydra.sweep.dir={sweep_dir}",
            "hydra.sweep.subdir=seed${seed}", *overrides]


def run(run: Run) -> dict:
    p, out_dir = run.params, run.out_dir
    rows = []
    for jobs in p.jobs:
        with tempfile.TemporaryDirectory(prefix="sdexp-bench-sweep-") as cache:
            sweep_dir = out_dir / "sweeps" / f"jobs{jobs}"
            cmd = sweep_command(str(p.experiment), int(p.seeds), int(jobs), cache, sweep_dir, list(p.overrides))
            log.info(f"sdexp: {p.seeds} seeds of {p.experiment}, {jobs} job(s) side by side")
            t0 = time.perf_counter()
            res = subprocess.run(cmd, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            (out_dir / f"sweep_jobs{jobs}.log").write_text(res.stdout + res.stderr)
            if res.returncode != 0:
                raise RuntimeError(f"the sweep with {jobs} jobs failed (exit {res.returncode}): "
                                   f"see {out_dir / f'sweep_jobs{jobs}.log'}")
        done = len(list(sweep_dir.glob("*/metrics.json")))
        rows.append({"experiment": p.experiment, "seeds": int(p.seeds), "jobs": int(jobs), "wall_seconds": wall,
                     "finished": done})
    table = pd.DataFrame(rows)
    table["speedup"] = table["wall_seconds"].iloc[0] / table["wall_seconds"]
    run.table(table, "bench_sweep")
    log.info("\n" + table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    return {f"jobs{r.jobs}_wall_seconds": r.wall_seconds for r in table.itertuples()} | \
        {f"jobs{r.jobs}_speedup": r.speedup for r in table.itertuples()}
